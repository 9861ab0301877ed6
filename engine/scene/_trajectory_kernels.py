"""numba kernels of the trajectories' residual-square term (issue 13):
:func:`engine.scene.trajectory.inner_residual_sq` forward and backward in one pass each.

``params`` [N, K, C] float32/float64 contiguous, ``K = 3 (F - 1) + 1``; the residuals of
segment ``i`` are entries ``3 i + 1`` and ``3 i + 2``. Rounding as torch's
``(inner_residuals(params) ** 2).sum(-1)`` (squares summed left to right) and its
autograd backward ``grad * (2 * d)``; tests compare bit for bit.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..numba_cache import install_cache_locator
from ..numba_prefetch import ROWS_AHEAD, prefetch, prefetch_columns

install_cache_locator(__name__)


# Each kernel's work is independent per row: a row function shared by a serial driver (the name
# the callers knew) and a parallel one over numba's threads (``*_rows``), the same arithmetic per
# entry, so the same numbers. The curves are strided reads and writes of a few columns per row,
# bound by memory latency: two threads keep twice the misses in flight (docs/experiments/benchmark-history.md "A
# longer capture").


@njit(cache=True, nogil=True, inline="always")
def _residual_sq_row(params, out, r):
    segs, C = out.shape[1], params.shape[2]
    nonzero = False
    for i in range(segs):
        for j in range(2):
            x = params[r, 3 * i + 1 + j, 0]
            nonzero |= x != 0
            acc = x * x
            for c in range(1, C):
                x = params[r, 3 * i + 1 + j, c]
                nonzero |= x != 0
                acc = acc + x * x
            out[r, i, j] = acc
    return nonzero


@njit(cache=True, nogil=True)
def residual_sq(params, out):
    """``out[n, i, j] = sum_c params[n, 3 i + 1 + j, c] ** 2`` ([N, F - 1, 2]); returns
    whether any residual is nonzero (its square may underflow to 0: the values are tested)."""
    nonzero = False
    for r in range(out.shape[0]):
        nonzero |= _residual_sq_row(params, out, r)
    return nonzero


@njit(cache=True, nogil=True, parallel=True)
def residual_sq_rows(params, out):
    """:func:`residual_sq` on numba's threads."""
    rows = 0
    for r in prange(out.shape[0]):
        rows += 1 if _residual_sq_row(params, out, r) else 0
    return rows > 0


@njit(cache=True, nogil=True, inline="always")
def _residual_sq_backward_row(params, grad, out, r, add):
    K, C = params.shape[1], params.shape[2]
    segs = grad.shape[1]
    if not add:
        for c in range(C):
            out[r, K - 1, c] = 0.0
    for i in range(segs):
        if not add:
            for c in range(C):
                out[r, 3 * i, c] = 0.0
        for j in range(2):
            gr = grad[r, i, j]
            for c in range(C):
                x = params[r, 3 * i + 1 + j, c]
                if add:
                    out[r, 3 * i + 1 + j, c] = out[r, 3 * i + 1 + j, c] + gr * (x + x)
                else:
                    out[r, 3 * i + 1 + j, c] = gr * (x + x)  # x + x: 2 x exactly, in x's dtype


@njit(cache=True, nogil=True)
def residual_sq_backward(params, grad, out):
    """``out`` [N, K, C] (every entry written): ``grad[n, i, j] * (2 * d)`` at the residual
    entries, zero at the junctions."""
    for r in range(params.shape[0]):
        _residual_sq_backward_row(params, grad, out, r, False)


@njit(cache=True, nogil=True)
def residual_sq_backward_add(params, grad, out):
    """``out += residual_sq_backward``'s gradient, at the residual entries only (the junctions'
    zeros added change nothing): autograd's sum of the two, bit for bit (trajectory.sunk)."""
    for r in range(params.shape[0]):
        _residual_sq_backward_row(params, grad, out, r, True)


@njit(cache=True, nogil=True, parallel=True)
def residual_sq_backward_rows(params, grad, out, add):
    """:func:`residual_sq_backward` (``add`` False) or :func:`residual_sq_backward_add` (True)
    on numba's threads."""
    for r in prange(params.shape[0]):
        _residual_sq_backward_row(params, grad, out, r, add)


@njit(cache=True, nogil=True)
def all_finite(x):
    """Every entry of the contiguous array ``x`` finite (``torch.isfinite(x).all()`` in one
    pass with no bool temporary: ~0.8 ms of an RGB step at 26k Gaussians, measured)."""
    f = x.reshape(-1)
    ok = True
    for i in range(f.size):
        ok &= np.isfinite(f[i])
    return ok


# ---- the curves at one instant: engine.scene.trajectory._CurveAt -----------------------------
# ``out = sum_j w_j params[:, c_j]`` over a few columns, and its backward, in one pass over the
# rows each (the torch code reads / writes one strided column per op: ~2 ms forward and ~2.4
# backward for a 26k x 19 x 3 curve between knots, measured). Rounding as that code: each
# term ``params * w_j`` (w_j rounded to the tensor's dtype) added left to right; the
# backward's columns are ``grad * w_j``, everything else zero.


@njit(cache=True, nogil=True, inline="always")
def _curve_row(params, cols, weights, out, r):
    C, m = out.shape[1], cols.size
    for c in range(C):
        acc = params[r, cols[0], c] * weights[0]
        for j in range(1, m):
            acc = acc + params[r, cols[j], c] * weights[j]
        out[r, c] = acc


@njit(cache=True, nogil=True)
def curve_at(params, cols, weights, out):
    """``out[n, c] = sum_j params[n, cols[j], c] * weights[j]`` (j ascending)."""
    for r in range(out.shape[0]):
        _curve_row(params, cols, weights, out, r)


@njit(cache=True, nogil=True, inline="always")
def _prefetch_columns(arr, r, cols):
    """Request the lines of columns ``cols`` (ascending) of row ``r + ROWS_AHEAD`` of ``arr``
    [N, K, C] (numba_prefetch: the strided rows are latency-bound without)."""
    if r + ROWS_AHEAD < arr.shape[0]:
        _prefetch_row_columns(arr, r + ROWS_AHEAD, cols)


@njit(cache=True, nogil=True, inline="always")
def _prefetch_row_columns(arr, row, cols):
    """Request the lines of columns ``cols`` (ascending) of row ``row`` of ``arr`` [N, K, C]."""
    n, k, c = arr.shape
    prefetch_columns(arr.reshape(-1), row * k * c, cols, c)


@njit(cache=True, nogil=True, parallel=True)
def curve_at_rows(params, cols, weights, out):
    """:func:`curve_at` on numba's threads."""
    for r in prange(out.shape[0]):
        _prefetch_columns(params, r, cols)
        _curve_row(params, cols, weights, out, r)


@njit(cache=True, nogil=True, inline="always")
def _curve_backward_row(grad, cols, weights, out, add, r):
    K, C = out.shape[1], out.shape[2]
    if not add:
        for k in range(K):
            for c in range(C):
                out[r, k, c] = 0.0
    for j in range(cols.size):
        col, w = cols[j], weights[j]
        for c in range(C):
            x = grad[r, c] * w
            out[r, col, c] = out[r, col, c] + x if add else x


@njit(cache=True, nogil=True)
def curve_at_backward(grad, cols, weights, out, add):
    """Without ``add``: ``out`` [N, K, C] = ``grad * weights[j]`` in column ``cols[j]``, zero
    elsewhere (every entry written; the columns are distinct). With ``add``: that gradient
    added into ``out``, columns ``cols`` only (autograd's sum of the two; trajectory.sunk)."""
    for r in range(out.shape[0]):
        _curve_backward_row(grad, cols, weights, out, add, r)


@njit(cache=True, nogil=True, parallel=True)
def curve_at_backward_rows(grad, cols, weights, out, add):
    """:func:`curve_at_backward` on numba's threads."""
    for r in prange(out.shape[0]):
        if add:  # a kept buffer's few columns (grad_buffers); without, every entry is written in order
            _prefetch_columns(out, r, cols)
        _curve_backward_row(grad, cols, weights, out, add, r)


# ---- a row subset of the curves at one instant, inner columns only: spike_flow._InnerAt -------
# Rounding as the torch code it replaces: each term ``params[idx, c_j] * w_j`` (w_j rounded to the
# dtype) added left to right, then ``base + sum``; the backward ``0 + grad * w_j`` accumulated into
# rows ``idx`` of the inner columns (``index_add_`` into a zero tensor: a -0 product becomes +0).


@njit(cache=True, nogil=True)
def inner_at(params, base, idx, cols, weights, out):
    """``out[m, c] = base[m, c] + sum_j params[idx[m], cols[j], c] * weights[j]`` (j ascending)."""
    M, C = out.shape
    nj = cols.size
    for m in range(M):
        if m + ROWS_AHEAD < M:  # rows in random order: their lines requested ahead (numba_prefetch)
            _prefetch_row_columns(params, idx[m + ROWS_AHEAD], cols)
        r = idx[m]
        for c in range(C):
            acc = params[r, cols[0], c] * weights[0]
            for j in range(1, nj):
                acc = acc + params[r, cols[j], c] * weights[j]
            out[m, c] = base[m, c] + acc


@njit(cache=True, nogil=True)
def inner_at_backward(grad, idx, cols, weights, out):
    """``out[idx[m], cols[j], c] += 0 + grad[m, c] * weights[j]`` for the inner columns
    (``cols[j] % 3 != 0``), columns in the order given, rows in order. Into a zero-filled
    ``out`` this is the torch ``index_add_`` it replaces; into a gradient already there (``idx``
    distinct, trajectory.sunk) it is autograd's sum of that and the zero-filled one: the
    ``0 +`` turns a -0 product into the +0 the zero-filled gradient would hold."""
    M, C = grad.shape
    K = out.shape[1]
    flat = out.reshape(-1)
    for j in range(cols.size):
        col, w = cols[j], weights[j]
        if col % 3 == 0:
            continue
        for m in range(M):
            if m + ROWS_AHEAD < M:  # rows in random order (numba_prefetch)
                prefetch(flat, (idx[m + ROWS_AHEAD] * K + col) * C)
            r = idx[m]
            for c in range(C):
                out[r, col, c] = out[r, col, c] + (0.0 + grad[m, c] * w)
