"""The wall-clock budget: how many steps fit in ``seconds``.

The step count is chosen up front from the measured cost of a few throw-away steps on a
copy of the model (:func:`measure_step_seconds`, :func:`steps_for_budget`), then
re-estimated once from the rate of the real steps after ~5% of the run
(:func:`reestimate_at`, :func:`reestimate_steps`), while the run is still in the static
stage so that every schedule (a fraction of the total) stays consistent.
"""
from __future__ import annotations

import copy
import math
import time

import numpy as np

from .presets import TrainConfig

__all__ = ["REESTIMATE_FRACTION", "measure_step_seconds", "reestimate_at", "reestimate_steps", "steps_for_budget"]


def measure_step_seconds(trainer, n_static: int = 4, n_deform: int = 4) -> tuple[float, float]:
    """Median seconds per step in each stage, from throw-away steps on a copy of the model."""
    probe = copy.copy(trainer)
    probe.model = copy.deepcopy(trainer.model)
    vars(probe.model.gaussians).pop("_replace", None)  # the freezer's watch belongs to the real model
    probe.model.gaussians.setup_optimizer(trainer.cfg, trainer.extent)
    probe.deform_opt = None
    probe.freeze = probe.early_stop = probe.cull = None
    probe.total_steps = 10 ** 6
    times = {}
    for stage, n in (("static", n_static), ("deform", n_deform)):
        probe.cfg = copy.copy(trainer.cfg)
        probe.cfg.static_fraction = 1.0 if stage == "static" else 0.0
        # the whole capture time admitted: a step at the curriculum's start would skip the
        # spike branch's in-between render (engine.train.instants), and under-price every later step
        probe.cfg.time_curriculum = 0.0
        probe.cfg.densify_from = probe.cfg.densify_until = 2.0  # no densification in the probe
        times[stage] = []
        for i in range(n):
            t0 = time.perf_counter()
            probe.step(i)
            times[stage].append(time.perf_counter() - t0)
    med = lambda v: float(np.median(v[1:] if len(v) > 1 else v))  # noqa: E731 (first call warms up)
    return med(times["static"]), med(times["deform"])


def steps_for_budget(seconds: float, t_static: float, t_deform: float, cfg: TrainConfig,
                     growth: float = 1.5, reserve_s: float = 0.0) -> int:
    """Steps that fit in ``seconds`` given per-step costs (Gaussian growth factored in)."""
    per = (cfg.static_fraction * t_static + (1 - cfg.static_fraction) * t_deform) * growth
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
    the static stage (the schedules are fractions of the total): the new total is clamped so
    that the next step stays static. Returns the record for run.json (``total_steps`` is the
    new total, or the old one with ``skipped``)."""
    cfg = trainer.cfg
    old = trainer.total_steps
    scale = step_seconds / max(probe["static_step_s"], 1e-9)
    rec = {"at_step": int(done), "static_step_s": round(step_seconds, 5),
           "deform_step_s": round(probe["deform_step_s"] * scale, 5), "total_steps": old}
    if cfg.static_fraction <= 0 or done >= trainer.static_steps:
        rec["skipped"] = "the deformation stage has started (its schedule is a fraction of the total)"
        return rec
    new = steps_for_budget(loop_seconds, step_seconds, probe["deform_step_s"] * scale, cfg)
    new = max(new, done + 1)
    while int(round(cfg.static_fraction * new)) <= done:  # keep the next step in the static stage
        new += 1
        rec["clamped"] = True
    rec["total_steps"] = int(new)
    return rec
