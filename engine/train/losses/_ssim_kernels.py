"""numba kernels of :func:`engine.train.losses.fused_ssim.fused_ssim` (issue 13).

SSIM as ``pytorch_msssim.ssim`` computes it (a separable Gaussian window applied without
padding, "valid": the maps are ``(H - w + 1) x (W - w + 1)``; K1 = 0.01, K2 = 0.03), on
images laid out [H, W, C] (a render's layout: no permute copies). An image row of ``W``
pixels by ``C`` channels is one flat run of ``W C`` values, so each window tap is one
contiguous multiply-add over a row (``j + k C``): LLVM vectorises the loops.

Backward (hand-written; tests compare it with autograd through ``pytorch_msssim`` and run
``gradcheck`` in float64): with ``S = A1 A2 / (B1 B2)``, ``A1 = 2 mu_x mu_y + C1``,
``B1 = mu_x^2 + mu_y^2 + C1``, ``A2 = 2 (s_xy - mu_x mu_y) + C2``,
``B2 = (s_xx - mu_x^2) + (s_yy - mu_y^2) + C2`` (``s_..`` the blurred products)::

    dS/dmu_x = 2 mu_y (A2 - A1) / (B1 B2) - 2 mu_x S (1 / B1 - 1 / B2)
    dS/ds_xx = -S / B2        dS/ds_xy = 2 A1 / (B1 B2)
    dL/dx = blur^T(dL/dmu_x) + 2 x blur^T(dL/ds_xx) + y blur^T(dL/ds_xy)

where ``blur^T`` is the adjoint of the valid blur (the window spread back, zero outside).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from ...numba_cache import install_cache_locator

install_cache_locator(__name__)


@njit(cache=True, nogil=True)
def _blur_rows(src, win, C, out):
    """``out[h, j] = sum_k win[k] src[h, j + k C]`` over ``j < out.shape[1]`` (a valid
    horizontal blur of [H, W C] rows)."""
    n = out.shape[1]
    for h in range(src.shape[0]):
        dst = out[h]
        for j in range(n):
            dst[j] = 0.0
        for k in range(win.size):
            w = win[k]
            s = src[h, k * C:k * C + n]  # a slice: loop indices from 0, no negative-index checks
            for j in range(n):
                dst[j] += w * s[j]


@njit(cache=True, nogil=True)
def _blur_cols(src, win, out):
    """``out[i, j] = sum_k win[k] src[i + k, j]`` (a valid vertical blur)."""
    for i in range(out.shape[0]):
        dst = out[i]
        for j in range(dst.size):
            dst[j] = 0.0
        for k in range(win.size):
            w = win[k]
            s = src[i + k]
            for j in range(dst.size):
                dst[j] += w * s[j]


@njit(cache=True, nogil=True)
def ssim_forward(x, y, win, C, consts, need_grad, coef):
    """SSIM of ``x`` against ``y`` ([H, W C] float, the same dtype); returns the sum of the
    SSIM map (float64) and its size. ``consts``: [C1, C2, 2, 1] in that dtype (numba would
    make a Python float literal float64 and the arithmetic with it). With ``need_grad``,
    ``coef`` [3, H', W' C] receives dS/dmu_x, dS/ds_xx, dS/ds_xy at each map element
    (module docstring)."""
    H = x.shape[0]
    ws = win.size
    Ho = H - ws + 1
    n = x.shape[1] - (ws - 1) * C
    xx = x * x
    yy = y * y
    xy = x * y
    rows = np.empty((5, H, n), x.dtype)
    _blur_rows(x, win, C, rows[0])
    _blur_rows(y, win, C, rows[1])
    _blur_rows(xx, win, C, rows[2])
    _blur_rows(yy, win, C, rows[3])
    _blur_rows(xy, win, C, rows[4])
    maps = np.empty((5, Ho, n), x.dtype)
    for q in range(5):
        _blur_cols(rows[q], win, maps[q])
    c1, c2, two, one = consts[0], consts[1], consts[2], consts[3]
    total = 0.0
    for i in range(Ho):
        mx, my, sxx, syy, sxy = maps[0, i], maps[1, i], maps[2, i], maps[3, i], maps[4, i]
        ca, cb, cc = coef[0, i], coef[1, i], coef[2, i]
        for j in range(n):
            mxy = mx[j] * my[j]
            mx2 = mx[j] * mx[j]
            my2 = my[j] * my[j]
            a1 = two * mxy + c1
            b1 = mx2 + my2 + c1
            a2 = two * (sxy[j] - mxy) + c2
            b2 = (sxx[j] - mx2) + (syy[j] - my2) + c2
            den = b1 * b2
            s = a1 * a2 / den
            total += s
            if need_grad:
                ca[j] = two * my[j] * (a2 - a1) / den - two * mx[j] * s * (one / b1 - one / b2)
                cb[j] = -s / b2
                cc[j] = two * a1 / den
    return total, Ho * n


@njit(cache=True, nogil=True)
def _spread(src, win, C, W, out):
    """``blur^T``: the adjoint of ``_blur_cols(_blur_rows(.))`` of a [H', W' C] map into
    ``out`` [H' + w - 1, W C]."""
    ws = win.size
    Ho, n = src.shape
    tmp = np.zeros((Ho + ws - 1, n), src.dtype)
    for i in range(Ho):
        s = src[i]
        for k in range(ws):
            w = win[k]
            d = tmp[i + k]
            for j in range(n):
                d[j] += w * s[j]
    for h in range(out.shape[0]):
        row = out[h]
        for j in range(row.size):
            row[j] = 0.0
        t = tmp[h]
        for k in range(ws):
            w = win[k]
            d = row[k * C:k * C + n]
            for j in range(n):
                d[j] += w * t[j]


@njit(cache=True, nogil=True)
def ssim_backward(x, y, win, C, coef, scale, two, out):
    """dL/dx [H, W C] into ``out`` for dL/dS = ``scale`` at every map element (``scale``,
    ``two``: scalars of the images' dtype)."""
    H, WC = x.shape
    a = np.empty((H, WC), x.dtype)
    b = np.empty((H, WC), x.dtype)
    c = np.empty((H, WC), x.dtype)
    _spread(coef[0], win, C, WC, a)
    _spread(coef[1], win, C, WC, b)
    _spread(coef[2], win, C, WC, c)
    for h in range(H):
        o, ah, bh, ch, xh, yh = out[h], a[h], b[h], c[h], x[h], y[h]
        for j in range(WC):
            o[j] = scale * (ah[j] + two * xh[j] * bh[j] + yh[j] * ch[j])
