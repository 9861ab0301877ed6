"""Sampler of training instants (RGB instants vs between-frame instants)."""
from __future__ import annotations

import numpy as np
import pytest

from engine.train.guidance.instants import InstantSampler


def test_rgb_and_between_instants_cover_the_stream():
    times = np.arange(7) / 30.0
    s = InstantSampler(times, p_between=0.5, seed=0)
    draws = [s.sample() for _ in range(600)]
    rgb = [d for d in draws if d.is_rgb]
    btw = [d for d in draws if not d.is_rgb]
    assert 200 < len(rgb) < 400
    assert {d.frame for d in rgb} == set(range(7))
    assert all(d.time == times[d.frame] for d in rgb)
    counts = np.bincount([d.interval for d in btw], minlength=6)
    assert counts.min() >= counts.max() - 2  # shuffled rounds: every interval equally often
    for d in btw:
        assert d.t1 < d.time < d.t2
        assert 0.05 <= d.eps <= 0.95
        assert abs(d.t1 + d.eps * (d.t2 - d.t1) - d.time) < 1e-12


def test_coverage_limits_between_instants_and_rgb_only_fallback():
    times = np.arange(7) / 30.0
    s = InstantSampler(times, coverage=(0.0, 0.1), seed=1)  # spikes cover the first 3 intervals
    assert s.intervals.tolist() == [0, 1, 2]
    assert all(s.between_instant().interval in (0, 1, 2) for _ in range(20))
    none = InstantSampler(times, coverage=(1.0, 2.0))
    assert not none.has_between
    assert all(none.sample().is_rgb for _ in range(20))
    with pytest.raises(ValueError):
        none.between_instant()
    single = InstantSampler([0.5])
    assert single.sample().time == 0.5


def test_snap_to_spike_grid_and_between_grid():
    times = np.array([0.0, 1 / 30, 2 / 30])
    s = InstantSampler(times, snap_hz=20000.0, seed=2)
    for _ in range(20):
        d = s.between_instant()
        i = d.time * 20000.0
        assert abs(i - round(i)) < 1e-6
        assert d.t1 < d.time < d.t2
    g = s.between_grid(9)
    assert len(g) == 18
    assert np.allclose([d.eps for d in g[:9]], np.arange(1, 10) / 10, atol=1e-3)
    with pytest.raises(ValueError):
        InstantSampler(times, margin=0.6)


def test_between_instants_follow_the_time_curriculum():
    s = InstantSampler([0.0, 0.1, 0.2, 0.3], seed=4)
    assert s.between_instant(max_time=0.0) is None  # nothing admitted yet
    for _ in range(50):
        inst = s.between_instant(max_time=0.15)
        assert inst.interval in (0, 1) and inst.time <= 0.15 + 1e-12
    seen = {s.between_instant(max_time=0.35).interval for _ in range(60)}
    assert seen == {0, 1, 2}  # the whole capture once the window has passed it
    snapped = InstantSampler([0.0, 0.1], seed=1, snap_hz=1000.0)
    assert snapped.between_instant(max_time=0.0005) is None  # not even one spike frame is open
    assert snapped.between_instant(max_time=0.02).time <= 0.02 + 1e-3
