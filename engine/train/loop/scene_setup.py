"""What a run derives from its capture before the first step: the train frames, the scene's
extent and the deformation field's bounds (the initial cloud's backdrop left out of both)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["capture_path", "train_frames", "scene_extent", "robust_bounds", "scene_points", "inside_box"]


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
