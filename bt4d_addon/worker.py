"""Background jobs for long engine work (training, evaluation, path rendering).

Why a thread and not a subprocess
    * torch (and numba) release the GIL in their kernels, so a training thread keeps the UI
      responsive: Blender's main thread only runs a short timer callback a few times a
      second.
    * Blender's bundled Python is the interpreter that already has torch on its path (the
      add-on's packages); a subprocess would need a second interpreter that can import torch
      and the engine, and a way to find it on every platform.
    * Results come back in shared memory: the trained model is sampled into numpy arrays
      in the worker and the main thread turns them into Blender data directly, with no
      files or pickling in between.
    * Cancelling is a ``threading.Event`` that ``engine.train.train`` checks every step (it
      then saves a checkpoint and returns status "cancelled").

The rule that makes this safe: **the worker never touches bpy**. It only calls the engine
and pushes messages into a ``queue.Queue``; the main thread drains that queue from a
``bpy.app.timers`` callback (or a modal operator's timer) and updates Blender state.

This module itself does not import bpy, so it can be tested in plain Python.
"""
from __future__ import annotations

import importlib
import queue
import threading
import time
import traceback

# ----------------------------------------------------------------------------- engine import

_BASE = (__package__ or "").rpartition(".")[0]  # "" when bt4d_addon is a top-level package


def engine_module(sub: str | None = None):
    """Import ``engine`` (or ``engine.<sub>``) from wherever this add-on lives: inside the
    extension package (``bl_ext.<repo>.bullettime4d.engine``) or top-level (tests, scripts)."""
    name = f"{_BASE}.engine" if _BASE else "engine"
    if sub:
        name += "." + sub
    return importlib.import_module(name)


# ----------------------------------------------------------------------------- jobs

class Job:
    """``target(progress=callable, cancel=Event, **kwargs)`` run in a daemon thread.

    Messages (drain with :meth:`poll`): ``("progress", dict)``, ``("done", result)``,
    ``("error", message, traceback_text)``. ``progress`` may be called with any dict; the
    last one is also kept in :attr:`last_progress`.
    """

    def __init__(self, target, kind: str = "job", **kwargs):
        self.target = target
        self.kind = kind
        self.kwargs = kwargs
        self.queue: queue.Queue = queue.Queue()
        self.cancel_event = threading.Event()
        self.thread: threading.Thread | None = None
        self.result = None
        self.error: str | None = None
        self.error_traceback: str | None = None
        self.last_progress: dict = {}
        self.started = None
        self.finished = False
        self.context: dict = {}  # free slot for the caller (main thread only)

    # worker side -----------------------------------------------------------------------
    def _progress(self, info: dict) -> None:
        self.queue.put(("progress", dict(info)))

    def _run(self) -> None:
        try:
            result = self.target(progress=self._progress, cancel=self.cancel_event, **self.kwargs)
        except BaseException as exc:  # noqa: BLE001 - reported to the user, never raised in the UI
            self.queue.put(("error", f"{exc.__class__.__name__}: {exc}", traceback.format_exc()))
        else:
            self.queue.put(("done", result))

    # main-thread side -------------------------------------------------------------------
    def start(self) -> "Job":
        self.started = time.monotonic()
        self.thread = threading.Thread(target=self._run, name=f"bt4d-{self.kind}", daemon=True)
        self.thread.start()
        return self

    def run_sync(self):
        """Run in the calling thread (background mode). Messages still go through the queue."""
        self.started = time.monotonic()
        self._run()
        return self

    def cancel(self) -> None:
        self.cancel_event.set()

    @property
    def cancelled(self) -> bool:
        return self.cancel_event.is_set()

    def poll(self) -> list[tuple]:
        """Every message since the last poll; sets result/error/finished on the final one."""
        out = []
        while True:
            try:
                msg = self.queue.get_nowait()
            except queue.Empty:
                break
            if msg[0] == "progress":
                self.last_progress = msg[1]
            elif msg[0] == "done":
                self.result, self.finished = msg[1], True
            elif msg[0] == "error":
                self.error, self.error_traceback, self.finished = msg[1], msg[2], True
            out.append(msg)
        return out

    @property
    def alive(self) -> bool:
        return self.thread is not None and self.thread.is_alive()

    def join(self, timeout=None) -> None:
        if self.thread is not None:
            self.thread.join(timeout)


_ACTIVE: dict[str, Job] = {}


def active_job(kind: str) -> Job | None:
    return _ACTIVE.get(kind)


def set_active(kind: str, job: Job | None) -> None:
    if job is None:
        _ACTIVE.pop(kind, None)
    else:
        _ACTIVE[kind] = job


def is_running(kind: str) -> bool:
    """A job of this kind is running (a thread still alive, or a synchronous run in progress)."""
    job = _ACTIVE.get(kind)
    if job is None:
        return False
    if job.thread is not None:
        return job.alive or not job.queue.empty() and not job.finished
    return not job.finished


def cancel_all() -> None:
    for job in list(_ACTIVE.values()):
        job.cancel()


# ----------------------------------------------------------------------------- engine work

def reconstruct_job(*, progress, cancel, capture_path: str, run_dir: str, preset: str = "fast",
                    seconds: float | None = None, rgb_only: bool = False, resume: bool = True,
                    device=None, seed: int = 0, overrides: dict | None = None, evaluate: bool = True,
                    bring_back: bool = True, num_samples: int = 0) -> dict:
    """Train -> evaluate -> sample the model for the bring-back. No bpy in here.

    Returns dict(summary=train summary, metrics=dict|None, metrics_error=str|None,
    samples=dict|None (``gaussian_nodes.sample_scene`` arrays), run_dir=str)."""
    train_mod = engine_module("train")
    summary = train_mod.train(capture_path, run_dir, preset=preset, seconds=seconds, rgb_only=rgb_only,
                              resume=resume, device=None if device in (None, "auto") else device,
                              seed=seed, progress=progress, cancel=cancel, overrides=overrides)
    out = {"summary": summary, "metrics": None, "metrics_error": None, "samples": None, "run_dir": run_dir}
    if summary.get("status") != "finished":
        return out
    if evaluate:
        progress({"stage": "evaluating"})
        try:
            ev = engine_module("evaluate")
            out["metrics"] = ev.evaluate(run_dir)
        except Exception as exc:  # noqa: BLE001 - a failed evaluation must not lose the run
            out["metrics_error"] = f"{exc.__class__.__name__}: {exc}"
    if bring_back:
        progress({"stage": "sampling"})
        out["samples"] = sample_run(run_dir, num_samples)
    return out


def sample_run(run_dir: str, num_samples: int = 0, device="cpu") -> dict:
    """Open a run and sample it at K times (K = 0: automatic). No bpy."""
    from .gaussian_nodes import auto_num_samples, sample_scene

    model_mod = engine_module("model")
    scene = model_mod.load_run(run_dir, device=device)
    t0, t1 = scene.time_range
    k = int(num_samples) if num_samples and num_samples >= 2 else auto_num_samples(t1 - t0, scene.num_gaussians)
    samples = sample_scene(scene, k, (t0, t1))
    samples["run_dir"] = str(run_dir)
    return samples


def render_views_job(*, progress, cancel, scene4d, views: list, outputs: list, file_format: str = "OPEN_EXR",
                     transparent: bool = True, background=(0.0, 0.0, 0.0)) -> dict:
    """Render engine Views (each at its own time) and write one file per view. No bpy.

    ``outputs``: file paths, one per view. EXR: linear RGBA (premultiplied, i.e. over black)
    + Z (camera distance along the view axis, 1e10 where nothing was hit). PNG: 8-bit sRGB,
    RGBA with straight alpha when ``transparent`` else RGB over ``background``."""
    import numpy as np

    colour = engine_module("colour")
    images = engine_module("images")
    written = []
    t_start = time.monotonic()
    for i, (view, path) in enumerate(zip(views, outputs)):
        if cancel is not None and cancel.is_set():
            return {"status": "cancelled", "written": written}
        if file_format == "OPEN_EXR" or not transparent:
            bg = (0.0, 0.0, 0.0) if file_format == "OPEN_EXR" else background
        else:
            bg = (0.0, 0.0, 0.0)
        opaque = file_format != "OPEN_EXR" and not transparent  # no black holes in an opaque frame (issue 14)
        r = scene4d.render([view], background=bg, fill_holes=opaque)[0]
        rgb, alpha, depth = r["rgb"], r["alpha"], r["depth"]
        if file_format == "OPEN_EXR":
            lin = colour.srgb_to_linear(np.clip(rgb, 0.0, None)).astype(np.float32)
            # engine depth: expected camera z normalised by alpha, 0 where nothing was hit
            z = np.where((alpha > 1e-4) & (depth > 0), depth, 1e10).astype(np.float32)
            images.write_exr(path, {"R": lin[..., 0], "G": lin[..., 1], "B": lin[..., 2], "A": alpha, "Z": z})
        else:
            if transparent:
                straight = np.where(alpha[..., None] > 1e-6, rgb / np.maximum(alpha[..., None], 1e-6), 0.0)
                img = np.concatenate([np.clip(straight, 0, 1), alpha[..., None]], axis=-1)
            else:
                img = rgb
            images.write_png(path, img)
        written.append(str(path))
        el = time.monotonic() - t_start
        progress({"step": i + 1, "total_steps": len(views), "stage": "rendering", "elapsed_s": el,
                  "eta_s": el / (i + 1) * (len(views) - i - 1), "path": str(path)})
    return {"status": "finished", "written": written}
