"""Sidebar contents for the Reconstruction, Result and Bullet Time panels (``panel.py``
calls the ``draw_*`` functions below). They draw ``Scene.bt4d_run`` (``properties.py``).
"""
from __future__ import annotations

from . import gaussian_nodes as gn
from . import preferences


def _fmt_time(s: float) -> str:
    s = max(0.0, float(s))
    if s >= 3600:
        return f"{int(s // 3600)}h{int(s % 3600 // 60):02d}m"
    if s >= 60:
        return f"{int(s // 60)}m{int(s % 60):02d}s"
    return f"{s:.0f}s"


def draw_torch_missing(layout) -> bool:
    """A warning with a way to the preferences when the engine cannot import torch (Blender does
    not ship it): without it Reconstruct can only fail. Returns whether it drew one."""
    if preferences.torch_location() is not None:
        return False
    box = layout.box()
    box.alert = True
    box.label(text="torch is not installed: Reconstruct needs it", icon="ERROR")
    op = box.operator("preferences.addon_show", text="Install Dependencies...", icon="PREFERENCES")
    op.module = preferences.ADDON_PACKAGE
    return True


def draw_advanced(layout, context) -> None:
    """The switches most runs leave alone (the collapsed Advanced sub-panel)."""
    s = context.scene.bt4d
    adv = layout.column(align=True)
    adv.enabled = context.scene.bt4d_run.status != "RUNNING"
    adv.prop(s, "motion")
    adv.prop(s, "freeze_static")
    adv.prop(s, "close_cracks")
    fill = adv.row()
    fill.enabled = bool(s.close_cracks)
    fill.prop(s, "crack_fill")
    adv.prop(s, "early_stop")


def draw_reconstruction(layout, context) -> None:
    scene = context.scene
    r = scene.bt4d_run
    s = scene.bt4d
    draw_torch_missing(layout)
    col = layout.column()
    col.prop(r, "resume")
    running = r.status == "RUNNING"
    row = col.row(align=True)
    row.enabled = bool(s.capture_dir) and not running
    row.operator("bt4d.reconstruct", text="Reconstruct", icon="PLAY")
    if r.status == "IDLE":
        return
    box = layout.box()
    if running:
        text = f"{r.stage or 'starting'} {r.step}/{r.total_steps}" if r.total_steps else (r.stage or "starting")
        box.progress(factor=r.progress, type="BAR", text=text)
        grid = box.grid_flow(columns=2, align=True)
        grid.label(text=f"Loss {r.loss:.4f}")
        grid.label(text=f"PSNR {r.psnr:.2f} dB")
        grid.label(text=f"ETA {_fmt_time(r.eta_s)}")
        grid.label(text=f"{r.num_gaussians} Gaussians")
        box.operator("bt4d.cancel_reconstruction", text="Cancel", icon="CANCEL")
    else:
        icon = {"FINISHED": "CHECKMARK", "CANCELLED": "CANCEL", "FAILED": "ERROR"}.get(r.status, "INFO")
        box.label(text=f"{r.status.title()}: {r.step}/{r.total_steps} steps, {_fmt_time(r.elapsed_s)}", icon=icon)
        if r.message:
            for line in r.message.splitlines()[:4]:
                box.label(text=line)


def draw_result(layout, context) -> None:
    scene = context.scene
    r = scene.bt4d_run
    col = layout.column()
    if r.has_metrics:
        box = col.box()
        box.label(text="Held-out evaluation", icon="SORTTIME")
        g = box.grid_flow(columns=2, align=True)
        g.label(text=f"PSNR {r.metric_psnr:.2f} dB")
        g.label(text=f"SSIM {r.metric_ssim:.3f}")
        g.label(text=f"LPIPS {r.metric_lpips:.3f}" if r.metric_lpips >= 0 else "LPIPS n/a")
        g.label(text=f"Between frames {r.metric_psnr_interframe:.2f} dB")
        g.label(text=f"Dynamic {r.metric_psnr_dynamic:.2f} dB")
        box.label(text=f"{r.metric_frames} frames, trained {_fmt_time(r.train_seconds)}")
    if r.run_dir:
        col.prop(r, "run_dir", text="Run")
    col.prop(r, "num_samples")
    op = col.operator("bt4d.load_result", text="Load Result", icon="IMPORT")
    if r.run_dir:
        op.directory = r.run_dir
    row = col.row()
    row.enabled = bool(r.run_dir)
    op = row.operator("bt4d.export_ply", text="Export PLY Sequence", icon="EXPORT")
    if r.run_dir:
        op.source = r.run_dir
    results = gn.find_result_objects(scene)
    if not results:
        col.label(text="No reconstruction in the scene", icon="INFO")


def draw_bullet_time(layout, context) -> None:
    scene = context.scene
    r = scene.bt4d_run
    results = gn.find_result_objects(scene)
    obj = context.active_object if context.active_object in results else (results[0] if results else None)
    if obj is None:
        layout.label(text="Bring a reconstruction back first", icon="INFO")
        return
    col = layout.column()
    mod = obj.modifiers[gn.MODIFIER_NAME]
    col.label(text=obj.name, icon="OUTLINER_OB_POINTCLOUD")
    try:
        col.prop(mod, f'["{gn.input_identifier(mod.node_group, gn.CAPTURE_TIME)}"]', text="Capture Time")
    except KeyError:
        pass
    row = col.row(align=True)
    row.operator("bt4d.freeze_capture_time", text="Freeze Here", icon="PAUSE")
    row.operator("bt4d.realtime_capture_time", text="Real Time", icon="PLAY")
    col.operator("bt4d.add_orbit_camera", text="Add Orbit Camera", icon="CAMERA_DATA")
    col.separator()
    if r.render_running:
        col.progress(factor=r.render_progress, type="BAR", text=r.render_message or "Rendering")
        col.operator("bt4d.cancel_render_path", text="Cancel", icon="CANCEL")
    else:
        col.operator("bt4d.render_path", text="Render Camera Path", icon="RENDER_ANIMATION")
        col.operator("bt4d.export_camera_path", text="Export Camera Path...", icon="EXPORT")
        if r.render_message:
            col.label(text=r.render_message)
