"""Numerical-stability stress suite: ``python -m tools stress``.

Each *optimisation case* runs Adam on raw parameters -- means, log-scales, quaternions
(raw, normalised inside the renderer), opacity logits, colours -- through the fast CPU
rasterizer (``backend="cpu"``) against a target image, and checks after **every** step that
the loss, every gradient and every parameter is finite. No step is ever skipped: a NaN, once
produced, propagates and is counted, exactly as it would in training.

Optimisation cases (a tiny scene: ``N`` Gaussians, a 24x24 image, one camera):

* ``scale_tiny`` / ``scale_huge`` / ``scale_range``: linear scales 1e-6, 1e3 and log-uniform
  in [1e-6, 1e3];
* ``opacity_zero`` (logits -30: everything below 1/255, culled), ``opacity_threshold``
  (opacities just around 1/255) and ``opacity_saturated`` (logits +30: sigmoid == 1 in
  float32, alpha clamped at ``alpha_max``);
* ``near_plane``: Gaussians behind the camera, exactly at / just around the near plane and
  straddling z = 0;
* ``degenerate_cov``: one axis 1e-8 (needle / flat discs seen edge-on), plus quaternions of
  norm 1e-12;
* ``extent_tiny`` / ``extent_huge``: the whole scene (and camera, near plane, learning rate)
  scaled by 1e-3 and 1e4;
* ``long_time``: a HexPlane deformation field (``engine.scene.deformation``) over a 1e4 s time
  range, queried at t in [0, 1e4] and beyond (normalised time must stay finite);
* ``empty_view``: every Gaussian outside the view (all culled): zero gradients, no NaN.

Check cases (no optimiser, fixed work):

* ``spikes_extreme``: all-zero and all-one spike streams through ``spike_sim`` (simulate,
  ``tfp``, ``tfi``), ``spikes.write_spikes/read_spikes`` and ``spike_render`` (expected
  counts, m-step integrate-and-fire with surrogate gradients, both losses, sensor fit);
* ``fp32_vs_fp64``: the float64 dense reference path against the float32 fast path on
  random scenes: image / alpha / depth difference and gradient relative error;
* ``bad_inputs``: NaN / inf in poses, intrinsics, times and image pixels of a capture must
  raise :class:`engine.errors.CaptureError` naming the file; a non-finite value that gets
  through is counted;
* ``trainer``: the real ``engine.train.train`` (both stages, densification) for up to 150
  steps on a tiny synthetic capture at scene scale 1 and 40 steps at 1e-3, every parameter
  and gradient of the Gaussians and the deformation field checked after each step.

``run_suite`` returns one :class:`CaseResult` per case; ``format_table`` prints them, and
the last line of ``python -m tools stress`` is ``non-finite values: <count>``.

Command line: runs every case (or those named with ``--cases``) for ``--steps`` optimisation steps each
(default 10,000; ``--quick``: 200 steps, a few minutes on a laptop CPU), shows a tqdm
progress bar, prints one table row per case (steps, non-finite parameters / gradients /
other values, max |grad|, final loss) with details, and ends with the line
``non-finite values: <count>``. Exit status 1 when a value was non-finite or a check failed.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from typing import Callable

from tqdm import tqdm

from .stress_cases import (
    CaseResult,
    case_degenerate_cov,
    case_empty_view,
    case_extent_huge,
    case_extent_tiny,
    case_long_time,
    case_near_plane,
    case_opacity_saturated,
    case_opacity_threshold,
    case_opacity_zero,
    case_scale_huge,
    case_scale_range,
    case_scale_tiny,
)
from .stress_checks import case_bad_inputs, case_fp32_vs_fp64, case_spikes_extreme, case_trainer

CASES: dict[str, Callable] = {
    "scale_tiny": case_scale_tiny,
    "scale_huge": case_scale_huge,
    "scale_range": case_scale_range,
    "opacity_zero": case_opacity_zero,
    "opacity_threshold": case_opacity_threshold,
    "opacity_saturated": case_opacity_saturated,
    "near_plane": case_near_plane,
    "degenerate_cov": case_degenerate_cov,
    "extent_tiny": case_extent_tiny,
    "extent_huge": case_extent_huge,
    "empty_view": case_empty_view,
    "long_time": case_long_time,
    "spikes_extreme": case_spikes_extreme,
    "fp32_vs_fp64": case_fp32_vs_fp64,
    "bad_inputs": case_bad_inputs,
    "trainer": case_trainer,
}


CASE_HELP = {
    "scale_tiny": "linear scales 1e-6",
    "scale_huge": "linear scales 1e3",
    "scale_range": "scales log-uniform in [1e-6, 1e3]",
    "opacity_zero": "opacity logits -30 (all below 1/255)",
    "opacity_threshold": "opacities around 1/255",
    "opacity_saturated": "opacity logits +30 (sigmoid == 1 in float32)",
    "near_plane": "Gaussians behind, at and around the near plane",
    "degenerate_cov": "one (or two) axes 1e-8, edge-on, quaternion norms 1e-12",
    "extent_tiny": "scene + camera scaled by 1e-3",
    "extent_huge": "scene + camera scaled by 1e4",
    "empty_view": "every Gaussian outside the view",
    "long_time": "deformation field over 1e4 s, queried up to 1e6 s",
    "spikes_extreme": "all-zero / all-one spike streams: sim, tfp/tfi, IO, spike renderer, sensor fit",
    "fp32_vs_fp64": "float32 fast path vs float64 dense reference",
    "bad_inputs": "NaN / inf in poses, intrinsics, times, image pixels -> CaptureError",
    "trainer": "the real trainer on a tiny synthetic capture at scale 1 and 1e-3",
}


def run_case(name: str, steps: int, tick=None, seed: int = 0) -> CaseResult:
    if name not in CASES:
        raise KeyError(f"unknown stress case {name!r}; cases: {', '.join(CASES)}")
    t0 = time.perf_counter()
    try:
        res = CASES[name](int(steps), tick, seed)
    except Exception as exc:  # a crash is a failure of the case, reported, not hidden
        res = CaseResult(name)
        res.failures.append(f"raised {type(exc).__name__}: {exc}")
    res.seconds = time.perf_counter() - t0
    return res


def run_suite(steps: int = 10_000, cases=None, *, seed: int = 0, progress: bool = True) -> list[CaseResult]:
    names = list(CASES) if not cases else list(cases)
    bar = None
    tick = None
    if progress:
        bar = tqdm(total=steps * len(names), unit="step", desc="stress", dynamic_ncols=True)
        tick = bar.update
    out = []
    try:
        for name in names:
            if bar is not None:
                bar.set_postfix_str(name)
            before = bar.n if bar is not None else 0
            res = run_case(name, steps, tick, seed)
            if bar is not None and bar.n < before + steps:  # cases that stop early
                bar.update(before + steps - bar.n)
            out.append(res)
    finally:
        if bar is not None:
            bar.close()
    return out


def total_nonfinite(results: list[CaseResult]) -> int:
    return int(sum(r.nonfinite for r in results))


def format_table(results: list[CaseResult]) -> str:
    head = f"{'case':<18}{'steps':>7}{'nf params':>10}{'nf grads':>10}{'nf other':>10}{'max |grad|':>12}" \
           f"{'final loss':>12}{'sec':>8}  status"
    lines = [head, "-" * len(head)]
    for r in results:
        fl = "-" if not math.isfinite(r.final_loss) and r.nonfinite == 0 else f"{r.final_loss:.4g}"
        status = "ok" if r.ok else "FAIL"
        lines.append(f"{r.name:<18}{r.steps:>7}{r.nonfinite_params:>10}{r.nonfinite_grads:>10}{r.nonfinite_other:>10}"
                     f"{r.max_grad:>12.3g}{fl:>12}{r.seconds:>8.1f}  {status}")
    details = []
    for r in results:
        for f in r.failures:
            details.append(f"  {r.name}: FAIL {f}")
        if r.first_bad_step is not None:
            details.append(f"  {r.name}: first non-finite value at step {r.first_bad_step}")
        for n in r.notes:
            details.append(f"  {r.name}: {n}")
    return "\n".join(lines + (["", "details:"] + details if details else []))


HELP = "numerical-stability stress suite: extreme scales, opacities, depths, extents, times, spikes, bad inputs"

QUICK_STEPS = 200


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--steps", type=int, default=None,
                        help="optimisation steps per case (default 10000, or 200 with --quick)")
    parser.add_argument("--quick", action="store_true", help=f"a few-minute version ({QUICK_STEPS} steps per case)")
    parser.add_argument("--cases", default=None, help="comma-separated case names (default: all)")
    parser.add_argument("--list", action="store_true", help="list the cases and exit")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=None, help="also write the results to this JSON file")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def main(args) -> int:
    if args.list:
        for name in CASES:
            print(f"{name:<18} {CASE_HELP.get(name, '')}")
        return 0
    steps = args.steps if args.steps is not None else (QUICK_STEPS if args.quick else 10_000)
    if steps < 1:
        print("error: --steps must be at least 1")
        return 2
    cases = [c.strip() for c in args.cases.split(",") if c.strip()] if args.cases else None
    if cases:
        unknown = [c for c in cases if c not in CASES]
        if unknown:
            print(f"error: unknown case(s) {', '.join(unknown)}; cases: {', '.join(CASES)}")
            return 2
    results = run_suite(steps, cases, seed=args.seed, progress=not args.no_progress)
    print(format_table(results))
    total = total_nonfinite(results)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"steps": steps, "cases": [r.to_dict() for r in results], "nonfinite": total}, fh, indent=2)
    print(f"non-finite values: {total}")
    return 0 if total == 0 and all(r.ok for r in results) else 1
