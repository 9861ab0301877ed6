"""Births with temporal opacity (engine.train.births; README "Motion representation")."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from train_util import trajectory_model

from engine.scene.model import TIME_CENTER, TIME_LOG_SCALE, temporal_opacity
from engine.train.births import ALWAYS_LOG_SCALE, birth_candidates, ensure_temporal_opacity
from engine.train.presets import get_preset

KNOTS = [0.0, 0.1, 0.2, 0.3]


def test_temporal_opacity_fades_born_rows_and_leaves_the_others_exactly():
    m = trajectory_model(KNOTS, 30)
    g = m.gaussians
    before = {t: m.attributes(t)["opacities"].detach().clone() for t in (0.0, 0.3)}
    ensure_temporal_opacity(g)
    for t in (0.0, 0.3):  # log std 30: factor exactly 1
        assert torch.equal(m.attributes(t)["opacities"], before[t])
    with torch.no_grad():
        getattr(g, TIME_CENTER)[:5] = 0.2
        getattr(g, TIME_LOG_SCALE)[:5] = math.log(0.05)
    at = m.attributes(0.2)["opacities"]
    far = m.attributes(0.0)["opacities"]
    assert torch.allclose(at[:5], torch.sigmoid(g.opacity_logits[:5]))
    assert torch.allclose(far[:5], torch.sigmoid(g.opacity_logits[:5]) * math.exp(-0.5 * 16), rtol=1e-4)
    assert torch.equal(far[5:], before[0.0][5:])
    c = torch.tensor([[0.2]], requires_grad=True)
    s = torch.tensor([[math.log(0.05)]], requires_grad=True)
    temporal_opacity(c, s, 0.25).sum().backward()  # learnable: gradients reach centre and width
    assert float(c.grad) > 0 and float(s.grad) > 0
    assert ALWAYS_LOG_SCALE >= 20


def test_append_keeps_old_moments_and_starts_new_rows_at_zero():
    m = trajectory_model(KNOTS, 20)
    g = m.gaussians
    ensure_temporal_opacity(g)
    m.attributes(0.15)["means"].sum().backward()
    g.optimizer.step()
    old = {n: g.optimizer.state[getattr(g, n)]["exp_avg"].clone() for n in ("means", TIME_CENTER)
           if getattr(g, n) in g.optimizer.state}
    g.grad_accum += 1.0
    rows = {n: torch.ones((3, *getattr(g, n).shape[1:])) for n in g.param_names}
    assert g.append(rows) == 3 and g.num_gaussians == 23
    for n, v in old.items():
        st = g.optimizer.state[getattr(g, n)]["exp_avg"]
        assert torch.equal(st[:20], v) and not st[20:].any()
    assert g.grad_accum.shape == (23,) and torch.equal(g.grad_accum[:20], torch.ones(20))
    assert not g.grad_accum[20:].any()
    assert torch.equal(getattr(g, TIME_CENTER)[20:], torch.ones(3, 1))
    m.attributes(0.15)["means"].sum().backward()  # the optimiser still steps every row
    g.optimizer.step()


def test_birth_candidates_are_missed_pixels_with_depth_on_the_grid():
    H, W = 12, 16
    img = np.zeros((H, W, 3), np.float32)
    ren = img.copy()
    ren[2:8, 4:12] = 0.5  # the render misses a block
    depth = np.full((H, W), 2.0, np.float32)
    ok = np.ones((H, W), bool)
    ok[:, 4:6] = False    # no stereo depth there
    rng = np.random.default_rng(0)
    r, c = birth_candidates(ren, img, depth, ok, 0.2, 2, 1000, rng)
    assert len(r) and (r % 2 == 0).all() and (c % 2 == 0).all()
    assert ((r >= 2) & (r < 8) & (c >= 6) & (c < 12)).all()
    assert len(r) == 3 * 3
    assert len(birth_candidates(ren, img, depth, ok, 0.6, 2, 1000, rng)[0]) == 0   # within tolerance
    assert len(birth_candidates(ren, img, depth, ok, 0.2, 2, 4, rng)[0]) == 4      # capped


@pytest.mark.slow  # ~1 min on a loaded 2-core machine (stereo for every instant)
def test_trainer_gives_birth_at_admitted_instants(demo_capture, tmp_path):
    from engine.scene.model import load_run
    from engine.train import train

    over = {"iterations": 12, "static_fraction": 0.25, "init_max_points": 300, "init_random_points": 100,
            "densify_from": 0.3, "densify_until": 0.9, "densify_every": 3, "densify_grad_threshold": 0.0,
            "time_curriculum": 0.5, "motion": "trajectory", "traj_carry": "velocity", "birth_error": 0.05}
    assert get_preset("fast").birth_error > 0  # on by default
    summary = train(demo_capture, tmp_path / "run", preset="fast", overrides=over, rgb_only=True, resume=False)
    assert summary["status"] == "finished"
    rec = json.loads((tmp_path / "run" / "run.json").read_text())["births"]
    assert len(rec) >= 2 and sum(r["born"] for r in rec) > 0
    scene = load_run(tmp_path / "run")
    g = scene.model.gaussians
    centres = getattr(g, TIME_CENTER).detach()[:, 0]
    born = getattr(g, TIME_LOG_SCALE).detach()[:, 0] < 10
    at = torch.tensor([r["birth_at"] for r in rec], dtype=centres.dtype)
    # centres learn, a little
    assert born.any() and ((centres[born][:, None] - at[None]).abs().min(1).values < 0.01).all()
    t = float(centres[born][0])
    near, far = scene.gaussians_at(t)["opacities"], scene.gaussians_at(t + 1.0)["opacities"]
    assert (far[born.numpy()] < near[born.numpy()]).all()   # born Gaussians fade away from their instant
    assert np.array_equal(far[~born.numpy()], near[~born.numpy()])
