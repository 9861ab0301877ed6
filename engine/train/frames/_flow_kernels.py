"""numba kernels of the Lucas-Kanade flow (engine.train.frames.interpolation, issue 13).

Each one gives torch's numbers bit for bit (tests/test_interpolation.py); the warp's
equality rests on how torch's CPU grid sampler rounds (fused multiply-adds in its AVX2
build), so :mod:`engine.train.frames.interpolation` checks it against ``F.grid_sample`` once per
process and keeps torch's where they differ.

:func:`box_replicate` is ``F.avg_pool2d(F.pad(x, (r,) * 4, mode="replicate"), 2 r + 1,
stride=1)`` over float32 [P, H, W] planes, rounding exactly as torch's CPU kernel: per
output, ``sum = 0`` then the window added row by row, left to right, then ``sum / (2 r +
1) ** 2``. torch loops over the window per output (scalar code); here the loop over the
outputs of a row is innermost, so the same adds run 8 outputs per instruction (the
order of each output's sum is unchanged). ~46 % of an ``lk_flow`` was that pooling.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from ...numba_cache import install_cache_locator
from ...numba_fma import fma32 as _fma32

install_cache_locator(__name__)




@njit(cache=True, nogil=True)
def box_replicate(x, r, out):
    """``out[p]`` = the (2 r + 1)^2 box mean of ``x[p]`` with replicated borders; x, out
    float32 [P, H, W] contiguous."""
    n_planes, h, w = x.shape
    win = 2 * r + 1
    div = np.float32(win * win)
    zero = np.float32(0.0)
    acc = np.empty(w, np.float32)
    row = np.empty(w + 2 * r, np.float32)
    for p in range(n_planes):
        for oh in range(h):
            for j in range(w):
                acc[j] = zero
            for kh in range(win):
                ih = min(max(oh - r + kh, 0), h - 1)
                for j in range(w + 2 * r):
                    row[j] = x[p, ih, min(max(j - r, 0), w - 1)]
                for kw in range(win):
                    for j in range(w):
                        acc[j] = acc[j] + row[j + kw]
            for j in range(w):
                out[p, oh, j] = acc[j] / div


@njit(cache=True, nogil=True)
def median3_replicate(x, out):
    """``out[p]`` = the 3 x 3 median of ``x[p]`` (replicated borders; the lower median of
    the 9 values, i.e. the 5th smallest, as ``torch.median``; NaN if the window holds a
    NaN); x, out float32 [P, H, W] contiguous. A selection, not arithmetic: the values are
    torch's exactly."""
    n_planes, h, w = x.shape
    v = np.empty(9, np.float32)
    for p in range(n_planes):
        for i in range(h):
            for j in range(w):
                k = 0
                nan = False
                for di in range(-1, 2):
                    ii = min(max(i + di, 0), h - 1)
                    for dj in range(-1, 2):
                        val = x[p, ii, min(max(j + dj, 0), w - 1)]
                        nan |= val != val
                        v[k] = val
                        k += 1
                if nan:
                    out[p, i, j] = np.float32(np.nan)
                    continue
                for a in range(5):  # partial selection sort: v[4] ends the 5th smallest
                    m = a
                    for b in range(a + 1, 9):
                        if v[b] < v[m]:
                            m = b
                    t = v[a]
                    v[a] = v[m]
                    v[m] = t
                out[p, i, j] = v[4]


@njit(cache=True, nogil=True)
def _finite(flow):
    """All of ``flow`` finite (then every grid coordinate below is, and its int conversion safe)."""
    ok = True
    f = flow.reshape(-1)
    for k in range(f.size):
        ok &= np.isfinite(f[k])
    return ok


@njit(cache=True, nogil=True, inline="always")
def _corners(flow, b, i, j, w, h):
    """(x0, y0, has_east, has_south, nw, ne, sw, se) of the bilinear sample at pixel (i, j)
    moved by ``flow[b, :, i, j]``, as torch's grid sampler computes them (:func:`warp_border`)."""
    f32 = np.float32
    one, half, two, zero = f32(1.0), f32(0.5), f32(2.0), f32(0.0)
    wf, hf = f32(w), f32(h)
    gx = (f32(j) + flow[b, 0, i, j] + half) / wf * two - one
    gy = (f32(i) + flow[b, 1, i, j] + half) / hf * two - one
    x = min(max(_fma32(gx + one, wf / two, -half), zero), wf - one)
    y = min(max(_fma32(gy + one, hf / two, -half), zero), hf - one)
    x0 = np.floor(x)
    y0 = np.floor(y)
    we = x - x0
    ea = one - we
    no = y - y0
    so = one - no
    ix, iy = int(x0), int(y0)
    return ix, iy, ix + 1 < w, iy + 1 < h, so * ea, so * we, no * ea, no * we


@njit(cache=True, nogil=True, inline="always")
def _sample(img, bi, c, ix, iy, has_e, has_s, nw, ne, sw, se):
    zero = np.float32(0.0)
    v01 = img[bi, c, iy, ix + 1] if has_e else zero
    v10 = img[bi, c, iy + 1, ix] if has_s else zero
    v11 = img[bi, c, iy + 1, ix + 1] if (has_e and has_s) else zero
    acc = _fma32(v01, ne, img[bi, c, iy, ix] * nw)
    acc = _fma32(v10, sw, acc)
    return _fma32(v11, se, acc)


@njit(cache=True, nogil=True)
def warp_border(img, flow, out):
    """``out[b, c, i, j] = img[b % B_img, c](i + flow[b, 1, i, j], j + flow[b, 0, i, j])``:
    bilinear, border-clamped, as :func:`engine.train.frames.interpolation.warp` builds its grid and
    ``F.grid_sample(..., "bilinear", "border", align_corners=False)`` samples it (its AVX2
    kernel's order and fused multiply-adds: ``(g + 1) * size / 2 - 0.5`` and the four
    weighted corners accumulated left to right; a corner past the last row / column reads
    0 with weight 0). img float32 [B_img, C, H, W], flow float32 [B, 2, H, W] (B a multiple
    of B_img: flows of several candidates over the same images), out [B, C, H, W].
    Returns False (nothing written) for a non-finite flow: the caller then uses torch's."""
    if not _finite(flow):
        return False
    nb, h, w = flow.shape[0], flow.shape[2], flow.shape[3]
    for b in range(nb):
        bi = b % img.shape[0]
        for i in range(h):
            for j in range(w):
                ix, iy, has_e, has_s, nw, ne, sw, se = _corners(flow, b, i, j, w, h)
                for c in range(img.shape[1]):
                    out[b, c, i, j] = _sample(img, bi, c, ix, iy, has_e, has_s, nw, ne, sw, se)
    return True


@njit(cache=True, nogil=True)
def warped_sad(a, img, flow, out):
    """``out[b, 0] = sum_c |a[b % B_img, c] - warp(img, flow)[b, c]|`` (channels added left to
    right from 0, as torch's ``(a - warped).abs().sum(1, keepdim=True)``): the block
    matching's cost of each candidate flow without materialising the warped images.
    a, img float32 [B_img, C, H, W]; flow [B, 2, H, W]; out [B, 1, H, W]. False (nothing
    written) for a non-finite flow."""
    if not _finite(flow):
        return False
    nb, h, w = flow.shape[0], flow.shape[2], flow.shape[3]
    for b in range(nb):
        bi = b % img.shape[0]
        for i in range(h):
            for j in range(w):
                ix, iy, has_e, has_s, nw, ne, sw, se = _corners(flow, b, i, j, w, h)
                total = np.float32(0.0)
                for c in range(img.shape[1]):
                    total = total + abs(a[bi, c, i, j] - _sample(img, bi, c, ix, iy, has_e, has_s, nw, ne, sw, se))
                out[b, 0, i, j] = total
    return True


@njit(cache=True, nogil=True)
def select_best(costs, cands, n, best_cost, best):
    """The block matching's choice, in the candidates' order: candidate ``k`` (rows ``k b ..
    (k + 1) b - 1`` of ``costs`` [n b, 1, H, W] / ``cands`` [n b, 2, H, W]) replaces the best
    so far where its cost is below ``best_cost - 1e-7`` (float32, as torch computes it);
    ``best_cost`` [b, 1, H, W] and ``best`` [b, 2, H, W] in place."""
    b, h, w = best.shape[0], best.shape[2], best.shape[3]
    tol = np.float32(1e-7)
    for k in range(n):
        for q in range(b):
            r = k * b + q
            for i in range(h):
                for j in range(w):
                    c = costs[r, 0, i, j]
                    if c < best_cost[q, 0, i, j] - tol:
                        best_cost[q, 0, i, j] = c
                        best[q, 0, i, j] = cands[r, 0, i, j]
                        best[q, 1, i, j] = cands[r, 1, i, j]
