"""HexPlane deformation field: identity start, normalisation, heads, fine hook, regularisers."""
from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from engine.scene.deformation import PLANES, DeformationField, HexPlane, make_field, time_resolution_for
from engine.train.config import get_preset


def _field(**kw):
    return DeformationField([-1, -1, -1], [1, 1, 1], (0.0, 0.2), resolution=8, multires=(1, 2), time_resolution=5,
                            features=4, width=16, **kw)


def _gaussians(n=20, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g) * 2 - 1, torch.randn(n, 4, generator=g), torch.randn(n, 3, generator=g),
            torch.randn(n, generator=g))


def test_hexplane_shapes_and_static_start():
    h = HexPlane(features=4, resolution=8, multires=(1, 2), time_resolution=5)
    assert len(h.spatial) == 2 and len(h.temporal) == 2 and h.out_dim == 8
    # plane (a, b) is [1, C, res_b, res_a]; time planes are [.., T, res]
    assert tuple(h.plane(0, 0).shape) == (1, 4, 8, 8) and tuple(h.plane(0, 3).shape) == (1, 4, 5, 8)
    assert tuple(h.plane(1, 0).shape) == (1, 4, 16, 16)
    x = torch.rand(10, 3) * 2 - 1
    f0 = h(torch.cat([x, torch.full((10, 1), -1.0)], 1))
    f1 = h(torch.cat([x, torch.full((10, 1), 0.7)], 1))
    torch.testing.assert_close(f0, f1)  # time planes start at 1: no motion before training
    assert PLANES[3] == (0, 3)


def test_bilinear_sampling_hits_grid_values():
    h = HexPlane(features=1, resolution=3, multires=(1,), time_resolution=3)
    with torch.no_grad():
        for p in h.parameters():
            p.fill_(1.0)
        h.spatial[0][0, 0] = torch.tensor([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0], [6.0, 7.0, 8.0]])  # xy plane, [y, x]
    pt = torch.tensor([[1.0, 0.0, 0.3, 0.1]])   # x = +1 (last column), y = 0 (middle row)
    assert float(h(pt).detach()) == pytest.approx(5.0)
    pt = torch.tensor([[0.5, 0.0, 0.3, 0.1]])   # halfway between columns 1 and 2
    assert float(h(pt).detach()) == pytest.approx(4.5)


def test_identity_at_initialisation_and_gradients_reach_grid_and_mlp():
    d = _field()
    m, q, s, o = _gaussians()
    out = d(m, q, s, o, 0.1)
    torch.testing.assert_close(out["means"], m)
    torch.testing.assert_close(out["quats"], q)
    assert out["log_scales"] is s and out["opacity_logits"] is o and out["color_delta"] is None
    opt = torch.optim.Adam(d.parameters(), lr=1e-2)
    for _ in range(3):
        opt.zero_grad()
        out = d(m, q, s, o, 0.1)
        (out["means"][:, 0] - 0.3).pow(2).mean().backward()
        opt.step()
    assert all(p.grad is not None for p in d.grid_parameters())
    assert d.grid.temporal[0].grad.abs().sum() > 0  # the time planes
    assert d.phi[0].weight.grad.abs().sum() > 0


def test_normalisation_of_space_and_time():
    d = DeformationField([0, 0, 0], [2, 4, 8], (1.0, 3.0), resolution=4, time_resolution=3, features=2, width=8)
    torch.testing.assert_close(d.normalize_xyz(torch.tensor([[0.0, 0, 0], [2, 4, 8], [1, 2, 4]])),
                               torch.tensor([[-1.0, -1, -1], [1, 1, 1], [0, 0, 0]]))
    assert d.normalize_time(1.0) == -1.0 and d.normalize_time(3.0) == 1.0 and d.normalize_time(2.5) == 0.5
    assert d.pos_scale == pytest.approx(math.sqrt(4 + 16 + 64) / 2)


def test_learns_a_time_dependent_translation_continuously():
    torch.manual_seed(0)
    d = _field()
    m, q, s, o = _gaussians(50)
    times = [0.0, 0.05, 0.1, 0.15, 0.2]
    target = lambda t: m + torch.tensor([t * 2.0, 0.0, 0.0])  # noqa: E731  (0.4 units over 0.2 s)
    opt = torch.optim.Adam([{"params": d.grid_parameters(), "lr": 3e-2}, {"params": d.mlp_parameters(), "lr": 3e-3}])
    for it in range(300):
        t = times[it % len(times)]
        opt.zero_grad()
        ((d(m, q, s, o, t)["means"] - target(t)) ** 2).mean().backward()
        opt.step()
    with torch.no_grad():
        err_train = ((d(m, q, s, o, 0.1)["means"] - target(0.1)).norm(dim=1)).mean()
        err_between = ((d(m, q, s, o, 0.125)["means"] - target(0.125)).norm(dim=1)).mean()
    assert float(err_train) < 0.05
    assert float(err_between) < 0.06  # any instant can be queried; motion interpolates


def test_optional_heads_and_mask():
    d = _field(deform_scale=True, deform_opacity=True, deform_color=True)
    for head in (d.pos_head, d.rot_head, d.scale_head, d.opacity_head, d.color_head):
        nn.init.normal_(head[-1].weight, std=0.1)
    m, q, s, o = _gaussians()
    out = d(m, q, s, o, 0.05)
    assert not torch.allclose(out["log_scales"], s) and not torch.allclose(out["opacity_logits"], o)
    assert out["color_delta"].shape == (20, 3)
    assert _field().scale_head is None  # off by default (DynTCG)
    mask = torch.zeros(20, dtype=torch.bool)
    mask[:5] = True
    part = d(m, q, s, o, 0.05, mask=mask)
    torch.testing.assert_close(part["means"][:5], out["means"][:5])
    torch.testing.assert_close(part["means"][5:], m[5:])


def test_fine_feature_hook_is_added_before_the_decoder():
    d = _field()
    nn.init.normal_(d.pos_head[-1].weight, std=0.1)
    m, q, s, o = _gaussians()
    base = d(m, q, s, o, 0.05)["means"]
    zero = d(m, q, s, o, 0.05, fine=torch.zeros(20, d.feature_dim))["means"]
    torch.testing.assert_close(base, zero)
    fine = torch.randn(20, d.feature_dim)
    f_expected = d.features(m, 0.05) + fine
    torch.testing.assert_close(d.features(m, 0.05, fine), f_expected)
    assert not torch.allclose(d(m, q, s, o, 0.05, fine=fine)["means"], base)

    calls = []

    class Enc(nn.Module):
        def forward(self, xyz, t):
            calls.append(t)
            return torch.ones(xyz.shape[0], d.feature_dim)

    d.fine_encoder = Enc()
    d(m, q, s, o, 0.07)
    assert calls == [0.07]
    assert all(id(p) not in {id(x) for x in d.grid_parameters()} for p in d.mlp_parameters())


def test_regularisers():
    d = _field()
    with torch.no_grad():
        for p in d.grid.parameters():
            p.fill_(0.5)
    assert float(d.grid.tv_loss().detach()) == 0.0
    # time planes linear in t: zero second difference, non-zero deviation from 1
    with torch.no_grad():
        for p in d.grid.temporal:
            p.copy_(torch.linspace(0, 1, p.shape[-2])[None, None, :, None].expand_as(p))
    assert float(d.grid.time_smoothness_loss().detach()) == pytest.approx(0.0, abs=1e-10)
    assert float(d.grid.time_l1_loss().detach()) > 0
    with torch.no_grad():
        d.grid.temporal[0][0, 0, 2, 0] += 1.0
    assert float(d.grid.time_smoothness_loss().detach()) > 0
    assert float(d.regularization(1.0, 1.0, 1.0).detach()) > 0


def test_config_round_trip_and_make_field():
    d = _field(deform_scale=True)
    d2 = DeformationField.from_config(d.config())
    d2.load_state_dict(d.state_dict())
    m, q, s, o = _gaussians()
    torch.testing.assert_close(d2(m, q, s, o, 0.1)["means"], d(m, q, s, o, 0.1)["means"])
    assert time_resolution_for([0, 1 / 30, 2 / 30, 2 / 30, 0.1], 1.0) == 5
    cfg = get_preset("fast")
    f = make_field(cfg.hexplane, [0, 0, 0], [1, 1, 1], (0, 0.2), [0, 0.1, 0.2])
    assert f.grid.resolutions[0] == [cfg.hexplane.resolution] * 3 + [4]
    assert f.scale_head is None
