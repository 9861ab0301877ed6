"""``bpy.ops.bt4d.export_camera_path(filepath=...)``: the scene camera's keyframed path as a camera JSON.

The same views Render Camera Path renders (``render_path.collect_views``: the scene camera at
every frame of the range, at the capture time the result object shows then) written as camera
records (``engine.export.render_views.write_camera_file``), so that a render node without
Blender renders the same frames: ``python -m engine render RUN --path FILE.json --out DIR``.
"""
from __future__ import annotations

import bpy
from bpy.props import IntProperty, StringProperty
from bpy.types import Operator
from bpy_extras.io_utils import ExportHelper

from ..bt4d_addon import engine_bridge, gaussian_nodes
from .render_path import collect_views


class BT4D_OT_export_camera_path(Operator, ExportHelper):
    """Write the scene camera's path (pose, lens and capture time at every frame) as a camera JSON
    that the command line renders without Blender"""

    bl_idname = "bt4d.export_camera_path"
    bl_label = "Export Camera Path"
    bl_options = {"REGISTER"}

    filename_ext = ".json"
    filter_glob: StringProperty(default="*.json", options={"HIDDEN"})
    frame_start: IntProperty(name="Start", default=-1, description="First frame (-1: the scene's)")
    frame_end: IntProperty(name="End", default=-1, description="Last frame (-1: the scene's)")

    def execute(self, context):
        scene = context.scene
        obj = gaussian_nodes.pick_result_object(context)
        if obj is None:
            self.report({"ERROR"}, "No reconstruction in the scene: load a result first")
            return {"CANCELLED"}
        if scene.camera is None:
            self.report({"ERROR"}, "The scene has no camera")
            return {"CANCELLED"}
        fs = scene.frame_start if self.frame_start < 0 else self.frame_start
        fe = scene.frame_end if self.frame_end < 0 else self.frame_end
        frames = list(range(fs, fe + 1, max(1, scene.frame_step)))
        views = collect_views(scene, None, obj, frames)
        for f, v in zip(frames, views):
            v.name = f"frame_{f:04d}"
        path = engine_bridge.write_camera_file(bpy.path.abspath(self.filepath), views)
        self.report({"INFO"}, f"Wrote {len(views)} cameras to {path}")
        return {"FINISHED"}


classes = (BT4D_OT_export_camera_path,)
