"""Pure helpers that turn capture cameras into Blender camera objects (and back).

No operator state here: every function takes the datablocks it changes, so the import
operator, the capture generator (``scripts/make_capture.py``) and the tests share one
definition of the camera model.

Blender's camera model (``BKE_camera_params_compute_viewplane``), for a render of
``W x H`` pixels with pixel aspect ``ax, ay`` and ``sensor_fit = 'HORIZONTAL'``:

* the sensor width spans the image width, so ``fx = lens * W / sensor_width``;
* a pixel is ``ycor = ay / ax`` times as tall as it is wide, so ``fy = fx / ycor``;
* ``shift_x, shift_y`` move the view plane by ``shift * W`` *horizontal* pixels, so
  ``cx = W/2 - shift_x * W`` and ``cy = H/2 + shift_y * W / ycor`` (``cy`` measured from
  the top, Blender's shift_y points up).

Inverting: ``lens = fx * sensor_width / W``, ``shift_x = (W/2 - cx) / W``,
``shift_y = (cy - H/2) * ycor / W`` with ``ycor = fx / fy``. Horizontal fit is used
instead of AUTO so the mapping does not flip when an image is taller than wide.
Pixel aspect is a *scene* setting in Blender, so a camera with ``fx != fy`` only renders
exactly with the scene's ``pixel_aspect_x/y`` set by :func:`configure_render`.
"""
from __future__ import annotations

import math
from typing import Iterable, Sequence

import bpy
from mathutils import Matrix

SENSOR_WIDTH_MM = 36.0


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


def intrinsics_from_camera(cam_data, width: int, height: int,
                           pixel_aspect_x: float = 1.0, pixel_aspect_y: float = 1.0) -> tuple:
    """(fx, fy, cx, cy) of a Blender camera rendered at ``width x height`` (any sensor fit)."""
    ycor = pixel_aspect_y / pixel_aspect_x
    fit = cam_data.sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if pixel_aspect_x * width >= pixel_aspect_y * height else "VERTICAL"
    if fit == "HORIZONTAL":
        sensor = cam_data.sensor_width
        viewfac = width
    else:
        sensor = cam_data.sensor_height if cam_data.sensor_fit == "VERTICAL" else cam_data.sensor_width
        viewfac = ycor * height
    fx = cam_data.lens * viewfac / sensor
    fy = fx / ycor
    cx = width / 2.0 - cam_data.shift_x * viewfac
    cy = height / 2.0 + cam_data.shift_y * viewfac / ycor
    return fx, fy, cx, cy


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


def matrix_from_rows(rows: Sequence[Sequence[float]]) -> Matrix:
    """4x4 row-major nested list / numpy array -> mathutils.Matrix."""
    return Matrix([[float(v) for v in row] for row in rows])


def poses_differ(a, b, tol: float = 1e-6) -> bool:
    return any(abs(float(a[i][j]) - float(b[i][j])) > tol for i in range(4) for j in range(4))


def create_camera_object(name: str, intr, c2w, collection) -> "bpy.types.Object":
    """A camera object called ``name`` (data of the same name) at pose ``c2w`` (OpenGL c2w)."""
    data = bpy.data.cameras.new(name)
    apply_intrinsics(data, intr)
    obj = bpy.data.objects.new(name, data)
    collection.objects.link(obj)
    obj.matrix_world = matrix_from_rows(c2w)
    return obj


def keyframe_poses(obj, timed_poses: Iterable[tuple[float, object]], fps: float, frame_start: int) -> int:
    """Keyframe ``obj``'s location/rotation/scale at each (time s, c2w). Returns the key count.

    Keys sit at ``frame_start + time * fps`` (fractional frames are allowed: subframes), with
    linear interpolation so the pose between frames is a plain blend.
    """
    count = 0
    obj.rotation_mode = "QUATERNION"
    prev_q = None
    for t, c2w in timed_poses:
        frame = frame_start + float(t) * fps
        obj.matrix_world = matrix_from_rows(c2w)
        q = obj.rotation_quaternion.copy()
        if prev_q is not None and prev_q.dot(q) < 0.0:  # shortest path between keys
            q.negate()
            obj.rotation_quaternion = q
        prev_q = q
        for path in ("location", "rotation_quaternion", "scale"):
            obj.keyframe_insert(data_path=path, frame=frame)
        count += 1
    ad = obj.animation_data
    if ad and ad.action:
        _set_linear(ad.action)
    return count


def action_fcurves(action) -> list:
    """Every F-curve of ``action``: through its layers' channelbags (Blender >= 4.4, where
    ``Action.fcurves`` is gone in 5.0), or ``action.fcurves`` on older versions."""
    curves = []
    if hasattr(action, "layers") and len(action.layers):
        for layer in action.layers:
            for strip in layer.strips:
                for bag in getattr(strip, "channelbags", []):
                    curves.extend(bag.fcurves)
    elif hasattr(action, "fcurves"):
        curves.extend(action.fcurves)
    return curves


def _set_linear(action) -> None:
    """Linear interpolation on every key of ``action``."""
    for fc in action_fcurves(action):
        for kp in fc.keyframe_points:
            kp.interpolation = "LINEAR"


def scene_frame_range(time_range: tuple[float, float], fps: float, frame_start: int = 1) -> tuple[int, int]:
    """Blender frames covering the capture time range at ``fps`` (time 0 -> frame_start)."""
    t0, t1 = time_range
    first = frame_start + int(math.floor(t0 * fps + 1e-6))
    last = frame_start + int(math.ceil(t1 * fps - 1e-6))
    return first, max(first, last)
