"""Blender camera objects <-> engine ``View`` records.

Intrinsics follow Blender's own view-plane rule (``BKE_camera_params_compute_viewplane``):

* render size ``W = resolution_x * resolution_percentage / 100`` (same for ``H``), pixel
  aspect ``ax = pixel_aspect_x``, ``ay = pixel_aspect_y`` and ``ycor = ay / ax``;
* sensor fit: AUTO uses ``sensor_width`` and fits the wider of ``ax*W`` / ``ay*H``;
  HORIZONTAL uses ``sensor_width`` across ``W``; VERTICAL uses ``sensor_height`` across
  ``ycor * H``;
* ``viewfac = W`` (horizontal fit) or ``ycor * H`` (vertical fit);
* ``fx = lens * viewfac / sensor``, ``fy = fx / ycor``;
* ``cx = W/2 - shift_x * viewfac``, ``cy = H/2 + shift_y * viewfac / ycor``
  (pixel coordinates from the top-left corner, pixel centres at +0.5, as in
  ``engine.cameras``).

The pose is ``Object.matrix_world`` with its scale removed (camera-to-world, OpenGL
convention: -Z forward, +Y up) — exactly what captures store.

Only perspective cameras are supported (orthographic and panoramic cameras raise
``ValueError``). ``bpy`` is imported only inside :func:`view_to_camera`; the other functions
work on the objects passed in. ``scene_build.py`` (import side) uses the same model.
"""
from __future__ import annotations

import math

import numpy as np

from . import scene_build
from .worker import engine_module

_cams = engine_module("cameras")
Intrinsics, View = _cams.Intrinsics, _cams.View


def render_size(scene) -> tuple[int, int]:
    """Pixel size of the final render (resolution x percentage), as Blender rounds it."""
    r = scene.render
    pct = r.resolution_percentage / 100.0
    return int(r.resolution_x * pct), int(r.resolution_y * pct)


def intrinsics_from_params(width: int, height: int, lens: float, sensor_width: float,
                           sensor_height: float, sensor_fit: str = "AUTO", shift_x: float = 0.0,
                           shift_y: float = 0.0, pixel_aspect_x: float = 1.0,
                           pixel_aspect_y: float = 1.0) -> Intrinsics:
    """Pure-number version of :func:`camera_intrinsics` (no bpy needed)."""
    W, H = int(width), int(height)
    ycor = pixel_aspect_y / pixel_aspect_x
    if sensor_fit == "VERTICAL":
        sensor, fit = sensor_height, "VERTICAL"
    elif sensor_fit == "HORIZONTAL":
        sensor, fit = sensor_width, "HORIZONTAL"
    else:  # AUTO
        sensor = sensor_width
        fit = "HORIZONTAL" if pixel_aspect_x * W >= pixel_aspect_y * H else "VERTICAL"
    viewfac = W if fit == "HORIZONTAL" else ycor * H
    fx = lens * viewfac / sensor
    fy = fx / ycor
    cx = 0.5 * W - shift_x * viewfac
    cy = 0.5 * H + shift_y * viewfac / ycor
    return Intrinsics(W, H, float(fx), float(fy), float(cx), float(cy))


def camera_intrinsics(cam_obj, scene, width: int | None = None, height: int | None = None) -> Intrinsics:
    """Intrinsics of a Blender camera object rendered with ``scene``'s render settings.

    ``width``/``height`` override the render size (percentage already applied)."""
    cam = cam_obj.data
    if cam.type != "PERSP":
        raise ValueError(f"camera {cam_obj.name!r} is {cam.type}; only perspective cameras are supported")
    W, H = render_size(scene)
    if width is not None:
        W = int(width)
    if height is not None:
        H = int(height)
    r = scene.render
    # (with lens_unit FOV, Blender keeps ``lens`` in sync with the angle)
    return intrinsics_from_params(W, H, cam.lens, cam.sensor_width, cam.sensor_height, cam.sensor_fit,
                                  cam.shift_x, cam.shift_y, r.pixel_aspect_x, r.pixel_aspect_y)


def _normalized_c2w(matrix_world) -> np.ndarray:
    m = np.array(matrix_world, dtype=np.float64).reshape(4, 4)
    r = m[:3, :3]
    norms = np.linalg.norm(r, axis=0)
    norms[norms == 0] = 1.0
    out = np.eye(4)
    out[:3, :3] = r / norms
    out[:3, 3] = m[:3, 3]
    return out


def camera_to_view(cam_obj, scene, time: float = 0.0, *, width: int | None = None,
                   height: int | None = None, name: str | None = None) -> View:
    """An engine ``View`` for ``cam_obj`` as it is *now* (evaluate the frame first)."""
    return View(camera_intrinsics(cam_obj, scene, width, height), _normalized_c2w(cam_obj.matrix_world),
                float(time), name if name is not None else cam_obj.name)


def apply_intrinsics(cam_data, intr: Intrinsics, scene=None) -> dict:
    """Set a ``bpy.types.Camera`` (and, when given, the scene's resolution / pixel aspect) to
    reproduce ``intr``, with the import operator's camera model (``scene_build``). Returns the
    parameters used."""
    p = scene_build.apply_intrinsics(cam_data, intr)
    if scene is not None:
        scene_build.configure_render(scene, intr)
    return p


def view_to_camera(view: View, name: str | None = None, scene=None, collection=None,
                   set_scene_resolution: bool = False):
    """Create a Blender camera object for an engine ``View`` (pose + intrinsics)."""
    import bpy
    from mathutils import Matrix

    scene = scene or bpy.context.scene
    name = name or view.name or "BT4D Camera"
    data = bpy.data.cameras.new(name)
    obj = bpy.data.objects.new(name, data)
    (collection or scene.collection).objects.link(obj)
    apply_intrinsics(data, view.intrinsics, scene if set_scene_resolution else None)
    obj.matrix_world = Matrix(np.asarray(view.c2w, dtype=np.float64).tolist())
    return obj


def fov_x(intr: Intrinsics) -> float:
    return 2.0 * math.atan(0.5 * intr.width / intr.fx)
