"""Quiet curves (engine.train.guidance.quiet_curves): no in-between bend where the spike view saw no change."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from engine.scene.model import TRAJ_MEANS, TRAJ_QUATS
from engine.spike.change import SpikeChange
from engine.train.config import get_preset
from engine.train.guidance.quiet_curves import inner_keep, quiet_segments, zero_inner

W, H = 16, 8  # spike view (px); 4 x 2 change blocks of 4 px


def _change(changed_blocks):
    """A SpikeChange with 2 intervals; ``changed_blocks`` [(interval, block row, block col)]."""
    changed = np.zeros((2, H // 4, W // 4), bool)
    for k, r, c in changed_blocks:
        changed[k, r, c] = True
    return SpikeChange(statistic=changed.astype(np.float32), changed=changed, threshold=0.5, sigma=0.1,
                       block=4, shape=(H, W))


def _points_at(px):
    """World points 2 m in front of an identity camera (K: f = 10, centre (8, 4)) at pixels ``px``."""
    K = torch.tensor([[10.0, 0, W / 2], [0, 10.0, H / 2], [0, 0, 1]])
    uv = torch.as_tensor(px, dtype=torch.float32)
    z = 2.0
    pts = torch.stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z,
                       torch.full((len(uv),), z)], -1)
    return pts, K


def test_quiet_segments_follow_the_change_map_per_interval():
    # block (row 0, col 3) = pixels x 12..16, y 0..4 changed in interval 1 only
    ch = _change([(1, 0, 3)])
    pts, K = _points_at([[2.0, 6.0], [14.0, 2.0], [30.0, 2.0]])  # quiet corner, the changing block, outside
    pts = torch.cat([pts, torch.tensor([[0.0, 0.0, -1.0]])])  # behind the camera
    junctions = torch.zeros(4, 3, 3)  # F = 3 instants: 2 segments, nothing moves at the junctions
    q = quiet_segments(pts, junctions, ch, [0, 1], torch.eye(4), K, W, H, dilate=0)
    assert q.shape == (4, 2)
    assert q[0].tolist() == [True, True]  # never near a change
    assert q[1].tolist() == [True, False]  # changes in interval 1 only
    assert q[2].tolist() == [False, False] and q[3].tolist() == [False, False]  # the spike view cannot say
    # dilation reaches the neighbouring block (pixel x 10 is in block col 2, next to col 3)
    near, _ = _points_at([[10.0, 2.0]])
    assert quiet_segments(near, torch.zeros(1, 3, 3), ch, [0, 1], torch.eye(4), K, W, H, dilate=0)[0, 1]
    assert not quiet_segments(near, torch.zeros(1, 3, 3), ch, [0, 1], torch.eye(4), K, W, H, dilate=1)[0, 1]
    # a segment whose end moves onto the changing block is not quiet; one not covered by spikes never is
    moved = torch.zeros(1, 3, 3)
    moved[0, 1] = pts[1] - pts[0]  # at the middle instant the Gaussian sits on the changing block
    still = torch.zeros(1, 3, 3)
    assert quiet_segments(pts[:1], still, ch, [1, None], torch.eye(4), K, W, H, dilate=0)[0].tolist() == [True, False]
    assert quiet_segments(pts[:1], moved, ch, [1, None], torch.eye(4), K, W, H, dilate=0)[0].tolist() == [False, False]


def test_zero_inner_clears_only_the_quiet_segments_inner_points():
    p = torch.randn(3, 7, 3)  # F = 3 knots: K = 7 columns, inner 1, 2 (segment 0) and 4, 5 (segment 1)
    before = p.clone()
    quiet = torch.tensor([[True, False], [False, True], [False, False]])
    zero_inner(p, quiet)
    assert (p[0, 1:3] == 0).all() and torch.equal(p[0, 3:], before[0, 3:]) and torch.equal(p[0, 0], before[0, 0])
    assert (p[1, 4:6] == 0).all() and torch.equal(p[1, :4], before[1, :4]) and torch.equal(p[1, 6], before[1, 6])
    assert torch.equal(p[2], before[2])
    again = before.clone()
    zero_inner(again, quiet, inner_keep(quiet, 3))  # the hook's prebuilt, per-channel mask: the same
    assert torch.equal(again, p) and inner_keep(quiet, 4).shape == (3, 7, 4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_quiet_columns_kernel_equals_the_mask_multiply(dtype, monkeypatch):
    """The in-place kernel gives the mask multiply's numbers bit for bit (the sign of a zeroed
    negative entry included), over every column or a step's few, without building the mask."""
    from engine.train.guidance import quiet_curves as qc

    gen = torch.Generator().manual_seed(3)
    n, f = 50, 6
    quiet = torch.rand(n, f - 1, generator=gen) > 0.5
    base = torch.randn(n, 3 * (f - 1) + 1, 4, generator=gen, dtype=dtype)
    for cols in (None, np.array([0, 1, 5, 7, 8, 15]), np.array([3, 6])):
        want = base.clone()
        monkeypatch.setattr(qc, "FUSED", False)
        keeps = {}
        qc.zero_quiet_columns(want, quiet, cols, keeps)
        assert set(keeps) == {4}  # the fallback builds (and keeps) the mask
        if cols is None:
            assert torch.equal(want, base * inner_keep(quiet, 4).to(dtype))
        monkeypatch.setattr(qc, "FUSED", True)
        monkeypatch.setattr(qc, "MASK_MAX_BYTES", 0)  # a large curve: the kernels for every column too
        got, keeps = base.clone(), {}
        qc.zero_quiet_columns(got, quiet, cols, keeps)
        assert keeps == {}  # no mask built
        assert torch.equal(got.view(-1).view(torch.int64 if dtype == torch.float64 else torch.int32),
                           want.view(-1).view(torch.int64 if dtype == torch.float64 else torch.int32))
        assert not torch.equal(got, base) or cols is not None
        monkeypatch.setattr(qc, "MASK_MAX_BYTES", 32 << 20)  # a small curve, every column: the mask
        small, keeps = base.clone(), {}
        qc.zero_quiet_columns(small, quiet, cols, keeps)
        assert torch.equal(small, want) and (set(keeps) == {4}) == (cols is None)


_TINY = {"iterations": 12, "static_fraction": 0.25, "init_max_points": 300, "init_random_points": 100,
         "densify_from": 2.0, "densify_until": 2.0, "between_colocated_p": 1.0, "time_curriculum": 0.0,
         "spike_skip_static": False, "traj_carry": "velocity", "birth_error": 0.0}


def _inner_norms(tr):
    p = getattr(tr.model.gaussians, TRAJ_MEANS).detach()
    inner = torch.stack([p[:, 3 * k + 1:3 * k + 3] for k in range((p.shape[1] - 1) // 3)], 1)  # [N, F-1, 2, 3]
    return inner.norm(dim=-1).amax(-1)  # [N, F-1]


@pytest.mark.slow
def test_trainer_holds_quiet_curves_and_only_those(demo_capture):
    """Real guided steps on the demo capture: with the switch, the segments the hook calls quiet
    have zero inner residuals (positions and rotations) while others still bend; without it, the
    spike terms bend quiet segments too (what the switch exists to stop)."""
    from engine.io.capture import load_capture
    from engine.train.loop.trainer import Trainer

    runs = {}
    for on in (True, False):
        tr = Trainer(load_capture(demo_capture), get_preset("fast", {**_TINY, "quiet_curves": on}), device="cpu")
        assert hasattr(tr, "quiet_curves") == on
        tr.init_model()
        for step in range(_TINY["iterations"]):
            tr.step(step)
        runs[on] = tr
    on, off = runs[True], runs[False]
    used = on.quiet_curves._mask[2]  # the mask the last step's hook applied
    assert 0.05 < float(used.float().mean()) < 0.95  # the demo's spike view: mostly still, not all
    inner = _inner_norms(on)
    assert float(inner[used].max()) == 0.0
    q = getattr(on.model.gaussians, TRAJ_QUATS).detach()
    for k in range(used.shape[1]):
        assert (q[used[:, k], 3 * k + 1:3 * k + 3] == 0).all()
    assert float(inner[~used].max()) > 0.0  # where the spike view changed, curves bend
    # a copy of the model (the budget probe's) gets its own mask, not the run's cached one
    import copy

    probe = copy.deepcopy(on.model)
    on.quiet_curves.mask(probe, _TINY["iterations"] - 1)
    assert on.quiet_curves._mask[4] == id(getattr(probe.gaussians, TRAJ_MEANS))
    # without the switch the spike terms bend segments that the hook would have held
    off_quiet = on.quiet_curves.mask(off.model, 10 ** 6)
    assert float(_inner_norms(off)[off_quiet].max()) > 0.0


@pytest.mark.parametrize("refresh", [10, 50])
def test_quiet_mask_is_reused_for_the_configured_steps(refresh, monkeypatch):
    """``REFRESH``: the hook recomputes its mask (projections + change-map lookups,
    ~14 ms at 23k Gaussians) only after that many steps, when the Gaussian count changes, or
    for another curves tensor; in between every step applies the cached one."""
    import types

    from train_util import trajectory_model

    from engine.train.guidance import quiet_curves as qc

    calls = []
    real = qc.quiet_segments

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(qc, "quiet_segments", counting)
    pts, K = _points_at([[2, 2], [14, 6]])
    stream = types.SimpleNamespace(view=lambda t: types.SimpleNamespace(viewmat=np.eye(4)), width=W, height=H,
                                   intrinsics=types.SimpleNamespace(K=K.numpy()))
    monkeypatch.setattr(qc, "REFRESH", refresh)
    from train_util import fake_run

    tr = fake_run()
    hook = qc.QuietCurves(tr, stream, _change([(0, 0, 0)]), [0.0, 0.1, 0.2])
    m = trajectory_model([0.0, 0.1, 0.2], n=2)
    with torch.no_grad():
        m.gaussians.means.copy_(pts)
    first = hook.mask(m, 100)
    assert first.shape == (2, 2) and len(calls) == 1
    assert bool(first[1, 0]) and not bool(first[0, 0])  # interval 0 changed under the first point only
    assert hook.mask(m, 100 + refresh - 1) is first and len(calls) == 1
    hook.mask(m, 100 + refresh)
    assert len(calls) == 2


def test_switch_is_a_config_field_and_needs_the_spike_guidance():

    from engine.train.guidance import quiet_curves as qc
    from engine.train.guidance.quiet_curves import quiet_curves_factory

    assert get_preset("fast").spike.quiet_curves and qc.DILATE == 1  # on, one block of dilation
    cfg = get_preset("fast", {"quiet_curves": True})
    from train_util import fake_run

    tr = fake_run(cfg)
    assert quiet_curves_factory(tr) == [] and tr.post_step_hooks == []  # rgb_only / no spikes: nothing
    tr.cfg = get_preset("fast", {"quiet_curves": True, "motion": "hexplane"})
    tr.parts["spike_guidance"] = object()
    assert quiet_curves_factory(tr) == [] and tr.post_step_hooks == []  # curves only


@pytest.mark.slow
def test_a_finished_run_keeps_no_rotation_bend_and_a_cancelled_one_does(demo_capture, tmp_path):
    """Through ``train``: the spike terms bend rotation curves during training; a finished run's
    result has every rotation curve's inner points at zero (run.json counts them) and no position
    bend smaller than its Gaussian's largest axis, while larger position bends stay; a cancelled
    run's checkpoint, what a resume starts from, keeps them all."""
    import json
    import threading

    from engine.scene.model import load_run
    from engine.train import train

    def curves(run):
        g = load_run(run).model.gaussians
        return getattr(g, TRAJ_MEANS).detach(), getattr(g, TRAJ_QUATS).detach()

    def bends(run):  # [N, segments]: each segment's largest position bend, and [N] largest axes
        g = load_run(run).model.gaussians
        p = getattr(g, TRAJ_MEANS).detach()
        segs = (p.shape[1] - 1) // 3
        return p[:, :3 * segs].reshape(p.shape[0], segs, 3, 3)[:, :, 1:].norm(dim=-1).amax(-1), \
            g.log_scales.detach().exp().amax(-1)

    over = {**_TINY, "iterations": 12}
    assert train(demo_capture, tmp_path / "done", preset="fast", overrides=over, resume=False)["status"] == "finished"
    p, q = curves(tmp_path / "done")
    assert q.shape[1] > 3 and not q[:, 1::3].any() and not q[:, 2::3].any() and q[:, 0::3].any()
    assert p[:, 1::3].any()  # where the spike view changed, positions still bend
    bend, size = bends(tmp_path / "done")
    assert ((bend == 0) | (bend >= size[:, None])).all()
    info = json.loads((tmp_path / "done" / "run.json").read_text())["quiet_curves"]
    assert info["rotation_bends_flattened"] > 0 and info["small_bends_flattened"] > 0
    assert info["position_bends_kept"] == int((bend > 0).sum()) > 0

    cancel = threading.Event()

    def progress(p):
        if p["step"] >= over["iterations"] - 1:
            cancel.set()
    s = train(demo_capture, tmp_path / "cut", preset="fast", overrides=over, resume=False, progress=progress,
              cancel=cancel)
    assert s["status"] == "cancelled"
    _, q = curves(tmp_path / "cut")
    assert q[:, 1::3].any() or q[:, 2::3].any()
    bend, size = bends(tmp_path / "cut")
    assert ((bend > 0) & (bend < size[:, None])).any()
    assert "quiet_curves" not in json.loads((tmp_path / "cut" / "run.json").read_text())


@pytest.mark.slow
def test_between_frame_renders_leave_still_gaussians_alone(demo_capture, monkeypatch):
    """A real between-frame render of a guided demo run: the Gaussians the spike view saw still over
    the render's interval (quiet there) get no gradient from it, in any attribute; the others do (into
    their size, not the ratios of their scales).
    Without the rule the still ones get one too (the spike loss repainted them: issue 47)."""
    from engine.io.capture import load_capture
    from engine.train.guidance.spike_guidance import SpikeGuidance
    from engine.train.loop.trainer import Trainer
    from engine.train.losses.terms import StepContext

    tr = Trainer(load_capture(demo_capture), get_preset("fast", _TINY), device="cpu")
    tr.init_model()
    for step in range(_TINY["iterations"]):
        tr.step(step)
    g, step = tr.model.gaussians, _TINY["iterations"]

    def between_grads():
        ctx = StepContext(tr.run, step, "deform", tr.items[0], None, None, {}, {})
        b = tr.spike_guidance.between(ctx)
        assert b is not None and b["camera"] == tr.spike_guidance.colocated
        g.optimizer.zero_grad(set_to_none=True)
        b["rgb"].sum().backward()
        still = tr.quiet_curves.still_at(tr.model, b["instant"].time)
        grads = torch.cat([p.grad.reshape(p.shape[0], -1).abs() for p in (g.means, g.sh_dc, g.opacity_logits,
                                                                         g.log_scales, g.quats)], 1).amax(1)
        # a size, not a shape: a row's three log-scales get one gradient (BETWEEN_GRAD_ATTRS)
        ls = g.log_scales.grad
        assert torch.allclose(ls[:, 0], ls[:, 1], rtol=1e-5, atol=1e-12) and bool((ls != 0).any())
        assert torch.allclose(ls[:, 1], ls[:, 2], rtol=1e-5, atol=1e-12)
        return still, grads

    still, grads = between_grads()
    assert 0.05 < float(still.float().mean()) < 0.95
    assert float(grads[still].max()) == 0.0
    assert int((grads[~still] > 0).sum()) > 0
    # right after the count changed the run's mask no longer fits: the render computes its own and
    # leaves the run's to the hook (which zeroes what it calls quiet before a render reads it)
    stale = tr.quiet_curves._mask = (0, -1, torch.zeros(0, 0, dtype=torch.bool), {}, 0)
    t = 0.5 * sum(tr.model.trajectory["knots"][:2])
    fresh = tr.quiet_curves.still_at(tr.model, t)
    assert tr.quiet_curves._mask is stale
    assert torch.equal(fresh, tr.quiet_curves.mask(tr.model, step)[:, 0])
    monkeypatch.setattr(SpikeGuidance, "trainable_between", staticmethod(lambda ctx, t: None))
    still, grads = between_grads()
    assert int((grads[still] > 0).sum()) > 0
