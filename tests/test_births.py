"""Births with temporal opacity (engine.train.motion.births; docs/experiments/motion-representation.md "Motion
representation")."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from train_util import fake_run, trajectory_model

from engine.scene.model import TIME_CENTER, TIME_LOG_SCALE, temporal_opacity
from engine.train.config import get_preset
from engine.train.motion.births import ALWAYS_LOG_SCALE, birth_candidates, ensure_temporal_opacity

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
    assert get_preset("fast").births.error > 0  # on by default
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


def _flat_view():
    from engine.cameras import Intrinsics, View, look_at_c2w
    c2w = look_at_c2w((0.0, -5.0, 0.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0))
    return View(c2w=c2w, intrinsics=Intrinsics(80, 60, 70.0, 70.0, 40.0, 30.0), time=0.0)


def test_born_gaussians_get_the_backward_flow_lifted_by_depth_and_the_rest_their_nearest_neighbour():
    """Issue 11 "ghost": a Gaussian born at T_j on an object that moved 7 px right since T_{j-1}
    must sit 7 px left at T_{j-1} (at the stereo depth there), not at its T_j place."""
    from engine.cameras import project_points
    from engine.train.motion.births import backward_displacement
    from engine.train.motion.scene_flow import backproject_pixels

    v = _flat_view()
    d_j = np.full((60, 80), 5.0, np.float32)
    d_i = np.full((60, 80), 4.5, np.float32)    # the surface was 0.5 m closer at T_{j-1}
    ok = np.ones((60, 80), bool)
    ok[:, 60:] = False                           # no stereo right of x = 60
    flow = np.zeros((60, 80, 2), np.float32)
    flow[..., 0] = -7.0                          # T_j -> T_{j-1}: 7 px to the left
    born = backproject_pixels(v, np.array([[30.5, 30.5], [70.5, 30.5], [70.5, 10.5]]), np.array([5.0, 5.0, 5.0]))
    others = born[1:2] + np.array([[0.0, 0.0, 0.05]])        # an alive Gaussian near the second one
    others_delta = np.array([[-0.2, 0.0, 0.0]], np.float32)  # ... moved by its own curve
    delta, decided, n_flow = backward_displacement(born, [(v, flow, d_j, ok, d_i, ok)], others, others_delta, 0.1)
    assert decided.tolist() == [True, True, False] and n_flow == 1
    uv, z = project_points(v, born[:1] + delta[:1])
    np.testing.assert_allclose(uv, [[23.5, 30.5]], atol=1e-3)
    np.testing.assert_allclose(z, [4.5], atol=1e-4)
    np.testing.assert_allclose(delta[1], [-0.2, 0.0, 0.0], atol=1e-6)   # no stereo: its neighbour's motion
    np.testing.assert_array_equal(delta[2], 0.0)                         # nothing near: stays put
    # "nearest": the flow is not read
    delta, decided, n_flow = backward_displacement(born, [(v, flow, d_j, ok, d_i, ok)], others, others_delta, 0.1,
                                                   use_flow=False)
    assert decided.tolist() == [False, True, False] and n_flow == 0


def test_birth_motion_is_off_by_default_and_checked():
    from engine.train.motion.births import BIRTH_MOTIONS
    assert get_preset("fast").births.motion in BIRTH_MOTIONS


@pytest.mark.slow  # ~1 min on a loaded 2-core machine (stereo and flow for every instant)
def test_trainer_moves_born_gaussians_back_to_the_previous_instant(demo_capture, tmp_path):
    """birth_motion=lk: Gaussians born at a later instant start from the flow's displacement
    at the knot before it (junctions held), recorded in run.json (static curves without it)."""
    from engine.scene.model import TRAJ_MEANS, load_run
    from engine.train import train

    over = {"iterations": 12, "static_fraction": 0.25, "init_max_points": 300, "init_random_points": 100,
            "densify_from": 0.3, "densify_until": 0.9, "densify_every": 3, "densify_grad_threshold": 0.0,
            "time_curriculum": 0.5, "motion": "trajectory", "traj_carry": "flow", "birth_error": 0.05,
            "birth_motion": "lk", "lr_traj": 1e-12, "lr_traj_final": 1e-12}
    summary = train(demo_capture, tmp_path / "run", preset="fast", overrides=over, rgb_only=True, resume=False)
    assert summary["status"] == "finished"
    rec = json.loads((tmp_path / "run" / "run.json").read_text())["births"]
    later = [r for r in rec if r["born"] > 0 and r["birth_at"] > 1e-6]
    assert later and all("moved_back" in r for r in later) and sum(r["moved_back"] for r in later) > 0
    model = load_run(tmp_path / "run").model
    g, knots = model.gaussians, torch.tensor(model.trajectory["knots"])
    centre = getattr(g, TIME_CENTER).detach()[:, 0]
    born = (getattr(g, TIME_LOG_SCALE).detach()[:, 0] < 10) & (centre > knots[0] + 1e-3)
    j = (centre[born][:, None] - knots[None]).abs().argmin(1)            # knot of each born Gaussian's birth
    before = getattr(g, TRAJ_MEANS).detach()[born][torch.arange(int(born.sum())), 3 * (j - 1)]
    # frozen curves: what the births wrote at T_{j-1} stays (all zero: static curves without
    # birth_motion; "moved_back" also counts those decided still)
    assert int((before.norm(dim=-1) > 1e-6).sum()) >= 100


def test_component_flow_finds_a_jump_of_an_objects_own_size():
    """Issue 11 "ghost": a textured block that jumps 12 px right and 5 px up (more than its
    own size) between frames gets that translation at every one of its pixels, zero elsewhere."""
    from engine.train.motion.births import component_flow

    rng = np.random.default_rng(3)
    bg = np.kron(rng.uniform(size=(12, 16, 3)), np.ones((4, 4, 1))).astype(np.float32)   # 48 x 64
    obj = rng.uniform(size=(8, 8, 3)).astype(np.float32)
    a, b = bg.copy(), bg.copy()
    a[20:28, 30:38] = obj
    b[15:23, 42:50] = obj
    mask = np.zeros((48, 64), bool)
    mask[20:28, 30:38] = True
    mask[2, 2] = True                       # a speck under min_area: no flow
    flow = component_flow(a, b, mask, radius=16)
    np.testing.assert_array_equal(flow[20:28, 30:38], np.broadcast_to([12.0, -5.0], (8, 8, 2)))
    assert not flow[~mask].any() and not flow[2, 2].any()


def test_unchanged_pixels_are_those_a_neighbouring_instant_repeats():
    from engine.train.motion.births import unchanged_pixels

    img = np.zeros((4, 5, 3), np.float32)
    img[1, :] = 0.8
    before, after = img.copy(), img.copy()
    before[1, 0] = 0.0                        # changed since the instant before only: still static
    before[1, 1] = after[1, 1] = 0.3          # changed on both sides: a moving surface
    rows, cols = np.array([1, 1, 1, 0]), np.array([0, 1, 2, 0])
    np.testing.assert_array_equal(unchanged_pixels(img, [before, after], rows, cols, 0.15), [True, False, True, True])
    np.testing.assert_array_equal(unchanged_pixels(img, [before], rows, cols, 0.15), [False, False, True, True])
    assert not unchanged_pixels(img, [], rows, cols, 0.15).any()


@pytest.mark.parametrize("static_life", [0.0, 4.0])
def test_born_gaussians_on_a_static_surface_get_the_static_lifespan(static_life, monkeypatch):
    """birth_static_lifespan: a born Gaussian whose pixel shows the same colour at a neighbouring
    RGB instant (a disoccluded static wall) gets that temporal std; one on a patch seen only at
    its instant (a moving object) keeps birth_lifespan. Off (0): every one gets birth_lifespan."""
    from types import SimpleNamespace

    from engine.cameras import View
    from engine.scene.gaussians import rgb_to_sh
    from engine.train.motion.births import spawn_at_instant

    knots = [0.0, 0.1, 0.2]
    model = trajectory_model(knots, 10, centre=(0.0, -50.0, 0.0))  # behind the camera: renders black
    view0 = _flat_view()
    H, W = view0.intrinsics.height, view0.intrinsics.width
    wall = np.zeros((H, W, 3), np.float32)
    wall[:, : W // 2] = 0.7                               # static: the same at every instant
    images = {t: wall.copy() for t in knots}
    images[0.1][20:30, 50:60] = 0.9                       # moving: only at 0.1
    frames = [SimpleNamespace(camera="L", time=t) for t in knots]
    from engine.train.motion import births

    monkeypatch.setattr(births, "MAX_PER_FRAME", 100000)
    cfg = get_preset("fast").replace(birth_error=0.15, birth_lifespan=0.5,
                                     birth_static_lifespan=static_life, birth_motion="none")
    depth, ok = np.full((H, W), 3.0, np.float32), np.ones((H, W), bool)
    trainer = fake_run(
        cfg, model=model, capture=SimpleNamespace(view=lambda f: View(view0.intrinsics, view0.c2w, time=f.time)),
        memo={"stereo_priors": {id(f): (depth, ok) for f in frames},
              "item_images": {("L", round(t, 9)): torch.from_numpy(images[t])[None] for t in knots}})
    rec = spawn_at_instant(trainer, frames, 0.1)
    g = model.gaussians
    born = rec["born"]
    assert born == (H // 2) * (W // 4) + 5 * 5            # the wall's grid pixels + the patch's
    std = torch.exp(getattr(g, TIME_LOG_SCALE).detach()[-born:, 0]).numpy() / 0.1
    on_patch = (g.sh_dc.detach()[-born:, 0, 0] > float(rgb_to_sh(torch.tensor(0.8)))).numpy()  # colour 0.9
    if static_life == 0:
        np.testing.assert_allclose(std, 0.5, rtol=1e-5)
        assert "static" not in rec
    else:
        np.testing.assert_allclose(std[on_patch], 0.5, rtol=1e-5)
        np.testing.assert_allclose(std[~on_patch], 4.0, rtol=1e-5)
        assert rec["static"] == born - 25


def test_stereo_in_front_needs_an_opaque_render_and_the_ratio():
    from engine.train.motion.births import stereo_in_front

    stereo = np.array([3.0, 4.5, 3.0, 6.0])
    render = np.array([5.0, 5.0, 5.0, 5.0])
    alpha = np.array([0.9, 0.9, 0.2, 0.9])
    np.testing.assert_array_equal(stereo_in_front(stereo, render, alpha, 0.8), [True, False, False, False])


@pytest.mark.parametrize("guard", [0.0, 0.8])
def test_static_births_in_front_of_the_rendered_surface_are_dropped(guard, monkeypatch):
    """birth_depth_guard: the model already has an opaque wall 5 m away (black); the frame shows
    it grey at every instant and stereo puts it at 3 m on the left half (a wrong match: dropped)
    and at 4.5 m on the right (kept); a patch seen only at its instant, at 3 m, is a moving
    object in front of the wall and is born whatever the guard."""
    from types import SimpleNamespace

    from engine.cameras import View
    from engine.scene.gaussians import rgb_to_sh
    from engine.train.motion.births import spawn_at_instant

    knots = [0.0, 0.1, 0.2]
    gx, gz = np.meshgrid(np.linspace(-3.5, 3.5, 48), np.linspace(-2.7, 2.7, 36))
    wall = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], 1)
    model = trajectory_model(knots, len(wall))
    g = model.gaussians
    with torch.no_grad():
        g.means.copy_(torch.as_tensor(wall, dtype=torch.float32))
        g.log_scales.fill_(math.log(0.15))
        g.opacity_logits.fill_(6.0)
        g.sh_dc.copy_(rgb_to_sh(torch.zeros(len(wall), 1, 3)))
    view0 = _flat_view()
    H, W = view0.intrinsics.height, view0.intrinsics.width
    images = {t: np.full((H, W, 3), 0.6, np.float32) for t in knots}
    images[0.1][20:30, 10:20] = 0.95                      # moving: only at 0.1
    frames = [SimpleNamespace(camera="L", time=t) for t in knots]
    from engine.train.motion import births

    monkeypatch.setattr(births, "MAX_PER_FRAME", 100000)
    cfg = get_preset("fast").replace(birth_error=0.15, birth_lifespan=0.5,
                                     birth_static_lifespan=0.0, birth_depth_guard=guard, birth_motion="none")
    depth, ok = np.full((H, W), 4.5, np.float32), np.ones((H, W), bool)
    depth[:, : W // 2] = 3.0
    trainer = fake_run(
        cfg, model=model, capture=SimpleNamespace(view=lambda f: View(view0.intrinsics, view0.c2w, time=f.time)),
        memo={"stereo_priors": {id(f): (depth, ok) for f in frames},
              "item_images": {("L", round(t, 9)): torch.from_numpy(images[t])[None] for t in knots}})
    n0 = g.num_gaussians
    rec = spawn_at_instant(trainer, frames, 0.1)
    everywhere = (H // 2) * (W // 2)                      # the stride-2 grid
    patch = 5 * 5
    born_cols = g.sh_dc.detach()[n0:, 0, 0]
    on_patch = int((born_cols > float(rgb_to_sh(torch.tensor(0.8)))).sum())
    if guard == 0:
        assert rec["born"] == everywhere and "guarded" not in rec and on_patch == patch
    else:
        left_wall = (H // 2) * (W // 4) - patch           # the left half's grid pixels but the patch's
        assert rec["guarded"] == left_wall and rec["born"] == everywhere - left_wall and on_patch == patch
        cam_y = g.means.detach()[n0:, 1].numpy()          # depth 5 - |y - (-5)|: wall births at 4.5 m
        assert (np.abs(cam_y[: rec["born"]] + 5.0 - 4.5) < 1e-3).sum() == rec["born"] - patch
