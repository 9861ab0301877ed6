"""Synthetic captures for tests and benchmarks (not shipped with the extension).

:func:`synthetic_scene` is a known set of Gaussians (a textured wall plus a textured blob
moving in front of it); :func:`write_synthetic_capture` renders it with the engine's
rasterizer from stereo train cameras and an eval camera into a capture folder
(``CAPTURE_FORMAT.md``), so training can be checked against a known answer.
:func:`write_tiny_capture` (one 8x8 frame, any pose / intrinsics / pixels: bad-input checks)
and :func:`write_moving_capture` (a bright block moving over noise, scene scaled by
``scale``: extreme-extent training) serve the stress suite.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from engine.cameras import Intrinsics, View, look_at_c2w
from engine.io.images import write_exr, write_png
from engine.io.points import write_points
from engine.raster import rasterization

__all__ = ["synthetic_scene", "write_moving_capture", "write_synthetic_capture", "write_tiny_capture"]

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
    cameras = {**{c: {**k, "role": "train"} for c in train_names}, "eval0": {**k, "role": "eval"}}
    data = {"version": 1, "cameras": cameras, "frames": [], "eval_frames": []}
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
        pts = np.concatenate([wall["means"], blob["means"]])
        cols = np.concatenate([wall["colors"], blob["colors"]])
        write_points(out / "points.ply", pts, cols)
    (out / "transforms.json").write_text(json.dumps(data, indent=1))
    return out


def write_tiny_capture(root: Path, *, pose=None, fl_x=20.0, time_value=0.0, image: np.ndarray | None = None,
                        exr: bool = False) -> Path:
    """A one-camera, one-frame capture (ours layout); returns transforms.json's path."""

    root.mkdir(parents=True, exist_ok=True)
    img = np.full((8, 8, 3), 0.5, np.float32) if image is None else image
    name = "f0.exr" if exr else "f0.png"
    if exr:
        write_exr(root / name, img)
    else:
        write_png(root / name, img)
    c2w = np.eye(4).tolist() if pose is None else pose
    data = {"cameras": {"cam": {"w": 8, "h": 8, "fl_x": fl_x, "fl_y": 20.0, "cx": 4.0, "cy": 4.0}},
            "frames": [{"file_path": name, "camera": "cam", "time": time_value, "transform_matrix": c2w}]}
    (root / "transforms.json").write_text(json.dumps(data, allow_nan=True))
    return root / "transforms.json"


def write_moving_capture(root: Path, scale: float = 1.0, seed: int = 0) -> Path:
    """Two 32x24 cameras, three instants of a bright moving block, scene scaled by ``scale``."""

    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    frames = []
    for cam, x in (("a", -0.3), ("b", 0.3)):
        c2w = look_at_c2w((x * scale, -4.0 * scale, 0.0), (0.0, 0.0, 0.0)).tolist()
        for i in range(3):
            img = np.clip(rng.random((24, 32, 3)) * 0.3 + 0.3, 0, 1).astype(np.float32)
            img[8:16, 4 + 4 * i: 12 + 4 * i] = 0.9
            write_png(root / f"{cam}{i}.png", img)
            frames.append({"file_path": f"{cam}{i}.png", "camera": cam, "time": i / 30, "transform_matrix": c2w})
    intr = {"w": 32, "h": 24, "fl_x": 30.0, "fl_y": 30.0, "cx": 16.0, "cy": 12.0}
    (root / "transforms.json").write_text(json.dumps({"cameras": {"a": intr, "b": intr}, "frames": frames}))
    return root
