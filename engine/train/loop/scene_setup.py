"""What a run derives from its capture before the first step: the train frames, the scene's
extent and the deformation field's bounds (the initial cloud's backdrop left out of both)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["capture_path", "train_frames", "scene_extent", "robust_bounds", "scene_points", "inside_box",
           "DENSIFY_REFERENCE_PIXELS", "densify_cap"]

# densify.max_gaussians is the count for train frames of this many pixels (160x120, where it was
# tuned); larger frames get it times the square root of their pixel ratio (320x240: 2x), up to
# DENSIFY_MAX_SCALE: at 320x240 the fixed 20k left no room once the 15k-point backdrop ring was in
# (docs/experiments/more-steps-random-scenes.md, "The densification cap")
DENSIFY_REFERENCE_PIXELS = 160 * 120
DENSIFY_MAX_SCALE = 4.0


def capture_path(capture) -> str | None:
    root = getattr(capture, "root", None)
    return str(Path(root).resolve()) if root is not None else None


def train_frames(capture) -> list:
    """The RGB frames of cameras with role 'train'."""
    out = []
    for f in capture.frames:
        cam = capture.cameras.get(f.camera) if hasattr(capture, "cameras") else None
        if cam is not None and getattr(cam, "role", "train") != "train":
            continue
        out.append(f)
    return out


def scene_extent(points: np.ndarray, centers: np.ndarray) -> float:
    """Scene radius: the larger of 3DGS's camera radius and the points' robust half-diagonal."""
    cam = 0.0
    if len(centers):
        c = centers.mean(0)
        cam = float(np.linalg.norm(centers - c, axis=1).max()) * 1.1
    pts = 0.0
    if len(points) >= 4:
        lo, hi = np.percentile(points, 2, axis=0), np.percentile(points, 98, axis=0)
        pts = float(np.linalg.norm(hi - lo)) / 2
    return max(cam, pts, 1e-3)


def robust_bounds(points: np.ndarray, margin: float = 0.1):
    lo, hi = np.percentile(points, 1, axis=0), np.percentile(points, 99, axis=0)
    pad = (hi - lo) * margin + 1e-6
    return lo - pad, hi + pad


def scene_points(xyz: np.ndarray, info: dict) -> np.ndarray:
    """The initial points [N,3] less the ``init_backdrop`` tail (``info["backdrop"]`` rows,
    appended last by engine.geometry.init_points): the ring beyond the image borders must not
    widen the scene extent (position lr, densify thresholds, near plane) nor the field bounds."""
    n_back = int(info.get("backdrop", 0) or 0)
    return xyz[:len(xyz) - n_back] if 0 < n_back < len(xyz) else xyz


def inside_box(points: np.ndarray, box) -> np.ndarray:
    """Rows of ``points`` [N,3] inside the axis-aligned ``box`` (lo[3], hi[3]); all of them
    where that leaves fewer than 4 (or ``box`` is None)."""
    if box is None:
        return points
    keep = np.all((points >= np.asarray(box[0])) & (points <= np.asarray(box[1])), axis=1)
    return points[keep] if keep.sum() >= 4 else points


def densify_cap(max_gaussians: int, items: list) -> tuple[int, float]:
    """(the Gaussian count densification stops at, the scale applied) for train ``items`` (view dicts
    with width and height): ``max_gaussians`` x sqrt(mean frame pixels / DENSIFY_REFERENCE_PIXELS),
    the scale between 1 and DENSIFY_MAX_SCALE."""
    if not items:
        return int(max_gaussians), 1.0
    px = float(np.mean([int(it["width"]) * int(it["height"]) for it in items]))
    scale = float(min(DENSIFY_MAX_SCALE, max(1.0, (px / DENSIFY_REFERENCE_PIXELS) ** 0.5)))
    return int(round(int(max_gaussians) * scale)), round(scale, 4)
