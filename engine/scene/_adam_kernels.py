"""numba kernels of :class:`engine.scene.fused_adam.FusedAdam` (issue 13).

Two passes over flat float32 arrays that round exactly as torch's single-tensor Adam
does on an AVX2 CPU (``torch.optim.adam._single_tensor_adam``): its ``lerp_`` and
``addcmul_`` kernels use fused multiply-adds (``vec::fmadd``), so these do too
(``llvm.fma.f32``); the square root between the passes is torch's own (its CPU ``sqrt``
is not correctly rounded: +-1 ulp against IEEE, measured). The engine checks the result
against torch's on first use and falls back to torch when they differ
(:func:`engine.scene.fused_adam.exact`).
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..numba_cache import install_cache_locator
from ..numba_fma import fma32 as _fma32
from ..numba_prefetch import ROWS_AHEAD, prefetch_columns
from ..numba_vml import vml_sqrt32 as _vml_sqrt32

install_cache_locator(__name__)


# Serial loops from index 0 (numba then drops its negative-index handling and LLVM
# vectorises them: 8 floats per instruction); ``error_model="numpy"``: IEEE division with no
# zero check, which would stop the vectoriser too. ``parallel=True`` on these loops measured
# slower (CPU time) on this 2-core machine; :func:`step_threads` instead gives each of numba's
# threads one run of whole blocks of :func:`step` (docs/experiments/benchmark-history.md "Adam on numba's threads").


@njit(cache=True, nogil=True)
def moments(g, m, v, w1, b2, c2, root_in):
    """``m.lerp_(g, w1)``; ``v.mul_(b2).addcmul_(g, g, value=c2)`` (in place, flat float32);
    ``root_in`` gets ``v`` with its zeros replaced by 1 (what torch's sqrt is given next:
    its MKL kernel takes a slow path on zeros, 5x slower on the trajectories' moments,
    ~70 % zeros; its value at any other element does not depend on its neighbours,
    measured)."""
    one = np.float32(1.0)
    if abs(w1) < np.float32(0.5):  # torch's lerp: two formulas around weight 0.5
        for i in range(g.size):
            gi = g[i]
            m[i] = _fma32(w1, gi - m[i], m[i])
            vi = _fma32(c2 * gi, gi, v[i] * b2)
            v[i] = vi
            root_in[i] = vi if vi != 0 else one
    else:
        w1m = w1 - one
        for i in range(g.size):
            gi = g[i]
            m[i] = _fma32(w1m, gi - m[i], gi)
            vi = _fma32(c2 * gi, gi, v[i] * b2)
            v[i] = vi
            root_in[i] = vi if vi != 0 else one


@njit(cache=True, nogil=True, error_model="numpy")
def update(p, m, v, root, bc2s, eps, neg_step):
    """``p.addcdiv_(m, sqrt(v) / bc2s + eps, value=neg_step)`` (in place, flat float32) with
    ``root`` = torch's square roots of :func:`moments`' ``root_in`` (sqrt(0) = 0)."""
    zero = np.float32(0.0)
    for i in range(p.size):
        sq = root[i] if v[i] != 0 else zero
        p[i] = p[i] + (neg_step * m[i]) / (sq / bc2s + eps)


# ---- one pass: moments, torch's square root and update a block at a time --------------------
# The two passes above with torch's ``sqrt`` between them stream every array from memory twice
# (moments: g, m, v, the roots' inputs; update: p, m, v, the roots) and the roots once more:
# ~60 bytes per float where Adam needs 28 (read p, g, m, v; write p, m, v). :func:`step` runs
# the same three stages over blocks of ``buf.size`` elements, the square roots by the very
# function torch's ``sqrt`` calls (MKL's ``vmsSqrt``, :mod:`engine.numba_vml`), so the update
# reads m, v and the roots back from the cache, not from memory: same numbers, one pass.


@njit(cache=True, nogil=True, error_model="numpy")
def _step_block(p, g, m, v, w1, b2, c2, bc2s, eps, neg_step, root):
    """:func:`moments`, ``vmsSqrt`` and :func:`update` over one block (slices from index 0:
    the loops vectorise as the dense kernels'; ``root`` holds the block's square roots)."""
    moments(g, m, v, w1, b2, c2, root)
    _vml_sqrt32(root, root)
    update(p, m, v, root, bc2s, eps, neg_step)


@njit(cache=True, nogil=True, error_model="numpy")
def step(p, g, m, v, w1, b2, c2, bc2s, eps, neg_step, buf):
    """One Adam update in place (flat float32 ``p``, ``g``, ``m``, ``v``): :func:`moments`,
    torch's ``sqrt`` and :func:`update`, ``buf.size`` elements at a time (``buf``: float32
    scratch, the block's square roots)."""
    n = p.size
    b = buf.size
    for s in range(0, n, b):
        e = min(n, s + b)
        _step_block(p[s:e], g[s:e], m[s:e], v[s:e], w1, b2, c2, bc2s, eps, neg_step, buf[:e - s])


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def step_threads(p, g, m, v, w1, b2, c2, bc2s, eps, neg_step, bufs, per):
    """:func:`step` on numba's threads: thread ``t`` updates elements ``[t per, (t + 1) per)``
    (whole blocks of ``bufs.shape[1]``) with scratch ``bufs[t]``. Elementwise: the same
    numbers as :func:`step`. numba's own pool, not Python threads: after the rasterizer's
    parallel loops its OpenMP workers spin-wait on the other core, and a Python thread
    competing with them measured slower than one thread (docs/experiments/benchmark-history.md "Adam on numba's
    threads")."""
    n = p.size
    for t in prange(bufs.shape[0]):
        s = t * per
        e = min(n, s + per)
        if s < e:
            step(p[s:e], g[s:e], m[s:e], v[s:e], w1, b2, c2, bc2s, eps, neg_step, bufs[t])


@njit(cache=True, nogil=True)
def vml_sqrt(x, out):
    """``out[:] = sqrt(x)`` by :mod:`engine.numba_vml` (the exactness check's probe)."""
    _vml_sqrt32(x, out)


# ---- selective (sparse) Adam: engine.scene.selective_adam ------------------------------------
# The same per-element arithmetic as :func:`moments` / :func:`update` over the elements a step
# selects: flat float32 arrays of ``N`` rows of ``D`` elements; within a selected row, the
# element spans ``[start, stop)`` of ``spans`` (the whole row, or a curve's touched
# control-point columns). Adjacent selected ranges merge into runs (consecutive visible rows
# of a parameter updated whole: one long loop, vectorised like the dense kernels). The first
# pass leaves, compactly in visiting order, the square roots' inputs, the new first moments
# and whether the second moment is zero, so that torch's ``sqrt`` runs on the selected
# elements only and the second pass touches only the parameter at its (strided) places.


@njit(cache=True, nogil=True)
def select_runs(g, D, visible, spans, runs):
    """Element runs ``runs[:R]`` [R, 2] (uint64 start, length) of the rows ``r`` with
    ``visible[r]`` or a nonzero gradient ``g`` in a span, at ``spans`` [S, 2] (int64 (start,
    stop) within a row, ascending); adjacent ones merged. Returns (R, rows selected, elements)."""
    n_runs = 0
    n_rows = 0
    n_el = 0
    start = -1
    end = -1
    for r in range(visible.size):
        base = r * D
        take = visible[r]
        if not take:  # a loss term that is not a render (a prior, the spike-view flow) reached it
            for s in range(spans.shape[0]):
                a = base + spans[s, 0]
                for jj in range(spans[s, 1] - spans[s, 0]):
                    if g[a + jj] != 0:
                        take = True
        if not take:
            continue
        n_rows += 1
        for s in range(spans.shape[0]):
            a = base + spans[s, 0]
            length = spans[s, 1] - spans[s, 0]
            n_el += length
            if a != end:
                if end >= 0:
                    runs[n_runs, 0] = np.uint64(start)
                    runs[n_runs, 1] = np.uint64(end - start)
                    n_runs += 1
                start = a
            end = a + length
    if end >= 0:
        runs[n_runs, 0] = np.uint64(start)
        runs[n_runs, 1] = np.uint64(end - start)
        n_runs += 1
    return n_runs, n_rows, n_el


# The loops below index with unsigned integers (the runs' starts and lengths): numba then
# drops its negative-index handling, and LLVM vectorises a long run like the dense kernels.


@njit(cache=True, nogil=True)
def selective_moments(g, m, v, runs, n_runs, w1, b2, c2, root_in, m_out, zero):
    """:func:`moments` over ``runs[:n_runs]`` (:func:`select_runs`); writes compactly
    ``root_in`` (``v`` with its zeros replaced by 1), ``m_out`` (the new ``m``) and ``zero``
    (``v == 0``)."""
    one = np.float32(1.0)
    low = abs(w1) < np.float32(0.5)  # torch's lerp: two formulas around weight 0.5
    w1m = w1 - one
    k = np.uint64(0)
    for q in range(n_runs):
        a = runs[q, 0]
        length = runs[q, 1]
        if low:
            for j in range(length):
                i = a + j
                o = k + j
                gi = g[i]
                mi = _fma32(w1, gi - m[i], m[i])
                m[i] = mi
                m_out[o] = mi
                vi = _fma32(c2 * gi, gi, v[i] * b2)
                v[i] = vi
                zero[o] = vi == 0
                root_in[o] = vi if vi != 0 else one
        else:
            for j in range(length):
                i = a + j
                o = k + j
                gi = g[i]
                mi = _fma32(w1m, gi - m[i], gi)
                m[i] = mi
                m_out[o] = mi
                vi = _fma32(c2 * gi, gi, v[i] * b2)
                v[i] = vi
                zero[o] = vi == 0
                root_in[o] = vi if vi != 0 else one
        k += length


@njit(cache=True, nogil=True, error_model="numpy")
def selective_update(p, runs, n_runs, root, m_new, zero, bc2s, eps, neg_step):
    """:func:`update` over the runs of :func:`selective_moments`, reading its compact
    outputs (``root``: torch's square roots of its ``root_in``)."""
    zf = np.float32(0.0)
    k = np.uint64(0)
    for q in range(n_runs):
        a = runs[q, 0]
        length = runs[q, 1]
        for j in range(length):
            o = k + j
            sq = zf if zero[o] else root[o]
            p[a + j] = p[a + j] + (neg_step * m_new[o]) / (sq / bc2s + eps)
        k += length


# ---- lazy curve Adam: engine.scene.lazy_adam ----------------------------------------------
# A curve [N, K, C] (flat, D = K C floats a row) is updated at its touched columns ``cols``
# only, each first caught up on the steps it skipped: the parameter moved by ``coast[j]``
# times m / sqrt(v) (the skipped steps' momentum, summed in closed form) and the moments
# decayed by ``d1[j]`` = beta1^s, ``d2[j]`` = beta2^s. Then :func:`moments` / :func:`update`'s
# arithmetic per element, in one pass with an IEEE square root (torch's MKL root differs by
# an ulp here and there: the caller takes FusedAdam's pass when every column is touched and
# none skipped). A row's few columns are strided reads, bound by memory latency: one pass, the
# rows on numba's threads (a second pass over the same strided lines measured 2x the time), and
# the lines of the row ``ROWS_AHEAD`` ahead requested first (engine.numba_prefetch).


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def lazy_step(p, g, m, v, D, C, cols, coast, d1, d2, w1, b2, c2, has_grad, decay, bc2s, eps, neg_step, clear,
              write_mv):
    """Catch-up, then (``has_grad``) Adam at columns ``cols`` of every row, the gradient of the
    inner columns (``col % 3``) plus ``decay`` times the parameter (the inner-residual prior's,
    folded in); ``clear``: the gradient's entries set to zero once read (a kept gradient buffer,
    engine.scene.grad_buffers, zeroed in the pass that has its lines in the cache); ``write_mv``
    False: the moments are read, not written (a read's catch-up of the values alone)."""
    one = np.float32(1.0)
    zf = np.float32(0.0)
    low = abs(w1) < np.float32(0.5)  # torch's lerp: two formulas around weight 0.5
    w1m = w1 - one
    J = cols.size
    R = p.size // D
    for r in prange(R):
        base = r * D
        if r + ROWS_AHEAD < R:  # the lines of the row ahead requested now (numba_prefetch: 2.6x here)
            ahead = base + ROWS_AHEAD * D
            prefetch_columns(p, ahead, cols, C)
            prefetch_columns(m, ahead, cols, C)
            prefetch_columns(v, ahead, cols, C)
            if has_grad:
                prefetch_columns(g, ahead, cols, C)
        for j in range(J):
            a = base + cols[j] * C
            cj = coast[j]
            f1 = d1[j]
            f2 = d2[j]
            dj = decay if cols[j] % 3 != 0 else zf
            for c in range(C):
                i = a + c
                mi = m[i]
                vi = v[i]
                pi = p[i]
                pn = pi
                if cj != zf and vi > zf:
                    pn = pi - cj * (mi / np.sqrt(vi))
                mi = mi * f1
                vi = vi * f2
                if has_grad:
                    gi = g[i]
                    if clear:
                        g[i] = zf
                    if dj != zf:
                        gi = gi + dj * pi
                    if low:
                        mi = _fma32(w1, gi - mi, mi)
                    else:
                        mi = _fma32(w1m, gi - mi, gi)
                    vi = _fma32(c2 * gi, gi, vi * b2)
                    sq = np.sqrt(vi) if vi != zf else zf
                    pn = pn + (neg_step * mi) / (sq / bc2s + eps)
                if write_mv:
                    m[i] = mi
                    v[i] = vi
                p[i] = pn
