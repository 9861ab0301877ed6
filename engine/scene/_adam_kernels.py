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
from numba import njit, types
from numba.extending import intrinsic

from ..numba_cache import install_cache_locator

install_cache_locator(__name__)


@intrinsic
def _fma32(typingctx, a, b, c):
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return sig, codegen


# Serial loops from index 0 (numba then drops its negative-index handling and LLVM
# vectorises them: 8 floats per instruction); ``error_model="numpy"``: IEEE division with no
# zero check, which would stop the vectoriser too. ``parallel=True`` measured slower (CPU
# time) on this 2-core machine: the work is memory-bound.


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


# ---- selective (sparse) Adam: engine.scene.selective_adam ------------------------------------
# The same per-element arithmetic as :func:`moments` / :func:`update`, over the rows a step
# selects and, within each row, the element spans ``[start, stop)`` it selects (a curve's
# touched control-point columns); the square roots travel in a compact buffer in visiting
# order (rows ascending, spans in order), so torch's ``sqrt`` runs on the selected elements only.


@njit(cache=True, nogil=True)
def selective_moments(g, m, v, visible, spans, w1, b2, c2, root_in, sel):
    """:func:`moments` on the rows ``r`` of the [N, D] arrays ``g, m, v`` (float32) with
    ``visible[r]`` or a nonzero gradient in a span, at the elements of ``spans`` [S, 2]
    (int64 ``(start, stop)``) only. Writes the selected rows to ``sel`` [N] (ascending)
    and the root inputs compactly to ``root_in``; returns (rows selected, elements written)."""
    one = np.float32(1.0)
    low = abs(w1) < np.float32(0.5)  # torch's lerp: two formulas around weight 0.5
    w1m = w1 - one
    n_sel = 0
    k = 0
    for r in range(g.shape[0]):
        take = visible[r]
        if not take:  # a loss term that is not a render (a prior, the spike-view flow) reached it
            for s in range(spans.shape[0]):
                for j in range(spans[s, 0], spans[s, 1]):
                    if g[r, j] != 0:
                        take = True
                        break
                if take:
                    break
        if not take:
            continue
        sel[n_sel] = r
        n_sel += 1
        for s in range(spans.shape[0]):
            for j in range(spans[s, 0], spans[s, 1]):
                gi = g[r, j]
                mi = m[r, j]
                if low:
                    m[r, j] = _fma32(w1, gi - mi, mi)
                else:
                    m[r, j] = _fma32(w1m, gi - mi, gi)
                vi = _fma32(c2 * gi, gi, v[r, j] * b2)
                v[r, j] = vi
                root_in[k] = vi if vi != 0 else one
                k += 1
    return n_sel, k


@njit(cache=True, nogil=True, error_model="numpy")
def selective_update(p, m, v, root, sel, n_sel, spans, bc2s, eps, neg_step):
    """:func:`update` on the rows ``sel[:n_sel]`` and ``spans`` of :func:`selective_moments`,
    reading its compact square roots ``root`` in the same order."""
    zero = np.float32(0.0)
    k = 0
    for i in range(n_sel):
        r = sel[i]
        for s in range(spans.shape[0]):
            for j in range(spans[s, 0], spans[s, 1]):
                sq = root[k] if v[r, j] != 0 else zero
                p[r, j] = p[r, j] + (neg_step * m[r, j]) / (sq / bc2s + eps)
                k += 1
