"""Skipping spike windows with no change (engine.spike.change) and the fine-feature gate."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch
from test_spike_guidance import _ctx, _fake_trainer

from engine.io.capture import load_capture
from engine.io.spikes import write_spikes
from engine.spike.change import block_change_statistic, detect_change
from engine.spike.simulate import simulate_spikes


def _rates(spikes: np.ndarray, intervals: int, k_sub: int = 8) -> list[np.ndarray]:
    out = []
    for chunk in np.array_split(spikes, intervals):
        out.append(np.stack([s.mean(0) for s in np.array_split(chunk, k_sub)]))
    return out


def _bar_light(T: int, h: int, w: int, moving_from: int) -> np.ndarray:
    """Grey background, a bright bar still until ``moving_from``, then sweeping right."""
    light = np.full((T, h, w), 0.25, np.float32)
    for i in range(T):
        x = 4 + max(0, i - moving_from) * 2
        light[i, :, x:x + 4] = 0.9
    return light


def test_static_stream_has_no_change_and_moving_bar_is_found_where_it_moves():
    h, w, n = 24, 48, 3000
    static = simulate_spikes(np.full((2, h, w), 0.3, np.float32), rate_hz=20000, num_frames=n, t0=0.0,
                             light_times=np.array([0.0, n / 20000]), threshold=1.0, shot_noise=True,
                             photons_per_threshold=1000, seed=1)
    ch = detect_change(_rates(static, 3), n // 3)
    assert ch.active_intervals.size == 0 and not ch.changed.any()
    assert ch.statistic.max() < ch.threshold

    T = 31
    light = _bar_light(T, h, w, moving_from=10)  # still for the first third, then moving
    moving = simulate_spikes(light, rate_hz=20000, num_frames=n, t0=0.0,
                             light_times=np.linspace(0, (n - 1) / 20000, T), threshold=1.0, shot_noise=True,
                             photons_per_threshold=1000, seed=2)
    ch = detect_change(_rates(moving, 3), n // 3)
    assert ch.active_intervals.tolist() == [1, 2]  # the first window is static: skipped
    frac = ch.changed_fraction
    assert frac[0] == 0 and 0 < frac[1] < 0.6 and 0 < frac[2] < 0.6  # only the bar's path changes
    rows_changed = ch.changed[1].any(1)
    assert rows_changed.all()  # the bar spans every row...
    cols = np.nonzero(ch.changed[1].any(0))[0]
    assert cols.min() >= 1 and cols.max() <= 10  # ...but only the columns it swept (x 4..28 px)


def test_nan_rates_count_as_change():
    r = np.zeros((8, 8, 8), np.float32)
    r[3, 0, 0] = np.nan
    ch = detect_change([r], 800)
    assert ch.changed[0, 0, 0] and ch.changed.sum() == 1


def test_block_statistic_shape_and_value():
    r = np.zeros((4, 10, 9), np.float32)
    r[2, :4, :4] = 0.4  # one sub-window brighter in the first block
    s = block_change_statistic(r, 4)
    assert s.shape == (3, 3)
    assert s[0, 0] == pytest.approx(0.3) and s[2, 2] == 0


def test_gate_samples_the_dilated_change_map():
    changed = np.zeros((1, 4, 4), bool)
    changed[0, 0, 0] = True
    from engine.spike.change import SpikeChange

    ch = SpikeChange(np.zeros((1, 4, 4), np.float32), changed, 0.1, 0.01, 4, (16, 16))
    grid = torch.tensor([[-0.9, -0.9], [0.9, 0.9], [-0.4, -0.4]])  # block (0,0), far corner, dilated ring
    g0 = ch.gate(0, grid, dilate=0)
    assert g0[0] == 1 and g0[1] == 0 and g0[2] == 0
    g1 = ch.gate(0, grid, dilate=1)
    assert g1[0] == 1 and g1[1] == 0 and g1[2] == 1


@pytest.fixture(scope="module")
def static_capture(demo_capture, tmp_path_factory):
    """The demo capture with its spike stream replaced by a static one (same size)."""
    root = tmp_path_factory.mktemp("static_spikes") / "cap"
    shutil.copytree(demo_capture, root)
    cap = load_capture(root)
    info = cap.spike_streams[0]
    light = np.full((2, info.height, info.width), 0.3, np.float32)
    spikes = simulate_spikes(light, rate_hz=info.rate_hz, num_frames=info.num_frames, t0=info.t0,
                             light_times=np.array([info.t0, info.t0 + info.num_frames / info.rate_hz]),
                             threshold=1.0, seed=3)
    assert str(info.path).startswith(str(root))
    write_spikes(info.path, spikes)
    return load_capture(root)


def test_guidance_skips_every_window_of_a_static_stream(static_capture, demo_capture):
    from engine.train.guidance.spike_guidance import SpikeGuidance

    tr = _fake_trainer(static_capture, between_colocated_p=1.0)
    g = SpikeGuidance(tr)
    assert g.change is not None and g.change.active_intervals.size == 0
    assert not g.spike_sampler.has_between and not g.sampler.has_between
    assert all(g.between(_ctx(tr, step=s)) is None for s in range(10, 20))  # no between renders at all
    # switched off: the same capture trains the between instants as before
    tr_off = _fake_trainer(static_capture, between_colocated_p=1.0, spike_skip_static=False)
    assert SpikeGuidance(tr_off).between(_ctx(tr_off)) is not None
    # the demo moves in every window: nothing skipped
    g_demo = SpikeGuidance(_fake_trainer(load_capture(demo_capture)))
    assert g_demo.skipped_intervals == 0 and g_demo.change.active_intervals.size == g_demo.change.num_intervals
    assert 0.02 < g_demo.change.changed_fraction.mean() < 0.5


def test_fine_feature_is_gated_off_where_the_spike_view_never_changes(static_capture, demo_capture):
    from engine.scene.deformation import DeformationField
    from engine.train.guidance.spike_guidance import make_fine_encoder

    field = DeformationField([-3, -3, -1], [3, 3, 3], (0.0, 0.2), features=4, resolution=4, multires=(1,),
                             time_resolution=4, width=16)
    xyz = torch.rand(64, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    outs = {}
    for name, cap, gate in (("static", static_capture, True), ("static-nogate", static_capture, False),
                            ("demo", demo_capture, True)):
        c = load_capture(cap) if not hasattr(cap, "frames") else cap
        tr = _fake_trainer(c, fine_d_model=16, fine_channels=8, fine_k_sub=4, fine_change_gate=gate)
        enc = make_fine_encoder(tr, field)
        torch.manual_seed(1)
        enc.net.out.weight.data.normal_()
        enc.net.out.bias.data.normal_()
        outs[name] = enc(xyz, 0.05).detach()
    assert torch.count_nonzero(outs["static"]) == 0  # nothing changes: no spike-driven motion
    assert torch.count_nonzero(outs["static-nogate"]) > 0
    moving = outs["demo"].abs().sum(1) > 0
    assert 0 < int(moving.sum()) < 64  # only Gaussians over the changing part of the view


def test_static_prior_holds_gaussians_where_the_spike_view_never_changes(static_capture, demo_capture):
    from engine.cameras import look_at_c2w  # noqa: F401  (the demo rig is look-at cameras)
    from engine.train.guidance.spike_guidance import SpikeGuidance

    cap = load_capture(demo_capture)
    g = SpikeGuidance(_fake_trainer(cap))
    prior = g.static_prior()
    stream = g.stream
    view = stream.view(0.0)
    c2w = np.linalg.inv(view.viewmat)
    # points 5 m in front of the spike camera through a grid of its pixels
    K = stream.intrinsics.K
    us, vs = np.meshgrid(np.linspace(2, stream.width - 3, 16), np.linspace(2, stream.height - 3, 12))
    rays = np.stack([(us.ravel() - K[0, 2]) / K[0, 0], (vs.ravel() - K[1, 2]) / K[1, 1], np.ones(us.size)], 1)
    pts = torch.as_tensor((rays * 5.0) @ c2w[:3, :3].T + c2w[:3, 3], dtype=torch.float32)
    behind = torch.as_tensor(c2w[:3, 3] - 2.0 * c2w[:3, 2], dtype=torch.float32)[None]  # OpenCV +z is forward
    mask = prior(torch.cat([pts, behind]))
    assert not mask[-1]  # not seen by the spike camera: never held by its prior
    frac = float(mask[:-1].float().mean())
    assert 0.3 < frac < 0.98  # most of the demo's view is static, the moving objects' paths are not
    ch = g.change.union_map(2)
    # a held point projects where no window changed; a free point where one did
    gx = ((us.ravel() + 0.5) / stream.width * ch.shape[1]).astype(int).clip(0, ch.shape[1] - 1)
    gy = ((vs.ravel() + 0.5) / stream.height * ch.shape[0]).astype(int).clip(0, ch.shape[0] - 1)
    at = ch[gy, gx].numpy()
    assert (at[mask[:-1].numpy()] == 0).all()
    assert (at[~mask[:-1].numpy()] > 0).mean() > 0.8  # free ones sit on or next to a change (bilinear edges)
    # a static stream holds every visible point
    g_static = SpikeGuidance(_fake_trainer(static_capture))
    assert g_static.static_prior()(pts).all()


def test_model_applies_saves_and_restores_the_static_prior():
    from engine.scene.deformation import DeformationField
    from engine.scene.gaussians import GaussianModel
    from engine.scene.model import Model4D

    rng = np.random.default_rng(0)
    g = GaussianModel(rng.uniform(-1, 1, (20, 3)).astype(np.float32), rng.uniform(0, 1, (20, 3)).astype(np.float32))
    field = DeformationField([-1, -1, -1], [1, 1, 1], (0.0, 1.0), features=4, resolution=4, multires=(1,),
                             time_resolution=4, width=16)
    with torch.no_grad():
        for p in list(field.mlp_parameters()) + list(field.grid_parameters()):
            p.normal_(0, 0.5)
    m = Model4D(g, field)
    held = torch.zeros(20, dtype=torch.bool)
    held[:10] = True
    m.static_prior = lambda means: held.clone()
    a0, a1 = m.attributes(0.1), m.attributes(0.9)
    assert torch.equal(a0["means"][:10], g.means[:10]) and torch.equal(a1["means"][:10], g.means[:10])
    assert not torch.allclose(a0["means"][10:], a1["means"][10:])  # the rest still moves
    again = Model4D.from_state(m.state())
    assert again.static_prior is None and torch.equal(again.prior_mask, held)
    assert torch.equal(again.attributes(0.9)["means"][:10], g.means[:10].detach())
