"""The wall-clock budget: how many steps fit in ``seconds``.

The step count is chosen up front from the measured cost of a few throw-away steps on a
copy of the model (:func:`measure_step_seconds`, :func:`steps_for_budget`), then
re-estimated from the rate of the real steps after ~5% of the run
(:func:`reestimate_at`, :func:`reestimate_steps`), while the run is still in the static
stage, and again every 10% of the deformation stage from that stage's own rate
(:func:`reestimate_deform_steps`). The run applies a new total with
:meth:`engine.train.loop.schedule.Schedule.replan`: every schedule keeps its current progress and
spreads the rest over the new remaining steps, so a re-plan never moves a stage boundary
back or makes a schedule jump. Steps past the schedule's own length settle, and a settling run
ends when it has converged (engine.train.loop.settle): no step cap.
Kernel compilation and first imports run before the budget's clock starts
(:func:`warm_up_runtime`).
"""
from __future__ import annotations

import copy
import math
import time

import numpy as np
import torch

from ...raster import warmup as raster_warmup
from ...scene.fused_adam import warmup as adam_warmup
from ...scene.hexplane_fused import warmup as hexplane_warmup
from ...scene.lazy_adam import warmup as lazy_warmup
from ...scene.selective_adam import warmup as selective_warmup
from ...scene.trajectory import warmup as trajectory_warmup
from ..config import TrainConfig
from ..frames.interpolation import warmup as flow_warmup
from ..guidance.quiet_curves import warmup as quiet_warmup
from ..losses.fused_ssim import warmup as ssim_warmup
from ..motion.nearest import warmup as nearest_warmup

__all__ = ["DEFORM_REESTIMATE_EVERY", "END_RESERVE_S", "REESTIMATE_FRACTION", "measure_step_seconds", "reestimate_at",
           "reestimate_deform_steps", "reestimate_steps", "steps_for_budget", "warm_up_runtime"]


def measure_step_seconds(trainer, n_static: int = 4, n_deform: int = 4) -> tuple[float, float]:
    """Median seconds per step in each stage, from throw-away steps on a copy of the model."""
    probe = trainer.probe_copy()
    probe.model = copy.deepcopy(trainer.model)
    vars(probe.model.gaussians).pop("_replace", None)  # the freezer's watch belongs to the real model
    probe.model.gaussians.setup_optimizer(trainer.cfg.gaussians, trainer.extent)
    probe.deform_opt = None
    probe.freeze = probe.early_stop = probe.cull = None
    probe.total_steps = 10 ** 6
    # The probe shares the trainer's loss terms (a shallow copy). The spike-view flow term
    # fits each interval's curves once and remembers it: a probe step that fitted would take
    # that fit from the real run (its curves never fitted: between, 120 s, cube 31.5 mm in the
    # image plane against 11.7 at 1000 plain steps) and price every step at a fit's ~1 s (the
    # run planned 186 steps for 120 s, then re-planned its schedule upward ten times). So the
    # probe runs with every interval marked fitted, and the real marks come back afterwards.
    flow = getattr(trainer, "spike_flow", None)
    fitted = dict(flow.fitted) if flow is not None else None
    if flow is not None:
        flow.fitted.update({k: {"probe": True} for k in range(max(0, len(flow.times) - 1)) if k not in fitted})
    try:
        times = _probe_times(probe, trainer, n_static, n_deform)
    finally:
        if flow is not None:
            flow.fitted.clear()
            flow.fitted.update(fitted)
    med = lambda v: float(np.median(v[1:] if len(v) > 1 else v))  # noqa: E731 (first call warms up)
    return med(times["static"]), med(times["deform"])


def _probe_times(probe, trainer, n_static: int, n_deform: int) -> dict:
    times = {}
    for stage, n in (("static", n_static), ("deform", n_deform)):
        probe.cfg = copy.deepcopy(trainer.cfg)  # its groups too: the probe must not change the run's settings
        probe.cfg.schedule.static_fraction = 1.0 if stage == "static" else 0.0
        # the whole capture time admitted: a step at the curriculum's start would skip the
        # spike branch's in-between render (engine.train.guidance.instants), and under-price every later step
        probe.cfg.schedule.time_curriculum = 0.0
        probe.cfg.densify.start = probe.cfg.densify.stop = 2.0  # no densification in the probe
        times[stage] = []
        for i in range(n):
            t0 = time.perf_counter()
            probe.step(i)
            times[stage].append(time.perf_counter() - t0)
    return times


def steps_for_budget(seconds: float, t_static: float, t_deform: float, cfg: TrainConfig,
                     growth: float = 1.5, reserve_s: float = 0.0) -> int:
    """Steps that fit in ``seconds`` given per-step costs (Gaussian growth factored in)."""
    per = (cfg.schedule.static_fraction * t_static + (1 - cfg.schedule.static_fraction) * t_deform) * growth
    return max(20, int((max(0.0, seconds - reserve_s)) / max(per, 1e-4)))


REESTIMATE_FRACTION = 0.05  # re-estimate the budget's step count after this share of the probe's estimate


def reestimate_at(total_steps: int) -> int:
    """Completed steps after which a budget run re-estimates its step count (>= 6, so that
    the rate excludes the first step and still averages a few)."""
    return max(6, int(math.ceil(REESTIMATE_FRACTION * total_steps)))


def reestimate_steps(trainer, done: int, step_seconds: float, probe: dict, loop_seconds: float) -> dict:
    """The budget's step count from the measured seconds per (static) step of the real run.

    ``probe``: the up-front estimate (``static_step_s``, ``deform_step_s``); the deformation
    steps are scaled by the same factor as the static ones. Only while the run is still in
    the static stage (the deformation stage re-plans from its own rate). Returns the record
    for run.json (``total_steps`` is the new total, or the old one with ``skipped``)."""
    cfg = trainer.cfg
    old = trainer.total_steps
    scale = step_seconds / max(probe["static_step_s"], 1e-9)
    rec = {"at_step": int(done), "static_step_s": round(step_seconds, 5),
           "deform_step_s": round(probe["deform_step_s"] * scale, 5), "total_steps": old}
    if cfg.schedule.static_fraction <= 0 or done >= trainer.static_steps:
        rec["skipped"] = "the deformation stage has started (it re-plans from its own rate)"
        return rec
    new = steps_for_budget(loop_seconds, step_seconds, probe["deform_step_s"] * scale, cfg)
    rec["total_steps"] = int(max(new, done + 1))
    return rec


DEFORM_REESTIMATE_EVERY = 0.1  # in the deformation stage: re-estimate after every this share of the total
PREPARATION_SHARE = 0.5  # of a budget spent before the first step: the run says it trained little
END_RESERVE_S = 0.15  # the final checkpoint and run.json after the last step (~0.1 s on the demo)


def reestimate_deform_steps(trainer, done: int, step_seconds: float, remaining_s: float) -> dict:
    """In the deformation stage: the total that ends the run at its budget, from the
    measured seconds per step of the latest deformation steps.

    One up-front estimate cannot know how the step cost grows with densification and the
    curriculum (the probe's fixed 1.5x growth made runs end 17% early, issue 13), so the
    deformation stage re-plans from its own recent rate every ``DEFORM_REESTIMATE_EVERY``
    of the run; a rising cost is caught by the next re-estimate, and the budget's hard stop
    bounds the last one. The new total lets at least the next step run (the schedule's
    virtual clock keeps the stage, engine.train.loop.schedule). Returns the record for run.json."""
    new = done + max(1, int(max(0.0, remaining_s) / max(step_seconds, 1e-6)))
    return {"at_step": int(done), "deform_step_s": round(step_seconds, 5), "remaining_s": round(remaining_s, 3),
            "total_steps": int(new), "previous_total_steps": int(trainer.total_steps)}


def warm_up_runtime(device) -> float:
    """Compile (first run on a machine: ~30 s) or load from cache (~0.5 s) the numba kernels
    that training calls (the rasterizer's, the fused HexPlane sampler's, FusedAdam's, the
    neighbour search's), and import what torch imports on its first optimizer (torch._dynamo:
    2-5 s), so that none of it is charged to a ``--seconds`` budget (issue 13: a 60 s first
    Reconstruct in Blender got 20 steps). Returns the seconds taken (run.json
    ``warmup_seconds``). (The PNG row decoder's kernel is not warmed: its numba cache is
    keyed by file, not import name, so inside Blender a cache written by ``python -m
    engine`` cannot be loaded (the same ModuleNotFoundError the rasterizer's per-import-name
    cache locator avoids): it stays lazy, as before.)"""
    t0 = time.perf_counter()
    # Host-side kernels that run on any device: the admissions' optical flow and neighbour
    # search work on host copies. On a GPU box their first compile (~9 s on an H100 machine's
    # CPU) was charged to the first admissions: RGB admission 56.7 ms/step cold, 11.9 warm.
    nearest_warmup()  # the trajectories' hidden-Gaussian neighbour search (engine.train.motion.nearest)
    flow_warmup()  # the admissions' Lucas-Kanade flow kernels (engine.train.frames.interpolation)
    if torch.device(device).type == "cpu":
        raster_warmup("cpu")
        hexplane_warmup()  # the fused HexPlane sampler's kernels (engine.scene.hexplane_fused)
        adam_warmup()  # the Gaussians' optimizer's kernels and its exactness check (engine.scene.fused_adam)
        trajectory_warmup()  # the trajectories' residual-square term (engine.scene.trajectory)
        selective_warmup()  # gaussian_adam=selective's kernels (engine.scene.selective_adam)
        lazy_warmup()  # gaussian_adam=lazy / auto's kernels (engine.scene.lazy_adam)
        ssim_warmup()  # the D-SSIM term's kernels (engine.train.losses.fused_ssim)
        quiet_warmup()  # the quiet curves' in-place zeroing (engine.train.guidance.quiet_curves)
    torch.optim.Adam([torch.zeros(1, requires_grad=True)], lr=1e-3)  # imports torch._dynamo once
    return time.perf_counter() - t0
