"""``bpy.ops.bt4d.render_path()``: render the scene camera's path with the engine's exact
splat renderer.

For every frame of the scene's frame range the scene is evaluated at that frame, the
active scene camera becomes an engine ``View`` (``bt4d_addon/blender_cameras.py``: lens,
sensor fit, shift, pixel aspect, resolution x percentage) at the capture time the result
object's "Capture Time" input has at that frame (its F-curve, so bullet time and slow
motion render as keyed), and the engine's render-to-file (``write_renders``, through
``bt4d_addon/engine_bridge.py``) draws and writes it. Files go to ``scene.render.filepath``
with Blender's frame numbering (``#`` placeholders, or 4 digits appended), in the engine's
conventions: EXR = linear RGBA (premultiplied) + Z, PNG = 8-bit sRGB (RGBA when
``film_transparent``, else RGB over black). The sequence is loaded back as an image
datablock (source 'SEQUENCE'). ``prune_unobserved`` ("Drop Unobserved Gaussians", off by
default) renders without the Gaussians no train camera saw inside its image
(``engine.scene.observed``, issue 14; docs/experiments/orbit-around-the-demo.md "Orbit around the demo").

Interactive: a modal operator with a window-manager timer pumps the job (``Job.pump``); the
renders run in a worker thread (no bpy there), ESC or ``bt4d.cancel_render_path`` stops
it. Background mode (or no window): synchronous (``Job.run_sync``).
"""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty
from bpy.types import Operator

from ..bt4d_addon import attributes as A
from ..bt4d_addon import blender_cameras, engine_bridge, gaussian_nodes, worker

KIND = "render_path"
FORMAT_ITEMS = (
    ("SCENE", "Scene Setting", "EXR when the scene's output format is OpenEXR, PNG otherwise"),
    ("OPEN_EXR", "OpenEXR", "Linear RGBA + Z depth, 32-bit float"),
    ("PNG", "PNG", "8-bit sRGB"),
)
_EXT = {"OPEN_EXR": ".exr", "PNG": ".png"}
_SCENE4D_CACHE: dict = {}


def get_scene4d(source: str, prune_unobserved: bool = False):
    """The engine's result for a run folder or a compact cache (``.bt4c``), kept while its file
    is unchanged; a run folder optionally without the Gaussians no train camera constrained
    (issue 14), which a compact cache cannot tell."""
    path = Path(source)
    if path.is_file() and prune_unobserved:
        raise RuntimeError(f"{path}: Drop Unobserved Gaussians needs the run folder; this is a compact cache")
    ck = path if path.is_file() else path / "checkpoint.pt"
    key = (str(source), ck.stat().st_mtime if ck.exists() else None, bool(prune_unobserved))
    if key not in _SCENE4D_CACHE:
        _SCENE4D_CACHE.clear()
        _SCENE4D_CACHE[key] = (engine_bridge.load_result(source, device="cpu") if path.is_file() else
                               engine_bridge.load_run(source, device="cpu", prune_unobserved=prune_unobserved))
    return _SCENE4D_CACHE[key]


def resolve_format(scene, file_format: str) -> str:
    if file_format != "SCENE":
        return file_format
    fmt = getattr(scene.render.image_settings, "file_format", "PNG")
    return "OPEN_EXR" if fmt in ("OPEN_EXR", "OPEN_EXR_MULTILAYER") else "PNG"


def output_path(scene, frame: int, file_format: str) -> str:
    """Blender's own frame path (``#`` placeholders, 4 digits appended when there are
    none, relative to the .blend; in the temp folder for a relative path in an unsaved
    file) with the extension of ``file_format``."""
    p = scene.render.frame_path(frame=int(frame))
    root, ext = os.path.splitext(p)
    if ext.lower() in (".png", ".exr", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".tga", ".webp", ".hdr",
                       ".jp2", ".dpx", ".cin", ".rgb"):
        p = root
    p = bpy.path.abspath(p)
    if not os.path.isabs(p):  # "//..." in an unsaved file: Blender would use the working dir
        p = os.path.join(tempfile.gettempdir(), p)
    return p + _EXT[file_format]


def collect_views(scene, camera, obj, frames) -> list:
    """Engine Views of ``camera`` at each frame, at the Capture Time ``obj`` shows then."""
    views = []
    current = scene.frame_current
    try:
        for f in frames:
            scene.frame_set(int(f))
            cam = camera or scene.camera
            t = gaussian_nodes.capture_time_at(obj, f)
            views.append(blender_cameras.camera_to_view(cam, scene, time=t, name=f"frame {f}"))
    finally:
        scene.frame_set(current)
    return views


def show_progress(scene, info: dict) -> None:
    """A progress message of the render job into ``scene.bt4d_run`` (main thread)."""
    r = getattr(scene, "bt4d_run", None)
    if r is not None:
        r.render_progress = info.get("step", 0) / max(1, info.get("total_steps", 1))
        r.render_message = f"Frame {info.get('step')}/{info.get('total_steps')}"


def load_sequence(paths: list[str], name: str | None = None):
    """Load written frames back as an image sequence datablock."""
    if not paths:
        return None
    img = bpy.data.images.load(paths[0], check_existing=False)
    img.source = "SEQUENCE"
    if name:
        img.name = name
    return img


class BT4D_OT_render_path(Operator):
    """Render the scene camera's keyframed path with the exact splat renderer (EXR/PNG
    sequence at the scene's output path)"""

    bl_idname = "bt4d.render_path"
    bl_label = "Render Camera Path"
    bl_options = {"REGISTER"}

    file_format: EnumProperty(name="Format", items=FORMAT_ITEMS, default="SCENE")
    frame_start: IntProperty(name="Start", default=-1, description="First frame (-1: the scene's)")
    frame_end: IntProperty(name="End", default=-1, description="Last frame (-1: the scene's)")
    run_dir: StringProperty(name="Run", subtype="DIR_PATH",
                            description="Run folder to render (empty: the active / first result object's)")
    load_back: BoolProperty(name="Load Sequence", default=True,
                            description="Load the rendered frames as an image sequence")
    prune_unobserved: BoolProperty(
        name="Drop Unobserved Gaussians", default=False,
        description="Leave out the Gaussians whose centre no train camera saw inside its image (held by a "
                    "fringe only: speckled floaters at the sides of new viewpoints); the hole fill shows there "
                    "instead. Needs the run's capture")

    _timer = None
    _job = None

    def _prepare(self, context):
        scene = context.scene
        obj = gaussian_nodes.pick_result_object(context)
        if obj is None:
            raise RuntimeError("No reconstruction in the scene: load a result first")
        if scene.camera is None:
            raise RuntimeError("The scene has no camera")
        run_dir = bpy.path.abspath(self.run_dir) if self.run_dir else obj.get(A.RUN_DIR, "")
        if not run_dir:
            raise RuntimeError(f"{obj.name!r} does not say which run it came from")
        fs = scene.frame_start if self.frame_start < 0 else self.frame_start
        fe = scene.frame_end if self.frame_end < 0 else self.frame_end
        frames = list(range(fs, fe + 1, max(1, scene.frame_step)))
        fmt = resolve_format(scene, self.file_format)
        views = collect_views(scene, None, obj, frames)
        outputs = [output_path(scene, f, fmt) for f in frames]
        scene4d = get_scene4d(run_dir, self.prune_unobserved)
        transparent = bool(scene.render.film_transparent)
        return worker.Job(worker.render_views_job, kind=KIND, scene4d=scene4d, views=views, outputs=outputs,
                          file_format=fmt, transparent=transparent)

    def _finish(self, context, job):
        r = context.scene.bt4d_run if hasattr(context.scene, "bt4d_run") else None
        if r is not None:
            r.render_running = False
        if job.error:
            if r is not None:
                r.render_message = f"Failed: {job.error}"
            self.report({"ERROR"}, f"Path render failed: {job.error}")
            return {"CANCELLED"}
        res = job.result or {}
        written = res.get("written", [])
        if self.load_back and written:
            img = load_sequence(written, name=f"BT4D {Path(written[0]).parent.name} path")
            if img is not None:
                context.scene["bt4d_last_render"] = img.name
        msg = f"{res.get('status', 'finished').title()}: {len(written)} frames"
        if written:
            msg += f" in {Path(written[0]).parent}"
        if r is not None:
            r.render_message = msg
            r.render_progress = 1.0 if res.get("status") == "finished" else r.render_progress
        self.report({"INFO" if res.get("status") == "finished" else "WARNING"}, msg)
        return {"FINISHED"}

    def execute(self, context):
        if worker.is_running(KIND):
            self.report({"ERROR"}, "A path render is already running")
            return {"CANCELLED"}
        try:
            job = self._prepare(context)
        except Exception as exc:  # noqa: BLE001
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        r = getattr(context.scene, "bt4d_run", None)
        if bpy.app.background or context.window_manager is None or not context.window_manager.windows:
            last = [0.0]

            def prog(info):
                now = time.monotonic()
                if now - last[0] >= 1.0 or info.get("step") == info.get("total_steps"):
                    last[0] = now
                    print(f"BT4D render_path: frame {info.get('step')}/{info.get('total_steps')} -> "
                          f"{info.get('path')}", flush=True)

            return self._finish(context, job.run_sync(prog))
        # interactive: modal + timer
        if r is not None:
            r.render_running, r.render_progress, r.render_message = True, 0.0, "starting"
        scene = context.scene
        self._job = job.watch(on_progress=lambda info: show_progress(scene, info))
        job.start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.2, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def invoke(self, context, event):
        return self.execute(context)

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC":
            job.cancel()
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        running = job.pump()
        for area in context.screen.areas if context.screen else []:
            if area.type == "VIEW_3D":
                area.tag_redraw()
        if running:
            return {"RUNNING_MODAL"}
        context.window_manager.event_timer_remove(self._timer)
        return self._finish(context, job)


class BT4D_OT_cancel_render_path(Operator):
    """Stop the running path render (frames written so far are kept)"""

    bl_idname = "bt4d.cancel_render_path"
    bl_label = "Cancel Path Render"

    @classmethod
    def poll(cls, context):
        return worker.is_running(KIND)

    def execute(self, context):
        job = worker.active_job(KIND)
        if job is not None:
            job.cancel()
        return {"FINISHED"}


classes = (BT4D_OT_render_path, BT4D_OT_cancel_render_path)
