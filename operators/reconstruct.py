"""``bpy.ops.bt4d.reconstruct()`` and ``bpy.ops.bt4d.cancel_reconstruction()``.

Reconstructs the imported capture (``scene.bt4d.capture_dir``) with the scene's settings
(preset, time budget, output folder, device, spikes on/off, resume vs restart, and the
advanced switches "Freeze Static Gaussians" / "Stop Early", passed as the training
overrides ``freeze_static`` / ``early_stop``):

* interactive Blender: ``engine.train.train`` runs in a worker thread
  (``bt4d_addon/worker.py``: it never touches bpy); a ``bpy.app.timers`` callback pumps
  its progress queue (``Job.pump``) into ``scene.bt4d_run`` (progress bar, loss, PSNR,
  ETA) a few times a second. Cancel sets the job's Event; the engine saves a checkpoint
  and stops.
* background mode (``blender --background``, the ``bpy`` module: no timers, no events):
  the same work runs synchronously (``Job.run_sync``) and prints one progress line per
  second.

The operator's ``run_mode`` picks one of the two explicitly (default: by the mode Blender
runs in); a script in background mode that pumps the job itself
(``worker.active_job("reconstruct").pump()``) can ask for the worker thread.

On success the run is evaluated (``engine.evaluate``, held-out metrics into the Result
panel) and brought back (``load_result``). A failure reports the error and changes
nothing but the status fields: the capture and the scene stay as they were and the run
folder keeps its last checkpoint (``resume`` continues from it).

Run folder: ``<scene.bt4d.output_dir>/<capture name>``; the default output folder
``//bt4d_runs/`` is next to the saved .blend, or in the system temp folder while the file
is unsaved. A run never overwrites another (:func:`choose_run_dir`): Resume continues the run
in that folder only when it was made with the same settings; otherwise, and whenever Resume
is off and the folder holds a run, the run goes to ``<capture name>_2``, ``_3``, ...
"""
from __future__ import annotations

import json
import math
import os
import tempfile
import time
from pathlib import Path

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty
from bpy.types import Operator

from ..bt4d_addon import worker
from ..bt4d_addon.properties import CRACK_FILL_ITEMS, MOTION_ITEMS
from . import load_result

KIND = "reconstruct"
RUN_MODE_ITEMS = (
    ("AUTO", "Auto", "A worker thread in the interactive UI; to the end before returning in background mode"),
    ("THREAD", "Worker Thread", "Return at once; a timer (or the caller, with Job.pump) follows the job"),
    ("WAIT", "Wait", "Run to the end before returning"),
)


def use_thread(run_mode: str) -> bool:
    """Whether ``run_mode`` runs the job in a worker thread (see RUN_MODE_ITEMS)."""
    return run_mode == "THREAD" or (run_mode == "AUTO" and not bpy.app.background)


def capture_name(scene) -> str:
    s = scene.bt4d
    return s.capture_name or Path(bpy.path.abspath(s.capture_dir).rstrip("/\\")).name or "capture"


def resolve_run_dir(scene) -> str:
    """Absolute run folder for the scene's capture (see module doc)."""
    out = scene.bt4d.output_dir or "//bt4d_runs/"
    if out.startswith("//") and not bpy.data.filepath:
        base = Path(tempfile.gettempdir()) / "bt4d_runs" / out[2:].strip("/\\").removeprefix("bt4d_runs").strip("/\\")
    else:
        base = Path(bpy.path.abspath(out))
    return str((base / capture_name(scene)).resolve())


def _run_settings(run_dir: Path) -> dict | None:
    """The settings a run folder's run.json records (None: no run there, or unreadable)."""
    try:
        info = json.loads((run_dir / "run.json").read_text())
    except (OSError, ValueError):
        return None
    return {k: info.get(k) for k in ("capture", "preset", "overrides", "rgb_only", "seed")}


def choose_run_dir(base: str, wanted: dict, resume: bool) -> str:
    """The folder a new reconstruction writes to, never overwriting another run (issue 45):
    ``base`` when it holds no run, or when ``resume`` is on and its run has the ``wanted``
    settings (capture, preset, overrides, rgb_only, seed: what decides whether a checkpoint
    can be continued); else the first of ``base_2``, ``base_3``, ... that holds no run or, with
    ``resume``, that run."""
    root = Path(base)
    wanted = json.loads(json.dumps(wanted))  # the types run.json gives back (lists, not tuples)
    for k in range(1, 10_000):
        cand = root if k == 1 else root.with_name(f"{root.name}_{k}")
        have = _run_settings(cand)
        if have is None and not (cand / "checkpoint.pt").exists():
            return str(cand)
        if resume and have == wanted:
            return str(cand)
    raise RuntimeError(f"{root}: no free run folder")


def advanced_overrides(settings) -> dict:
    """The advanced settings of ``scene.bt4d`` as training overrides (only those that differ
    from the engine's defaults: a switch turned on, "Close Cracks" turned off, a motion or a
    crack fill other than the first item)."""
    out = {}
    motion = getattr(settings, "motion", MOTION_ITEMS[0][0])
    if motion != MOTION_ITEMS[0][0]:
        out["motion.representation"] = str(motion)
    if getattr(settings, "freeze_static", False):
        out["skip.freeze_static"] = True
    if getattr(settings, "early_stop", False):
        out["skip.early_stop"] = True
    if not getattr(settings, "close_cracks", True):
        out["losses.cover"] = 0.0  # on in the engine by default
    else:
        fill = getattr(settings, "crack_fill", CRACK_FILL_ITEMS[0][0])
        if fill != CRACK_FILL_ITEMS[0][0]:
            out["losses.cover_grad"] = str(fill)
    return out


def _num(v, default=0.0):
    try:
        v = float(v)
    except (TypeError, ValueError):
        return default
    return v if math.isfinite(v) else default


def apply_progress(scene, info: dict) -> None:
    r = scene.bt4d_run
    if "stage" in info:
        r.stage = str(info["stage"])
    if "total_steps" in info:
        r.total_steps = int(info["total_steps"])
    if "step" in info:
        r.step = int(info["step"])
        r.progress = min(1.0, r.step / max(1, r.total_steps))
    for key in ("loss", "psnr", "eta_s", "elapsed_s"):
        if key in info:
            setattr(r, key, _num(info[key]))
    if "num_gaussians" in info:
        r.num_gaussians = int(info["num_gaussians"])


def progress_line(info: dict) -> str:
    if "step" not in info:
        return f"BT4D reconstruct: {info.get('stage', '')}"
    return (f"BT4D reconstruct: step {info['step']}/{info.get('total_steps', '?')} {info.get('stage', '')} "
            f"loss {_num(info.get('loss')):.4f} psnr {_num(info.get('psnr')):.2f} dB "
            f"gaussians {info.get('num_gaussians', '?')} eta {_num(info.get('eta_s')):.0f}s")


def apply_metrics(scene, metrics: dict | None, summary: dict) -> None:
    r = scene.bt4d_run
    r.train_seconds = _num(summary.get("train_seconds"))
    if not metrics:
        r.has_metrics = False
        return
    r.has_metrics = True
    r.metric_psnr = _num(metrics.get("psnr"))
    r.metric_ssim = _num(metrics.get("ssim"))
    r.metric_lpips = _num(metrics.get("lpips"), -1.0)  # -1: a metrics.json from before LPIPS
    r.metric_psnr_interframe = _num(metrics.get("psnr_interframe"))
    r.metric_psnr_dynamic = _num(metrics.get("psnr_dynamic"))
    r.metric_frames = int(_num(metrics.get("n_frames")))
    if metrics.get("train_seconds") is not None:
        r.train_seconds = _num(metrics.get("train_seconds"))


def finish(scene, job: worker.Job) -> tuple[str, str]:
    """Apply a finished job to ``scene`` (main thread). Returns (report level, message)."""
    r = scene.bt4d_run
    if job.error:
        r.status = "FAILED"
        r.message = job.error
        print(f"BT4D reconstruct failed: {job.error}\n{job.error_traceback or ''}")
        return "ERROR", f"Reconstruction failed: {job.error} (checkpoints in {r.run_dir} are kept)"
    res = job.result or {}
    summary = res.get("summary", {})
    status = str(summary.get("status", "finished"))
    apply_progress(scene, {"step": summary.get("step", r.step),
                           "total_steps": summary.get("total_steps", r.total_steps),
                           "num_gaussians": summary.get("num_gaussians", r.num_gaussians),
                           "elapsed_s": summary.get("train_seconds", r.elapsed_s), "eta_s": 0.0})
    if status == "cancelled":
        r.status = "CANCELLED"
        r.stage = "cancelled"
        r.message = "Cancelled; the checkpoint is kept (Reconstruct with Resume continues)"
        return "WARNING", r.message
    if status != "finished":
        r.status = "FAILED"
        r.message = f"Training ended with status {status!r}"
        return "ERROR", r.message
    apply_metrics(scene, res.get("metrics"), summary)
    msgs = []
    if summary.get("stopped_early"):
        se = summary["stopped_early"]
        msgs.append(f"stopped early at step {se.get('step')}/{se.get('total_steps')} "
                    "(held-out PSNR no longer improving)")
    elif (summary.get("settle") or {}).get("converged_at") is not None and summary.get("budget_used") is not None:
        msgs.append(f"converged after {summary.get('step')} steps, {summary['budget_used']:.0%} of the time budget "
                    f"(the schedule ended at step {summary['settle']['from_step']}; more steps would not sharpen "
                    "the new view)")
    prep = summary.get("budget_estimates") or {}
    if summary.get("ended_by") == "budget" and prep.get("preparation_heavy"):
        msgs.append(f"preparing the capture took {prep['preparation_s']:.0f} s, "
                    f"{prep['preparation_share']:.0%} of the time budget; {summary.get('step')} steps trained "
                    "(raise the budget)")
    if res.get("metrics_error"):
        msgs.append(f"evaluation failed: {res['metrics_error']}")
    if res.get("samples") is not None:
        try:
            obj = load_result.load_samples(scene, res["samples"], res.get("run_dir", r.run_dir),
                                           metrics=res.get("metrics"))
            msgs.append(f"loaded as {obj.name!r}")
        except Exception as exc:  # noqa: BLE001
            msgs.append(f"bring-back failed: {exc}")
    r.status = "FINISHED"
    r.stage = "finished"
    r.progress = 1.0
    if r.has_metrics:
        msgs.insert(0, f"eval PSNR {r.metric_psnr:.2f} dB, SSIM {r.metric_ssim:.3f}")
    r.message = "; ".join(msgs)
    return "INFO", "Reconstruction finished" + (": " + r.message if r.message else "")


def _tag_redraw() -> None:
    wm = bpy.context.window_manager
    for win in getattr(wm, "windows", []):
        for area in win.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


def _popup(text: str) -> None:
    """Show an error from a timer (no operator to report through)."""
    wm = bpy.context.window_manager
    if wm is None or not getattr(wm, "windows", None):
        return

    def draw(menu, _context):
        for line in text.splitlines()[:6]:
            menu.layout.label(text=line)

    try:
        wm.popup_menu(draw, title="BulletTime4D", icon="ERROR")
    except (RuntimeError, AttributeError):
        pass


def _watch(job: worker.Job, scene_name: str, scene_uid: int = 0) -> worker.Job:
    """Hand the job's messages to the scene it started from, found by its session id (survives
    renames; a scene of another, newly loaded file never matches)."""
    def scene():
        if scene_uid:
            return next((sc for sc in bpy.data.scenes if sc.session_uid == scene_uid), None)
        return bpy.data.scenes.get(scene_name)

    def on_progress(info):
        sc = scene()
        if sc is not None:
            apply_progress(sc, info)
            _tag_redraw()

    def on_finish(job):
        sc = scene()
        if sc is None:  # file closed / scene deleted
            print(f"BT4D: reconstruction ended ({job.error or 'done'}); its scene is gone, the run "
                  f"folder {job.kwargs.get('run_dir')} holds the result")
            return
        level, text = finish(sc, job)
        print(f"BT4D: {text}")
        _tag_redraw()
        if level == "ERROR":
            _popup(text)

    return job.watch(on_progress, on_finish)


def _timer(job: worker.Job):
    """The bpy.app.timers callback: pump the job until it has finished."""
    return lambda: 0.25 if job.pump() else None


class BT4D_OT_reconstruct(Operator):
    """Reconstruct the imported capture as 4D Gaussians (runs in the background; in
    background mode it runs to the end before returning)"""

    bl_idname = "bt4d.reconstruct"
    bl_label = "Reconstruct"
    bl_options = {"REGISTER"}

    resume: BoolProperty(name="Resume", default=True,
                         description="Continue from a matching checkpoint in the run folder (off: start over)")
    use_scene_resume: BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"},
                                   description="Take Resume from scene.bt4d_run.resume")
    bring_back: BoolProperty(name="Load Result", default=True,
                             description="Load the result into the scene when training finishes")
    evaluate: BoolProperty(name="Evaluate", default=True,
                           description="Score the result on the capture's held-out eval frames")
    seconds: FloatProperty(name="Time Budget", default=-1.0, min=-1.0, options={"SKIP_SAVE"},
                           description="Training budget in seconds (-1: scene setting)")
    iterations: IntProperty(name="Iterations", default=0, min=0, options={"SKIP_SAVE"},
                            description="Fixed number of training steps instead of a time budget (0: use the budget)")
    run_mode: EnumProperty(name="Run", items=RUN_MODE_ITEMS, default="AUTO", options={"SKIP_SAVE"},
                           description="Where the training runs (see the items)")

    @classmethod
    def poll(cls, context):
        return bool(context.scene.bt4d.capture_dir) and not worker.is_running(KIND)

    def execute(self, context):
        scene = context.scene
        s = scene.bt4d
        r = scene.bt4d_run
        if worker.is_running(KIND):
            self.report({"ERROR"}, "A reconstruction is already running")
            return {"CANCELLED"}
        capture = bpy.path.abspath(s.capture_dir).rstrip("/\\") if s.capture_dir else ""
        if not capture or not os.path.isfile(os.path.join(capture, "transforms.json")):
            self.report({"ERROR"}, f"No capture to reconstruct: {capture or 'import one first'} "
                                   "(needs transforms.json)")
            return {"CANCELLED"}
        resume = r.resume if self.use_scene_resume else self.resume
        seconds = float(self.seconds if self.seconds >= 0 else s.seconds)
        overrides = advanced_overrides(s)
        if self.iterations > 0:
            seconds = None
            overrides["schedule.iterations"] = int(self.iterations)
        overrides = overrides or None
        wanted = {"capture": str(Path(capture).resolve()), "preset": s.preset, "overrides": overrides or {},
                  "rgb_only": not s.use_spikes, "seed": 0}
        run_dir = choose_run_dir(resolve_run_dir(scene), wanted, resume)
        job = worker.Job(worker.reconstruct_job, kind=KIND, capture_path=capture, run_dir=run_dir,
                         preset=s.preset, seconds=seconds if seconds and seconds > 0 else None,
                         rgb_only=not s.use_spikes, resume=resume, device=s.device, overrides=overrides,
                         evaluate=self.evaluate, bring_back=self.bring_back, num_samples=r.num_samples,
                         seed=wanted["seed"])  # the seed the run folder was chosen for
        r.status, r.stage, r.message, r.run_dir = "RUNNING", "starting", "", run_dir
        r.progress, r.step, r.total_steps, r.loss, r.psnr, r.eta_s = 0.0, 0, 0, 0.0, 0.0, 0.0
        r.has_metrics = False

        if not use_thread(self.run_mode):
            return self._run_sync(scene, job)
        _watch(job, scene.name, scene.session_uid).start()
        # persistent: keeps polling across file loads, so the job is always reaped
        bpy.app.timers.register(_timer(job), first_interval=0.2, persistent=True)
        self.report({"INFO"}, f"Reconstruction started in {run_dir}")
        return {"FINISHED"}

    def _run_sync(self, scene, job):
        last = [0.0]
        print(f"BT4D reconstruct: {job.kwargs['capture_path']} -> {job.kwargs['run_dir']} "
              f"(preset {job.kwargs['preset']}, budget {job.kwargs['seconds']} s)", flush=True)

        def on_progress(info):
            now = time.monotonic()
            final = info.get("step") is not None and info.get("step") == info.get("total_steps")
            if now - last[0] >= 1.0 or final or "step" not in info:
                last[0] = now
                print(progress_line(info), flush=True)
            apply_progress(scene, info)

        job.run_sync(on_progress)
        level, text = finish(scene, job)
        print(f"BT4D: {text}", flush=True)
        self.report({level}, text)
        return {"CANCELLED"} if level == "ERROR" else {"FINISHED"}


class BT4D_OT_cancel_reconstruction(Operator):
    """Stop the running reconstruction (a checkpoint is saved; Resume continues from it)"""

    bl_idname = "bt4d.cancel_reconstruction"
    bl_label = "Cancel Reconstruction"

    @classmethod
    def poll(cls, context):
        return worker.is_running(KIND)

    def execute(self, context):
        job = worker.active_job(KIND)
        if job is None:
            return {"CANCELLED"}
        job.cancel()
        context.scene.bt4d_run.stage = "cancelling"
        self.report({"INFO"}, "Cancelling: the reconstruction stops after the current step")
        return {"FINISHED"}


classes = (BT4D_OT_reconstruct, BT4D_OT_cancel_reconstruction)


def unregister():
    worker.cancel_all()
