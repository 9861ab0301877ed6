"""Ground truth written by scripts/make_capture.py (CAPTURE_FORMAT: ``depth_file_path`` and
the ``ground_truth.objects`` block).

* :func:`planar_depth` — planar depth (metres along the camera's viewing axis) of the
  surface at each pixel centre, by casting the pixel's ray into the evaluated scene: the
  geometry Cycles renders, at the pixel centre the engine's pinhole model uses (no sample
  jitter or anti-aliasing blend of the Cycles Z pass at silhouettes). ``inf`` where the
  ray hits nothing.
* :func:`object_matrices` — each moving object's object-to-world matrix at given times.
* :func:`surface_samples` — area-uniform points on an object's surface in object space.
"""
from __future__ import annotations

import bpy
import numpy as np


def pixel_rays(intr, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origin [3], unit directions [H, W, 3] in world, forward axis [3]) of pixel centres.

    OpenCV pinhole of engine.cameras (x right, y down, z forward; centre of pixel (v, u)
    at (u + 0.5, v + 0.5)); ``c2w`` is OpenGL camera-to-world (looks down -Z)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    u = (np.arange(intr.width) + 0.5 - intr.cx) / intr.fx
    v = (np.arange(intr.height) + 0.5 - intr.cy) / intr.fy
    uu, vv = np.meshgrid(u, v)
    d_gl = np.stack([uu, -vv, -np.ones_like(uu)], axis=-1)  # OpenCV -> OpenGL camera axes
    d = d_gl @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return c2w[:3, 3].copy(), d, -c2w[:3, 2]


def planar_depth(scene, intr, c2w: np.ndarray) -> np.ndarray:
    """float32 [H, W]: planar depth of the first surface at each pixel centre, inf on a miss."""
    bpy.context.view_layer.update()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    origin, dirs, forward = pixel_rays(intr, c2w)
    out = np.full(dirs.shape[:2], np.inf, np.float32)
    o = origin.tolist()
    cast = scene.ray_cast
    for v in range(dirs.shape[0]):
        row = dirs[v].tolist()
        for u, d in enumerate(row):
            hit, loc, *_ = cast(depsgraph, o, d)
            if hit:
                out[v, u] = float(np.dot(np.asarray(loc) - origin, forward))
    return out


def object_matrices(objs: dict, times, set_time) -> dict[str, np.ndarray]:
    """name -> float64 [T, 4, 4] object-to-world matrices at ``times`` (``set_time(t)`` poses
    the scene)."""
    out = {name: np.empty((len(times), 4, 4)) for name in objs}
    for i, t in enumerate(times):
        set_time(float(t))
        bpy.context.view_layer.update()
        for name, obj in objs.items():
            out[name][i] = np.array(obj.matrix_world)
    return out


def surface_samples(obj, n: int, seed: int) -> np.ndarray:
    """float32 [n, 3]: points uniform over the object's surface area, in object space."""
    mesh = obj.data
    mesh.calc_loop_triangles()
    verts = np.array([v.co[:] for v in mesh.vertices], dtype=np.float64)
    tris = np.array([t.vertices[:] for t in mesh.loop_triangles], dtype=np.int64)
    # Blender lists loop triangles in a run-dependent order: sort them so a seed gives one sample
    tris = np.sort(tris, axis=1)
    tris = tris[np.lexsort(tris.T[::-1])]
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(tris), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w0, w1, w2 = 1.0 - s, s * (1.0 - r2), s * r2
    pts = w0[:, None] * a[pick] + w1[:, None] * b[pick] + w2[:, None] * c[pick]
    return pts.astype(np.float32)
