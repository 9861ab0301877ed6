"""``bench-raster --breakdown``: every stage it names is really timed (a renamed kernel
would otherwise show as 0 ms and its time would land in "torch glue"), the stages add up
to the total, and the timers are removed afterwards. No timing thresholds here."""
from __future__ import annotations

import pytest

from engine.raster import cpu as raster_cpu
from tools import raster_breakdown
from tools.bench_raster import make_scene

pytestmark = pytest.mark.skipif(not raster_cpu.available(), reason="numba unavailable")


def test_breakdown_times_every_stage_and_restores_the_kernels():
    k = raster_cpu._load()
    before = {a: getattr(k, a) for _, a, _, _ in raster_breakdown.STAGES if hasattr(k, a)}
    before_cpu = raster_cpu.bin_gaussians
    rows = raster_breakdown.breakdown(make_scene(400, 48, 40), 48, 40, repeats=2)
    got = {label: (w, c) for label, w, c in rows}
    for _, _, label, _ in raster_breakdown.STAGES:
        assert got[label][0] > 0.0, f"stage {label!r} was never called"
    top = sum(got[s[2]][0] for s in raster_breakdown.STAGES if s[3] is None)
    total = got["total"][0]
    assert abs(top + got["torch glue + Python"][0] - total) < 1e-6 * max(total, 1.0)
    assert got["tile lists"][0] <= got["binning (all)"][0]
    for a, fn in before.items():
        assert getattr(k, a) is fn
    assert raster_cpu.bin_gaussians is before_cpu
