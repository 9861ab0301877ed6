"""The spike camera simulator and the TFP / TFI reconstructions."""
from __future__ import annotations

import numpy as np
import pytest

import engine
from engine.io.spikes import read_spikes
from engine.spike.simulate import iter_spike_chunks, make_gain_map, simulate_spikes, simulate_spikes_to_file, tfi, tfp


def test_lazy_exports():
    assert engine.simulate_spikes is simulate_spikes and engine.tfp is tfp and engine.tfi is tfi


def test_deterministic_rate_and_remainder_kept():
    # light 0.25 with zero phase fires exactly every 4th frame (frames 3, 7, 11, ...)
    s = simulate_spikes(np.full((2, 3), 0.25), rate_hz=1000, num_frames=40, initial_phase="zero")
    assert s.dtype == np.uint8 and s.shape == (40, 2, 3)
    assert np.array_equal(np.flatnonzero(s[:, 0, 0]), np.arange(3, 40, 4))
    # non-commensurate light: the remainder is kept, so counts are floor(N * L) exactly
    light = np.array([[0.3, 0.37, 0.013, 0.999]])
    n = 997  # n * light is never within float rounding of an integer
    s = simulate_spikes(light, rate_hz=1000, num_frames=n, initial_phase="zero")
    counts = s.sum(axis=0)[0]
    assert np.array_equal(counts, np.floor(n * light[0]).astype(int))
    # with any phase, counts are floor or ceil of the integrated light
    s = simulate_spikes(light, rate_hz=1000, num_frames=n, seed=7)
    c = s.sum(axis=0)[0]
    assert np.all((c >= np.floor(n * light[0])) & (c <= np.ceil(n * light[0])))


def test_mean_count_equals_integrated_light_with_random_phase():
    # many pixels at the same light, short window: the count is unbiased over phases
    light = np.full((100, 100), 0.137)
    window = 10
    s = simulate_spikes(light, rate_hz=20000, num_frames=window, seed=3)
    mean = s.sum(axis=0).mean()
    # per-pixel count is floor/ceil of 1.37 -> Bernoulli(0.37) + 1; std of the mean ~ 0.0048
    assert mean == pytest.approx(window * 0.137, abs=0.03)


def test_time_varying_light_is_interpolated():
    # light ramps 0 -> 0.5 over 1000 frames; integrated ~ 250
    light = np.stack([np.zeros((20, 20)), np.full((20, 20), 0.5)])
    s = simulate_spikes(light, rate_hz=1000, num_frames=1000, light_times=[0.0, 0.999], seed=1)
    assert s.sum(axis=0).mean() == pytest.approx(0.5 * 0.5 * 1000, abs=1.5)
    # early frames almost silent, late frames busy
    assert s[:100].mean() < 0.05 < 0.4 < s[-100:].mean()
    # a callable light source gives the same stream
    def fn(t):
        return np.full((20, 20), 0.5 * min(max(t / 0.999, 0.0), 1.0))
    s2 = simulate_spikes(fn, rate_hz=1000, num_frames=1000, seed=1)
    assert (s2 != s).mean() < 1e-3


def test_gain_and_dark_current():
    light = np.full((50, 50), 0.1)
    gain = np.ones((50, 50))
    gain[:, 25:] = 2.0
    s = simulate_spikes(light, rate_hz=1000, num_frames=500, gain=gain, seed=2)
    left, right = s[:, :, :25].sum(0).mean(), s[:, :, 25:].sum(0).mean()
    assert left == pytest.approx(50, abs=1) and right == pytest.approx(100, abs=1)
    s = simulate_spikes(np.zeros((10, 10)), rate_hz=1000, num_frames=500, dark_current=0.02, seed=2)
    assert s.sum(0).mean() == pytest.approx(10, abs=1)
    g = make_gain_map(30, 40, 0.1, seed=4)
    assert g.shape == (30, 40) and g.dtype == np.float32
    assert abs(g.mean() - 1) < 0.02 and abs(g.std() - 0.1) < 0.02
    assert np.array_equal(g, make_gain_map(30, 40, 0.1, seed=4))


def test_saturation_one_spike_per_frame():
    s = simulate_spikes(np.full((3, 3), 5.0), rate_hz=1000, num_frames=50)
    assert s.max() == 1 and s.sum(0).min() >= 49


def test_shot_noise_keeps_mean_but_adds_variance():
    light = np.full((60, 60), 0.2)
    clean = simulate_spikes(light, rate_hz=1000, num_frames=200, seed=5)
    noisy = simulate_spikes(light, rate_hz=1000, num_frames=200, seed=5, shot_noise=True, photons_per_threshold=20)
    assert noisy.sum(0).mean() == pytest.approx(40, abs=0.5)
    assert noisy.sum(0).std() > 2 * clean.sum(0).std()


def test_seed_reproducible_and_chunking_invariant():
    light = np.random.default_rng(0).random((2, 8, 9)) * 0.6
    a = simulate_spikes(light, rate_hz=500, num_frames=300, light_times=[0, 0.5], seed=11)
    b = simulate_spikes(light, rate_hz=500, num_frames=300, light_times=[0, 0.5], seed=11, chunk_frames=7)
    assert np.array_equal(a, b)
    chunks = list(iter_spike_chunks(light, rate_hz=500, num_frames=300, light_times=[0, 0.5], seed=11,
                                    chunk_frames=64))
    assert [len(c) for c in chunks] == [64, 64, 64, 64, 44]
    assert np.array_equal(np.concatenate(chunks), a)


def test_numpy_fallback_matches_compiled(monkeypatch):
    import engine.spike.simulate as sim

    light = np.random.default_rng(1).random((3, 10, 12)) * 0.8
    kw = dict(rate_hz=1000, num_frames=200, light_times=[0, 0.05, 0.2], seed=3, gain=make_gain_map(10, 12, 0.2),
              dark_current=0.01)
    fast = simulate_spikes(light, **kw)
    monkeypatch.setattr(sim, "_fire_kernel", lambda: None)
    slow = simulate_spikes(light, **kw)
    assert (fast != slow).mean() < 1e-3


def test_simulate_to_file(tmp_path):
    light = np.random.default_rng(2).random((6, 16)) * 0.5
    p = simulate_spikes_to_file(tmp_path / "sim.dat", light, rate_hz=100, num_frames=70, seed=9, chunk_frames=16)
    assert np.array_equal(read_spikes(p, 6, 16), simulate_spikes(light, rate_hz=100, num_frames=70, seed=9))
    assert [q.name for q in tmp_path.iterdir()] == ["sim.dat"]


def test_tfp_recovers_static_light():
    light = np.random.default_rng(4).random((40, 30)) * 0.9
    s = simulate_spikes(light, rate_hz=20000, num_frames=400, seed=0)
    est = tfp(s)
    assert est.dtype == np.float32 and est.shape == (40, 30)
    assert np.abs(est - light).max() <= 1.0 / 400 + 1e-6  # floor/ceil of the count
    est2 = tfp(s, 100, index=200, threshold=2.0)  # window of 100, scaled by threshold
    assert np.abs(est2 / 2 - light).max() <= 1.0 / 100 + 1e-6
    assert np.corrcoef(est2.ravel(), light.ravel())[0, 1] > 0.99


def test_tfi_interval_estimate():
    light = np.array([[0.25, 0.1, 0.0]])
    s = simulate_spikes(light, rate_hz=1000, num_frames=100, initial_phase="zero")
    est = tfi(s, 50)
    assert est[0, 0] == pytest.approx(0.25) and est[0, 1] == pytest.approx(0.1) and est[0, 2] == 0.0
    # random phase, many pixels: TFI matches the light within one interval step
    light = np.random.default_rng(3).uniform(0.1, 0.9, size=(20, 20))
    s = simulate_spikes(light, rate_hz=1000, num_frames=200, seed=1)
    est = tfi(s, 100, threshold=1.0)
    rel = np.abs(1 / est - 1 / light)  # interval error below one frame
    assert rel.max() < 1.0 + 1e-6
    # bound: a pixel with a single spike gives an upper bound, not zero
    one = np.zeros((10, 1, 1), np.uint8)
    one[6] = 1
    assert tfi(one, 2)[0, 0] == pytest.approx(1 / 7)  # next=6, prev=-1
    assert tfi(one, 8)[0, 0] == pytest.approx(1 / 4)  # prev=6, next=10
