"""Along-ray prior (issue 11, engine.train.along_ray): the unseen component of in-between
motion is pinned, the image-plane component is left to the spike loss."""
from __future__ import annotations

import types

import numpy as np
import pytest
import torch
from train_util import GUIDED_TINY as _TINY
from train_util import term_values, trajectory_model

from engine.scene.deformation import DeformationField
from engine.scene.gaussians import GaussianModel
from engine.scene.model import TRAJ_MEANS, Model4D
from engine.train.along_ray import (
    AlongRayPrior,
    along_ray_loss,
    along_ray_target,
    motion_positions,
    ray_depth,
)
from engine.train.presets import get_preset

KNOTS = [0.0, 0.1, 0.2, 0.3]
CENTER = torch.tensor([0.2, -0.1, -3.0])


def _traj_model(n=12, seed=0):
    """Gaussians in front of CENTER, static at every RGB instant (zero junctions)."""
    return trajectory_model(KNOTS, n, seed, spread=0.3)


def _loss_at(m, t, idx):
    times = {"prev": 0.0, "a": 0.1, "b": 0.2, "next": 0.3}
    with torch.no_grad():
        depths = {k: ray_depth(motion_positions(m, v, idx), CENTER) for k, v in times.items()}
    target = along_ray_target(times, depths, t, "hermite")
    return along_ray_loss(motion_positions(m, t, idx), CENTER, target, scale=1.0)


def _wobble(m, direction):
    """Segment 1's inner control points (indices 4, 5) displaced by ``direction`` [N, 3]:
    the Gaussians leave their (static) RGB-instant positions between 0.1 and 0.2 only."""
    with torch.no_grad():
        p = getattr(m.gaussians, TRAJ_MEANS)
        p.zero_()
        p[:, 4] = direction
        p[:, 5] = direction


def test_along_ray_wobble_is_penalised_image_plane_move_is_not():
    m = _traj_model()
    g = m.gaussians
    idx = torch.arange(g.num_gaussians)
    x = g.means.detach()
    ray = (x - CENTER) / (x - CENTER).norm(dim=1, keepdim=True)
    side = torch.linalg.cross(ray, torch.tensor([0.0, 1.0, 0.0]).expand_as(ray), dim=1)
    side = side / side.norm(dim=1, keepdim=True)  # perpendicular to the ray: image-plane motion
    delta = 2e-3
    grads, losses = {}, {}
    for name, d in {"ray": ray * delta, "plane": side * delta}.items():
        _wobble(m, d)
        tm = getattr(g, TRAJ_MEANS)
        tm.grad = None
        loss = _loss_at(m, 0.15, idx)
        loss.backward()
        losses[name], grads[name] = float(loss.detach()), tm.grad[:, 4].clone()
    assert losses["ray"] > 0
    # the along-ray wobble is pulled back along the ray (gradient parallel to it, pointing outwards
    # = descent moves the control point back towards the camera-side curve)
    cos = torch.nn.functional.cosine_similarity(grads["ray"], ray, dim=1)
    assert bool((cos > 0.999).all())
    # an image-plane move of the same size changes the ray depth only to second order:
    # loss and gradient are orders of magnitude smaller, and nothing pushes across the ray
    assert losses["plane"] < 1e-3 * losses["ray"]
    assert float(grads["plane"].norm()) < 1e-2 * float(grads["ray"].norm())
    assert float((grads["ray"] * side).sum(1).abs().max()) < 1e-3 * float(grads["ray"].norm(dim=1).min())


def test_exact_image_plane_move_has_no_loss_and_no_gradient():
    """A point moving on the sphere around the camera centre (pure image-plane motion) with
    the same ray depth at both RGB instants: zero loss, zero gradient."""
    x0 = torch.tensor([[0.0, 0.0, 1.0], [0.5, 0.2, 2.0]])
    rho = ray_depth(x0, CENTER)
    target = along_ray_target({"a": 0.0, "b": 1.0}, {"a": rho, "b": rho}, 0.4, "linear")
    rot = torch.tensor([[np.cos(0.2), -np.sin(0.2), 0.0], [np.sin(0.2), np.cos(0.2), 0.0], [0.0, 0.0, 1.0]],
                       dtype=torch.float32)
    x_t = ((x0 - CENTER) @ rot.T + CENTER).requires_grad_(True)
    loss = along_ray_loss(x_t, CENTER, target, scale=1.0)
    loss.backward()
    assert float(loss.detach()) < 1e-10
    # float32 round-off only: a 1 mm along-ray error gets a gradient of 0.05 here
    assert float(x_t.grad.abs().max()) < 1e-4


def test_target_curves():
    times = {"prev": 0.0, "a": 0.1, "b": 0.2, "next": 0.3}
    quad = lambda t: torch.tensor([1.0 + 2 * t + 3 * t * t])  # noqa: E731
    depths = {k: quad(v) for k, v in times.items()}
    # Catmull-Rom tangents on uniform knots reproduce a quadratic exactly
    for t in (0.1, 0.13, 0.15, 0.2):
        assert torch.allclose(along_ray_target(times, depths, t, "hermite"), quad(t), atol=1e-6)
    lin = along_ray_target(times, depths, 0.15, "linear")
    assert torch.allclose(lin, 0.5 * (quad(0.1) + quad(0.2)))
    # one-sided tangents at the ends: a straight line stays straight
    line = {"a": torch.tensor([1.0]), "b": torch.tensor([3.0])}
    assert torch.allclose(along_ray_target({"a": 0.0, "b": 1.0}, line, 0.25, "hermite"), torch.tensor([1.5]))
    with pytest.raises(ValueError, match="along_ray_curve"):
        along_ray_target(times, depths, 0.15, "spline")


def test_motion_positions_detach_canonical_and_train_the_field():
    rng = np.random.default_rng(1)
    g = GaussianModel(rng.normal(size=(20, 3)) * 0.3, rng.uniform(size=(20, 3)))
    field = DeformationField([-1, -1, -1], [1, 1, 1], (0.0, 0.3), resolution=8, time_resolution=4, seed=0)
    with torch.no_grad():  # a non-zero motion
        field.pos_head[-1].bias.fill_(0.05)
    m = Model4D(g, field)
    m.static_mask = torch.zeros(20, dtype=torch.bool)
    m.static_mask[:4] = True
    idx = torch.arange(20)
    x = motion_positions(m, 0.17, idx)
    assert torch.allclose(x, m.attributes(0.17)["means"], atol=1e-6)  # same positions as a render's
    assert torch.equal(x[:4], g.means.detach()[:4])  # static rows do not move
    x.sum().backward()
    assert g.means.grad is None and field.pos_head[-1].bias.grad is not None


def test_bracket_uses_admitted_rgb_instants_only():
    tr = types.SimpleNamespace(cfg=get_preset("fast", {"lambda_along_ray": 1.0}), frame_times=[0.0, 0.1, 0.2, 0.3])
    p = AlongRayPrior(tr, guidance=None)
    assert p.bracket(0.15, 0.3) == {"prev": 0.0, "a": 0.1, "b": 0.2, "next": 0.3}
    assert p.bracket(0.15, 0.2) == {"prev": 0.0, "a": 0.1, "b": 0.2}  # T+2 not admitted yet
    assert p.bracket(0.15, 0.18) is None  # the right end has not been trained yet
    assert p.bracket(0.05, 0.3) == {"a": 0.0, "b": 0.1, "next": 0.2}
    assert p.bracket(0.35, 0.3) is None



@pytest.mark.slow
def test_switch_off_adds_nothing(demo_capture):
    from engine.io.capture import load_capture
    from engine.train.trainer import Trainer

    cap = load_capture(demo_capture)
    assert get_preset("fast").lambda_along_ray == 0.0
    off = Trainer(cap, get_preset("fast", _TINY), device="cpu")
    assert "along_ray" not in {t.name for t in off.loss_terms} and not hasattr(off, "along_ray")
    on = Trainer(cap, get_preset("fast", {**_TINY, "lambda_along_ray": 1.0}), device="cpu")
    assert "along_ray" in {t.name for t in on.loss_terms}
    rgb = Trainer(cap, get_preset("fast", {**_TINY, "lambda_along_ray": 1.0}), device="cpu", rgb_only=True)
    assert "along_ray" not in {t.name for t in rgb.loss_terms}
    nospike = Trainer(cap, get_preset("fast", {**_TINY, "lambda_along_ray": 1.0, "spike_loss_weight": 0.0}),
                      device="cpu")
    assert "along_ray" not in {t.name for t in nospike.loss_terms}  # rides on the spike loss's render


@pytest.mark.slow
@pytest.mark.parametrize("motion", ["hexplane", "trajectory"])
def test_trainer_steps_with_the_prior(demo_capture, motion):
    """The term runs inside real guided steps for both motion representations: finite values
    on the spike camera's between-frame renders, and its gradient reaches the motion only."""
    from engine.io.capture import load_capture
    from engine.train.trainer import Trainer

    over = {**_TINY, "lambda_along_ray": 1.0, "motion": motion, "traj_carry": "velocity"}
    tr = Trainer(load_capture(demo_capture), get_preset("fast", over), device="cpu")
    tr.init_model()
    seen = term_values(tr, "along_ray", steps=8)
    assert seen and all(np.isfinite(v) and v >= 0 for v in seen)
    assert tr.along_ray.last["gaussians"] > 0
