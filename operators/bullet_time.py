"""Bullet-time helpers.

* ``bpy.ops.bt4d.add_orbit_camera()``: a camera orbiting the reconstruction's centre,
  keyed on every frame of the scene's frame range, made the scene camera; by default the
  Capture Time is frozen (keyed constant) at the value it has on the current frame.
* ``bpy.ops.bt4d.freeze_capture_time()``: key Capture Time constant over the frame range at
  the current frame's value (bullet time).
* ``bpy.ops.bt4d.realtime_capture_time(speed=1)``: key Capture Time linearly again,
  ``speed`` capture seconds per scene second from the first frame (0.1 = 10x slow motion).
"""
from __future__ import annotations

import math

import bpy
import numpy as np
from bpy.props import BoolProperty, FloatProperty
from bpy.types import Operator
from bpy_extras import anim_utils
from mathutils import Matrix

from ..bt4d_addon import attributes as A
from ..bt4d_addon import gaussian_nodes as gn
from ..bt4d_addon.engine_bridge import look_at_c2w


def result_centre_and_radius(obj, capture_time: float) -> tuple[np.ndarray, float]:
    """Robust centre (opacity-weighted median) and radius (90th percentile distance) of the
    Gaussians at the sample nearest ``capture_time``, in world space."""
    mesh = obj.data
    N, K = int(mesh[A.NUM_GAUSSIANS]), int(mesh[A.NUM_SAMPLES])
    times = np.asarray(mesh[A.SAMPLE_TIMES], dtype=np.float64)
    k = int(np.argmin(np.abs(times - capture_time))) if len(times) else 0
    co = np.empty(N * K * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    pts = co.reshape(K, N, 3)[k].astype(np.float64)
    op = np.empty(N * K, np.float32)
    mesh.attributes[A.OPACITY.name].data.foreach_get(A.OPACITY.value_key, op)
    op = op.reshape(K, N)[k]
    keep = op >= 0.2 if np.count_nonzero(op >= 0.2) >= 4 else np.ones(N, bool)
    pts = pts[keep]
    mw = np.array(obj.matrix_world)
    pts = pts @ mw[:3, :3].T + mw[:3, 3]
    centre = np.median(pts, axis=0)
    radius = float(np.percentile(np.linalg.norm(pts - centre, axis=1), 90)) if len(pts) else 1.0
    return centre, max(radius, 1e-3)


def freeze(obj, scene, value: float | None = None) -> float:
    if value is None:
        value = gn.capture_time_at(obj, scene.frame_current)
    gn.key_capture_time(obj, [(scene.frame_start, value), (scene.frame_end, value)], interpolation="CONSTANT")
    gn.set_modifier_input(obj, gn.CAPTURE_TIME, float(value))
    return float(value)


def add_orbit_camera(context, obj, *, turns: float = 1.0, radius: float = 0.0, height: float | None = None,
                     do_freeze: bool = True, name: str = "BT4D Orbit"):
    scene = context.scene
    t_now = gn.capture_time_at(obj, scene.frame_current)
    centre, extent = result_centre_and_radius(obj, t_now)
    ref = scene.camera
    if ref is not None:
        off = np.array(ref.matrix_world.translation) - centre
        r_xy = float(np.hypot(off[0], off[1]))
        start = math.atan2(off[1], off[0]) if r_xy > 1e-6 else 0.0
        h = float(off[2]) if height is None else height
        rad = radius if radius > 0 else (r_xy if r_xy > 1e-3 else 4.0 * extent)
        data = ref.data.copy() if ref.type == "CAMERA" else bpy.data.cameras.new(name)
        data.name = name
    else:
        start, rad = -math.pi / 2, radius if radius > 0 else 4.0 * extent
        h = 0.3 * rad if height is None else height
        data = bpy.data.cameras.new(name)
    cam = bpy.data.objects.new(name, data)
    scene.collection.objects.link(cam)
    cam.rotation_mode = "XYZ"
    fs, fe = scene.frame_start, scene.frame_end
    n = max(1, fe - fs)
    prev = None
    for f in range(fs, fe + 1):
        a = start + 2.0 * math.pi * turns * (f - fs) / n
        eye = centre + np.array([rad * math.cos(a), rad * math.sin(a), h])
        m = Matrix(look_at_c2w(eye, centre).tolist())
        cam.location = m.to_translation()
        eul = m.to_euler("XYZ", prev) if prev is not None else m.to_euler("XYZ")
        cam.rotation_euler = eul
        prev = eul.copy()
        cam.keyframe_insert("location", frame=f)
        cam.keyframe_insert("rotation_euler", frame=f)
    # linear between the per-frame keys (sub-frames, motion blur)
    ad = cam.animation_data
    cb = anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot)
    for fc in cb.fcurves:
        for kp in fc.keyframe_points:
            kp.interpolation = "LINEAR"
    scene.camera = cam
    frozen = freeze(obj, scene, t_now) if do_freeze else None
    cam["bt4d_orbit_centre"] = [float(c) for c in centre]
    return cam, frozen


class BT4D_OT_add_orbit_camera(Operator):
    """Add a camera orbiting the reconstruction over the frame range and make it the scene
    camera; freezes Capture Time at the current frame (bullet time)"""

    bl_idname = "bt4d.add_orbit_camera"
    bl_label = "Add Orbit Camera"
    bl_options = {"REGISTER", "UNDO"}

    turns: FloatProperty(name="Turns", default=1.0, soft_min=-2.0, soft_max=2.0,
                         description="Revolutions over the frame range (negative: clockwise)")
    radius: FloatProperty(name="Radius", default=0.0, min=0.0, unit="LENGTH",
                          description="Orbit radius (0: the scene camera's distance, or 4x the scene size)")
    freeze: BoolProperty(name="Freeze Capture Time", default=True,
                         description="Hold Capture Time at the current frame's value over the whole range")

    @classmethod
    def poll(cls, context):
        return bool(gn.find_result_objects(context.scene))

    def execute(self, context):
        obj = gn.pick_result_object(context)
        if obj is None:
            self.report({"ERROR"}, "No reconstruction in the scene")
            return {"CANCELLED"}
        cam, frozen = add_orbit_camera(context, obj, turns=self.turns, radius=self.radius, do_freeze=self.freeze)
        msg = f"Added {cam.name!r}"
        if frozen is not None:
            msg += f", Capture Time frozen at {frozen:.4f} s"
        self.report({"INFO"}, msg)
        return {"FINISHED"}


class BT4D_OT_freeze_capture_time(Operator):
    """Hold the Capture Time the reconstruction shows on this frame over the whole frame
    range (bullet time: the camera moves, time stands still)"""

    bl_idname = "bt4d.freeze_capture_time"
    bl_label = "Freeze Capture Time Here"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return bool(gn.find_result_objects(context.scene))

    def execute(self, context):
        obj = gn.pick_result_object(context)
        v = freeze(obj, context.scene)
        self.report({"INFO"}, f"Capture Time frozen at {v:.4f} s")
        return {"FINISHED"}


class BT4D_OT_realtime_capture_time(Operator):
    """Key Capture Time to run with the scene again: speed 1 is real time, 0.1 is 10x slow
    motion, from the capture start on the first frame"""

    bl_idname = "bt4d.realtime_capture_time"
    bl_label = "Real-Time Capture Time"
    bl_options = {"REGISTER", "UNDO"}

    speed: FloatProperty(name="Speed", default=1.0, min=1e-4, soft_max=4.0,
                         description="Capture seconds per scene second (below 1: slow motion)")

    @classmethod
    def poll(cls, context):
        return bool(gn.find_result_objects(context.scene))

    def execute(self, context):
        obj = gn.pick_result_object(context)
        scene = context.scene
        t0, t1 = (float(x) for x in obj[A.TIME_RANGE])
        fps = scene.render.fps / scene.render.fps_base
        fe = scene.frame_start + (t1 - t0) * fps / self.speed
        gn.key_capture_time(obj, [(scene.frame_start, t0), (fe, t1)])
        self.report({"INFO"}, f"Capture Time runs {t0:.3f}-{t1:.3f} s over frames {scene.frame_start}-{fe:.1f}")
        return {"FINISHED"}


classes = (BT4D_OT_add_orbit_camera, BT4D_OT_freeze_capture_time, BT4D_OT_realtime_capture_time)
