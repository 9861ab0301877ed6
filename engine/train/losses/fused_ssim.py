"""SSIM of a render against its target in two numba passes, with a hand-written backward (issue 13).

The D-SSIM term of the frame loss (paper Eq. 22, ``engine.train.losses.terms``) called
``pytorch_msssim.ssim``: ten grouped ``conv2d`` calls (a separable 11-tap Gaussian window
over five maps), about twenty element-wise tensors and their autograd backward, on a
[1, 3, H, W] permuted copy of the render. :func:`fused_ssim` computes the same value
(``data_range=1``, ``win_size=11``, ``win_sigma=1.5``, K = (0.01, 0.03), valid window, mean
over the map) from the render's own [H, W, 3] layout in one kernel, and its gradient in one
more (:mod:`engine.train.losses._ssim_kernels`); only the prediction gets a gradient (the target is
data). Float rounding aside it equals ``pytorch_msssim.ssim`` in value and gradient (tests:
against autograd through it, and ``gradcheck`` in float64).
"""
from __future__ import annotations

import numpy as np
import torch

from ...numba_cache import LazyKernels

KERNELS = LazyKernels(__package__, "_ssim_kernels")

WIN_SIZE, WIN_SIGMA, K1, K2 = 11, 1.5, 0.01, 0.03
# False: the D-SSIM term uses pytorch_msssim (bench-step's "ssim-msssim" variant switches it)
ENABLED = True


def gaussian_window(dtype=torch.float32) -> torch.Tensor:
    """The 1-D window [11], as ``pytorch_msssim._fspecial_gauss_1d`` builds it (float32)."""
    coords = torch.arange(WIN_SIZE, dtype=torch.float)
    coords -= WIN_SIZE // 2
    g = torch.exp(-(coords ** 2) / (2 * WIN_SIGMA ** 2))
    g /= g.sum()
    return g.to(dtype)


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred, target):
        k = KERNELS.module
        h, w, c = pred.shape
        x = pred.detach().contiguous().reshape(h, w * c).numpy()
        y = target.detach().to(pred.dtype).contiguous().reshape(h, w * c).numpy()
        win = gaussian_window(pred.dtype).numpy()
        consts = np.array([K1 ** 2, K2 ** 2, 2.0, 1.0], dtype=x.dtype)  # data_range 1
        need = ctx.needs_input_grad[0]
        coef = np.empty((3, h - WIN_SIZE + 1, (w - WIN_SIZE + 1) * c) if need else (3, 0, 0), x.dtype)
        total, count = k.ssim_forward(x, y, win, c, consts, need, coef)
        ctx.keep = (x, y, win, c, coef, count, pred.shape)
        return pred.new_tensor(total / count)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        x, y, win, c, coef, count, shape = ctx.keep
        out = np.empty_like(x)
        scale = x.dtype.type(float(grad) / count)
        KERNELS.module.ssim_backward(x, y, win, c, coef, scale, x.dtype.type(2.0), out)
        return torch.from_numpy(out).reshape(shape), None


def fused_ssim(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor | None:
    """Mean SSIM (scalar tensor) of ``pred`` against ``target``, both [H, W, C] in [0, 1] (or
    [1, H, W, C]); differentiable in ``pred``. None when the images are smaller than the
    window, or where the kernels cannot run (not CPU / float32-64, no numba): the caller
    falls back to ``pytorch_msssim``."""
    if pred.dim() == 4:
        if pred.shape[0] != 1:
            return None
        pred, target = pred[0], target[0]
    if (not ENABLED or pred.device.type != "cpu" or pred.dtype not in (torch.float32, torch.float64)
            or pred.shape != target.shape or min(pred.shape[:2]) < WIN_SIZE or KERNELS.load() is None):
        return None
    return _FusedSSIM.apply(pred, target)


def warmup() -> float:
    """Compile (first run on a machine) or load the kernels now; seconds taken."""
    import time

    t0 = time.perf_counter()
    p = torch.rand(12, 12, 3, requires_grad=True)
    s = fused_ssim(p, torch.rand(12, 12, 3))
    if s is not None:
        s.backward()
    return time.perf_counter() - t0
