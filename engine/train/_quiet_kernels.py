"""numba kernel of :mod:`engine.train.quiet_curves`: the quiet segments' inner control points
held at zero in place, without a mask the size of the curves."""
from __future__ import annotations

from numba import njit, prange

from ..numba_cache import install_cache_locator

install_cache_locator(__name__)


@njit(cache=True, nogil=True, parallel=True)
def zero_quiet_inner(p, quiet, cols, C):
    """``p`` [N, K C] (a curve's rows, flat per row): the entries of columns ``cols`` (int64,
    inner columns ``3k+1, 3k+2`` only) of the rows where ``quiet`` [N, F-1] (bool) holds for
    segment ``col // 3``, multiplied by zero (what multiplying by :func:`inner_keep`'s 0 does,
    sign of zero included); every other entry is not written (what its 1 leaves)."""
    zero = p.dtype.type(0.0)
    for r in prange(p.shape[0]):
        for j in range(cols.size):
            col = cols[j]
            if quiet[r, col // 3]:
                a = col * C
                for c in range(C):
                    p[r, a + c] = p[r, a + c] * zero
