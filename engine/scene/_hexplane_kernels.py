"""numba kernels of the fused HexPlane sampler (issue 13): forward and hand-derived backward.

Imported lazily by :mod:`engine.scene.hexplane_fused` (numba is optional). One call
handles one resolution level: the three spatial planes ``sp`` [3, R, R, C] and the three
time planes ``tp`` [3, T, R, C], **channels last** so that the C features of a texel are
contiguous and the per-point channel loops vectorise. Plane ``p`` is sampled at the
coordinates (``xyzt[:, PA[p]]``, ``xyzt[:, PB[p]]``): the first indexes the width (last
spatial axis), the second the height, exactly as ``F.grid_sample`` reads a grid.

Semantics are ``grid_sample(mode="bilinear", padding_mode="border", align_corners=True)``:
``u -> (u + 1) / 2 * (size - 1)`` then clipped to [0, size - 1]; the clip passes the
coordinate gradient only strictly inside (0, size - 1): a point on the border gets none,
as from torch's CPU kernel (measured: ``grid_sample`` at u = -1 or 1 returns a zero
coordinate gradient). A NaN coordinate reads texel 0 (torch would return NaN): the
kernels index memory with it, so it must not leave the grid.

The four coordinates of a point are mapped to texels once (x, y, z on the R texels of
every spatial axis, t on the T rows) and shared by the six planes. Parallel over points
in ``n_chunks`` contiguous chunks; the backward accumulates each chunk's grid gradient in
its own buffer (summed afterwards in chunk order), so results do not depend on thread
scheduling (only on ``n_chunks``).

Measured (20k points, 16 features, levels 24 and 48, 43 time rows, one thread, CPU time):
forward + backward 24 ms against 79 ms for the ``grid_sample`` reference.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..numba_cache import install_cache_locator

install_cache_locator(__name__)

# (width coordinate, height coordinate) of the six planes xy xz yz xt yt zt; 3 is time
PA = np.array([0, 0, 1, 0, 1, 2], np.int64)
PB = np.array([1, 2, 2, 3, 3, 3], np.int64)


@njit(cache=True, nogil=True, inline="always")
def _axes(xyzt, n, lim_r, lim_t, one, half, zero, i0, i1, w0, w1, du):
    """Texel coordinates of point ``n``'s x, y, z (last texel ``lim_r``) and t (``lim_t``),
    in the coordinates' dtype: floor index ``i0``, next index ``i1`` (= i0 on the last
    texel, whose weight ``w1`` is then 0), weights ``w0`` / ``w1`` and d texel / d u
    (``du``: 0 on or beyond the border)."""
    for a in range(4):
        lim = lim_t if a == 3 else lim_r
        f = (xyzt[n, a] + one) * half * lim
        d = half * lim
        if f >= lim:  # on or beyond the border: torch's CPU kernel passes no gradient there
            f = lim
            d = zero
        elif not (f > zero):  # on or below the border, or NaN
            f = zero
            d = zero
        f0 = np.floor(f)
        i = int(f0)
        i0[a] = i
        i1[a] = i + 1 if f0 < lim else i
        w1[a] = f - f0
        w0[a] = (f0 + one) - f
        du[a] = d


@njit(parallel=True, cache=True, error_model="numpy", fastmath={"contract"})
def hexplane_fwd(xyzt, sp, tp, out, col0, n_chunks):
    """xyzt [N, 4] in [-1, 1]; sp [3, R, R, C]; tp [3, T, R, C] -> out[:, col0:col0+C]
    (the product over the six planes of their bilinear samples)."""
    N = xyzt.shape[0]
    C = sp.shape[3]
    one = xyzt.dtype.type(1.0)
    half = xyzt.dtype.type(0.5)
    zero = xyzt.dtype.type(0.0)
    lim_r = xyzt.dtype.type(sp.shape[2] - 1)
    lim_t = xyzt.dtype.type(tp.shape[1] - 1)
    step = (N + n_chunks - 1) // n_chunks
    for k in prange(n_chunks):
        acc = np.empty(C, xyzt.dtype)
        i0 = np.empty(4, np.int64)
        i1 = np.empty(4, np.int64)
        w0 = np.empty(4, xyzt.dtype)
        w1 = np.empty(4, xyzt.dtype)
        du = np.empty(4, xyzt.dtype)
        for n in range(k * step, min(N, (k + 1) * step)):
            _axes(xyzt, n, lim_r, lim_t, one, half, zero, i0, i1, w0, w1, du)
            for c in range(C):
                acc[c] = one
            for p in range(6):
                g = sp[p] if p < 3 else tp[p - 3]
                a, b = PA[p], PB[p]
                x0, x1, y0, y1 = i0[a], i1[a], i0[b], i1[b]
                wx0, wx1, wy0, wy1 = w0[a], w1[a], w0[b], w1[b]
                for c in range(C):
                    acc[c] *= (wy0 * (wx0 * g[y0, x0, c] + wx1 * g[y0, x1, c])
                               + wy1 * (wx0 * g[y1, x0, c] + wx1 * g[y1, x1, c]))
            for c in range(C):
                out[n, col0 + c] = acc[c]


@njit(parallel=True, cache=True, error_model="numpy", fastmath={"contract", "reassoc", "nsz"})
def hexplane_bwd(xyzt, sp, tp, gout, col0, n_chunks, gsp, gtp, gxyzt, want_coords):
    """Backward of :func:`hexplane_fwd`. gout [N, *] (columns col0:col0+C are this level's);
    gsp [n_chunks, 3, R, R, C] and gtp [n_chunks, 3, T, R, C] (zeroed by the caller) get
    each chunk's plane gradients; with ``want_coords`` gxyzt [N, 4] += the coordinate
    gradient (all four; the caller keeps what it needs)."""
    N = xyzt.shape[0]
    C = sp.shape[3]
    one = xyzt.dtype.type(1.0)
    half = xyzt.dtype.type(0.5)
    zero = xyzt.dtype.type(0.0)
    lim_r = xyzt.dtype.type(sp.shape[2] - 1)
    lim_t = xyzt.dtype.type(tp.shape[1] - 1)
    step = (N + n_chunks - 1) // n_chunks
    for k in prange(n_chunks):
        s = np.empty((6, C), xyzt.dtype)    # each plane's sample
        sx = np.empty((6, C), xyzt.dtype)   # its derivative along the plane's x (per texel)
        sy = np.empty((6, C), xyzt.dtype)   # ... and y
        dl = np.empty((7, C), xyzt.dtype)   # products of the planes before p, then d loss / d s[p]
        after = np.empty(C, xyzt.dtype)
        i0 = np.empty(4, np.int64)
        i1 = np.empty(4, np.int64)
        w0 = np.empty(4, xyzt.dtype)
        w1 = np.empty(4, xyzt.dtype)
        du = np.empty(4, xyzt.dtype)
        for n in range(k * step, min(N, (k + 1) * step)):
            _axes(xyzt, n, lim_r, lim_t, one, half, zero, i0, i1, w0, w1, du)
            for p in range(6):
                g = sp[p] if p < 3 else tp[p - 3]
                a, b = PA[p], PB[p]
                x0, x1, y0, y1 = i0[a], i1[a], i0[b], i1[b]
                wx0, wx1, wy0, wy1 = w0[a], w1[a], w0[b], w1[b]
                for c in range(C):
                    v00 = g[y0, x0, c]
                    v01 = g[y0, x1, c]
                    v10 = g[y1, x0, c]
                    v11 = g[y1, x1, c]
                    top = wx0 * v00 + wx1 * v01
                    bottom = wx0 * v10 + wx1 * v11
                    s[p, c] = wy0 * top + wy1 * bottom
                    sx[p, c] = wy0 * (v01 - v00) + wy1 * (v11 - v10)
                    sy[p, c] = bottom - top
            for c in range(C):
                dl[0, c] = one
                after[c] = gout[n, col0 + c]
            for p in range(6):
                for c in range(C):
                    dl[p + 1, c] = dl[p, c] * s[p, c]
            # d loss / d s[p] = gout * (product before p) * (product after p), no division
            for p in range(5, -1, -1):
                for c in range(C):
                    dl[p, c] = dl[p, c] * after[c]
                    after[c] = after[c] * s[p, c]
            for p in range(6):
                a, b = PA[p], PB[p]
                x0, x1, y0, y1 = i0[a], i1[a], i0[b], i1[b]
                wx0, wx1, wy0, wy1 = w0[a], w1[a], w0[b], w1[b]
                buf = gsp[k, p] if p < 3 else gtp[k, p - 3]
                w00 = wx0 * wy0
                w01 = wx1 * wy0
                w10 = wx0 * wy1
                w11 = wx1 * wy1
                # on the last texel x1 = x0 with w01 = w11 = 0: adding 0 there is harmless
                for c in range(C):
                    buf[y0, x0, c] += w00 * dl[p, c]
                for c in range(C):
                    buf[y0, x1, c] += w01 * dl[p, c]
                for c in range(C):
                    buf[y1, x0, c] += w10 * dl[p, c]
                for c in range(C):
                    buf[y1, x1, c] += w11 * dl[p, c]
                if want_coords:
                    gx = zero
                    gy = zero
                    for c in range(C):
                        gx += dl[p, c] * sx[p, c]
                        gy += dl[p, c] * sy[p, c]
                    gxyzt[n, a] += gx * du[a]
                    gxyzt[n, b] += gy * du[b]
