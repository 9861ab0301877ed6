"""A tiny stand-in for engine.scene.model.Scene4D: Gaussians moving linearly in time, rendered by
an obviously-correct numpy EWA splatter (3DGS rules: 0.3 px^2 dilation, pixel centres at
+0.5, alpha capped at 0.99, alpha < 1/255 skipped, front-to-back by depth)."""
from __future__ import annotations

import numpy as np

from engine.scene.model import Scene4D


def quat_to_mat(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def splat(g, view, background=None):
    """Render one view of a Gaussian dict (means, quats, scales, opacities, colors)."""
    k = view.intrinsics
    W, H = k.width, k.height
    vm = view.viewmat
    R, T = vm[:3, :3], vm[:3, 3]
    cam = (R @ g["means"].T.astype(np.float64)).T + T
    order = np.argsort(cam[:, 2])
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    rgb = np.zeros((H, W, 3))
    depth = np.zeros((H, W))
    Tr = np.ones((H, W))
    for i in order:
        x, y, z = cam[i]
        if z < 0.01:
            continue
        Rg = quat_to_mat(np.asarray(g["quats"][i], np.float64))
        S = np.diag(np.asarray(g["scales"][i], np.float64) ** 2)
        cov = R @ Rg @ S @ Rg.T @ R.T
        J = np.array([[k.fx / z, 0, -k.fx * x / z ** 2], [0, k.fy / z, -k.fy * y / z ** 2]])
        c2 = J @ cov @ J.T + 0.3 * np.eye(2)
        inv = np.linalg.inv(c2)
        u, v = k.fx * x / z + k.cx, k.fy * y / z + k.cy
        dx, dy = xs - u, ys - v
        m = inv[0, 0] * dx * dx + 2 * inv[0, 1] * dx * dy + inv[1, 1] * dy * dy
        a = np.minimum(0.99, g["opacities"][i] * np.exp(-0.5 * m))
        a[a < 1 / 255] = 0
        w = a * Tr
        rgb += w[..., None] * np.asarray(g["colors"][i], np.float64)
        depth += w * z
        Tr *= 1 - a
    alpha = 1 - Tr
    depth = np.where(alpha > 1e-6, depth / np.maximum(alpha, 1e-6), 0.0)  # expected depth, as the engine
    if background is not None:
        rgb += Tr[..., None] * np.asarray(background, np.float64)
    return dict(rgb=rgb.astype(np.float32), alpha=alpha.astype(np.float32), depth=depth.astype(np.float32))


class FakeScene4D:
    """N Gaussians in a small cluster around ``center``, moving with constant velocity.
    ``sample`` is the real ``Scene4D.sample`` (it only needs ``gaussians_at``)."""

    sample = Scene4D.sample

    def __init__(self, n=40, seed=0, time_range=(0.0, 0.2), center=(0.0, 0.0, 0.0), speed=2.0):
        rng = np.random.default_rng(seed)
        self.time_range = tuple(float(t) for t in time_range)
        self.num_gaussians = n
        self.m0 = (rng.normal(0, 0.35, (n, 3)) + np.asarray(center)).astype(np.float32)
        self.vel = (rng.normal(0, 1, (n, 3)) * speed * 0.3).astype(np.float32)
        q = rng.normal(0, 1, (n, 4))
        self.quats = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
        self.scales = np.exp(rng.uniform(np.log(0.04), np.log(0.15), (n, 3))).astype(np.float32)
        self.opac = rng.uniform(0.5, 0.95, n).astype(np.float32)
        self.colors = rng.uniform(0.1, 0.95, (n, 3)).astype(np.float32)

    def gaussians_at(self, t):
        t = float(np.clip(t, *self.time_range)) - self.time_range[0]
        return dict(means=(self.m0 + t * self.vel).astype(np.float32), quats=self.quats.copy(),
                    scales=self.scales.copy(), opacities=self.opac.copy(), colors=self.colors.copy())

    def render(self, views, background=None, time=None):
        return [splat(self.gaussians_at(v.time if time is None else time), v, background) for v in views]


def make_fake_capture(root, *, width=64, height=48, rgb_fps=30.0, eval_fps=150.0, duration=0.2, n=40, seed=0):
    """A small capture (transforms.json + PNGs) rendered from :class:`FakeScene4D`: a stereo
    pair of train cameras and one eval camera, no spike stream. Returns (root, model)."""
    import json
    from pathlib import Path

    from engine.cameras import Intrinsics, View, look_at_c2w
    from engine.io.images import write_png

    root = Path(root)
    model = FakeScene4D(n=n, seed=seed, time_range=(0.0, duration))
    k = Intrinsics(width, height, 0.9 * width, 0.9 * width, width / 2, height / 2)
    cams = {"rgb0": look_at_c2w([0.3, -3.2, 0.6], [0, 0, 0]), "rgb1": look_at_c2w([-0.3, -3.2, 0.6], [0, 0, 0]),
            "eval0": look_at_c2w([0.0, -3.0, 1.2], [0, 0, 0])}
    frames, eval_frames = [], []
    for i in range(int(round(duration * rgb_fps)) + 1):
        t = i / rgb_fps
        for name in ("rgb0", "rgb1"):
            rel = f"rgb/{name}/{i:06d}.png"
            img = model.render([View(k, cams[name], t)])[0]["rgb"]
            write_png(root / rel, np.clip(img, 0, 1))
            frames.append({"file_path": rel, "camera": name, "time": t, "transform_matrix": cams[name].tolist()})
    for i in range(int(round(duration * eval_fps)) + 1):
        t = i / eval_fps
        rel = f"eval/eval0/{i:06d}.png"
        write_png(root / rel, np.clip(model.render([View(k, cams["eval0"], t)])[0]["rgb"], 0, 1))
        eval_frames.append({"file_path": rel, "camera": "eval0", "time": t, "transform_matrix": cams["eval0"].tolist()})
    cam = {"w": width, "h": height, "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy}
    data = {"version": 1,
            "cameras": {"rgb0": {**cam, "role": "train"}, "rgb1": {**cam, "role": "train"},
                        "eval0": {**cam, "role": "eval"}},
            "frames": frames, "eval_frames": eval_frames, "spike_streams": []}
    (root / "transforms.json").write_text(json.dumps(data, indent=1))
    return root, model
