"""``engine.numba_prefetch.prefetch``: a hint that changes no value and never faults."""
from __future__ import annotations

import numpy as np
import pytest

numba = pytest.importorskip("numba")


def test_prefetch_changes_nothing_and_never_faults():
    from engine.numba_prefetch import prefetch

    @numba.njit
    def touch(a, b):
        s = 0.0
        for i in range(a.size):
            prefetch(a, i + 64)  # past the end at the last 64 elements: still no fault
            prefetch(b, i)
            s += a[i]
            b[i] = a[i] * 2.0
        prefetch(a, 1 << 40)  # far outside the process's memory
        return s

    a = np.arange(1000, dtype=np.float32)
    b = np.zeros((10, 100), np.float64).reshape(-1)
    assert touch(a, b) == float(a.sum())
    assert np.array_equal(b, a * 2.0)
