"""3D viewport sidebar, tab "BT4D": one panel per stage of the workflow.

* Capture        — import a capture folder, summary of what was imported (this issue).
* Reconstruction — training settings and the Train button (filled by the training issue).
* Result         — the reconstruction brought back into Blender (bring-back issue).
* Bullet Time    — capture-time control and path rendering (render issue).

Later issues fill the ``draw_*`` hooks below; each panel polls nothing so the layout
stays put while a stage is not available yet.
"""
from __future__ import annotations

import bpy
from bpy.types import Panel

from . import panel_run


class _BT4DPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "BT4D"


class BT4D_PT_capture(_BT4DPanel, Panel):
    bl_idname = "BT4D_PT_capture"
    bl_label = "Capture"

    def draw(self, context):
        layout = self.layout
        s = context.scene.bt4d
        layout.operator("bt4d.import_capture", text="Import Capture...", icon="IMPORT")
        if not s.capture_dir:
            layout.label(text="No capture imported", icon="INFO")
            return
        box = layout.box()
        col = box.column(align=True)
        col.label(text=s.capture_name or bpy.path.basename(s.capture_dir.rstrip("/\\")), icon="FILE_FOLDER")
        col.label(text=f"{s.num_cameras} cameras, main: {s.main_camera}")
        col.label(text=f"{s.num_frames} frames, {s.num_eval_frames} eval frames")
        col.label(text=f"Spikes: {s.spike_summary}" if s.num_spike_streams else "Spikes: none")
        col.label(text=f"Time: {s.time_start:.4g} s to {s.time_end:.4g} s")
        box.prop(s, "capture_dir", text="")


class BT4D_PT_reconstruction(_BT4DPanel, Panel):
    bl_idname = "BT4D_PT_reconstruction"
    bl_label = "Reconstruction"

    def draw(self, context):
        layout = self.layout
        s = context.scene.bt4d
        col = layout.column()
        col.enabled = bool(s.capture_dir)
        col.prop(s, "preset")
        col.prop(s, "seconds")
        col.prop(s, "device")
        col.prop(s, "use_spikes")
        col.prop(s, "output_dir")
        draw_reconstruction(col, context)


class BT4D_PT_reconstruction_advanced(_BT4DPanel, Panel):
    bl_idname = "BT4D_PT_reconstruction_advanced"
    bl_label = "Advanced"
    bl_parent_id = "BT4D_PT_reconstruction"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        panel_run.draw_advanced(self.layout, context)


class BT4D_PT_result(_BT4DPanel, Panel):
    bl_idname = "BT4D_PT_result"
    bl_label = "Result"

    def draw(self, context):
        draw_result(self.layout, context)


class BT4D_PT_bullet_time(_BT4DPanel, Panel):
    bl_idname = "BT4D_PT_bullet_time"
    bl_label = "Bullet Time"

    def draw(self, context):
        draw_bullet_time(self.layout, context)


# -- hooks for later stages (filled by panel_run.py) --------------------------------------

def draw_reconstruction(layout, context) -> None:
    """Reconstruct button, progress bar, live loss/PSNR/ETA, Cancel."""
    panel_run.draw_reconstruction(layout, context)


def draw_result(layout, context) -> None:
    """Held-out metrics and Load Result."""
    panel_run.draw_result(layout, context)


def draw_bullet_time(layout, context) -> None:
    """Capture Time, freeze / real time, orbit camera, path render."""
    panel_run.draw_bullet_time(layout, context)


classes = (BT4D_PT_capture, BT4D_PT_reconstruction, BT4D_PT_reconstruction_advanced, BT4D_PT_result,
           BT4D_PT_bullet_time)
