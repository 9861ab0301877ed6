"""The resolution geometry works at: stereo, fusion and the initial cloud's backdrop (points beyond
the image borders, :func:`backdrop_points`) are sized by what they need, not by the camera's pixel
count (issue 43: at the paper's 1080x720 they took minutes and GBs, and the backdrop ring alone
became 170k Gaussians)."""
from __future__ import annotations

import cv2
import numpy as np

from ..cameras import View

# Stereo matching and fusion run at most this wide (the images area-averaged down, the cameras
# scaled): at the paper's 1080x720 full-size fusion held [T, T, H, W] arrays (GBs) and took minutes
# (issue 43); the depth priors get the fused depth back at the frames' size (at_size). Captures up
# to this width are matched as before, bit for bit.
FUSION_MAX_WIDTH = 480
# The backdrop ring beyond the image borders: one point every 4 px up to this width, then sparser,
# so a wider image gets no more backdrop points than this width does
BACKDROP_REFERENCE_WIDTH = 320


def backdrop_stride(width: int, stride: int = 4) -> int:
    """Pixels between backdrop points for an image ``width`` wide (``stride`` up to
    :data:`BACKDROP_REFERENCE_WIDTH`, proportionally more beyond)."""
    return max(stride, int(round(stride * width / BACKDROP_REFERENCE_WIDTH)))


def working_view(view):
    """``view`` at the resolution stereo and fusion run at: at most :data:`FUSION_MAX_WIDTH` wide
    (the same view when it is no wider)."""
    k = view.intrinsics
    if k.width <= FUSION_MAX_WIDTH:
        return view
    w = FUSION_MAX_WIDTH
    h = max(1, int(round(k.height * w / k.width)))
    return View(k.scaled(w, h), view.c2w, view.time, view.name)


def resized_to(image: np.ndarray, view) -> np.ndarray:
    """``image`` at ``view``'s size (area-averaged when smaller; unchanged when it already is)."""
    k = view.intrinsics
    image = np.asarray(image)
    if image.shape[:2] == (k.height, k.width):
        return image
    return cv2.resize(np.asarray(image, np.float32), (k.width, k.height), interpolation=cv2.INTER_AREA)


def at_size(array: np.ndarray, height: int, width: int) -> np.ndarray:
    """A per-pixel map ([H, W], from a working-resolution fusion) at ``height`` x ``width``, nearest
    sample: interpolating depth across an edge would invent surfaces in between."""
    array = np.asarray(array)
    if array.shape[:2] == (height, width):
        return array
    src = array.astype(np.uint8) if array.dtype == bool else array
    out = cv2.resize(src, (width, height), interpolation=cv2.INTER_NEAREST)
    return out.astype(bool) if array.dtype == bool else out


def extrapolate_inverse_depth(inv: np.ndarray, pad_x: int, pad_y: int, k: int = 6) -> np.ndarray:
    """[H + 2 pad_y, W + 2 pad_x] inverse depth continued linearly beyond each border from the
    slope over the last ``k`` pixels (a plane's inverse depth is affine in pixel coordinates,
    so a floor or wall continues as itself); clamped to stay positive (beyond the horizon:
    the farthest value seen)."""
    floor = float(np.nanmin(inv[inv > 0])) if np.any(inv > 0) else 1e-3

    def extend_cols(a: np.ndarray, pad: int) -> np.ndarray:
        if pad <= 0:
            return a
        kk = min(k, a.shape[1] - 1)
        r = np.arange(1, pad + 1, dtype=np.float64)[None, :]
        sl = (a[:, :1] - a[:, kk:kk + 1]) / kk
        sr = (a[:, -1:] - a[:, -1 - kk:-kk]) / kk
        left = (a[:, :1] + sl * r)[:, ::-1]
        right = a[:, -1:] + sr * r
        return np.concatenate([left, a, right], 1)

    out = extend_cols(np.asarray(inv, np.float64), pad_x)
    out = extend_cols(out.T, pad_y).T
    return np.maximum(out, floor).astype(np.float32)


def continued_depth(view, filled_depth: np.ndarray, fraction: float) -> np.ndarray:
    """[H + 2 py, W + 2 px] planar depth of ``view``: ``filled_depth`` (its hole-filled static
    depth, 0 where unknown) continued a ring ``fraction`` x the image size wide beyond each border
    by :func:`extrapolate_inverse_depth`; NaN where nothing is known."""
    k = view.intrinsics
    px, py = int(round(fraction * k.width)), int(round(fraction * k.height))
    inv = np.where(filled_depth > 0, 1.0 / np.maximum(filled_depth, 1e-9), 0.0)
    if not np.any(inv > 0):
        return np.full((k.height + 2 * py, k.width + 2 * px), np.nan, np.float32)
    ext = extrapolate_inverse_depth(inv, px, py)
    return np.where(ext > 0, 1.0 / np.maximum(ext, 1e-12), np.nan).astype(np.float32)


def backdrop_points(fused, filled_depth: np.ndarray, fraction: float, stride: int = 4):
    """Points beyond the image borders of the camera of ``fused`` (a stereo.FusedDepth; a ring
    ``fraction`` x the image size wide): depth continued from the (hole-filled) static depth by
    :func:`extrapolate_inverse_depth`, colour the nearest border pixel's. What a viewer sees
    where no train camera looked (docs/experiments/two-view-geometry.md "No black holes"). Returns (xyz [N,3], rgb
    [N,3])."""
    k = fused.view.intrinsics
    px, py = int(round(fraction * k.width)), int(round(fraction * k.height))
    if px <= 0 and py <= 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    depth_ext = continued_depth(fused.view, filled_depth, fraction)
    med = np.median(fused.images, axis=0).astype(np.float32)
    col = cv2.copyMakeBorder(med, py, py, px, px, cv2.BORDER_REPLICATE)
    He, We = depth_ext.shape
    ring = np.ones((He, We), bool)
    ring[py:py + k.height, px:px + k.width] = False
    grid = np.zeros_like(ring)
    grid[stride // 2::stride, stride // 2::stride] = True
    sel = ring & grid
    v, u = np.nonzero(sel)
    d = depth_ext[v, u]
    cam = np.stack([(u - px + 0.5 - k.cx) / k.fx * d, (v - py + 0.5 - k.cy) / k.fy * d, d], -1)
    c2w = np.linalg.inv(np.asarray(fused.view.viewmat, np.float64))
    xyz = cam @ c2w[:3, :3].T + c2w[:3, 3]
    return xyz.astype(np.float32), col[v, u].astype(np.float32)
