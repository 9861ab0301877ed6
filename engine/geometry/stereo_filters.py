"""Outlier filters for semi-global matching disparities (issue 14; used by :mod:`.stereo`).

SGBM's left-right check keeps what both directions agree on, and two of its errors agree:
the half-occluded band beside a foreground edge takes the foreground's disparity in both
directions (docs/experiments/two-view-geometry.md: the novel scene's p90 depth error 25-32 %).
:func:`half_occlusion_band` finds it from the disparity map alone.
"""
from __future__ import annotations

import numpy as np


def half_occlusion_band(disp: np.ndarray, margin: int, *, rel_jump: float = 0.05, min_jump: float = 1.0,
                        gap_margin: int | None = None) -> np.ndarray:
    """bool [H, W]: the pixels of the left image of a rectified pair that semi-global matching
    most likely gave a foreground's disparity although they show the background.

    Left of a foreground edge, a band as wide as the disparity jump ``Δd`` shows background the
    right camera cannot see (half-occluded); SGBM gives it the foreground's disparity, the same in
    both directions, so the left-right check keeps it. A pixel is marked when a known pixel
    ``k`` px to its left is farther by ``Δd`` (> ``min_jump`` px and ``rel_jump`` of its
    disparity) and ``k <= Δd + margin``; on the other side, where both cameras see the
    background, only the block's own fattening (``margin`` px) is marked. Where the left-right
    check already rejected pixels between the two, the fattening continues into a flat area
    beside the gap: the gap counts as background (the farther of the values bounding it) for
    ``gap_margin`` px (default ``2 margin``). The foreground loses at most ``margin`` px where
    SGBM fattened it across the band (a thin foreground next to a rejected band loses
    ``gap_margin`` px a side). ``disp``: [H, W] float, NaN where unknown (epipolar lines =
    rows; the right image's map is matched mirrored)."""
    d = np.asarray(disp, np.float32)
    known = np.isfinite(d)
    H, W = d.shape
    out = np.zeros((H, W), bool)
    if not known.any():
        return out
    gap_margin = 2 * margin if gap_margin is None else gap_margin
    filled = _fill_gaps_far(d)
    span = int(np.ceil(float(d[known].max() - d[known].min())))
    with np.errstate(invalid="ignore"):
        thr = np.maximum(min_jump, rel_jump * d)
        for k in range(1, min(W, span + margin + 1)):
            jump = d[:, k:] - d[:, :-k]                     # pixel x against the known pixel k to its left
            out[:, k:] |= (jump > thr[:, k:]) & (jump + margin >= k)
        for k in range(1, min(W, max(margin, gap_margin) + 1)):
            if k <= margin:
                jump = d[:, :-k] - d[:, k:]                 # pixel x against the known pixel k to its right
                out[:, :-k] |= jump > thr[:, :-k]
            if k <= gap_margin:                             # against a rejected gap, either side
                gl = (d[:, k:] - filled[:, :-k]) * ~known[:, :-k]
                gr = (d[:, :-k] - filled[:, k:]) * ~known[:, k:]
                out[:, k:] |= gl > thr[:, k:]
                out[:, :-k] |= gr > thr[:, :-k]
    return out & known


def _fill_gaps_far(d: np.ndarray) -> np.ndarray:
    """[H, W] disparity with each row's unknown runs filled by the farther (smaller) of the
    known values that bound them (unknown at a row's ends: the one neighbour), so a depth
    edge hidden behind a few rejected pixels is still an edge."""
    H, W = d.shape
    ok = np.isfinite(d)
    idx = np.where(ok, np.arange(W)[None, :], -1)
    left_i = np.maximum.accumulate(idx, axis=1)
    idx_r = np.where(ok, np.arange(W)[None, :], W)
    right_i = np.minimum.accumulate(idx_r[:, ::-1], axis=1)[:, ::-1]
    rows = np.arange(H)[:, None]
    left = np.where(left_i >= 0, d[rows, np.clip(left_i, 0, W - 1)], np.nan)
    right = np.where(right_i < W, d[rows, np.clip(right_i, 0, W - 1)], np.nan)
    return np.where(ok, d, np.fmin(left, right)).astype(np.float32)
