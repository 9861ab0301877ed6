"""Spike-view optical-flow supervision (issue 11, engine.train.guidance.spike_flow): the flow's sign and
pixel convention, the loss bending a curve toward a known displacement, the switch, the cache."""
from __future__ import annotations

import types

import numpy as np
import pytest
import torch
from train_util import fake_run, patch_constants, term_values, trajectory_model

from engine.scene.model import TRAJ_MEANS
from engine.train.config import get_preset
from engine.train.guidance.spike_flow import (
    SpikeFlowSupervision,
    flow_pair,
    inner_only_positions,
    lift,
    project,
    projected_flow_loss,
    sample_map,
    spike_flow_factory,
)


def _texture(h=60, w=80, seed=0):
    """A smooth random texture (blobs a few pixels wide), linear luminance in [0.05, 1]."""
    import cv2

    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(size=(h + 40, w + 40)).astype(np.float32), (0, 0), 1.5)
    img = (img - img.min()) / (img.max() - img.min())
    return 0.05 + 0.95 * img


def test_flow_sign_and_convention_on_a_translated_image():
    """b(p) = a(p - d): the flow a -> b is +d (x, y), so a(p) = b(p + flow(p))."""
    big = _texture(100, 120)
    dx, dy = 2, 1
    a = big[20:80, 20:100]
    b = big[20 - dy:80 - dy, 20 - dx:100 - dx]  # content moved right by dx, down by dy
    flow, valid = flow_pair(a, b)
    assert flow.shape == (60, 80, 2) and valid.shape == (60, 80)
    inner = valid[8:-8, 8:-8]
    assert inner.mean() > 0.8  # forward and backward agree on a clean translation
    med = np.median(flow[8:-8, 8:-8][inner], axis=0)
    assert abs(med[0] - dx) < 0.25 and abs(med[1] - dy) < 0.25
    # and the backward direction is the opposite
    back, _ = flow_pair(b, a)
    assert np.allclose(np.median(back[8:-8, 8:-8].reshape(-1, 2), axis=0), [-dx, -dy], atol=0.25)


def test_forward_backward_check_drops_disagreeing_pixels():
    a = _texture()
    b = _texture(seed=1)  # unrelated content: no consistent motion
    _, valid = flow_pair(a, a)
    assert valid.mean() > 0.95  # identical images: zero flow both ways
    _, valid = flow_pair(a, b)
    assert valid.mean() < 0.8


def test_sample_map_uses_pixel_centres():
    img = torch.arange(12, dtype=torch.float32).reshape(3, 4, 1)
    uv = torch.tensor([[0.5, 0.5], [3.5, 2.5], [1.5, 1.5], [2.0, 1.5]])
    out = sample_map(img, uv)[:, 0]
    assert torch.allclose(out, torch.tensor([0.0, 11.0, 5.0, 5.5]), atol=1e-5)


KNOTS = [0.0, 0.1, 0.2, 0.3]
VIEWMAT = torch.eye(4)
K = torch.tensor([[80.0, 0.0, 40.0], [0.0, 80.0, 30.0], [0.0, 0.0, 1.0]])


def _traj_model(n=8, seed=0):
    return trajectory_model(KNOTS, n, seed, spread=0.1, centre=(0.0, 0.0, 2.0))


def test_loss_bends_the_curve_toward_a_known_displacement():
    """Gaussians at rest at every RGB instant; the 'flow' says they moved +3 px in x at t=0.15
    (reference 0.1). Descending the loss on the inner control points alone moves their
    projection there, and leaves the junctions (what the RGB frames saw) untouched."""
    m = _traj_model()
    idx = torch.arange(m.gaussians.num_gaussians)
    params = getattr(m.gaussians, TRAJ_MEANS)
    t_ref, t = 0.1, 0.15
    with torch.no_grad():
        uv_ref, _ = project(inner_only_positions(m, t_ref, idx), VIEWMAT, K)
    target = uv_ref + torch.tensor([3.0, 0.0])
    opt = torch.optim.Adam([params], lr=2e-3)
    junctions0 = params.detach()[:, 0::3].clone()
    first = None
    for _ in range(300):
        opt.zero_grad()
        uv_t, _ = project(inner_only_positions(m, t, idx), VIEWMAT, K)
        loss = projected_flow_loss(uv_t, target, beta=1.0)
        first = float(loss.detach()) if first is None else first
        loss.backward()
        assert torch.all(params.grad[:, 0::3] == 0)  # junctions get no gradient
        opt.step()
    with torch.no_grad():
        uv_t, _ = project(inner_only_positions(m, t, idx), VIEWMAT, K)
    assert first > 1.0
    err = (uv_t - target).norm(dim=1)
    assert float(err.max()) < 0.3, err
    assert torch.equal(params.detach()[:, 0::3], junctions0)
    # the curve passes through its (unchanged) junctions at the RGB instants
    with torch.no_grad():
        assert torch.allclose(project(inner_only_positions(m, t_ref, idx), VIEWMAT, K)[0], uv_ref, atol=1e-4)


def _inner_only_positions_gather(model, t, idx):
    """The former form: gather the rows, detach the junctions with a mask, evaluate."""
    from engine.scene import trajectory as traj

    params = getattr(model.gaussians, TRAJ_MEANS)[idx]
    inner = torch.ones(params.shape[1], dtype=torch.bool)
    inner[0::3] = False
    params = torch.where(inner[None, :, None], params, params.detach())
    return model.gaussians.means.detach()[idx] + traj.evaluate(params, model.trajectory["knots"], t)


def test_inner_only_positions_equal_the_gather_form_bit_for_bit():
    """Value and gradient (into the inner columns of the subset's rows only) as the gather +
    mask + evaluate form, at and between the knots, for a random distinct subset."""
    m = _traj_model()
    params = getattr(m.gaussians, TRAJ_MEANS)
    with torch.no_grad():
        params.normal_(0.0, 0.01, generator=torch.Generator().manual_seed(5))
    n = m.gaussians.num_gaussians
    idx = torch.randperm(n, generator=torch.Generator().manual_seed(6))[: max(1, n // 2)]
    w = torch.randn(idx.numel(), 3, generator=torch.Generator().manual_seed(7))
    knots = m.trajectory["knots"]
    for t in (knots[0], 0.5 * (knots[0] + knots[1]), knots[1], 0.3 * knots[1] + 0.7 * knots[-1], knots[-1]):
        out = []
        for fn in (_inner_only_positions_gather, inner_only_positions):
            params.grad = None
            x = fn(m, t, idx)
            (x * w).sum().backward()
            out.append((x.detach(), params.grad.clone()))
        assert torch.equal(out[0][0], out[1][0]) and torch.equal(out[0][1], out[1][1])
        rows = torch.zeros(n, dtype=torch.bool)
        rows[idx] = True
        assert torch.all(out[1][1][~rows] == 0) and torch.all(out[1][1][:, 0::3] == 0)
        assert m.gaussians.means.grad is None


def test_loss_gradient_is_in_the_image_plane():
    """The projection's gradient has no component along the viewing ray."""
    m = _traj_model()
    idx = torch.arange(m.gaussians.num_gaussians)
    params = getattr(m.gaussians, TRAJ_MEANS)
    uv_t, _ = project(inner_only_positions(m, 0.15, idx), VIEWMAT, K)
    projected_flow_loss(uv_t, uv_t.detach() + torch.tensor([2.0, -1.0])).backward()
    x = m.gaussians.means.detach()
    ray = x / x.norm(dim=1, keepdim=True)  # camera at the origin (identity viewmat)
    g = params.grad[:, 4]
    assert float((g * ray).sum(1).abs().max()) < 1e-6 * float(g.norm(dim=1).max()) + 1e-9


_MP = []  # this test's monkeypatch (the autouse fixture below): constants patched for its duration


@pytest.fixture(autouse=True)
def _monkeypatch_for_helpers(monkeypatch):
    _MP[:] = [monkeypatch]
    yield
    _MP.clear()


def _bare_supervision(**over) -> SpikeFlowSupervision:
    """The term on a fake 80 x 60 spike stream at the identity pose, RGB instants KNOTS; ``over``
    may name the flow's constants by their old setting names (train_util.CONSTANTS)."""
    cfg = get_preset("fast", {"spike_flow_weight": 1.0, **patch_constants(_MP[0], over)})
    view = types.SimpleNamespace(viewmat=np.eye(4), K=K.numpy(), center=np.zeros(3))
    stream = types.SimpleNamespace(t0=0.0, rate_hz=20000.0, width=80, height=60, view=lambda t: view)
    return SpikeFlowSupervision(fake_run(cfg, frame_times=KNOTS),
                                types.SimpleNamespace(stream=stream, sensor=None))


def _fake_supervision(steps=3, **over):
    sup = _bare_supervision(spike_flow_steps=steps, **over)
    calls = []

    def estimate(t_ref, t, init=None):
        calls.append((t_ref, t))
        sup.inits.append(None if init is None else (float(init[0][0, 0, 0]), float(init[1][0, 0, 0])))
        fw = np.full((60, 80, 2), t - t_ref, np.float32)
        return fw, np.ones((60, 80), bool), -fw

    sup.inits = []

    sup.estimate = estimate
    return sup, calls


def test_instants_quantise_and_use_the_nearer_admitted_rgb_instant():
    sup, _ = _fake_supervision(steps=3)  # grid 0.125, 0.15, 0.175 inside [0.1, 0.2]
    ref, tq = sup.instants(0.1801, admitted=0.3)
    assert ref == 0.2 and abs(tq - 0.175) < 1e-12
    ref, tq = sup.instants(0.1801, admitted=0.19)  # 0.2 not admitted yet: the left end
    assert ref == 0.1 and abs(tq - 0.175) < 1e-12
    ref, tq = sup.instants(0.101, admitted=0.3)  # never the RGB instant itself
    assert ref == 0.1 and abs(tq - 0.125) < 1e-12
    assert sup.instants(0.05, admitted=0.0)[0] == 0.0
    assert sup.instants(0.35, admitted=0.3) is None


def test_flow_cache_computes_each_pair_once():
    sup, calls = _fake_supervision(spike_flow_warm=False)
    f1, v1 = sup.flow(0.1, 0.125)
    f2, _ = sup.flow(0.1, 0.125 + 1e-6)  # the same spike frame
    assert len(calls) == 1 and f1 is f2
    assert f1.shape == (60, 80, 2) and v1.shape == (60, 80, 1)
    sup.flow(0.2, 0.125)
    assert len(calls) == 2 and sup.inits == [None, None]


def test_warm_flows_start_from_the_grid_instant_one_step_closer():
    """spike_flow_warm: the flow from an RGB instant to a grid instant starts from the (forward,
    backward) pair to the grid instant one step closer to that RGB instant, computed first and
    once; only chain ends with a successor are kept (grid 0.125, 0.15, 0.175 in [0.1, 0.2])."""
    sup, calls = _fake_supervision()
    assert get_preset("fast").spike_flow.warm  # on by default
    sup.flow(0.2, 0.125)  # back from 0.2: 0.175 from zero, then 0.15, then 0.125
    assert [round(t, 6) for _, t in calls] == [0.175, 0.15, 0.125]
    assert sup.inits[0] is None
    assert np.allclose(sup.inits[1], (-0.025, 0.025)) and np.allclose(sup.inits[2], (-0.05, 0.05))
    assert not sup._warm  # 0.125 is the last step from 0.2: nothing left to start from it
    sup.flow(0.1, 0.15)  # ahead from 0.1: 0.125, then 0.15, which 0.175 will start from
    assert [round(t, 6) for _, t in calls[3:]] == [0.125, 0.15] and sup.inits[3] is None
    assert len(sup._warm) == 1
    sup.flow(0.2, 0.15)  # cached: nothing computed
    sup.flow(0.1, 0.175)
    assert len(calls) == 6 and np.allclose(sup.inits[5], (0.05, -0.05)) and not sup._warm
    sup.flow(0.1, 0.16)  # off the grid: from zero, alone
    assert len(calls) == 7 and sup.inits[6] is None


def test_switch_off_builds_no_term():
    cfg = get_preset("fast", {"spike_flow_weight": 0.0})
    assert get_preset("fast").spike_flow.weight == 1.0  # on by default
    stream = types.SimpleNamespace(c2w=np.eye(4), intrinsics=object())
    guid = types.SimpleNamespace(renderer=object(), stream=stream)
    tr = fake_run(cfg, parts={"spike_guidance": guid})
    assert spike_flow_factory(tr) == [] and tr.part("spike_flow") is None
    tr.cfg = get_preset("fast", {"spike_flow_weight": 1.0, "motion": "hexplane"})
    assert spike_flow_factory(tr) == []  # curves only
    tr.cfg = get_preset("fast", {"spike_flow_weight": 1.0, "spike_loss_weight": 0.0})
    assert spike_flow_factory(tr) == []  # rides on the spike loss's instants
    tr.parts["spike_guidance"] = None
    tr.cfg = get_preset("fast", {"spike_flow_weight": 1.0})
    assert spike_flow_factory(tr) == []  # rgb_only / no spike stream: no guidance


_TINY = {"iterations": 8, "static_fraction": 0.25, "init_max_points": 300, "init_random_points": 100,
         "densify_from": 2.0, "densify_until": 2.0, "between_colocated_p": 1.0, "time_curriculum": 0.0,
         "spike_skip_static": False, "traj_carry": "velocity", "spike_flow_weight": 1.0}


@pytest.mark.slow
def test_trainer_steps_with_the_flow_term(demo_capture):
    """Inside real guided steps on the demo capture: finite values, surface Gaussians found,
    and only the curves' inner control points get the term's gradient."""
    from engine.io.capture import load_capture
    from engine.train.loop.trainer import Trainer

    tr = Trainer(load_capture(demo_capture), get_preset("fast", _TINY), device="cpu")
    assert "spike_flow" in {t.name for t in tr.loss_terms}
    tr.init_model()
    seen = term_values(tr, "spike_flow", steps=8)
    assert seen and all(np.isfinite(v) and v >= 0 for v in seen)
    assert tr.spike_flow.last["gaussians"] > 0 and tr.spike_flow._flows
    off = Trainer(load_capture(demo_capture), get_preset("fast", {**_TINY, "spike_flow_weight": 0.0}), device="cpu")
    assert "spike_flow" not in {t.name for t in off.loss_terms}


@pytest.mark.slow
def test_run_records_the_interval_fits_and_junction_moves(demo_capture, tmp_path):
    """A real run on the demo capture: every interval fit (with ``spike_flow_junctions``, on by
    default) is recorded in run.json's ``spike_flow_fits`` with what it moved."""
    import json

    from engine.train import train

    assert get_preset("fast").spike_flow.junctions == "all"
    summary = train(demo_capture, tmp_path / "run", preset="fast", overrides={**_TINY, "iterations": 12},
                    resume=False)
    assert summary["status"] == "finished"
    fits = json.loads((tmp_path / "run" / "run.json").read_text())["spike_flow_fits"]
    assert fits and all("junctions_ahead" in f and "junctions_back" in f for f in fits)
    assert all(f["junctions_ahead"]["moved"] <= f["junctions_ahead"]["surface"] for f in fits)


def test_fit_inner_residuals_recovers_a_bump():
    """Curves at rest at both ends; targets = a known bump a(u) D0 + b(u) D1: the least-squares
    change is D (up to the small ridge), and unobserved curves (weight 0) do not move."""
    from engine.train.guidance.spike_flow import fit_inner_residuals, segment_basis

    u = torch.arange(1, 16, dtype=torch.float32) / 16
    D = torch.tensor([[[0.02, -0.01, 0.0], [0.03, 0.0, 0.01]], [[-0.05, 0.02, 0.0], [-0.04, 0.02, 0.0]],
                      [[0.01, 0.01, 0.01], [0.01, 0.01, 0.01]]])
    B = segment_basis(u)
    cur = torch.zeros(15, 3, 3)
    tgt = torch.einsum("ja,mac->jmc", B, D)
    w = torch.ones(15, 3)
    w[:, 2] = 0.0
    dD = fit_inner_residuals(cur, tgt, w, u, ridge=1e-6)
    assert torch.allclose(dD[:2], D[:2], atol=1e-4)
    assert torch.allclose(dD[2], torch.zeros(2, 3))


def test_lift_inverts_project():
    vm = torch.tensor([[1.0, 0.0, 0.0, 0.1], [0.0, 0.0, -1.0, 0.2], [0.0, 1.0, 0.0, 1.5], [0.0, 0.0, 0.0, 1.0]])
    x = torch.tensor([[0.1, 0.3, -0.2], [-0.4, 1.0, 0.5]])

    uv, z = project(x, vm, K)
    assert torch.allclose(lift(uv, z, vm, K), x, atol=1e-5)


@pytest.mark.parametrize("every", [10, 30])
def test_surface_is_found_and_reused_for_a_few_steps(every):
    """A toy model in front of the fake spike camera: surface() finds Gaussians the render sees;
    cached_surface() renders again only after ``spike_flow_surface_every`` steps or when the
    count changes, and re-projects the cached Gaussians' pixels every call."""
    sup, _ = _fake_supervision(spike_flow_surface_every=every)
    m = _traj_model(n=30)
    renders = []
    real = sup.surface

    def counting(model, t_ref):
        renders.append(t_ref)
        return real(model, t_ref)

    sup.surface = counting
    idx, uv = sup.cached_surface(m, 0.1, step=100)
    assert idx.numel() > 0 and uv.shape == (idx.numel(), 2)
    assert bool(((uv[:, 0] >= 0) & (uv[:, 0] < 80) & (uv[:, 1] >= 0) & (uv[:, 1] < 60)).all())
    with torch.no_grad():  # move the curves: the cached set is re-projected, not re-rendered
        getattr(m.gaussians, TRAJ_MEANS)[:, 3] += torch.tensor([0.01, 0.0, 0.0])
    idx2, uv2 = sup.cached_surface(m, 0.1, step=105)
    assert len(renders) == 1 and torch.equal(idx, idx2)
    assert torch.allclose(uv2[:, 0] - uv[:, 0], 80.0 * 0.01 / project(m.gaussians.means.detach()[idx]
                                                                        + torch.tensor([0.01, 0.0, 0.0]),
                                                                        VIEWMAT, K)[1], atol=1e-3)
    sup.cached_surface(m, 0.1, step=100 + every - 1)
    assert len(renders) == 1
    sup.cached_surface(m, 0.1, step=100 + every)
    assert len(renders) == 2
    sup.cached_surface(m, 0.2, step=111)  # another RGB instant: its own set
    assert len(renders) == 3


def _dis_spy(monkeypatch, **over):
    """A supervision with blank grey images whose flow pairs are recorded (their keyword
    arguments) instead of computed: (supervision, list of kwargs dicts)."""
    from engine.train.guidance import spike_flow_cache as sfc

    sup = _bare_supervision(**over)
    seen = []

    def pair(a, b, init, **kw):
        seen.append(kw)
        z = np.zeros(a.shape + (2,), np.float32)
        return z, z, np.ones(a.shape, bool)

    monkeypatch.setattr(sfc, "warm_flow_pair", pair)
    sup.gray = lambda t: np.zeros((60, 80), np.float32)
    return sup, seen


@pytest.mark.parametrize("upsample", [1, 2])
def test_estimate_runs_dis_at_the_configured_upsampling(upsample, monkeypatch):
    """``spike_flow_upsample`` reaches the flow pair (DIS on the grey images upsampled that many
    times): the term's flows are the ones docs/experiments/spike-flow.md's EPE figures measured."""
    sup, seen = _dis_spy(monkeypatch, spike_flow_upsample=upsample, spike_flow_prefetch=0)
    sup.estimate(0.1, 0.15)
    assert [kw["upsample"] for kw in seen] == [upsample]


@pytest.mark.slow
def test_budget_probe_neither_fits_nor_takes_the_runs_fits(demo_capture, monkeypatch):
    """``measure_step_seconds`` runs guided steps on a copy that shares this term: it must not
    fit (a fit costs ~1 s and made a 120 s run plan 186 steps) nor leave intervals marked as
    fitted (the real run then never fitted them: curves 3x off in the image plane)."""
    from engine.io.capture import load_capture
    from engine.train.guidance.spike_flow import SpikeFlowSupervision
    from engine.train.loop.budget import measure_step_seconds
    from engine.train.loop.trainer import Trainer

    tr = Trainer(load_capture(demo_capture), get_preset("fast", _TINY), device="cpu")
    tr.init_model()
    calls = []
    monkeypatch.setattr(SpikeFlowSupervision, "fit_interval", lambda self, *a, **k: calls.append(a) or {})
    tr.spike_flow.fitted[0] = {"fitted": 1}  # a real fit from before stays
    measure_step_seconds(tr, n_static=1, n_deform=3)
    assert calls == [] and tr.spike_flow.fitted == {0: {"fitted": 1}}
    term_values(tr, "spike_flow", steps=8)  # the real run still fits what the probe saw
    assert calls


def test_flow_junctions_take_the_other_end_from_the_flow():
    """spike_flow_junctions: the visible Gaussians at one end of an interval get their place at
    the other end from the spike flow (here 4 px in x over the interval: the flow to the cached
    instant nearest the other end, extended to it, lifted at the Gaussian's depth), held beyond
    it; ``born_only``: only those born at that end; others keep their curves."""
    from engine.scene.model import TIME_CENTER, TIME_LOG_SCALE
    from engine.train.motion.births import ensure_temporal_opacity

    sup, _ = _fake_supervision(steps=3)
    patch_constants(_MP[0], {"spike_flow_min_px": 0.5})
    sup.estimate = lambda t_ref, t, init=None: (
        np.tile(np.array([4.0 * (t - t_ref) / 0.1, 0.0], np.float32), (60, 80, 1)), np.ones((60, 80), bool), None)
    m = _traj_model(n=12)
    g = m.gaussians
    ensure_temporal_opacity(g)
    with torch.no_grad():
        getattr(g, TIME_CENTER)[:4] = 0.1  # born at 0.1
        getattr(g, TIME_CENTER)[4:8] = 0.2  # born at 0.2
        getattr(g, TIME_LOG_SCALE)[:8] = float(np.log(0.05))
    before = getattr(g, TRAJ_MEANS).detach().clone()
    idx = torch.arange(12)
    uv, _ = project(g.means.detach(), VIEWMAT, K)
    assert sup.flow_junctions(m, 1, 0.1, 0.2, idx, uv, born_only=True)["moved"] == 4
    after = getattr(g, TRAJ_MEANS).detach()
    for j in (2, 3):  # the junction at 0.2 and the one after it hold the place at 0.2
        uv_j, _ = project(g.means.detach()[:4] + after[:4, 3 * j], VIEWMAT, K)
        assert torch.allclose(uv_j - uv[:4], torch.tensor([4.0, 0.0]).expand(4, 2), atol=1e-3)
    assert torch.equal(after[:4, :6], before[:4, :6])  # up to 0.1: where it was born
    assert torch.equal(after[4:], before[4:])
    # back: the ones born at 0.2 get their place at 0.1 (and before) from the flow 0.2 -> 0.1
    assert sup.flow_junctions(m, 1, 0.2, 0.1, idx, uv, born_only=True)["moved"] == 4
    after = getattr(g, TRAJ_MEANS).detach()
    for j in (0, 1):
        uv_j, _ = project(g.means.detach()[4:8] + after[4:8, 3 * j], VIEWMAT, K)
        assert torch.allclose(uv_j - uv[4:8], torch.tensor([-4.0, 0.0]).expand(4, 2), atol=1e-3)
    assert torch.equal(after[8:], before[8:])
    # every visible Gaussian at the reference instant, born or not
    assert sup.flow_junctions(m, 1, 0.1, 0.2, idx, uv)["moved"] == 12
    uv_j, _ = project(g.means.detach()[8:] + getattr(g, TRAJ_MEANS).detach()[8:, 6], VIEWMAT, K)
    assert torch.allclose(uv_j - uv[8:], torch.tensor([4.0, 0.0]).expand(4, 2), atol=1e-3)
    # a flow under spike_flow_min_px moves nothing
    patch_constants(_MP[0], {"spike_flow_min_px": 10.0})
    assert sup.flow_junctions(m, 1, 0.1, 0.2, idx, uv)["moved"] == 0


def test_flow_junctions_move_only_what_the_spike_view_sees():
    """An interval fit moves the junctions of the Gaussians the spike view sees; one 10 cm behind
    a moved one, which the spike view does not see, keeps its junctions: handing it the moved
    one's change moved the static world near small objects on random scenes
    (docs/experiments/flow-junctions.md "Random scenes: the hidden hand-over removed, ...")."""
    from engine.scene import trajectory as traj

    sup, _ = _fake_supervision(steps=3, spike_flow_min_px=0.5)
    sup.estimate = lambda t_ref, t, init=None: (
        np.tile(np.array([4.0 * (t - t_ref) / 0.1, 0.0], np.float32), (60, 80, 1)), np.ones((60, 80), bool), None)
    m = _traj_model(n=30)
    g = m.gaussians
    params, knots = getattr(g, TRAJ_MEANS), m.trajectory["knots"]
    seen = sup.surface(m, 0.1)[0].tolist()
    front, hidden = seen[0], next(i for i in range(30) if i not in seen)
    with torch.no_grad():
        at = g.means + traj.evaluate(params, knots, 0.1)
        g.means[hidden] += at[front] - at[hidden] + torch.tensor([0.0, 0.0, 0.1])
    assert hidden not in sup.surface(m, 0.1)[0].tolist()
    before = params.detach().clone()
    info = sup.fit_interval(m, 1, extent=4.0)  # the old hand-over radius: 0.05 x 4 = 20 cm
    after = params.detach()
    assert info["junctions_ahead"]["moved"] > 0 and "hidden" not in info["junctions_ahead"]
    assert float((after[front, 6] - before[front, 6]).norm()) > 1e-3  # the seen one moved ahead
    assert torch.equal(after[hidden, 0::3], before[hidden, 0::3])  # the hidden one's junctions did not


def test_rgb_vote_keeps_the_place_the_rgb_frames_show():
    """rgb_vote: a textured image whose content moves 4 px right between the RGB instants 0.1 and
    0.2 in both train cameras; a junction at the place the frames show wins over one left where
    it was (and loses when the roles swap); a Gaussian no camera sees keeps the flow's place."""
    sup, _ = _fake_supervision(steps=3)
    rng = np.random.default_rng(0)
    tex = torch.from_numpy(rng.random((60, 100, 3)).astype(np.float32))
    tex = torch.nn.functional.avg_pool2d(tex.permute(2, 0, 1)[None], 3, 1, 1)[0].permute(1, 2, 0)  # smooth a little

    def item(cam, t, shift):
        img = tex[:, 10 - shift:90 - shift].contiguous()[None]  # 80 x 60, content moved ``shift`` px right
        return {"camera": cam, "time": t, "image": img, "viewmat": VIEWMAT[None], "K": K[None],
                "width": 80, "height": 60, "synthetic": False}

    sup.run.items[:] = [item(c, t, s) for c in ("rgb0", "rgb1") for t, s in ((0.1, 0), (0.2, 4))]
    uv = torch.tensor([[30.5, 20.5], [50.5, 35.5], [20.5, 40.5]])
    z = torch.full((3,), 2.0)
    x_ref = lift(uv, z, VIEWMAT, K)
    x_moved = lift(uv + torch.tensor([4.0, 0.0]), z, VIEWMAT, K)
    assert sup.rgb_vote(x_ref, x_moved, x_ref, 0.1, 0.2).all()
    assert not sup.rgb_vote(x_ref, x_ref, x_moved, 0.1, 0.2).any()
    far = x_ref + torch.tensor([0.0, 0.0, -10.0])  # behind the cameras: no frame votes
    assert sup.rgb_vote(far, far, x_moved, 0.1, 0.2).all()


def test_unknown_junction_mode_is_refused():
    with pytest.raises(ValueError, match="spike_flow_junctions"):
        _fake_supervision(spike_flow_junctions="some")


def test_warm_flow_pair_finds_a_jump_that_a_flow_from_zero_misses():
    """A textured disc (radius 10 px) on texture moves 25 px in 10 steps: from zero, DIS keeps
    it near the background's flow; warm-started step by step (each pair from the previous
    one), it follows the disc, and both directions agree (engine.train.guidance.spike_flow_pairs)."""
    import cv2

    from engine.train.guidance.spike_flow_pairs import warm_flow_pair

    rng = np.random.default_rng(0)
    h, w = 60, 80
    bg = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.5)
    fg = cv2.GaussianBlur(rng.random((h, w + 40)).astype(np.float32), (0, 0), 1.5) * 0.6 + 0.4
    yy, xx = np.mgrid[0:h, 0:w]

    def frame(dx: int):
        disc = (xx - 20 - dx) ** 2 + (yy - 30) ** 2 <= 100
        img = bg.copy()
        img[disc] = np.roll(fg, dx, axis=1)[:, :w][disc]
        return img, disc

    first, disc = frame(0)
    init = None
    for k in range(1, 11):
        fw, bw, ok = warm_flow_pair(first, frame(round(2.5 * k))[0], init)
        init = (fw, bw)
    cold, cold_ok = flow_pair(first, frame(25)[0])
    assert np.abs(fw[disc][:, 0] - 25.0).mean() < 1.0 and ok[disc].mean() > 0.9
    assert np.abs(cold[disc][:, 0] - 25.0).mean() > 10.0 and cold_ok[disc].mean() < 0.6


def test_grey_images_are_kept_least_recently_used_first_out(monkeypatch):
    """``gray`` keeps at most GRAY_CACHE images (every flow pair of a run kept them all: ~1 GB
    of a 3 s Vidar capture's); an evicted one asked for again is recomputed, the same array."""
    from engine.train.guidance import spike_flow_cache as sfc
    from engine.train.guidance.spike_flow_pairs import RecentGreys

    monkeypatch.setattr(sfc, "GRAY_CACHE", 3)
    sup, _ = _fake_supervision()
    made = []

    def tfp(stream, t, sensor, method="tfp", window=128):
        made.append(round(t * stream.rate_hz))
        return np.full((60, 80), t, np.float32)

    monkeypatch.setattr(sfc, "spike_to_gray", tfp)
    assert isinstance(sup._gray, RecentGreys) and sup._gray.capacity == 3
    frames = [0.1, 0.105, 0.11, 0.115]
    first = sup.gray(frames[0])
    for t in frames[1:3]:
        sup.gray(t)
    assert sup.gray(frames[0]) is first and len(made) == 3  # a hit moves it to the back
    sup.gray(frames[3])  # evicts the least recently used: 0.105
    assert len(sup._gray) == 3 and sup.frame_of(frames[1]) not in sup._gray
    again = sup.gray(frames[1])
    assert len(made) == 5 and made[-1] == sup.frame_of(frames[1])
    np.testing.assert_array_equal(again, np.full((60, 80), frames[1], np.float32))


def test_flow_cache_keeps_the_valid_mask_as_bytes_with_the_same_samples():
    """The cached mask is uint8 (a quarter of float32's bytes); the term reads it through
    sample_map, which gives the very 0 / 1 floats the float32 mask gave. The flow is kept in
    float16 (5 bytes per pixel and pair with the mask, against 12): its samples are the
    float32 flow's to float16 rounding (2^-11 relative: < 0.02 px below 32 px of motion)."""
    sup, _ = _fake_supervision()
    flow, valid = sup.flow(0.1, 0.15)
    assert flow.dtype == torch.float16 and valid.dtype == torch.uint8 and valid.shape == (60, 80, 1)
    exact = torch.as_tensor(sup.estimate(0.1, 0.15)[0])
    assert torch.allclose(sample_map(flow, torch.tensor([[3.5, 7.5]])), exact[7, 3][None], rtol=2 ** -11, atol=0)
    valid[:10] = 0  # some invalid rows
    uv = torch.rand(500, 2) * torch.tensor([80.0, 60.0])
    for mode in ("nearest", "bilinear"):
        assert torch.equal(sample_map(valid, uv, mode), sample_map(valid.float(), uv, mode))


def test_prefetch_computes_the_admitted_chains_on_its_thread_as_the_step_would():
    """``spike_flow_prefetch``: both chains of every interval up to the admitted one and of
    that many intervals beyond are computed on the background worker, earlier intervals
    first, warm-started along the grid exactly as the inline path does; a pair not queued is
    computed there too, at once, while the caller waits (engine.train.guidance.spike_flow_cache)."""
    import threading

    from engine.train.guidance import spike_flow_cache

    assert spike_flow_cache.PREFETCH == 2  # on by default
    inline, calls0 = _fake_supervision(spike_flow_prefetch=0)
    assert inline._worker is None
    sup, calls = _fake_supervision(spike_flow_prefetch=1)
    threads = []
    est = sup.estimate

    def estimate(*a, **k):
        threads.append(threading.current_thread().name)
        return est(*a, **k)

    sup.estimate = estimate
    assert sup.prefetch(admitted=0.05) == 1  # interval 0 admitted, interval 1 ahead; 2 not yet
    sup._worker.join(10)
    assert [(r, round(t, 6)) for r, t in calls] == [  # chains from each end to the far grid instant
        (0.0, 0.025), (0.0, 0.05), (0.0, 0.075), (0.1, 0.075), (0.1, 0.05), (0.1, 0.025),
        (0.1, 0.125), (0.1, 0.15), (0.1, 0.175), (0.2, 0.175), (0.2, 0.15), (0.2, 0.125)]
    assert set(threads) == {"bt4d-flow-prefetch"}
    for r, t in calls:
        inline.flow(r, t)
    assert calls0 == calls and inline.inits == sup.inits
    for key, (f, v) in inline._flows.items():
        assert torch.equal(sup._flows[key][0], f) and torch.equal(sup._flows[key][1], v)
    sup.flow(0.1, 0.15)  # prefetched: nothing computed
    assert len(calls) == 12
    flow, _ = sup.flow(0.3, 0.275)  # not queued: computed on the worker, this thread waits
    assert len(calls) == 13 and threads[-1] == "bt4d-flow-prefetch" and flow.shape == (60, 80, 2)
    assert sup.prefetch(admitted=0.3) == 2
    sup.close_flows()  # a finished or cancelled run: the rest is computed inline, if ever
    sup.flow(0.2, 0.26)  # off the grid: one pair
    assert sup._worker is None and threads[-1] == threading.current_thread().name


@pytest.mark.slow
def test_prefetched_flows_train_bit_for_bit_like_inline_ones(demo_capture):
    """Real guided steps on the demo: the run with the flows computed ahead on the worker has
    the very parameters of the run that computes them in the step (DIS is deterministic and
    each chain is computed in the same order)."""
    import hashlib

    from engine.io.capture import load_capture
    from engine.train.loop.trainer import Trainer

    cap = load_capture(demo_capture)
    digests, ran = [], []
    for ahead in (0, 2):
        torch.manual_seed(0)
        over = patch_constants(_MP[0], {**_TINY, "spike_flow_prefetch": ahead})
        tr = Trainer(cap, get_preset("fast", over), device="cpu")
        tr.init_model()
        for i in range(8):
            tr.step(i)
        assert tr.spike_flow._flows
        ran.append(0 if tr.spike_flow._worker is None else len(tr.spike_flow._worker.ran))
        tr.spike_flow.close_flows()
        h = hashlib.sha1()
        for grp in tr.model.gaussians.optimizer.param_groups:
            for p in grp["params"]:
                h.update(p.detach().numpy().tobytes())
        digests.append(h.hexdigest())
    assert ran[0] == 0 and ran[1] > 0 and digests[0] == digests[1]


def test_closing_cuts_a_running_chain_between_pairs_and_it_resumes_inline():
    """A cancelled run waits one DIS pair at most: ``close_flows`` stops the worker's chain
    before its next pair and drops the queued ones; a later inline flow resumes the cut chain
    from its last pair, warm-started as an uncut chain would be."""
    import threading
    import time

    sup, calls = _fake_supervision(spike_flow_prefetch=1)
    inline, _ = _fake_supervision(spike_flow_prefetch=0)
    gate, first = threading.Event(), threading.Event()
    est = sup.estimate

    def estimate(*a, **k):
        out = est(*a, **k)
        if len(calls) == 1:  # hold the worker inside the first pair
            first.set()
            gate.wait(10)
        return out

    sup.estimate = estimate
    sup.prefetch(admitted=0.05)  # four chains queued
    assert first.wait(10)
    closer = threading.Thread(target=sup.close_flows)
    closer.start()
    deadline = time.monotonic() + 10
    while not sup._stopping and time.monotonic() < deadline:
        time.sleep(0.001)
    gate.set()
    closer.join(10)
    assert not closer.is_alive() and sup._worker is None and len(calls) == 1
    sup.flow(0.0, 0.075)  # inline, on from the cut chain's first pair
    assert [round(t, 6) for _, t in calls] == [0.025, 0.05, 0.075]
    inline.flow(0.0, 0.075)
    assert sup.inits == inline.inits and not sup._warm


@pytest.mark.slow
def test_a_run_stops_its_flow_worker_when_it_ends(demo_capture, tmp_path, monkeypatch):
    """train() closes the prefetch worker however the run ends: with slow flows (40 ms a
    pair: ~7 s of queued chains) a finished run leaves no worker thread behind."""
    import threading
    import time

    from engine.train import train

    real = SpikeFlowSupervision.estimate

    def slow(self, *a, **k):
        time.sleep(0.04)
        return real(self, *a, **k)

    monkeypatch.setattr(SpikeFlowSupervision, "estimate", slow)
    summary = train(demo_capture, tmp_path / "run", preset="fast", overrides={**_TINY, "spike_flow_fit": False},
                    resume=False)
    assert summary["status"] == "finished"
    assert not [t for t in threading.enumerate() if t.name == "bt4d-flow-prefetch"]


def test_a_pair_the_step_needs_waits_for_one_queued_pair_at_most():
    """The worker's jobs are single pairs in chain order: a step that needs a pair while the
    worker is inside another chain waits for the pair being computed, then its own comes next
    (before the rest of that chain), warm-started as inline."""
    import threading

    sup, calls = _fake_supervision(spike_flow_prefetch=1)
    gate, first = threading.Event(), threading.Event()
    est = sup.estimate

    def estimate(*a, **k):
        out = est(*a, **k)
        if len(calls) == 1:
            first.set()
            gate.wait(10)
        return out

    sup.estimate = estimate
    sup.prefetch(admitted=0.05)  # intervals 0 and 1: 12 pairs queued, the first one running
    assert first.wait(10)
    threading.Timer(0.05, gate.set).start()
    sup.flow(0.1, 0.15)  # interval 1's chain from 0.1: 0.125, then 0.15
    assert [(r, round(t, 6)) for r, t in calls[:3]] == [(0.0, 0.025), (0.1, 0.125), (0.1, 0.15)]
    sup._worker.join(10)
    assert len(calls) == 12 and np.allclose(sup.inits[2], (0.025, -0.025))
    sup.close_flows()


def test_the_prefetch_worker_computes_both_flows_of_a_pair_on_its_own_low_priority_thread(monkeypatch):
    """On the worker a pair's backward flow does not go to the pair thread (normal priority): both
    flows run on the worker's thread at nice ``WORKER_NICE``; inline, the pair thread as before."""
    from engine.train.guidance import spike_flow_cache as sfc

    parallel = []
    for ahead in (0, 2):
        sup, seen = _dis_spy(monkeypatch, spike_flow_prefetch=ahead)
        sup.flow(0.1, 0.16)  # off the grid: one pair
        parallel += [kw["parallel"] for kw in seen]
        assert (sup._worker is None) == (ahead == 0)
        if ahead:
            assert sup._worker.nice == sfc.WORKER_NICE == 19
            sup.close_flows()
    assert parallel == [None, False]
