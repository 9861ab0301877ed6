"""Image metrics on sRGB-encoded images in [0, 1] (numpy [H,W,3] or torch).

PSNR and SSIM (pytorch_msssim, ``data_range=1``, 11x11 Gaussian window, as the papers
report); a motion mask from ground truth (pixels whose ground truth changes between
neighbouring eval frames by more than ``threshold``, max over channels, dilated); and the
static pixels (whose ground truth never changes over the capture) with the drift of their
mean colour between RGB instants.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from pytorch_msssim import ssim as _ssim


def _t(img) -> torch.Tensor:
    """[H,W,C] array/tensor -> [1,C,H,W] float32 tensor."""
    x = torch.as_tensor(np.asarray(img) if not isinstance(img, torch.Tensor) else img).float()
    if x.dim() == 2:
        x = x[..., None]
    return x.permute(2, 0, 1)[None]


def mse(pred, gt, mask=None) -> float:
    p, g = _t(pred), _t(gt)
    d = (p - g) ** 2
    if mask is None:
        return float(d.mean())
    m = torch.as_tensor(np.asarray(mask), dtype=torch.bool)
    if not bool(m.any()):
        return float("nan")
    return float(d[0][:, m].mean())


def psnr_from_mse(value: float) -> float:
    if value != value:  # nan
        return float("nan")
    return 10.0 * math.log10(1.0 / max(value, 1e-12))


def psnr(pred, gt, mask=None) -> float:
    """PSNR in dB for images in [0, 1]; with ``mask`` [H,W] only over those pixels (nan if empty)."""
    return psnr_from_mse(mse(pred, gt, mask))


def ssim(pred, gt) -> float:
    """SSIM (pytorch_msssim, data_range=1). Images smaller than the 11 px window use a smaller one."""

    p, g = _t(pred).clamp(0, 1), _t(gt).clamp(0, 1)
    win = 11
    m = min(p.shape[-2:])
    if m < win:
        win = max(3, m - (1 - m % 2))  # odd and <= the image size
    return float(_ssim(p, g, data_range=1.0, size_average=True, win_size=win))


def motion_mask(prev_gt, gt, next_gt, threshold: float = 0.04, dilate: int = 2) -> np.ndarray:
    """bool [H,W]: pixels whose GT changes to the previous or next frame by > ``threshold``.

    ``prev_gt`` / ``next_gt`` may be None (first / last frame). Dilated by ``dilate`` px.
    """
    g = np.asarray(gt, dtype=np.float32)[..., :3]
    m = np.zeros(g.shape[:2], dtype=bool)
    for other in (prev_gt, next_gt):
        if other is None:
            continue
        m |= np.abs(np.asarray(other, dtype=np.float32)[..., :3] - g).max(axis=-1) > threshold
    if dilate > 0 and m.any():
        t = torch.from_numpy(m.astype(np.float32))[None, None]
        m = F.max_pool2d(t, 2 * dilate + 1, stride=1, padding=dilate)[0, 0].numpy() > 0.5
    return m


def motion_masks(gts: list, threshold: float = 0.04, dilate: int = 2) -> list[np.ndarray]:
    """Motion masks of a time-sorted sequence of GT images of one camera."""
    out = []
    for i, g in enumerate(gts):
        prev = gts[i - 1] if i > 0 else None
        nxt = gts[i + 1] if i + 1 < len(gts) else None
        out.append(motion_mask(prev, g, nxt, threshold, dilate))
    return out


def is_interframe(t: float, rgb_times, tol: float = 1e-4) -> bool:
    """True when ``t`` lies strictly between two RGB frame times (and on none of them)."""
    times = np.asarray(sorted(rgb_times), dtype=np.float64)
    if len(times) < 2:
        return False
    if np.min(np.abs(times - t)) <= tol:
        return False
    return bool(times[0] < t < times[-1])


def static_mask(gts: list, tol: float = 0.03) -> np.ndarray:
    """bool [H, W]: the pixels whose ground truth never changes over a camera's frames ``gts``
    ([H, W, C] each): within ``tol`` of their temporal median in every frame and channel. What
    does not move must render identically at every instant; these pixels measure it."""
    stack = np.stack([np.asarray(g, np.float32)[..., :3] for g in gts])
    return (np.abs(stack - np.median(stack, axis=0)).max(axis=(0, 3)) <= tol)


def static_colour_bias(pred, gt, mask: np.ndarray) -> np.ndarray | None:
    """[3]: the mean colour error (render - truth) over the ``mask`` pixels, or None if empty."""
    if not mask.any():
        return None
    p = pred.detach().cpu().numpy() if isinstance(pred, torch.Tensor) else np.asarray(pred)
    return (p.astype(np.float32)[..., :3][mask] - np.asarray(gt, np.float32)[..., :3][mask]).mean(axis=0)


def static_colour_shift(biases: list, interframe: list) -> float | None:
    """The largest change of the static pixels' mean colour error between RGB instants: max over the
    between-instant frames of max_c |bias_t - bias at the RGB instants| (their mean). 0 for a model
    that holds still what does not move; None without both kinds of frame."""
    at = [b for b, inter in zip(biases, interframe) if b is not None and not inter]
    between = [b for b, inter in zip(biases, interframe) if b is not None and inter]
    if not at or not between:
        return None
    ref = np.mean(at, axis=0)
    return float(max(np.abs(b - ref).max() for b in between))
