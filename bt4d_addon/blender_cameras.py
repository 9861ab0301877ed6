"""Blender cameras <-> engine cameras (``Intrinsics``, ``View``): the one Blender camera
module, used by the capture import (writing cameras), the capture generator
(``scripts/make_capture.py``) and the path render (reading them).

Reading (:func:`intrinsics_from_camera`, the one reader) follows Blender's own view-plane
rule (``BKE_camera_params_compute_viewplane``):

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

Writing (:func:`camera_params`, :func:`apply_intrinsics`) inverts it with horizontal fit
(so the mapping does not flip when an image is taller than wide): ``lens = fx *
sensor_width / W``, ``shift_x = (W/2 - cx) / W``, ``shift_y = (cy - H/2) * ycor / W`` with
``ycor = fx / fy``. Pixel aspect is a *scene* setting in Blender, so a camera with
``fx != fy`` only renders exactly with the scene's ``pixel_aspect_x/y`` set by
:func:`configure_render`.

The pose is ``Object.matrix_world`` with its scale removed (camera-to-world, OpenGL
convention: -Z forward, +Y up) — exactly what captures store.

Only perspective cameras are read (orthographic and panoramic cameras raise
``ValueError``). Functions take the datablocks they read or change.
"""
from __future__ import annotations

import math

import bpy
import numpy as np
from mathutils import Matrix

from .engine_bridge import Intrinsics, View

SENSOR_WIDTH_MM = 36.0


def render_size(scene) -> tuple[int, int]:
    """Pixel size of the final render (resolution x percentage), as Blender rounds it."""
    r = scene.render
    pct = r.resolution_percentage / 100.0
    return int(r.resolution_x * pct), int(r.resolution_y * pct)


# ----------------------------------------------------------------------------- reading

def intrinsics_from_camera(cam_data, width: int, height: int, pixel_aspect_x: float = 1.0,
                           pixel_aspect_y: float = 1.0) -> Intrinsics:
    """Intrinsics of a ``bpy.types.Camera`` rendered at ``width x height`` with the given
    pixel aspect (any sensor fit; see the module docstring). With ``lens_unit`` FOV,
    Blender keeps ``lens`` in sync with the angle."""
    W, H = int(width), int(height)
    ycor = pixel_aspect_y / pixel_aspect_x
    fit = cam_data.sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if pixel_aspect_x * W >= pixel_aspect_y * H else "VERTICAL"
    # AUTO measures the sensor along its width whichever way it fits
    sensor = cam_data.sensor_height if cam_data.sensor_fit == "VERTICAL" else cam_data.sensor_width
    viewfac = W if fit == "HORIZONTAL" else ycor * H
    fx = cam_data.lens * viewfac / sensor
    fy = fx / ycor
    cx = 0.5 * W - cam_data.shift_x * viewfac
    cy = 0.5 * H + cam_data.shift_y * viewfac / ycor
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
    return intrinsics_from_camera(cam, W, H, r.pixel_aspect_x, r.pixel_aspect_y)


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


def fov_x(intr: Intrinsics) -> float:
    return 2.0 * math.atan(0.5 * intr.width / intr.fx)


# ----------------------------------------------------------------------------- writing

def camera_params(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                  sensor_width: float = SENSOR_WIDTH_MM) -> dict:
    """Blender camera/render settings reproducing a pinhole camera (pixels, top-left origin)."""
    if width <= 0 or height <= 0 or fx <= 0 or fy <= 0:
        raise ValueError(f"bad intrinsics: w={width} h={height} fx={fx} fy={fy}")
    ycor = fx / fy  # pixel height / pixel width
    if ycor >= 1.0:
        aspect_x, aspect_y = 1.0, ycor
    else:
        aspect_x, aspect_y = 1.0 / ycor, 1.0
    return {
        "lens": fx * sensor_width / width,
        "sensor_width": sensor_width,
        "sensor_height": sensor_width * height * ycor / width,
        "sensor_fit": "HORIZONTAL",
        "shift_x": (width / 2.0 - cx) / width,
        "shift_y": (cy - height / 2.0) * ycor / width,
        "resolution_x": int(width),
        "resolution_y": int(height),
        "pixel_aspect_x": aspect_x,
        "pixel_aspect_y": aspect_y,
    }


def apply_intrinsics(cam_data, intr) -> dict:
    """Set lens, sensor and shift of ``cam_data`` (bpy.types.Camera) from ``intr``.

    ``intr`` is anything with width/height/fx/fy/cx/cy (engine.cameras.Intrinsics).
    Returns the full parameter dict (including the render settings the scene needs).
    """
    p = camera_params(intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy)
    cam_data.type = "PERSP"
    cam_data.lens_unit = "MILLIMETERS"
    cam_data.sensor_fit = p["sensor_fit"]
    cam_data.sensor_width = p["sensor_width"]
    cam_data.sensor_height = p["sensor_height"]
    cam_data.lens = p["lens"]
    cam_data.shift_x = p["shift_x"]
    cam_data.shift_y = p["shift_y"]
    return p


def configure_render(scene, intr) -> None:
    """Scene resolution and pixel aspect so that a camera built from ``intr`` renders exactly."""
    p = camera_params(intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy)
    r = scene.render
    r.resolution_x = p["resolution_x"]
    r.resolution_y = p["resolution_y"]
    r.resolution_percentage = 100
    r.pixel_aspect_x = p["pixel_aspect_x"]
    r.pixel_aspect_y = p["pixel_aspect_y"]


def matrix_from_rows(rows) -> Matrix:
    """4x4 row-major nested list / numpy array -> mathutils.Matrix."""
    return Matrix([[float(v) for v in row] for row in rows])


def create_camera_object(name: str, intr, c2w, collection) -> "bpy.types.Object":
    """A camera object called ``name`` (data of the same name) at pose ``c2w`` (OpenGL c2w)."""
    data = bpy.data.cameras.new(name)
    apply_intrinsics(data, intr)
    obj = bpy.data.objects.new(name, data)
    collection.objects.link(obj)
    obj.matrix_world = matrix_from_rows(c2w)
    return obj


def view_to_camera(view: View, name: str | None = None, scene=None, collection=None,
                   set_scene_resolution: bool = False):
    """Create a Blender camera object for an engine ``View`` (pose + intrinsics); with
    ``set_scene_resolution`` the scene's resolution and pixel aspect follow its intrinsics."""
    scene = scene or bpy.context.scene
    obj = create_camera_object(name or view.name or "BT4D Camera", view.intrinsics, view.c2w,
                               collection or scene.collection)
    if set_scene_resolution:
        configure_render(scene, view.intrinsics)
    return obj
