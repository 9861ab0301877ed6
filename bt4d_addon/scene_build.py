"""Pure helpers for animating imported cameras and laying out the scene's frame range.

No operator state here: every function takes the datablocks it changes, so the import
operator and the tests share one definition. The camera model itself (intrinsics <->
lens, sensor, shift, pixel aspect) is ``blender_cameras.py``.
"""
from __future__ import annotations

import math
from typing import Iterable

from .blender_cameras import matrix_from_rows


def poses_differ(a, b, tol: float = 1e-6) -> bool:
    return any(abs(float(a[i][j]) - float(b[i][j])) > tol for i in range(4) for j in range(4))


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
