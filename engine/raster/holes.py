"""Fill what nothing covers (issue 14, "no black holes").

A render composites the Gaussians over a fixed background (black in training). Where the
accumulated alpha stays below 1 -- a crack between splats, a surface no train camera saw,
the border beyond every train frustum -- that background would show as if it were scene
content. :func:`fill_uncovered` replaces it by the colour the covered neighbourhood implies:
push-pull (Gortler et al. 1996) on the premultiplied image, i.e. the render composited over
a blurred, ever coarser version of itself, so a thin crack takes its edges' colour and a
wide empty border the colour of the nearest covered region, smoothly. Alpha is unchanged
(it still says what was reconstructed).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


def fill_uncovered(rgb: torch.Tensor, alpha: torch.Tensor, background, *, min_weight: float = 1e-4) -> torch.Tensor:
    """rgb [H,W,3] composited over ``background`` (3 floats), alpha [H,W] or [H,W,1] ->
    rgb [H,W,3] whose uncovered share ``1 - alpha`` shows the push-pull fill instead of the
    background. Pixels with alpha 1 are returned unchanged."""
    a = alpha.reshape(alpha.shape[0], alpha.shape[1], 1).clamp(0, 1)
    bg = torch.as_tensor(background, dtype=rgb.dtype, device=rgb.device).reshape(1, 1, 3)
    premult = (rgb - (1 - a) * bg).permute(2, 0, 1)[None]          # [1,3,H,W]
    w = a.permute(2, 0, 1)[None]                                      # [1,1,H,W]
    levels = [(premult, w)]
    while max(levels[-1][1].shape[-2:]) > 1:  # down to 1x1: every pixel reaches some coverage
        c, ww = levels[-1]
        levels.append((F.avg_pool2d(c, 2, ceil_mode=True), F.avg_pool2d(ww, 2, ceil_mode=True)))
    c, ww = levels[-1]
    est = torch.where(ww > min_weight, c / ww.clamp_min(min_weight), bg.permute(2, 0, 1)[None].expand_as(c))
    for c, ww in reversed(levels[1:-1]):
        up = F.interpolate(est, size=c.shape[-2:], mode="bilinear", align_corners=False)
        # normalised colour of this level composited over the coarser estimate
        norm = c / ww.clamp_min(min_weight)
        cover = ww.clamp(0, 1)
        est = torch.where(ww > min_weight, norm, up) * cover + up * (1 - cover)
    fill = F.interpolate(est, size=premult.shape[-2:], mode="bilinear", align_corners=False)
    return (premult[0].permute(1, 2, 0) + (1 - a) * fill[0].permute(1, 2, 0)).clamp(0, 1)
