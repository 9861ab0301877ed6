"""Local rigidity between RGB instants (issue 11, engine.train.between_rigidity): a part that
moves rigidly costs nothing at a between-frame instant, one that tears apart costs, and only
the motion is trained; Gaussians that do not move over the interval are left out."""
from __future__ import annotations

import types

import numpy as np
import pytest
import torch
from train_util import GUIDED_TINY as _TINY
from train_util import term_values, trajectory_model

from engine.scene.model import TRAJ_MEANS
from engine.train.between_rigidity import BetweenRigidity
from engine.train.presets import get_preset

KNOTS = [0.0, 0.1, 0.2, 0.3]


def _term(model, t=0.15, **over):
    cfg = get_preset("fast", {"rigidity_between_weight": 1.0, "rigidity_between_min_move": 0.01, **over})
    tr = types.SimpleNamespace(cfg=cfg, frame_times=KNOTS, extent=1.0, seed=0, model=model)
    between = {"instant": types.SimpleNamespace(time=t)}
    guid = types.SimpleNamespace(between=lambda ctx: between)
    term = BetweenRigidity(tr, guid)
    ctx = types.SimpleNamespace(trainer=tr, step=0, stage="deform")
    return term, ctx


def _translate(model, moving: torch.Tensor, step=(0.05, 0.0, 0.0)):
    """The ``moving`` rows translate by ``step`` per RGB interval (junction k at k x step),
    the others stay; all inner residuals zero (the Catmull-Rom curve between)."""
    with torch.no_grad():
        p = getattr(model.gaussians, TRAJ_MEANS)
        p.zero_()
        for k in range(len(KNOTS)):
            p[moving, 3 * k] = torch.tensor(step) * k


def test_rigid_translation_costs_nothing_a_tear_costs_and_trains_the_motion_only():
    m = trajectory_model(KNOTS, 40, seed=0, spread=0.2)
    moving = torch.zeros(40, dtype=torch.bool)
    moving[:30] = True
    _translate(m, moving)
    term, ctx = _term(m)
    loss = term(ctx)
    assert loss is not None and float(loss.detach()) < 1e-6  # the cluster moves as one body
    idx = term.last["gaussians"]
    assert idx == 30  # the 10 still Gaussians are not in the term
    assert set(term._nbrs[1][2].tolist()) == set(range(30))

    # one Gaussian leaves the body between 0.1 and 0.2 only (segment 1's inner control points)
    with torch.no_grad():
        p = getattr(m.gaussians, TRAJ_MEANS)
        p[3, 4] += torch.tensor([0.0, 0.08, 0.0])
        p[3, 5] += torch.tensor([0.0, 0.08, 0.0])
    ctx.step = 1  # the neighbour lists are reused (same Gaussians, within rigidity_between_every)
    loss = term(ctx)
    assert float(loss.detach()) > 1e-3
    assert term.last["iso"] > 0 and term.last["rigid"] > 0
    loss.backward()
    g = m.gaussians
    grad = getattr(g, TRAJ_MEANS).grad
    assert g.means.grad is None  # canonical Gaussians are not moved by this term
    assert float(grad[3, 4:6].norm()) > 0  # the torn Gaussian's inner control points are pulled back
    assert float(grad[30:].abs().sum()) == 0  # the still ones get nothing
    # descent brings the torn Gaussian back towards the body: the gradient on its inner points
    # points along the tear (+y)
    assert float(grad[3, 4, 1]) > 0


def test_a_rotating_body_costs_nothing_when_rotations_follow():
    """A rigid rotation about the body's centre (positions and rotations at the RGB instants and
    at t evaluated exactly: the curve interpolates the rotation's chord, so the check is at
    the instants, where the curve passes through the rotated positions)."""
    m = trajectory_model(KNOTS, 30, seed=1, spread=0.2)
    g = m.gaussians
    x0 = g.means.detach().clone()
    ang = 0.3  # radians per RGB interval about z

    def rot(a):
        c, s = np.cos(a), np.sin(a)
        return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float32)

    with torch.no_grad():
        p = getattr(m.gaussians, TRAJ_MEANS)
        q = getattr(m.gaussians, "traj_quats")
        p.zero_()
        q.zero_()
        for k in range(len(KNOTS)):
            p[:, 3 * k] = x0 @ rot(ang * k).T - x0
            # quaternion (w, x, y, z) of the rotation about z, as a residual on the canonical wxyz
            qk = torch.tensor([np.cos(ang * k / 2), 0.0, 0.0, np.sin(ang * k / 2)], dtype=torch.float32)
            w0, v0 = g.quats.detach()[:, :1], g.quats.detach()[:, 1:]
            # q_k * q0 (Hamilton product), minus q0
            qw = qk[0] * w0 - (v0 @ qk[1:, None])
            qv = qk[0] * v0 + w0 * qk[1:] + torch.linalg.cross(qk[1:].expand_as(v0), v0, dim=1)
            q[:, 3 * k] = torch.cat([qw, qv], 1) - g.quats.detach()
    term, ctx = _term(m, t=0.2 - 1e-6)
    loss = term(ctx)
    assert loss is not None and float(loss.detach()) < 1e-3  # at (almost) T_b: the exact rotated body
    with torch.no_grad():
        q[:, 3 * 2] = 0.0  # rotations that stop following the body: the rigid and rot terms see it
    term2, ctx2 = _term(m, t=0.2 - 1e-6)
    assert float(term2(ctx2).detach()) > 10 * float(loss.detach())


def test_interval_needs_both_ends_admitted():
    m = trajectory_model(KNOTS, 12, seed=0)
    term, _ = _term(m)
    assert term.interval(0.15, 0.3) == 1
    assert term.interval(0.15, 0.18) is None  # T_k+1 not trained yet
    assert term.interval(0.0, 0.3) is None and term.interval(0.3, 0.3) is None



@pytest.mark.slow
def test_switch_and_trainer_steps(demo_capture):
    """Off by default and in RGB-only runs; on, it runs inside real guided steps with finite
    values."""
    from engine.io.capture import load_capture
    from engine.train.trainer import Trainer

    cap = load_capture(demo_capture)
    assert get_preset("fast").rigidity_between_weight == 0.0
    off = Trainer(cap, get_preset("fast", _TINY), device="cpu")
    assert "rigidity_between" not in {t.name for t in off.loss_terms}
    over = {**_TINY, "rigidity_between_weight": 1.0, "rigidity_between_min_move": 0.0}
    rgb = Trainer(cap, get_preset("fast", over), device="cpu", rgb_only=True)
    assert "rigidity_between" not in {t.name for t in rgb.loss_terms}
    tr = Trainer(cap, get_preset("fast", over), device="cpu")
    assert "rigidity_between" in {t.name for t in tr.loss_terms}
    tr.init_model()
    seen = term_values(tr, "rigidity_between", steps=8)
    assert seen and all(np.isfinite(v) and v >= 0 for v in seen)
    assert tr.between_rigidity.last["gaussians"] > 0
