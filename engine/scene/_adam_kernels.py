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
