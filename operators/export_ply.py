"""``bpy.ops.bt4d.export_ply(directory=OUT, source=RUN_OR_CACHE, fps=F)``: write the result as a
3DGS PLY sequence (``OUT/frame_000000.ply ...`` + ``OUT/index.json``) that splat viewers,
editors and game-engine importers read (``engine/export/ply.py``).

The source is a run folder or a compact cache (``.bt4c``); by default the scene's current run
(Result panel). Instants: ``fps`` per capture second over the whole capture (0 = the scene's
frame rate). In the Result panel and in File > Export.
"""
from __future__ import annotations

from pathlib import Path

import bpy
from bpy.props import FloatProperty, StringProperty
from bpy.types import Operator

from ..bt4d_addon import engine_bridge


def default_source(scene) -> str:
    run = getattr(scene, "bt4d_run", None)
    return run.run_dir if run is not None and run.run_dir else ""


class BT4D_OT_export_ply(Operator):
    """Write the reconstruction as a sequence of 3D Gaussian Splatting PLY files, one per instant"""

    bl_idname = "bt4d.export_ply"
    bl_label = "Export PLY Sequence"
    bl_options = {"REGISTER"}

    directory: StringProperty(name="Output Folder", subtype="DIR_PATH",
                              description="Folder for frame_000000.ply ... and index.json")
    source: StringProperty(name="Result", subtype="FILE_PATH",
                           description="Run folder or compact cache (.bt4c); empty: the scene's current run")
    fps: FloatProperty(name="Instants per Second", default=0.0, min=0.0, soft_max=1000.0,
                       description="PLY files per capture second (0: the scene's frame rate)")

    def invoke(self, context, event):
        if not self.source:
            self.source = default_source(context.scene)
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        source = bpy.path.abspath(self.source or default_source(context.scene)).rstrip("/\\")
        out_dir = bpy.path.abspath(self.directory).rstrip("/\\") if self.directory else ""
        if not source:
            self.report({"ERROR"}, "No result to export: run a reconstruction or choose a run folder / .bt4c cache")
            return {"CANCELLED"}
        if not out_dir:
            self.report({"ERROR"}, "No output folder given")
            return {"CANCELLED"}
        r = context.scene.render
        fps = self.fps if self.fps > 0 else r.fps / r.fps_base
        wm = context.window_manager
        wm.progress_begin(0, 100)
        try:
            info = engine_bridge.export_ply_sequence(source, out_dir, fps,
                                                     progress=lambda i, n: wm.progress_update(int(100 * i / n)))
        except Exception as exc:  # noqa: BLE001 - RunError / PlyFormatError and friends, shown verbatim
            self.report({"ERROR"}, f"Could not export the PLY sequence: {exc}")
            return {"CANCELLED"}
        finally:
            wm.progress_end()
        self.report({"INFO"}, f"Wrote {info['frames']} PLY files of {info['gaussians']} Gaussians to "
                              f"{Path(out_dir).name} (index.json)")
        return {"FINISHED"}


def menu_func_export(self, context):
    self.layout.operator(BT4D_OT_export_ply.bl_idname, text="BulletTime4D PLY Sequence (.ply)")


classes = (BT4D_OT_export_ply,)


def register():
    bpy.types.TOPBAR_MT_file_export.append(menu_func_export)


def unregister():
    bpy.types.TOPBAR_MT_file_export.remove(menu_func_export)
