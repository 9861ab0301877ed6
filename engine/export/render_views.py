"""Camera records in, image files out: THE render-to-file of the engine.

* :func:`read_camera_file` turns a camera JSON (the capture's schema: a ``cameras`` block of
  intrinsics plus ``frames`` with ``camera``, ``transform_matrix`` (camera-to-world, OpenGL)
  and ``time``; or frames carrying ``w, h, fl_x, fl_y, cx, cy`` inline, or
  ``camera_angle_x``) into :class:`engine.cameras.View` objects. Intrinsics are parsed by
  the capture loader's strict parser (:func:`engine.io.records.parse_intrinsics`).
* :func:`write_renders` renders Views of a :class:`engine.scene.model.Scene4D` to files, one
  per view, with names that never collide (:func:`output_names`). The file conventions:

  - **EXR**: channels R G B A Z, float32. RGB is *linear* light, *premultiplied* by A
    (associated alpha: a pixel half covered by a white splat is (0.5, 0.5, 0.5, 0.5)),
    i.e. the image composited over black, as Blender's compositor expects. Z is the
    expected depth along the camera axis (metres in scene units) where A > 1e-4, and
    :data:`Z_BACKGROUND` (1e10, Blender's Z-pass value for "nothing hit") elsewhere.
  - **PNG**: 8-bit sRGB-encoded RGBA with *straight* (unassociated) alpha, as PNG requires.

* :func:`orbit_views` makes a bullet-time orbit around a scene at a frozen instant.
"""
from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path

import numpy as np

from ..cameras import Intrinsics, View, look_at_c2w
from ..colour import srgb_to_linear
from ..errors import CaptureError
from ..io.fileio import atomic_write
from ..io.images import write_exr, write_png
from ..io.records import parse_intrinsics

# Z of EXR pixels where nothing was hit (alpha <= 1e-4): Blender's Z pass uses 1e10 too.
Z_BACKGROUND = 1e10


# ---------------------------------------------------------------------------------- reading
def read_camera_file(path) -> list[View]:
    """Views from a camera JSON file (see module doc). Raises CaptureError when unusable."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CaptureError(path, "camera file does not exist") from None
    except (OSError, ValueError) as exc:
        raise CaptureError(path, f"not a readable JSON file: {exc}") from None
    return views_from_records(data, path)


def views_from_records(data: dict, path="cameras") -> list[View]:
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise CaptureError(path, "expected an object with a 'frames' list")
    cams = {}
    for name, c in (data.get("cameras") or {}).items():
        cams[name] = parse_intrinsics(c, f"cameras.{name}", path)
    top = None
    if any(k in data for k in ("fl_x", "camera_angle_x")) and "w" in data:
        top = parse_intrinsics(data, "top level", path)
    views = []
    for i, fr in enumerate(data["frames"]):
        where = f"frames[{i}]"
        if not isinstance(fr, dict):
            raise CaptureError(path, f"{where}: not an object")
        if any(k in fr for k in ("fl_x", "camera_angle_x")):
            k = parse_intrinsics(fr, where, path)
        elif fr.get("camera") is not None:
            if fr["camera"] not in cams:
                raise CaptureError(path, f"{where}: unknown camera {fr['camera']!r}; known: {sorted(cams)}")
            k = cams[fr["camera"]]
        elif top is not None:
            k = top
        elif len(cams) == 1:
            k = next(iter(cams.values()))
        else:
            raise CaptureError(path, f"{where}: no intrinsics (give 'camera' or w, h, fl_x, fl_y, cx, cy)")
        try:
            m = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except KeyError:
            raise CaptureError(path, f"{where}: missing transform_matrix") from None
        except (TypeError, ValueError):
            raise CaptureError(path, f"{where}: transform_matrix is not a 4x4 matrix of numbers") from None
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise CaptureError(path, f"{where}: transform_matrix must be a finite 4x4 matrix")
        try:
            t = float(fr.get("time", 0.0))
        except (TypeError, ValueError):
            raise CaptureError(path, f"{where}: time is not a number") from None
        name = str(fr.get("name") or (Path(fr["file_path"]).stem if fr.get("file_path") else f"{i:06d}"))
        views.append(View(k, m, t, name, {"camera": fr.get("camera"), "file_path": fr.get("file_path")}))
    return views


def views_to_records(views: list[View]) -> dict:
    """The inverse of :func:`views_from_records` (inline intrinsics)."""
    frames = []
    for v in views:
        k = v.intrinsics
        frames.append({"name": v.name, "w": k.width, "h": k.height, "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx,
                       "cy": k.cy, "time": float(v.time), "transform_matrix": np.asarray(v.c2w).tolist()})
    return {"frames": frames}


def write_camera_file(path, views: list[View]) -> Path:
    """Write ``views`` as a camera JSON (:func:`views_to_records`) atomically: what
    :func:`read_camera_file` and ``engine render --path`` read back, view for view."""
    text = json.dumps(views_to_records(views), indent=1).encode()
    return atomic_write(Path(path), lambda fh: fh.write(text))


# ---------------------------------------------------------------------------------- writing
def _unpremultiply(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    a = alpha[..., None]
    return np.where(a > 1e-6, rgb / np.maximum(a, 1e-6), 0.0).clip(0.0, 1.0)


def output_names(views: list[View], names: list[str] | None = None) -> list[str]:
    """One file stem per view, all different (never a silent overwrite).

    The stem is ``names[i]``, else the view's name, else its index. When two stems are equal
    (e.g. ``rgb0/000000.png`` and ``rgb1/000000.png`` of a capture both named ``000000``),
    every stem gets its view's camera (or its ``file_path`` folder) as a prefix:
    ``rgb0_000000``. Raises ValueError naming the duplicates when that still collides."""
    stems = [((names[i] if names else None) or v.name or f"{i:06d}").replace("/", "_") for i, v in enumerate(views)]
    if len(set(stems)) == len(stems):
        return stems

    def prefix(v: View) -> str:
        extra = v.extra or {}
        if extra.get("camera"):
            return str(extra["camera"])
        parent = Path(str(extra.get("file_path") or "")).parent
        return "_".join(p for p in parent.parts if p not in ("", ".", ".."))

    stems = [f"{prefix(v)}_{s}" if prefix(v) else s for v, s in zip(views, stems)]
    dup = sorted(k for k, n in Counter(stems).items() if n > 1)
    if dup:
        raise ValueError(f"{len(dup)} output name(s) would be written twice: {', '.join(dup[:5])}; "
                         "give each view a distinct name (or camera)")
    return stems


def write_renders(scene, views: list[View], out_dir, fmt: str = "png", *, time: float | None = None,
                  names: list[str] | None = None, paths: list | None = None,
                  png_background=None, fill_holes: bool = False) -> list[Path]:
    """Render ``views`` (each at its own time, or at ``time``) into ``out_dir``, one file each
    (EXR: linear premultiplied RGBA + Z; PNG: sRGB straight RGBA; see the module doc).

    ``paths``: one output file per view (then ``out_dir`` and ``names`` are not used), e.g.
    Blender's frame-numbered names. ``png_background``: PNG only; None writes RGBA with
    straight alpha, an RGB colour writes RGB composited over that colour -- or, with
    ``fill_holes``, over the colour the covered neighbourhood implies (issue 14: what no
    Gaussian covers does not show the background as if it were scene content). Colliding output
    names are refused before anything is rendered."""
    if fmt not in ("png", "exr"):
        raise ValueError(f"format must be png or exr, got {fmt!r}")
    if paths is not None:
        targets = [Path(p) for p in paths]
        if len(targets) != len(views):
            raise ValueError(f"{len(targets)} output paths for {len(views)} views")
        if len(set(targets)) != len(targets):
            raise ValueError("two views would write the same output file")
    else:
        stems = output_names(views, names)  # before rendering anything: a collision writes nothing
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        targets = [out_dir / f"{name}.{fmt}" for name in stems]
    written = []
    for v, target in zip(views, targets):
        bg = png_background if (fmt == "png" and png_background is not None) else (0.0, 0.0, 0.0)
        opaque = fmt == "png" and png_background is not None
        r = scene.render([v], background=bg, time=time, fill_holes=fill_holes and opaque)[0]
        rgb, alpha, depth = r["rgb"], r["alpha"], r["depth"]
        if fmt == "png":
            if png_background is not None:
                p = write_png(target, np.clip(rgb, 0.0, 1.0).astype(np.float32))
            else:
                straight = _unpremultiply(rgb, alpha)
                p = write_png(target, np.concatenate([straight, alpha[..., None]], -1).astype(np.float32))
        else:
            straight = _unpremultiply(rgb, alpha)
            lin = srgb_to_linear(straight.astype(np.float32)) * alpha[..., None]
            z = np.where(alpha > 1e-4, depth, Z_BACKGROUND).astype(np.float32)
            p = write_exr(target, {"R": lin[..., 0], "G": lin[..., 1], "B": lin[..., 2],
                                   "A": alpha.astype(np.float32), "Z": z})
        written.append(p)
    return written


def orbit_views(center, radius: float, intrinsics: Intrinsics, n: int = 36, *, height: float = 0.0,
                time: float = 0.0, up=(0.0, 0.0, 1.0), start_eye=None, degrees: float = 360.0) -> list[View]:
    """``n`` cameras on a circle around ``center`` (about the ``up`` axis), all at ``time``.

    With ``start_eye`` the circle passes through it (its height and radius are used).
    """
    center = np.asarray(center, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    if start_eye is not None:
        off = np.asarray(start_eye, dtype=np.float64) - center
        height = float(off @ up)
        horiz = off - height * up
        radius = float(np.linalg.norm(horiz))
        a = horiz / max(radius, 1e-12)
    else:
        a = np.cross(up, [1.0, 0.0, 0.0])
        if np.linalg.norm(a) < 1e-6:
            a = np.cross(up, [0.0, 1.0, 0.0])
        a = a / np.linalg.norm(a)
    b = np.cross(up, a)
    span = math.radians(degrees)
    full = abs(degrees - 360.0) < 1e-9
    views = []
    for i in range(n):
        if full:
            ang = span * i / n
        else:
            ang = -span / 2 + span * i / max(1, n - 1)
        eye = center + radius * (math.cos(ang) * a + math.sin(ang) * b) + height * up
        views.append(View(intrinsics, look_at_c2w(eye, center, up=tuple(up)), float(time), f"orbit_{i:03d}"))
    return views
