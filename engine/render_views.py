"""Camera records in, image files out (and a synthetic capture writer for tests/benchmarks).

* :func:`read_camera_file` turns a camera JSON (the capture's schema: a ``cameras`` block of
  intrinsics plus ``frames`` with ``camera``, ``transform_matrix`` (camera-to-world, OpenGL)
  and ``time``; or frames carrying ``w, h, fl_x, fl_y, cx, cy`` inline, or
  ``camera_angle_x``) into :class:`engine.cameras.View` objects.
* :func:`write_renders` renders Views of a :class:`engine.model.Scene4D` to files: EXR
  (linear light, associated alpha, channels R G B A Z; Z = expected depth along the
  camera axis, 1e10 where nothing was hit, as Blender's Z pass) or PNG (sRGB 8-bit,
  straight alpha).
* :func:`orbit_views` makes a bullet-time orbit around a scene at a frozen instant.
* :func:`write_synthetic_capture` renders known Gaussians (a textured wall plus a moving
  textured blob) from stereo train cameras and an eval camera into a capture folder.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .cameras import Intrinsics, View, look_at_c2w
from .errors import CaptureError

Z_BACKGROUND = 1e10


# ---------------------------------------------------------------------------------- reading
def _intrinsics(d: dict, where: str, path) -> Intrinsics:
    try:
        w, h = int(d["w"]), int(d["h"])
        if "fl_x" in d:
            fx = float(d["fl_x"])
            fy = float(d.get("fl_y", fx))
        elif "camera_angle_x" in d:
            fx = 0.5 * w / math.tan(0.5 * float(d["camera_angle_x"]))
            fy = fx
        else:
            raise KeyError("fl_x")
        cx = float(d.get("cx", w / 2.0))
        cy = float(d.get("cy", h / 2.0))
    except KeyError as exc:
        raise CaptureError(path, f"{where}: missing intrinsics field {exc.args[0]!r} (need w, h, fl_x)") from None
    except (TypeError, ValueError) as exc:
        raise CaptureError(path, f"{where}: bad intrinsics: {exc}") from None
    if w <= 0 or h <= 0 or fx <= 0 or fy <= 0:
        raise CaptureError(path, f"{where}: intrinsics must be positive")
    return Intrinsics(w, h, fx, fy, cx, cy)


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
        cams[name] = _intrinsics(c, f"cameras.{name}", path)
    top = None
    if any(k in data for k in ("fl_x", "camera_angle_x")) and "w" in data:
        top = _intrinsics(data, "top level", path)
    views = []
    for i, fr in enumerate(data["frames"]):
        where = f"frames[{i}]"
        if not isinstance(fr, dict):
            raise CaptureError(path, f"{where}: not an object")
        if any(k in fr for k in ("fl_x", "camera_angle_x")):
            k = _intrinsics(fr, where, path)
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
        views.append(View(k, m, t, name, {"camera": fr.get("camera")}))
    return views


def views_to_records(views: list[View]) -> dict:
    """The inverse of :func:`views_from_records` (inline intrinsics)."""
    frames = []
    for v in views:
        k = v.intrinsics
        frames.append({"name": v.name, "w": k.width, "h": k.height, "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx,
                       "cy": k.cy, "time": float(v.time), "transform_matrix": np.asarray(v.c2w).tolist()})
    return {"frames": frames}


# ---------------------------------------------------------------------------------- writing
def _unpremultiply(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    a = alpha[..., None]
    return np.where(a > 1e-6, rgb / np.maximum(a, 1e-6), 0.0).clip(0.0, 1.0)


def write_renders(scene, views: list[View], out_dir, fmt: str = "png", *, time: float | None = None,
                  names: list[str] | None = None, paths: list | None = None,
                  png_background=None) -> list[Path]:
    """Render ``views`` (each at its own time, or at ``time``) into ``out_dir``.

    ``paths``: one output file per view (then ``out_dir`` and ``names`` are not used), e.g.
    Blender's frame-numbered names. ``png_background``: PNG only; None writes RGBA with
    straight alpha, an RGB colour writes RGB composited over that colour."""
    from .colour import srgb_to_linear
    from .images import write_exr, write_png

    if fmt not in ("png", "exr"):
        raise ValueError(f"format must be png or exr, got {fmt!r}")
    if paths is not None:
        paths = [Path(p) for p in paths]
        if len(paths) != len(views):
            raise ValueError(f"{len(paths)} output paths for {len(views)} views")
        if len(set(paths)) != len(paths):
            raise ValueError("two views would write the same output file")
    else:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for i, v in enumerate(views):
        bg = png_background if (fmt == "png" and png_background is not None) else (0.0, 0.0, 0.0)
        r = scene.render([v], background=bg, time=time)[0]
        rgb, alpha, depth = r["rgb"], r["alpha"], r["depth"]
        if paths is not None:
            target = paths[i]
        else:
            name = (names[i] if names else None) or v.name or f"{i:06d}"
            target = out_dir / f"{name.replace('/', '_')}.{fmt}"
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


# ---------------------------------------------------------------------------------- synthetic capture
def synthetic_scene(seed: int = 0, n_wall: int = 900, n_blob: int = 150, speed=(1.5, 0.0, 0.0)):
    """Ground-truth Gaussians: a textured wall (y = 2) and a textured blob moving at ``speed``
    (m/s) in front of it. Returns (static dict, blob dict, speed) with numpy arrays."""
    rng = np.random.default_rng(seed)
    side = int(round(math.sqrt(n_wall)))
    gx, gz = np.meshgrid(np.linspace(-1.2, 1.2, side), np.linspace(-0.9, 0.9, side))
    wall_xyz = np.stack([gx.ravel(), np.full(gx.size, 2.0), gz.ravel()], -1)
    checker = ((np.floor(gx.ravel() * 2.5) + np.floor(gz.ravel() * 2.5)) % 2)
    wall_rgb = np.stack([0.2 + 0.6 * checker, 0.3 + 0.2 * (gz.ravel() + 0.9) / 1.8, 0.8 - 0.5 * checker], -1)
    step = 2.4 / (side - 1)
    wall = {"means": wall_xyz, "scales": np.tile([step * 0.7, 0.01, step * 0.7], (len(wall_xyz), 1)),
            "colors": wall_rgb, "opacities": np.full(len(wall_xyz), 0.95)}
    d = rng.normal(size=(n_blob, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    blob_xyz = d * 0.22 * rng.uniform(0.7, 1.0, (n_blob, 1)) + np.array([-0.25, 1.0, 0.0])
    stripes = (np.floor((blob_xyz[:, 2] + 1) * 12) % 2)
    blob_rgb = np.stack([0.9 * np.ones(n_blob), 0.2 + 0.7 * stripes, 0.1 * np.ones(n_blob)], -1)
    blob = {"means": blob_xyz, "scales": np.full((n_blob, 3), 0.05), "colors": blob_rgb,
            "opacities": np.full(n_blob, 0.9)}
    return wall, blob, np.asarray(speed, dtype=np.float64)


def _render_gt(wall, blob, speed, view: View):
    import torch

    from .raster import rasterization

    means = np.concatenate([wall["means"], blob["means"] + speed[None] * view.time])
    n = len(means)
    f = lambda k: torch.as_tensor(np.concatenate([wall[k], blob[k]]), dtype=torch.float32)  # noqa: E731
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    rgb, alpha, _ = rasterization(torch.as_tensor(means, dtype=torch.float32), quats, f("scales"), f("opacities"),
                                  f("colors"), torch.as_tensor(view.viewmat, dtype=torch.float32)[None],
                                  torch.as_tensor(view.K, dtype=torch.float32)[None], view.intrinsics.width,
                                  view.intrinsics.height, render_depth=False)
    return rgb[0].numpy()


def write_synthetic_capture(out, *, width: int = 64, height: int = 48, rgb_fps: float = 30.0, n_rgb: int = 5,
                            eval_fps: float = 150.0, baseline: float = 0.3, seed: int = 0, with_points: bool = False,
                            speed=(1.5, 0.0, 0.0), static: bool = False, train_cameras: int = 2) -> Path:
    """Write a small capture folder (CAPTURE_FORMAT.md) rendered from :func:`synthetic_scene`.

    rgb0 / rgb1: stereo train cameras at ``rgb_fps`` (``train_cameras`` > 2 adds rgb2... spread
    over a wider horizontal arc); eval0: a third viewpoint at ``eval_fps``.
    """
    from .images import write_png

    out = Path(out)
    wall, blob, v = synthetic_scene(seed, speed=(0, 0, 0) if static else speed)
    fl = 0.9 * width
    k = {"w": width, "h": height, "fl_x": fl, "fl_y": fl, "cx": width / 2, "cy": height / 2}
    intr = Intrinsics(width, height, fl, fl, width / 2, height / 2)
    target = np.array([0.0, 2.0, 0.0])
    eyes = {"rgb0": np.array([-baseline / 2, -1.5, 0.15]), "rgb1": np.array([baseline / 2, -1.5, 0.15])}
    for i in range(2, train_cameras):
        side = -1 if i % 2 == 0 else 1
        eyes[f"rgb{i}"] = np.array([side * baseline * (i // 2 + 0.5) * 1.5, -1.5, 0.15 + 0.25 * side])
    train_names = list(eyes)
    eyes["eval0"] = np.array([0.05, -1.45, 0.45])
    poses = {c: look_at_c2w(e, target) for c, e in eyes.items()}
    duration = (n_rgb - 1) / rgb_fps
    data = {"version": 1, "cameras": {**{c: {**k, "role": "train"} for c in train_names}, "eval0": {**k, "role": "eval"}},
            "frames": [], "eval_frames": []}
    for cam in train_names:
        for i in range(n_rgb):
            t = i / rgb_fps
            rel = f"rgb/{cam}/{i:06d}.png"
            write_png(out / rel, _render_gt(wall, blob, v, View(intr, poses[cam], t)))
            data["frames"].append({"file_path": rel, "camera": cam, "time": t,
                                   "transform_matrix": poses[cam].tolist()})
    n_eval = int(round(duration * eval_fps)) + 1
    for i in range(n_eval):
        t = i / eval_fps
        rel = f"eval/eval0/{i:06d}.png"
        write_png(out / rel, _render_gt(wall, blob, v, View(intr, poses["eval0"], t)))
        data["eval_frames"].append({"file_path": rel, "camera": "eval0", "time": t,
                                    "transform_matrix": poses["eval0"].tolist()})
    if with_points:
        from .capture import write_points

        pts = np.concatenate([wall["means"], blob["means"]])
        cols = np.concatenate([wall["colors"], blob["colors"]])
        write_points(out / "points.ply", pts, cols)
    (out / "transforms.json").write_text(json.dumps(data, indent=1))
    return out
