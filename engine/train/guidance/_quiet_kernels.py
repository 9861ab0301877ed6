"""numba kernel of :mod:`engine.train.guidance.quiet_curves`: the quiet segments' inner control points
held at zero in place, without a mask the size of the curves."""
from __future__ import annotations

from numba import njit, prange

from ...numba_cache import install_cache_locator
from ...numba_prefetch import ROWS_AHEAD, prefetch

install_cache_locator(__name__)


@njit(cache=True, nogil=True, parallel=True)
def zero_quiet_inner(p, quiet, cols, C):
    """``p`` [N, K C] (a curve's rows, flat per row): the entries of columns ``cols`` (int64,
    inner columns ``3k+1, 3k+2`` only) of the rows where ``quiet`` [N, F-1] (bool) holds for
    segment ``col // 3``, multiplied by zero (what multiplying by :func:`inner_keep`'s 0 does,
    sign of zero included); every other entry is not written (what its 1 leaves). A step's few
    columns are strided lines: those of the row ``ROWS_AHEAD`` on that will be written are
    requested first (engine.numba_prefetch)."""
    zero = p.dtype.type(0.0)
    n, D = p.shape
    flat = p.reshape(-1)
    few = cols.size <= 16  # every inner column: nearly a stream, which the hardware prefetches
    for r in prange(n):
        if few and r + ROWS_AHEAD < n:
            ra = r + ROWS_AHEAD
            for j in range(cols.size):
                if quiet[ra, cols[j] // 3]:
                    prefetch(flat, ra * D + cols[j] * C)
        for j in range(cols.size):
            col = cols[j]
            if quiet[r, col // 3]:
                a = col * C
                for c in range(C):
                    p[r, a + c] = p[r, a + c] * zero


@njit(cache=True, nogil=True, parallel=True)
def zero_quiet_segments(p, quiet, C):
    """:func:`zero_quiet_inner` over every inner column, segment by segment: the two inner
    columns ``3k+1, 3k+2`` of a quiet segment are ``2 C`` consecutive entries of the row."""
    zero = p.dtype.type(0.0)
    n, S = quiet.shape
    for r in prange(n):
        for k in range(S):
            if quiet[r, k]:
                a = (3 * k + 1) * C
                for e in range(2 * C):
                    p[r, a + e] = p[r, a + e] * zero
