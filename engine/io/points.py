"""PLY point clouds (a capture's ``points.ply``): read and write with trimesh."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import CaptureError
from .fileio import atomic_path

__all__ = ["load_points", "write_points"]


def load_points(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Point cloud from a PLY: (xyz float32 [N, 3], rgb float32 [N, 3] in [0, 1] or None)."""
    import trimesh  # lazy: a heavy import, needed only by captures with a point cloud

    path = Path(path)
    if not path.is_file():
        raise CaptureError(path, "point cloud file does not exist")
    try:
        geom = trimesh.load(path, process=False)
    except Exception as exc:
        raise CaptureError(path, f"cannot read point cloud: {exc}") from None
    if isinstance(geom, trimesh.Scene):
        geoms = list(geom.geometry.values())
        if not geoms:
            raise CaptureError(path, "PLY holds no geometry")
        geom = geoms[0]
    xyz = np.asarray(geom.vertices, dtype=np.float32)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) == 0:
        raise CaptureError(path, "PLY holds no vertices")
    if not np.all(np.isfinite(xyz)):
        raise CaptureError(path, "PLY vertices contain non-finite numbers (NaN or inf)")
    colors = None
    if isinstance(geom, trimesh.PointCloud):
        c = np.asarray(geom.colors)
        colors = c if c.size else None
    else:
        visual = getattr(geom, "visual", None)
        if visual is not None and getattr(visual, "kind", None) == "vertex":
            colors = np.asarray(visual.vertex_colors)
    rgb = None if colors is None else (colors[:, :3].astype(np.float32) / 255.0)
    return xyz, rgb


def write_points(path: str | Path, xyz: np.ndarray, rgb: np.ndarray | None = None) -> Path:
    """Write a PLY point cloud (rgb float in [0, 1] or None), atomically."""
    import trimesh  # lazy: a heavy import, needed only when a point cloud is written

    path = Path(path)
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    colors = None
    if rgb is not None:
        colors = np.clip(np.rint(np.asarray(rgb, dtype=np.float64).reshape(-1, 3) * 255), 0, 255).astype(np.uint8)
        colors = np.concatenate([colors, np.full((len(colors), 1), 255, np.uint8)], axis=1)
    pc = trimesh.PointCloud(xyz, colors=colors)
    with atomic_path(path, ".ply") as tmp:
        pc.export(tmp, file_type="ply")
    return path
