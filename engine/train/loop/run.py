"""``train()``: one training run from a capture into a run folder.

Resume from the folder's checkpoint when its config matches, size the schedule for a
wall-clock budget (:mod:`engine.train.loop.budget`; the budget is also enforced as a hard stop,
reported as ``stopped_by_budget``), step the :class:`engine.train.loop.trainer.Trainer`, report
progress, honour cancel (checkpoint and stop), early stop, end a budget run that settles past its
schedule once it converges (:mod:`engine.train.loop.settle`), and keep ``checkpoint.pt`` and
``run.json`` up to date (both budget estimates are in run.json).
"""
from __future__ import annotations

import datetime as _dt
import os
import platform
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ...errors import RunError
from ...io.capture import load_capture
from ...io.checkpoint import CHECKPOINT, load_checkpoint, read_run_json, save_checkpoint, update_run_json
from ...scene.model import default_device
from ..config import TrainConfig, get_preset
from ..frames.baselines import with_baseline
from ..guidance.spike_flow import close_flow_worker
from .budget import (
    DEFORM_REESTIMATE_EVERY,
    END_RESERVE_S,
    PREPARATION_SHARE,
    measure_step_seconds,
    reestimate_at,
    reestimate_deform_steps,
    reestimate_steps,
    steps_for_budget,
    warm_up_runtime,
)
from .settle import SettleMonitor
from .trainer import LOSS_FACTORIES, LossFactory, Trainer, capture_path

__all__ = ["train"]


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _load_capture(capture):
    return load_capture(capture) if isinstance(capture, (str, os.PathLike)) else capture


def _config_key(cfg: TrainConfig, seed: int, rgb_only: bool, capture_path: str | None) -> dict:
    d = cfg.to_dict()
    d["schedule"].pop("checkpoint_every_s", None)  # how often a run saves does not change what it computes
    return {"config": d, "seed": int(seed), "rgb_only": bool(rgb_only), "capture": capture_path}


def train(capture, out_dir, *, preset: str = "fast", seconds: float | None = None, rgb_only: bool = False,
          resume: bool = True, device=None, seed: int = 0, progress=None, cancel=None,
          overrides: dict | None = None, loss_factories: Sequence[LossFactory] = LOSS_FACTORIES,
          on_stage=None) -> dict:
    """Train a 4D Gaussian scene on ``capture`` (path or Capture) into ``out_dir``.

    ``on_stage(text)``: told which preparation stage runs before the first step (kernels, capture,
    stereo, initial Gaussians, the budget's timing); ``progress(dict)`` then reports every step.

    Returns a summary dict (status finished | cancelled | failed, step, total_steps,
    train_seconds, num_gaussians, device, run_dir, final psnr/loss, init). See module doc.
    ``loss_factories``: the extra loss terms (default: the spike guidance,
    :data:`engine.train.loop.trainer.LOSS_FACTORIES`); ignored with ``rgb_only``.
    """
    dev = default_device(device)
    threads = torch.get_num_threads()
    if dev.type == "cpu":
        # Our tensors are small (N ~ 1e4): a second intra-op thread gains nothing when the
        # machine is idle and, with OpenMP spin-waits, costs 10x+ when the cores are shared.
        torch.set_num_threads(1)
    try:
        clock = PreparationClock(on_stage)
        clock.start("compiling kernels (first run only, about a minute; then cached)")
        warm_s = warm_up_runtime(dev)  # before the budget's clock starts
        return _train(capture, out_dir, preset=preset, seconds=seconds, rgb_only=rgb_only, resume=resume, dev=dev,
                      seed=seed, progress=progress, cancel=cancel, overrides=overrides,
                      loss_factories=loss_factories, warmup_seconds=warm_s, clock=clock)
    finally:
        torch.set_num_threads(threads)


class PreparationClock:
    """The preparation stages before the first step: each is announced as it starts (``on_stage``:
    the CLI prints it, the Blender panel shows it; minutes can pass before the first step) and its
    wall time and the process's peak memory so far are kept for run.json's ``preparation``."""

    def __init__(self, on_stage=None):
        self.on_stage = on_stage
        self.records: list[dict] = []
        self._open: tuple[str, float] | None = None

    def start(self, text: str) -> None:
        self.stop()
        self._open = (text, time.perf_counter())
        if self.on_stage is not None:
            self.on_stage(text)

    def stop(self) -> None:
        if self._open is not None:
            text, t0 = self._open
            self.records.append({"stage": text, "seconds": round(time.perf_counter() - t0, 3),
                                 "peak_rss_mb": _peak_rss_mb()})
            self._open = None


def _peak_rss_mb() -> float | None:
    try:
        import resource
    except ImportError:  # not on this platform
        return None
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(kb / (1024.0 * 1024.0) if sys.platform == "darwin" else kb / 1024.0, 1)


def _train(capture, out_dir, *, preset, seconds, rgb_only, resume, dev, seed, progress, cancel, overrides,
           loss_factories, warmup_seconds: float = 0.0, clock: PreparationClock | None = None) -> dict:
    clock = clock if clock is not None else PreparationClock()
    t_start = time.perf_counter()
    run_dir = Path(out_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    clock.start("loading the capture")
    cap = _load_capture(capture)
    cfg = get_preset(preset, overrides)
    if cfg.baseline.kind:  # two-stage baselines (paper Table 1): synthetic in-between training frames
        cap = with_baseline(cap, cfg.baseline.kind, instants=cfg.baseline.instants)
    torch.manual_seed(seed)
    np.random.seed(seed % (2 ** 32))
    cap_path = capture_path(cap)
    key = _config_key(cfg, seed, rgb_only, cap_path)
    clock.start("reading frames and stereo depth")
    trainer = Trainer(cap, cfg, device=dev, seed=seed, rgb_only=rgb_only, loss_factories=loss_factories)

    start_step = 0
    prior_seconds = 0.0
    resumed = False
    ckpt_path = run_dir / CHECKPOINT
    if resume and ckpt_path.exists():
        try:
            state = load_checkpoint(run_dir, map_location=dev)
        except RunError:
            state = None
        if state is not None and state.get("config_key") == key:
            start_step = trainer.load_state(state)
            prior_seconds = float(state.get("train_seconds", 0.0))
            resumed = True
    budget_estimates = None
    if not resumed:
        clock.start("initial Gaussians from stereo")
        trainer.init_model()
        if seconds is not None:
            clock.start("timing a few steps for the budget")
            t_s, t_d = measure_step_seconds(trainer)
            elapsed = time.perf_counter() - t_start
            trainer.total_steps = steps_for_budget(seconds, t_s, t_d, cfg, reserve_s=elapsed + 1.0)
            budget_estimates = {"probe": {"static_step_s": round(t_s, 5), "deform_step_s": round(t_d, 5),
                                          "total_steps": trainer.total_steps}, "measured": None,
                                # steps past the schedule's own settle, and end when they converge
                                "schedule_steps": int(cfg.schedule.iterations),
                                # before the first step: a share near 1 leaves nothing to train; "preparation_heavy"
                                # is the one decision the command line's and the panel's notes read
                                "preparation_s": round(elapsed, 3),
                                "preparation_share": round(elapsed / float(seconds), 3),
                                "preparation_heavy": elapsed >= PREPARATION_SHARE * float(seconds)}
    total = trainer.total_steps
    budget_end = (t_start + float(seconds)) if seconds is not None else None
    skip_notes = {}
    if trainer.early_stop is not None:
        es = trainer.early_stop
        skip_notes["early_stop_proxy"] = {"source": es.source, "frames": list(es.names),
                                          "note": "train frames held back from training; eval frames are never scored"}
    elif cfg.skip.early_stop:
        skip_notes["early_stop_proxy"] = {"source": None, "frames": [],
                                          "note": "early stopping off: no instant is seen by two train cameras, so "
                                                  "no train frame can be held back as the proxy"}

    clock.stop()
    run_info = {
        "capture": cap_path, "preset": preset, "config": cfg.to_dict(), "overrides": overrides or {},
        "seed": seed, "rgb_only": rgb_only, "device": str(dev), "status": "running", "step": start_step,
        "total_steps": total, "train_seconds": prior_seconds, "created": _now(), "time_range": list(trainer.time_range),
        "init": trainer.init_info, "seconds_budget": seconds, "resumed_from": start_step if resumed else None,
        "host": platform.node(), "warmup_seconds": round(warmup_seconds, 3),
        "preparation": clock.records, **skip_notes,
    }
    if budget_estimates is not None:
        run_info["budget_estimates"] = budget_estimates
    if resumed:
        old = {}
        try:
            old = read_run_json(run_dir)
        except RunError:
            pass
        run_info["created"] = old.get("created", run_info["created"])
    update_run_json(run_dir, **run_info)

    def snapshot(step: int, status: str, train_seconds: float) -> None:
        st = trainer.state(step)
        st.update({"config_key": key, "config": cfg.to_dict(), "train_seconds": train_seconds, "status": status,
                   "preset": preset, "seed": seed})
        save_checkpoint(run_dir, st)

    status = "finished"
    stopped_by_budget = False
    early = trainer.early_stop
    stopped_early = early.stopped_at if early is not None else None  # a resumed run that had stopped
    loop_t0 = time.perf_counter()
    last_ckpt = loop_t0
    step = start_step
    t_first = None  # after the first step of this call (the re-estimate's rate excludes it)
    reestimate_step = reestimate_at(total) if budget_estimates is not None else None
    deform_mark = None  # (step, time) where the current deformation-stage rate window starts
    next_deform_check = None
    deform_rate = None  # the latest measured seconds per deformation step
    settle, settled = None, False  # a budget run past its schedule: has it converged? (engine.train.loop.settle)
    if budget_estimates is not None:
        budget_estimates["deform"] = []
    out = {"loss": float("nan"), "psnr": float("nan")}
    try:
        while step < trainer.total_steps and stopped_early is None and not settled:
            if cancel is not None and cancel.is_set():
                status = "cancelled"
                break
            if budget_end is not None and time.perf_counter() > budget_end and step > start_step:
                stopped_by_budget = True
                break
            out = trainer.step(step)
            step += 1
            total = trainer.total_steps
            if budget_end is not None and trainer.schedule.settling(step - 1):
                settle = settle or SettleMonitor(len(trainer.items), step - 1)
                settled = settle.update(step - 1, 10.0 ** (-out["psnr"] / 10.0))
            if early is not None and early.update(trainer.run, step):
                stopped_early = early.stopped_at
            now = time.perf_counter()
            if t_first is None:
                t_first = now
            if step == reestimate_step:
                rec = reestimate_steps(trainer, step, (now - t_first) / max(1, step - 1), budget_estimates["probe"],
                                       budget_end - loop_t0 - 1.0)
                budget_estimates["measured"] = rec
                if rec["total_steps"] != total:
                    trainer.schedule.replan(step, rec["total_steps"])  # continuous: engine.train.loop.schedule
                    total = trainer.total_steps
                    if early is not None:
                        early._next = min(early._next, step + early.every(total))
                update_run_json(run_dir, budget_estimates=budget_estimates, total_steps=total)
            if budget_estimates is not None and trainer.stage_of(step - 1) == "deform":
                if deform_mark is None:  # the first deformation step is done (it sets up the field: not timed)
                    deform_mark = (step, now)
                    next_deform_check = step + max(5, int(0.5 * DEFORM_REESTIMATE_EVERY * total))
                elif step >= next_deform_check and step < total:
                    rate = deform_rate = (now - deform_mark[1]) / max(1, step - deform_mark[0])
                    rec = reestimate_deform_steps(trainer, step, rate, budget_end - now - END_RESERVE_S)
                    budget_estimates["deform"].append(rec)
                    if rec["total_steps"] != total:
                        trainer.schedule.replan(step, rec["total_steps"])
                        total = trainer.total_steps
                        if early is not None:
                            early._next = min(early._next, step + early.every(total))
                    deform_mark = (step, now)
                    next_deform_check = step + max(5, int(DEFORM_REESTIMATE_EVERY * total))
                    update_run_json(run_dir, budget_estimates=budget_estimates, total_steps=total)
                if step == total and stopped_early is None and deform_mark is not None:
                    # the plan ran out with time left (steps got cheaper after the last re-estimate):
                    # fill it at the schedule's end values (the clock keeps them, engine.train.loop.schedule)
                    if step > deform_mark[0]:
                        deform_rate = (now - deform_mark[1]) / (step - deform_mark[0])
                    left = budget_end - now - END_RESERVE_S
                    rec = None if deform_rate is None or left < 2 * deform_rate else \
                        dict(reestimate_deform_steps(trainer, step, deform_rate, left), fill=True)
                    if rec is not None and rec["total_steps"] > step:
                        budget_estimates["deform"].append(rec)
                        trainer.schedule.replan(step, rec["total_steps"])
                        total = trainer.total_steps
                        deform_mark = (step, now)
                        next_deform_check = step + max(5, int(DEFORM_REESTIMATE_EVERY * total))
                        update_run_json(run_dir, budget_estimates=budget_estimates, total_steps=total)
            if progress is not None:
                el = now - loop_t0
                rate = el / max(1, step - start_step)
                progress({"step": step, "total_steps": total, "stage": out["stage"], "loss": out["loss"],
                          "psnr": out["psnr"], "elapsed_s": prior_seconds + (now - t_start),
                          "eta_s": rate * (total - step), "num_gaussians": trainer.model.gaussians.num_gaussians})
            if now - last_ckpt >= cfg.schedule.checkpoint_every_s and step < total:
                snapshot(step, "running", prior_seconds + now - t_start)
                update_run_json(run_dir, step=step, train_seconds=prior_seconds + now - t_start)
                last_ckpt = time.perf_counter()
    except BaseException as exc:
        train_seconds = prior_seconds + time.perf_counter() - t_start
        update_run_json(run_dir, status="failed", step=step, train_seconds=train_seconds,
                        error=f"{exc.__class__.__name__}: {exc}")
        raise
    finally:  # the spike-flow term's prefetch worker: what it has not started is not needed now
        close_flow_worker(trainer.run)
    train_seconds = prior_seconds + time.perf_counter() - t_start
    quiet = trainer.run.part("quiet_curves") if status == "finished" else None
    if quiet is not None:  # the result keeps no rotation bend (engine.train.guidance.quiet_curves)
        update_run_json(run_dir, quiet_curves=quiet.finish(trainer.model))
    snapshot(step, status, train_seconds)
    skips = trainer.skip_summary()
    if settle is not None:
        update_run_json(run_dir, settle=settle.summary())
    if trainer.carry_info:  # trajectories carried by scene flow (issue 11)
        update_run_json(run_dir, trajectory_carry=trainer.carry_info)
    if getattr(trainer, "birth_info", None):  # Gaussians born at admitted instants (engine.train.motion.births)
        update_run_json(run_dir, births=trainer.birth_info)
    fits = getattr(getattr(trainer, "spike_flow", None), "fitted", None)
    if fits:  # the spike-view flow's interval fits (engine.train.guidance.spike_flow.fit_interval)
        update_run_json(run_dir, spike_flow_fits=[fits[k] for k in sorted(fits) if fits[k]])
    ended_by = _ended_by(status, stopped_early or settled, seconds)
    budget_used = None if seconds is None else round(train_seconds / max(float(seconds), 1e-9), 3)
    summary = {
        "status": status, "ended_by": ended_by, "budget_used": budget_used,
        "step": step, "total_steps": total, "train_seconds": round(train_seconds, 3),
        "num_gaussians": trainer.model.gaussians.num_gaussians, "device": str(dev), "run_dir": str(run_dir.resolve()),
        "preset": preset, "loss": out.get("loss"), "psnr": out.get("psnr"), "init": trainer.init_info,
        "stopped_by_budget": stopped_by_budget, "resumed_from": start_step if resumed else None,
        "stopped_early": stopped_early, "skips": skips, "settle": None if settle is None else settle.summary(),
    }
    if budget_estimates is not None:
        budget_estimates["schedule"] = trainer.schedule.state_dict()  # the clock's segments, one per re-plan
        summary["budget_estimates"] = budget_estimates
        update_run_json(run_dir, budget_estimates=budget_estimates)
    update_run_json(run_dir, status=status, ended_by=ended_by, budget_used=budget_used, step=step, total_steps=total,
                    train_seconds=train_seconds,
                    num_gaussians=summary["num_gaussians"], stopped_by_budget=stopped_by_budget,
                    stopped_early=stopped_early, skips=skips, finished=_now())
    return summary


def _ended_by(status: str, converged, seconds) -> str:
    """Why the run ended (run.json ``ended_by``): cancelled | converged (a budget run that settled after
    its schedule and stopped gaining, run.json ``settle``; or the held-back train frames stopped
    improving, ``skip.early_stop``) | steps (a run of its steps, no budget) | budget (it used its time)."""
    if status == "cancelled":
        return "cancelled"
    if converged:
        return "converged"
    return "steps" if seconds is None else "budget"
