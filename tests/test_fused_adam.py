"""FusedAdam (engine.scene.fused_adam): torch.optim.Adam's numbers bit for bit, its state
format (densification, checkpoints), and torch's own step where it cannot take over."""
from __future__ import annotations

import copy

import pytest
import torch

from engine.scene import fused_adam
from engine.scene.fused_adam import FusedAdam

SIZES = [(1,), (5,), (8,), (17, 3), (20011, 19, 3), (1031, 4)]


def _params(seed=0):
    g = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(s, generator=g) * 10.0 ** (i % 4 - 2)) for i, s in enumerate(SIZES)]


def _groups(ps):
    return [{"params": [p], "lr": 10.0 ** -(i % 5 + 1), "name": f"g{i}"} for i, p in enumerate(ps)]


def _grads(steps, seed=1):
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(steps):
        # sparse-ish, wide dynamic range, some exact zeros (untouched trajectory columns)
        out.append([torch.randn(s, generator=g) * torch.rand(s, generator=g).pow(6) * 10.0
                    * (torch.rand(s, generator=g) < 0.4) for s in SIZES])
    return out


def _run(opt_cls, grads, betas=(0.9, 0.999), **kw):
    ps = _params()
    opt = opt_cls(_groups(ps), lr=0.0, eps=1e-15, betas=betas, **kw)
    for k, gs in enumerate(grads):
        for i, (p, gr) in enumerate(zip(ps, gs)):
            p.grad = None if (k + i) % 7 == 3 else gr.clone()  # some groups skip some steps
        opt.step()
    return ps, opt


@pytest.mark.parametrize("betas", [(0.9, 0.999), (0.3, 0.99)])
def test_bit_for_bit_torch_adam(betas):
    assert fused_adam.exact(), "the fused path disagrees with torch here: see engine.scene._adam_kernels"
    grads = _grads(12)
    ref, o_ref = _run(torch.optim.Adam, grads, betas=betas)
    fus, o_fus = _run(FusedAdam, grads, betas=betas)
    for a, b in zip(ref, fus):
        assert torch.equal(a, b)
        sa, sb = o_ref.state[a], o_fus.state[b]
        assert torch.equal(sa["exp_avg"], sb["exp_avg"]) and torch.equal(sa["exp_avg_sq"], sb["exp_avg_sq"])
        assert torch.equal(sa["step"], sb["step"]) and sb["step"].dtype == sa["step"].dtype


def test_state_dict_round_trips_with_torch_adam():
    grads = _grads(4)
    fus, o_fus = _run(FusedAdam, grads[:2])
    ps = [torch.nn.Parameter(p.detach().clone()) for p in fus]
    o_ref = torch.optim.Adam(_groups(ps), lr=0.0, eps=1e-15)
    o_ref.load_state_dict(copy.deepcopy(o_fus.state_dict()))  # (torch shares the step tensors)
    for gs in grads[2:]:
        for p, q, gr in zip(fus, ps, gs):
            p.grad, q.grad = gr.clone(), gr.clone()
        o_fus.step()
        o_ref.step()
    assert all(torch.equal(a, b) for a, b in zip(fus, ps))


def test_falls_back_to_torch_where_it_cannot_take_over(monkeypatch):
    calls = []
    real = fused_adam._fused_update
    monkeypatch.setattr(fused_adam, "_fused_update", lambda *a, **k: (calls.append(1), real(*a, **k)))
    p = torch.nn.Parameter(torch.randn(10, 3))
    for kw in ({"amsgrad": True}, {"weight_decay": 0.1}, {"maximize": True}):
        opt = FusedAdam([p], lr=1e-3, **kw)
        p.grad = torch.randn(10, 3)
        opt.step()
    q = torch.nn.Parameter(torch.randn(10, 3, dtype=torch.float64))
    q.grad = torch.randn(10, 3, dtype=torch.float64)
    FusedAdam([q], lr=1e-3).step()
    r = torch.nn.Parameter(torch.randn(3, 10))
    r.grad = torch.randn(10, 3).t()  # non-contiguous gradient
    FusedAdam([r], lr=1e-3).step()
    monkeypatch.setattr(fused_adam, "ENABLED", False)
    s = torch.nn.Parameter(torch.randn(10, 3))
    s.grad = torch.randn(10, 3)
    FusedAdam([s], lr=1e-3).step()
    assert calls == []
    monkeypatch.setattr(fused_adam, "ENABLED", True)
    FusedAdam([s], lr=1e-3).step()
    assert calls == [1]


def test_densification_keeps_working_with_the_fused_optimizer():
    import numpy as np

    from engine.scene.gaussians import GaussianModel
    from engine.train.presets import get_preset

    rng = np.random.default_rng(0)
    g = GaussianModel(rng.normal(size=(50, 3)), rng.uniform(size=(50, 3)))
    g.setup_optimizer(get_preset("fast"), 1.0)
    assert isinstance(g.optimizer, FusedAdam)
    (g.means.sum() + g.sh_dc.sum()).backward()
    g.optimizer.step()
    g.grad_accum[:10] = 1.0
    g.grad_count[:] = 1.0
    g.densify_and_prune(grad_threshold=0.5, percent_dense=10.0, min_opacity=0.0, max_world_scale=1e9,
                        max_gaussians=1000)
    assert g.num_gaussians == 60 and g.optimizer.state[g.means]["exp_avg"].shape == (60, 3)
    g.optimizer.zero_grad()
    g.means.sum().backward()
    g.optimizer.step()
