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
and pushes messages into a ``queue.Queue``; the main thread drains that queue with
:meth:`Job.pump` from a ``bpy.app.timers`` callback (reconstruct) or a modal operator's
timer (render_path) and updates Blender state.

One runner for both operators: :meth:`Job.start` (worker thread; the main thread calls
:meth:`Job.pump` until it returns False) or :meth:`Job.run_sync` (background mode, where no
timer ever fires). While a job runs it is the active job of its ``kind``
(:func:`is_running`, :func:`active_job`); it stops being so once its last message is drained.

This module itself does not import bpy, so it can be tested in plain Python.
"""
from __future__ import annotations

import queue
import threading
import time
import traceback

from . import engine_bridge

# ----------------------------------------------------------------------------- jobs


class Job:
    """``target(progress=callable, cancel=Event, **kwargs)`` run in a daemon thread or in the
    calling thread.

    Messages (drain with :meth:`poll` or :meth:`pump`): ``("progress", dict)``,
    ``("done", result)``, ``("error", message, traceback_text)``. ``progress`` may be called
    with any dict; the last one is also kept in :attr:`last_progress`.
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
        self._on_progress = None   # main-thread watchers (see watch)
        self._on_finish = None
        self._sync_progress = None  # run_sync's observer, called in the running thread

    # worker side -----------------------------------------------------------------------
    def _progress(self, info: dict) -> None:
        self.queue.put(("progress", dict(info)))
        if self._sync_progress is not None:
            self._sync_progress(dict(info))

    def _run(self) -> None:
        try:
            result = self.target(progress=self._progress, cancel=self.cancel_event, **self.kwargs)
        except BaseException as exc:  # noqa: BLE001 - reported to the user, never raised in the UI
            self.queue.put(("error", f"{exc.__class__.__name__}: {exc}", traceback.format_exc()))
        else:
            self.queue.put(("done", result))

    # main-thread side -------------------------------------------------------------------
    def start(self) -> "Job":
        """Run in a daemon thread; the main thread then calls :meth:`pump` (or :meth:`poll`)."""
        self.started = time.monotonic()
        _ACTIVE[self.kind] = self
        self.thread = threading.Thread(target=self._run, name=f"bt4d-{self.kind}", daemon=True)
        self.thread.start()
        return self

    def run_sync(self, progress=None) -> "Job":
        """Run to the end in the calling thread (background mode: no timers run there).
        ``progress(info)`` sees every progress message as it is sent; on return the job is
        finished (:attr:`result` or :attr:`error` set) and no longer active."""
        self.started = time.monotonic()
        _ACTIVE[self.kind] = self
        self._sync_progress = progress
        try:
            self._run()
        finally:
            self._sync_progress = None
            self.poll()
        return self

    def watch(self, on_progress=None, on_finish=None) -> "Job":
        """What :meth:`pump` does with the messages: ``on_progress(info)`` for each progress
        message, ``on_finish(job)`` once, after the final one (main thread)."""
        self._on_progress, self._on_finish = on_progress, on_finish
        return self

    def pump(self) -> bool:
        """The polling helper (main thread, from a timer): drain the messages into the
        watchers set by :meth:`watch`. Returns True while the job still runs, False once it
        has finished and ``on_finish`` has run."""
        was_finished = self.finished
        for msg in self.poll():
            if msg[0] == "progress" and self._on_progress is not None:
                self._on_progress(msg[1])
        if not self.finished:
            return True
        if not was_finished and self._on_finish is not None:
            self._on_finish(self)
        return False

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
        if self.finished and _ACTIVE.get(self.kind) is self:
            del _ACTIVE[self.kind]
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
    samples=dict|None (``Scene4D.sample`` arrays), run_dir=str)."""
    summary = engine_bridge.train(capture_path, run_dir, preset=preset, seconds=seconds, rgb_only=rgb_only,
                                  resume=resume, device=None if device in (None, "auto") else device,
                                  seed=seed, progress=progress, cancel=cancel, overrides=overrides,
                                  on_stage=lambda text: progress({"stage": text}))
    out = {"summary": summary, "metrics": None, "metrics_error": None, "samples": None, "run_dir": run_dir}
    if summary.get("status") != "finished":
        return out
    if evaluate:
        progress({"stage": "evaluating"})
        try:
            out["metrics"] = engine_bridge.evaluate(run_dir)
        except Exception as exc:  # noqa: BLE001 - a failed evaluation must not lose the run
            out["metrics_error"] = f"{exc.__class__.__name__}: {exc}"
    if bring_back:
        progress({"stage": "sampling"})
        out["samples"] = sample_run(run_dir, num_samples)
    return out


def sample_run(run_dir: str, num_samples: int = 0, device="cpu") -> dict:
    """Open a run folder or a compact cache (.bt4c) and sample it at K times (K = 0:
    automatic). No bpy."""
    samples = engine_bridge.load_result(run_dir, device=device).sample(num_samples)
    samples["run_dir"] = str(run_dir)
    return samples


_ENGINE_FORMAT = {"OPEN_EXR": "exr", "PNG": "png"}


def render_views_job(*, progress, cancel, scene4d, views: list, outputs: list, file_format: str = "OPEN_EXR",
                     transparent: bool = True, background=(0.0, 0.0, 0.0)) -> dict:
    """Render engine Views (each at its own time) to one file per view with the engine's
    render-to-file (``write_renders``: its EXR / PNG conventions). No bpy.

    ``outputs``: file paths, one per view. PNG: RGBA with straight alpha when
    ``transparent``, else RGB over ``background``. One view per call, so that cancel and
    progress act between frames."""
    fmt = _ENGINE_FORMAT[file_format]
    png_background = None if transparent else tuple(background)
    written = []
    t_start = time.monotonic()
    for i, (view, path) in enumerate(zip(views, outputs)):
        if cancel is not None and cancel.is_set():
            return {"status": "cancelled", "written": written}
        engine_bridge.write_renders(scene4d, [view], None, fmt, paths=[path], png_background=png_background,
                                    fill_holes=True)  # opaque PNG: no black holes (issue 14)
        written.append(str(path))
        el = time.monotonic() - t_start
        progress({"step": i + 1, "total_steps": len(views), "stage": "rendering", "elapsed_s": el,
                  "eta_s": el / (i + 1) * (len(views) - i - 1), "path": str(path)})
    return {"status": "finished", "written": written}
