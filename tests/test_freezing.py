"""engine.train.skipping.freezing: CPOStream-style prediction (freeze after K quiet checks) and observation
(wake under a residual), densification bookkeeping, motion of a deformation field, flicker."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from engine.evaluate.flicker import static_flicker
from engine.train.skipping.freezing import Freezer, abrupt_mask, deformation_motion, residual_map, residual_scores


def test_freezes_after_k_quiet_checks_only():
    f = Freezer(4, k_checks=3, motion_eps=0.1)
    motion = torch.tensor([0.0, 0.05, 0.5, 0.0])
    for i in range(2):
        f.update(motion)
        assert f.num_frozen == 0
    info = f.update(motion)
    assert f.frozen.tolist() == [True, True, False, True]
    assert info["newly_frozen"] == 3 and info["active"] == 1
    # motion resets the streak: Gaussian 0 moves once, is released and needs K quiet checks again
    f.update(torch.tensor([1.0, 0.0, 0.5, 0.0]))
    assert f.frozen.tolist() == [False, True, False, True]
    f.update(torch.zeros(4))
    f.update(torch.zeros(4))
    assert not f.frozen[0]
    f.update(torch.zeros(4))
    assert f.frozen[0]


def test_deltas_are_normed_and_nan_never_freezes():
    f = Freezer(3, k_checks=1, motion_eps=0.1)
    deltas = torch.tensor([[0.06, 0.06, 0.06], [0.01, 0.0, 0.0], [float("nan"), 0.0, 0.0]])
    f.update(deltas)  # |(0.06,0.06,0.06)| = 0.104 > 0.1
    assert f.frozen.tolist() == [False, True, False]
    f.update(torch.tensor([float("inf"), float("nan"), 0.0]))
    assert f.frozen.tolist() == [False, False, True]


def test_wake_and_observe():
    f = Freezer(5, k_checks=1, motion_eps=0.1, wake_residual=0.2)
    f.update(torch.zeros(5))
    assert f.num_frozen == 5
    assert f.wake(torch.tensor([True, False, False, False, False])) == 1
    assert f.observe(torch.tensor([0.0, 0.5, 0.1, float("nan"), 0.2])) == 2   # 0.5 and NaN wake
    assert f.frozen.tolist() == [False, False, True, False, True]
    assert f.total_woken == 3
    # a woken Gaussian needs K quiet checks again
    f.update(torch.tensor([0.0, 1.0, 0.0, 1.0, 0.0]))
    assert f.frozen.tolist() == [True, False, True, False, True]


def test_resize_on_densify_keep_mask_parents_and_append():
    f = Freezer(4, k_checks=1, motion_eps=0.1)
    f.update(torch.tensor([0.0, 1.0, 0.0, 0.0]))           # frozen: T F T T
    keep = torch.tensor([True, True, False, True])
    f.resize_on_densify(keep, 2, parent_index=torch.tensor([0, 1]))
    assert f.frozen.tolist() == [True, False, True, True, False]
    f.resize_on_densify(new_count=7)
    assert f.num_gaussians == 7 and f.frozen.tolist()[-2:] == [False, False]
    f.resize_on_densify(torch.ones(7, dtype=torch.bool), 1)
    assert f.num_gaussians == 8
    with pytest.raises(ValueError):
        f.resize_on_densify(new_count=3)
    with pytest.raises(ValueError):
        f.update(torch.zeros(3))


def test_state_dict_round_trip():
    f = Freezer(6, k_checks=2, motion_eps=0.3, wake_residual=0.4)
    f.update(torch.tensor([0, 0, 1, 0, 0, 1.0]))
    f.update(torch.tensor([0, 1, 0, 0, 0, 1.0]))
    g = Freezer.from_state_dict(f.state_dict())
    assert torch.equal(g.frozen, f.frozen) and torch.equal(g.streak, f.streak)
    assert (g.k_checks, g.motion_eps, g.wake_residual, g.checks) == (2, 0.3, 0.4, 2)
    g.update(torch.zeros(6))
    f.update(torch.zeros(6))
    assert torch.equal(g.frozen, f.frozen)


def test_deformation_motion_identity_field_is_zero_and_offset_is_measured():
    from engine.scene.deformation import DeformationField

    field = DeformationField([-1] * 3, [1] * 3, (0.0, 1.0), features=4, resolution=4, multires=(1,),
                             time_resolution=4, width=8)
    n = 5
    means = torch.rand(n, 3) - 0.5
    quats = torch.tensor([[1.0, 0, 0, 0]] * n)
    ls = torch.full((n, 3), -3.0)
    op = torch.zeros(n)
    m = deformation_motion(field, means, quats, ls, op, [0.0, 0.5, 1.0])
    assert torch.allclose(m, torch.zeros(n), atol=1e-6)
    with torch.no_grad():
        field.pos_head[-1].bias.copy_(torch.tensor([0.01, 0.0, 0.0]))   # constant shift
    m = deformation_motion(field, means, quats, ls, op, [0.3], relative="canonical")
    expect = 0.01 * field.pos_scale
    assert torch.allclose(m, torch.full((n,), expect), rtol=1e-4)
    # a time-independent offset is no motion in time
    m = deformation_motion(field, means, quats, ls, op, [0.0, 0.3, 1.0])
    assert torch.allclose(m, torch.zeros(n), atol=1e-6)
    # in pixels through a camera at distance 4 with fx 100: x fx / z
    vm = torch.eye(4)[None].clone()
    vm[0, 2, 3] = 4.0
    K = torch.tensor([[[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]])
    mp = deformation_motion(field, means, quats, ls, op, [0.3], viewmats=vm, Ks=K, relative="canonical")
    z = means[:, 2] + 4.0
    assert torch.allclose(mp, expect * 100.0 / z, rtol=1e-4)


def _moving_field(speed):
    """A stand-in field: the Gaussian with y == i moves along x at speed[i] (units per second)."""
    def field(means, quats, log_scales, opac, t):
        shift = torch.zeros_like(means)
        shift[:, 0] = speed[means[:, 1].round().long()] * t
        return {"means": means + shift, "quats": quats, "log_scales": log_scales, "opacity_logits": opac,
                "color_delta": None}
    return field


def test_deformation_motion_temporal_spread_and_bake():
    from types import SimpleNamespace

    from engine.train.skipping.freezing import bake_static

    speed = torch.tensor([0.0, 1.0, 2.0])
    field = _moving_field(speed)
    n = 3
    means = torch.zeros(n, 3)
    means[:, 1] = torch.arange(n)
    quats = torch.tensor([[1.0, 0, 0, 0]] * n)
    ls = torch.full((n, 3), -3.0)
    op = torch.zeros(n)
    m = deformation_motion(field, means, quats, ls, op, [0.0, 1.0, 2.0])
    assert torch.allclose(m, torch.tensor([0.0, 1.0, 2.0]), atol=1e-6)   # max |x(t) - mean_t x|
    g = SimpleNamespace(means=torch.nn.Parameter(means.clone()), quats=torch.nn.Parameter(quats.clone()),
                        log_scales=torch.nn.Parameter(ls.clone()), opacity_logits=torch.nn.Parameter(op.clone()))
    assert bake_static(g, field, torch.tensor([False, True, False]), [0.0, 1.0, 2.0]) == 1
    assert torch.allclose(g.means[1], torch.tensor([1.0, 1.0, 0.0]))    # the time-average position
    assert torch.allclose(g.means[0], torch.zeros(3)) and torch.allclose(g.log_scales, ls)


def test_residual_scores_projects_hot_region_to_gaussians():
    res = torch.zeros(10, 12)
    res[2:5, 3:6] = 1.0
    means2d = torch.tensor([[4.2, 3.7], [10.5, 8.5], [4.0, 3.0], [-3.0, 2.0], [float("nan"), 1.0]])
    radii = torch.tensor([2, 2, 0, 2, 2])
    s = residual_scores(res, means2d, radii)
    assert s.tolist() == [1.0, 0.0, 0.0, 0.0, 0.0]   # culled, off-image and NaN score 0
    rm = residual_map(torch.zeros(1, 4, 4, 3), torch.ones(1, 4, 4, 3), blur=1)
    assert rm.shape == (4, 4) and torch.allclose(rm, torch.ones(4, 4))


def test_abrupt_mask_only_new_motion():
    now = torch.tensor([[0.5, 0.5], [0.0, 0.5]])
    hist = [torch.tensor([[0.5, 0.0], [0.0, 0.0]])]
    assert abrupt_mask(now, hist, 0.1).tolist() == [[False, True], [False, True]]


def test_static_flicker_zero_for_constant_positive_for_noise_and_ignores_motion():
    rng = np.random.default_rng(0)
    H, W = 16, 20
    gts, steady, noisy = [], [], []
    base = rng.random((H, W, 3)).astype(np.float32)
    for t in range(5):
        g = base.copy()
        g[:, 2 * t:2 * t + 3] = 1.0 - g[:, 2 * t:2 * t + 3]   # a moving stripe
        gts.append(g)
        steady.append(g.copy())                                 # perfect renders
        noisy.append(np.clip(g + rng.normal(0, 0.02, g.shape), 0, 1).astype(np.float32))
    f0 = static_flicker(steady, gts)
    f1 = static_flicker(noisy, gts)
    assert f0["flicker"] == pytest.approx(0.0, abs=1e-7) and f0["drift"] == pytest.approx(0.0, abs=1e-7)
    assert 0.01 < f1["flicker"] < 0.05
    assert 0.3 < f0["static_fraction"] < 1.0
    assert math.isclose(f1["flicker_255"], f1["flicker"] * 255)
    with pytest.raises(ValueError):
        static_flicker(steady[:1], gts[:1])


def _fake_trainer(n=40):
    """What TrainFreezer reads from engine.train.loop.trainer.Trainer: model, static_steps, total_steps,
    frame_times and items (view tensors with a camera name)."""
    from types import SimpleNamespace

    from engine.cameras import Intrinsics, View, look_at_c2w
    from engine.scene.deformation import DeformationField
    from engine.scene.gaussians import GaussianModel
    from engine.scene.model import Model4D, view_tensors
    from engine.train.loop.schedule import Schedule

    rng = np.random.default_rng(0)
    g = GaussianModel(rng.uniform(-0.5, 0.5, (n, 3)), rng.random((n, 3)), init_opacity=0.5)
    field = DeformationField([-1] * 3, [1] * 3, (0.0, 1.0), features=4, resolution=4, multires=(1,),
                             time_resolution=4, width=8)
    model = Model4D(g, field)
    view = View(Intrinsics(32, 24, 30.0, 30.0, 16.0, 12.0), look_at_c2w((0, -4, 0), (0, 0, 0)), 0.0)
    item = view_tensors(view, "cpu")
    item["camera"] = "cam"
    item["image"] = torch.zeros(1, 24, 32, 3)
    return SimpleNamespace(model=model, static_steps=0, total_steps=100, frame_times=[0.0, 0.5, 1.0], items=[item],
                           schedule=Schedule.plan(100),
                           cfg=SimpleNamespace(schedule=SimpleNamespace(static_fraction=0.0)))


def test_train_freezer_freezes_static_field_follows_prune_wakes_and_checkpoints():
    from engine.train.skipping.freezing import TrainFreezer

    tr = _fake_trainer()
    fz = TrainFreezer(tr, k_checks=2, check_every=1, start_fraction=0.0, wake_residual=0.5)
    assert fz.schedule() == (0, 1)
    g = tr.model.gaussians

    def step(i, image=None):
        rgb, alpha, meta, attrs = tr.model.render(tr.items[0])
        item = dict(tr.items[0], image=rgb.detach() if image is None else image)
        fz.after_step(i, item, rgb, meta)
        return fz.maybe_check(i)

    assert step(0)["frozen"] == 0 and tr.model.static_mask is None   # 1 quiet check: nothing frozen yet
    step(1)
    assert tr.model.static_mask is not None and bool(tr.model.static_mask.all())  # identity field: all static
    assert fz.summary()["fraction_frozen"] == 1.0 and fz.summary()["checks"] == 2
    keep = torch.arange(g.num_gaussians) >= 5
    g.prune(~keep)                                                   # densification bookkeeping
    fz.follow(keep, 0)
    assert fz.freezer.num_gaussians == g.num_gaussians == 35
    assert tr.model.static_mask.shape[0] == 35
    state = fz.state_dict()
    # a frame whose residual is high everywhere wakes every visible frozen Gaussian
    rgb, alpha, meta, attrs = tr.model.render(tr.items[0])
    fz.after_step(2, dict(tr.items[0], image=torch.ones(1, 24, 32, 3)), rgb, meta)
    assert fz.woken > 0 and fz.freezer.total_woken == fz.woken
    assert tr.model.static_mask is None or int(tr.model.static_mask.sum()) < 35
    # the checkpointed state restores the frozen set
    other = TrainFreezer(tr, k_checks=2, check_every=1, start_fraction=0.0)
    other.load_state_dict(state)
    other.sync_mask()
    assert other.freezer.num_frozen == 35 and other.summary()["checks"] == 2
    assert bool(tr.model.static_mask.all())
