"""Spike windows, texture images and the fine-scale deformation feature (paper Eq. 6-10)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from engine.cameras import Intrinsics, View, look_at_c2w
from engine.io.spikes import SpikeStream, write_spikes
from engine.scene.fine_deformation import FineDeformation, count_parameters, project_to_grid, sinusoidal_encoding
from engine.spike.features import SpikeWindowCache, bracket, window_textures
from engine.spike.simulate import simulate_spikes


def _moving_bar(h=24, w=32, n=600, rate=20000.0):
    """Light of a bright bar moving left -> right over the stream."""
    def light(t):
        x = (t * rate / n) * w
        img = np.full((h, w), 0.1)
        img[:, int(x) % w: int(x) % w + 4] = 0.8
        return img
    return light


@pytest.fixture
def stream(tmp_path):
    n, rate = 600, 20000.0
    spikes = simulate_spikes(_moving_bar(n=n, rate=rate), rate_hz=rate, num_frames=n, seed=0)
    path = tmp_path / "s.dat"
    write_spikes(path, spikes)
    return SpikeStream(path, 32, 24, rate, 0.0)


def test_bracket_clamps_and_finds_interval():
    times = np.array([0.0, 0.1, 0.2])
    assert bracket(times, 0.05) == (0, 0.0, 0.1)
    assert bracket(times, 0.1) == (1, 0.1, 0.2)
    assert bracket(times, 0.25) == (1, 0.1, 0.2)
    assert bracket(times, -1.0) == (0, 0.0, 0.1)
    with pytest.raises(ValueError):
        bracket([0.0], 0.0)


def test_window_textures_estimate_light():
    light = np.full((8, 8), 0.25)
    s = simulate_spikes(light, rate_hz=20000, num_frames=400, seed=1)
    tex, frac = window_textures(s, 4)
    assert tex.shape == (4, 2, 8, 8) and frac.shape == (4,)
    assert np.allclose(frac, [0.125, 0.375, 0.625, 0.875])
    assert abs(tex[:, 0].mean() - 0.25) < 0.01  # TFP
    assert abs(tex[:, 1].mean() - 0.25) < 0.02  # TFI (period 4 -> 1/4)


def test_cache_computes_each_interval_once(stream, monkeypatch):
    rgb_times = [0.0, 0.01, 0.02, 0.03]  # 200 spike frames per interval
    cache = SpikeWindowCache(stream, rgb_times, k_sub=5)
    calls = []
    orig = stream.frames_between
    monkeypatch.setattr(stream, "frames_between", lambda a, b: calls.append((a, b)) or orig(a, b))
    w = cache.window(0.015)
    assert w.tex.shape == (5, 2, 24, 32) and w.times.shape == (5,)
    assert (w.t1, w.t2) == (0.01, 0.02)
    assert float(w.times.min()) > 0.01 and float(w.times.max()) < 0.02
    assert cache.window(0.011) is w and len(calls) == 1
    cache.precompute()
    assert len(cache) == 3 and len(calls) == 3
    # textures follow the bar: the bright column moves right within the window
    col = w.tex[:, 0].mean(1).argmax(-1)
    assert (col[1:] >= col[:-1]).all() and col[-1] > col[0]


def test_sinusoidal_encoding_distinguishes_times():
    e = sinusoidal_encoding(torch.tensor([0.0, 0.1, 0.5, 1.0]), 32)
    assert e.shape == (4, 32)
    d = torch.cdist(e, e)
    assert (d + torch.eye(4) * 10 > 0.1).all()


def _window(stream):
    return SpikeWindowCache(stream, [0.0, 0.01, 0.02, 0.03], k_sub=6).window(0.015)


@pytest.mark.slow
def test_fine_feature_starts_at_zero_and_learns_time(stream):
    torch.manual_seed(0)
    w = _window(stream)
    fine = FineDeformation(16, d_model=32, channels=16)
    f = fine(w, 0.012)
    assert f.shape == (1, 16)
    assert torch.count_nonzero(f) == 0  # zero-initialised output: coarse model unchanged
    # it can fit a time-dependent target inside the window (the query time matters)
    opt = torch.optim.Adam(fine.parameters(), lr=1e-2)
    ts = [0.011, 0.015, 0.019]
    target = {t: torch.full((1, 16), (t - 0.015) * 100) for t in ts}
    for _ in range(60):
        opt.zero_grad()
        loss = sum(((fine(w, t) - target[t]) ** 2).mean() for t in ts)
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.05 * sum(float((v ** 2).mean()) for v in target.values())


def test_frozen_encoder_has_no_trainable_conv(stream):
    a = FineDeformation(8, d_model=32, channels=16, frozen_encoder=True)
    b = FineDeformation(8, d_model=32, channels=16)
    assert count_parameters(b) - count_parameters(a) == count_parameters(b.encoder)
    w = _window(stream)
    a.out.weight.data.normal_()
    a(w, 0.015).sum().backward()
    assert all(p.grad is None for p in a.encoder.parameters())


def test_per_gaussian_features_follow_projection(stream):
    torch.manual_seed(0)
    intr = Intrinsics(32, 24, 30.0, 30.0, 16.0, 12.0)
    view = View(intr, look_at_c2w((0, -5, 0), (0, 0, 0)))
    means = torch.tensor([[0.0, 0.0, 0.0], [1.5, 0.0, 0.5], [0.0, -10.0, 0.0], [100.0, 0.0, 0.0]])
    grid, vis = project_to_grid(means, torch.as_tensor(view.viewmat), torch.as_tensor(view.K), 32, 24)
    assert vis.tolist() == [True, True, False, False]  # behind the camera / outside the image
    assert torch.allclose(grid[0], torch.zeros(2), atol=1e-5)  # the look-at target is the centre
    from engine.cameras import project_points
    uv, _ = project_points(view, means.numpy().astype(np.float64))
    assert np.allclose((grid[1].numpy() + 1) / 2 * [32, 24], uv[1], atol=1e-4)

    fine = FineDeformation(8, d_model=32, channels=16, per_gaussian=True)
    nn_init = torch.nn.init
    nn_init.normal_(fine.out.weight)
    w = _window(stream)
    f = fine(w, 0.015, grid=grid, visible=vis)
    assert f.shape == (4, 8)
    assert torch.count_nonzero(f[2:]) == 0 and torch.count_nonzero(f[:2]) > 0
    assert not torch.allclose(f[0], f[1])  # different pixels -> different features
    f.sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in fine.parameters() if p.grad is not None)
    with pytest.raises(ValueError):
        fine(w, 0.015)


def _two_windows(stream):
    cache = SpikeWindowCache(stream, [0.0, 0.01, 0.02, 0.03], k_sub=4)
    return cache.window(0.005), cache.window(0.015)


def _encode_with(memo, fine, w):
    enc = memo.get(w.index, fine.encoder.parameters(), lambda: fine.encode(w.tex))
    return enc


def test_encoded_windows_share_one_pass_per_window_and_weights(stream):
    """FINE_ENCODER_EVERY=1: two renders of one step in the same window share one encoder
    pass; values equal and gradients equal (float rounding) to two separate passes; a
    backward pass or an optimiser step ends the sharing."""
    from engine.scene.fine_deformation import EncodedWindows

    torch.manual_seed(0)
    w0, w1 = _two_windows(stream)
    fine = FineDeformation(8, d_model=32, channels=16)
    torch.nn.init.normal_(fine.out.weight)
    ts = (0.012, 0.017, 0.004)  # two queries in window 1, one in window 0

    def loss_of(memo):
        total = 0.0
        for t in ts:
            w = w1 if t >= 0.01 else w0
            enc = None if memo is None else _encode_with(memo, fine, w)
            total = total + (fine(w, t, encoded=enc) ** 2).sum()
        return total

    fine.zero_grad()
    ref = loss_of(None)
    ref.backward()
    ref_grads = [p.grad.clone() for p in fine.parameters()]
    memo = EncodedWindows(1)
    fine.zero_grad()
    got = loss_of(memo)
    assert memo.computed == 2 and memo.shared == 1  # window 1 encoded once for both queries
    assert torch.equal(got.detach(), ref.detach())
    got.backward()
    for a, b in zip(ref_grads, [p.grad for p in fine.parameters()]):
        assert float((a - b).abs().max()) <= 1e-5 * float(a.abs().max()) + 1e-9, float((a - b).abs().max())
    # its graph is consumed: the next pass (same weights) encodes again rather than reuse it
    loss_of(memo)
    assert memo.computed == 4 and memo.shared == 2
    # new weights: encoded again; without gradients (evaluation) kept while the weights hold
    torch.optim.SGD(fine.parameters(), lr=0.1).step()
    with torch.no_grad():
        loss_of(memo)
        loss_of(memo)
    assert memo.computed == 6 and memo.shared == 2 + 1 + 3
    off = EncodedWindows(0)  # 0: no reuse at all
    loss_of(off)
    assert off.computed == 3 and off.shared == 0


def test_frozen_encoder_is_encoded_once_per_window(stream):
    from engine.scene.fine_deformation import EncodedWindows

    w0, w1 = _two_windows(stream)
    fine = FineDeformation(8, d_model=32, channels=16, frozen_encoder=True)
    memo = EncodedWindows(1)
    opt = torch.optim.Adam([p for p in fine.parameters() if p.requires_grad], lr=1e-2)
    torch.nn.init.normal_(fine.out.weight)
    for step in range(4):
        opt.zero_grad()
        loss = sum((fine(w, t, encoded=_encode_with(memo, fine, w)) ** 2).sum()
                   for w, t in ((w0, 0.004), (w1, 0.015)))
        loss.backward()
        opt.step()
        memo.tick()
    assert memo.computed == 2 and memo.shared == 6


def test_encoder_every_k_reuses_stale_tokens_and_trains_the_encoder_on_refresh_steps(stream):
    """FINE_ENCODER_EVERY=k>1: a window's encoder runs (and gets gradients) once per k steps."""
    import copy

    from engine.scene.fine_deformation import EncodedWindows

    _, w1 = _two_windows(stream)
    fine = FineDeformation(8, d_model=32, channels=16)
    torch.nn.init.normal_(fine.out.weight)
    memo = EncodedWindows(3)
    opt = torch.optim.Adam(fine.parameters(), lr=1e-2)
    conv = fine.encoder.net[0].weight
    got_grad = []
    for step in range(7):
        opt.zero_grad(set_to_none=True)
        (fine(w1, 0.015, encoded=_encode_with(memo, fine, w1)) ** 2).sum().backward()
        got_grad.append(conv.grad is not None)
        assert fine.token_proj.weight.grad is not None  # the rest of the branch trains every step
        opt.step()
        memo.tick()
    assert got_grad == [True, False, False, True, False, False, True]
    assert memo.computed == 3 and memo.stale == 4
    # a copy (the budget probe's deep copy of the model) starts empty
    assert copy.deepcopy(memo).refresh_every == 3 and copy.deepcopy(memo).computed == 0
