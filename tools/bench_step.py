"""``python -m tools bench-step``: where a training step goes, per stage (issue 13).

Trains a short real schedule (``--steps``, the preset's own fractions: static stage,
densification, curriculum) twice on a capture -- RGB only, then with the spike branch --
and charges each step's *exclusive* wall time to its parts (:class:`StepProfiler`):

* ``raster_fwd``: ``engine.raster.rasterization`` as ``Model4D.render`` calls it (projection,
  SH, binning, compositing);
* ``raster_bwd``: the numba autograd functions' backward (compositing, projection, SH);
* ``field_fwd``: the motion model's forward: the per-Gaussian trajectories' curve evaluations
  (``trajectory._CurveAt``, the spike-view flow term's row subset ``spike_flow._InnerAt``) and
  ``DeformationField.forward`` (HexPlane sampling + decoder), fine branch excluded;
* ``fine_fwd``: the spike branch's fine encoder / fine deformation forward;
* ``field_bwd``: the curve evaluations' backward, and from the gradient reaching the HexPlane
  field's outputs until every field parameter has its gradient (autograd hooks; the fine
  branch's backward runs inside it);
* ``losses``: the loss terms' forward (``LossTerm.fn``; the spike branch's targets included);
* ``optimizer``: every ``Adam.step``;
* ``densify``: densification statistics, densify-and-prune, opacity reset;
* ``admit``: the time curriculum admitting the next RGB instant (``Trainer._carry_forward``:
  with trajectories, optical flow + stereo carry and the hidden Gaussians' neighbour search);
* ``other``: the rest of the step (the losses' and glue's backward, Python).

Stages: ``static`` (RGB run), ``rgb_deform`` and ``guided_deform`` (the deformation stage
of each run); the first step of each stage (set-up) is not timed. Prints a markdown table
of per-step ms and shares and the issue's two ratios: RGB deformation step / rasterizer
forward+backward, guided step / RGB step, on two clocks: wall time, and the process's CPU
time over all its threads (steadier on a shared machine; the load average is printed).

``--variants reference,current`` profiles the code paths of :data:`VARIANTS` in one
process, runs interleaved (RGB runs of each, then guided runs), and prints each one's
tables and the step speed-ups: before / after a change under the same load. ``--rounds N``
repeats the RGB and guided runs N times, alternating, and prints each round's ratios and their
median (:func:`round_ratios`): one pair's ratio moves with the machine between processes.
"""
from __future__ import annotations

import os
import sys
import time
from contextlib import contextmanager

import numpy as np
import torch

from engine.cli.train import parse_overrides
from engine.io.capture import load_capture
from engine.raster import cpu as raster_cpu
from engine.scene import fine_deformation as fd
from engine.scene import fused_adam, grad_buffers, lazy_adam, row_store, selective_adam, trajectory
from engine.scene import gaussians as scene_gaussians
from engine.scene import model as scene_model
from engine.scene.deformation import DeformationField, HexPlane
from engine.scene.gaussians import GaussianModel
from engine.train.config import get_preset
from engine.train.frames import interpolation
from engine.train.guidance import quiet_curves, spike_flow, spike_flow_cache, spike_flow_pairs, spike_guidance
from engine.train.loop.budget import warm_up_runtime
from engine.train.loop.trainer import Trainer
from engine.train.losses import fused_ssim
from engine.train.losses import terms as losses
from engine.train.motion import scene_flow

HELP = "profile a training step per stage: rasterizer, deformation field, fine branch, losses, optimizer"

CATEGORIES = ("raster_fwd", "raster_bwd", "field_fwd", "fine_fwd", "field_bwd", "losses", "optimizer",
              "densify", "admit", "other")


CLOCKS = ("wall", "cpu")


_SYNC_CUDA = False  # --device cuda: wait for the GPU at every timer edge, so that a stage is
# charged its kernels rather than their launches (costs a little speed; the step total is exact)


def _now() -> np.ndarray:
    """(wall seconds, this process's CPU seconds over all its threads)."""
    if _SYNC_CUDA:
        torch.cuda.synchronize()
    return np.array((time.perf_counter(), time.process_time()))


def _gsplat_functions() -> list:
    """gsplat's autograd functions (CUDA runs): their backward is ``raster_bwd``."""
    wrapper = sys.modules.get("gsplat.cuda._wrapper")  # loaded by the backend, never imported here
    if wrapper is None:
        return []
    return [c for c in vars(wrapper).values()
            if isinstance(c, type) and issubclass(c, torch.autograd.Function) and "backward" in vars(c)]


class StepProfiler:
    """Exclusive per-part times of each step on two clocks: wall time and the process's
    CPU time (all threads: the rasterizer's and the HexPlane sampler's numba kernels run
    on 2 threads, torch on 1). On a machine shared with other jobs the CPU times are the
    steadier ones; each table says which clock it shows."""

    def __init__(self):
        self.by_label: dict[str, dict] = {}
        self.totals = {c: np.zeros(2) for c in CATEGORIES}  # the accumulator in use (scratch outside run_step)
        self._bwd_charged = np.zeros(2)
        self._in_window = np.zeros(2)
        self._stack: list[list] = []  # [category, start, child seconds]
        self._patches: list[tuple] = []
        self._field_bwd_start = None
        self.fine_stats: dict | None = None  # EncodedWindows counters of the guided run
        self.rounds: list = []  # merged(): the per-round profilers this one sums

    def _acc(self, label):
        if label not in self.by_label:
            self.by_label[label] = {"totals": {c: np.zeros(2) for c in CATEGORIES}, "steps": 0,
                                    "seconds": np.zeros(2)}
        return self.by_label[label]

    # ---- exclusive timers ---------------------------------------------------------------
    def _enter(self, cat):
        self._stack.append([cat, _now(), np.zeros(2)])

    def _exit(self):
        cat, t0, child = self._stack.pop()
        dt = _now() - t0
        self.totals[cat] += dt - child
        if self._field_bwd_start is not None:  # charged already: not the field's backward
            self._in_window += dt - child
        if self._stack:
            self._stack[-1][2] += dt
        return dt

    def _wrap(self, owner, name, cat, static=False):
        orig = owner.__dict__[name] if name in owner.__dict__ else getattr(owner, name)
        fn = orig.__func__ if isinstance(orig, staticmethod) else orig
        prof = self

        def timed(*a, **k):
            prof._enter(cat)
            try:
                return fn(*a, **k)
            finally:
                prof._exit()

        timed.__wrapped__ = fn
        setattr(owner, name, staticmethod(timed) if (static or isinstance(orig, staticmethod)) else timed)
        self._patches.append((owner, name, orig))

    # ---- field backward window by autograd hooks -----------------------------------------
    def _hook_field(self, field, outputs):
        params = [p for p in field.parameters() if p.requires_grad]
        tensors = [o for o in _flatten(outputs) if isinstance(o, torch.Tensor) and o.requires_grad]
        if not params or not tensors:
            return
        prof = self

        def started(_g):
            if prof._field_bwd_start is None:
                prof._field_bwd_start = _now()
                prof._in_window = np.zeros(2)

        def done(_grads):
            if prof._field_bwd_start is not None:
                # less what ran meanwhile and is charged elsewhere (the spike branch's second
                # render's rasterizer backward runs inside this window)
                dt = _now() - prof._field_bwd_start - prof._in_window
                prof.totals["field_bwd"] += dt
                prof._bwd_charged += dt
                prof._field_bwd_start = None

        for t in tensors:
            t.register_hook(started)
        torch.autograd.graph.register_multi_grad_hook(params, done, mode="all")

    def __enter__(self):

        self._wrap(scene_model, "rasterization", "raster_fwd")  # Model4D.render's name for it
        for cls in (raster_cpu._RasterizeFused, raster_cpu._RasterizeToPixels, raster_cpu._Project,
                    raster_cpu._ShCombine, *_gsplat_functions()):
            self._wrap(cls, "backward", "raster_bwd", static=True)
        for cls in (fd.FineDeformation, fd.SpikeTextureEncoder, fd.SpikeFineEncoder):
            self._wrap(cls, "forward", "fine_fwd")
        for name in ("add_densification_stats", "densify_and_prune", "reset_opacity"):
            self._wrap(GaussianModel, name, "densify")
        self._wrap(Trainer, "_carry_forward", "admit")
        for cls in (torch.optim.Adam, fused_adam.FusedAdam, selective_adam.SelectiveAdam, lazy_adam.LazyCurveAdam):
            self._wrap(cls, "step", "optimizer")
        # the trajectories are the default motion model: without these the field rows read 0
        # and the curves' ~2.5 ms of an RGB step sat in "other" (and "losses")
        for cls in (trajectory._CurveAt, spike_flow._InnerAt):
            self._wrap(cls, "forward", "field_fwd", static=True)
            self._wrap(cls, "backward", "field_bwd", static=True)

        orig_forward = DeformationField.forward
        prof = self

        def field_forward(module, *a, **k):
            prof._enter("field_fwd")
            try:
                out = orig_forward(module, *a, **k)
            finally:
                prof._exit()
            if torch.is_grad_enabled():
                prof._hook_field(module, out)
            return out

        DeformationField.forward = field_forward
        self._patches.append((DeformationField, "forward", orig_forward))
        return self

    def __exit__(self, *exc):
        for owner, name, orig in reversed(self._patches):
            setattr(owner, name, orig)
        self._patches.clear()
        return False

    # ---- one step ---------------------------------------------------------------------------
    def run_step(self, trainer, step: int, label: str) -> dict:
        """One timed ``trainer.step(step)``, charged to ``label`` (e.g. the stage); its loss
        terms are timed as ``losses``."""
        acc = self._acc(label)
        self.totals = acc["totals"]
        for term in trainer.loss_terms:
            if not getattr(term.fn, "_bt4d_timed", False):
                fn = term.fn
                prof = self

                def timed(ctx, _fn=fn):
                    prof._enter("losses")
                    try:
                        return _fn(ctx)
                    finally:
                        prof._exit()

                timed._bt4d_timed = True
                term.fn = timed
        self._bwd_charged = np.zeros(2)
        self._field_bwd_start = None
        self._enter("other")
        out = trainer.step(step)
        dt = self._exit()
        # the field's backward ran inside "other" (autograd, not a patched call): move it
        self.totals["other"] -= self._bwd_charged
        acc["steps"] += 1
        acc["seconds"] += dt
        self.totals = {c: np.zeros(2) for c in CATEGORIES}  # untimed steps charge nothing
        return out

    def table(self, label: str, clock: str = "wall") -> dict:
        """Per-step milliseconds of each category and their shares of the step, on
        ``clock`` (wall | cpu)."""
        acc = self._acc(label)
        n = max(1, acc["steps"])
        k = CLOCKS.index(clock)
        ms = {c: 1e3 * float(v[k]) / n for c, v in acc["totals"].items()}
        step_ms = 1e3 * float(acc["seconds"][k]) / n
        return {"steps": acc["steps"], "step_ms": step_ms, "ms": ms,
                "share": {c: (v / step_ms if step_ms else 0.0) for c, v in ms.items()}}


def _flatten(x):
    if isinstance(x, dict):
        for v in x.values():
            yield from _flatten(v)
    elif isinstance(x, (list, tuple)):
        for v in x:
            yield from _flatten(v)
    else:
        yield x


def add_arguments(parser) -> None:
    parser.add_argument("capture", help="capture folder")
    parser.add_argument("--steps", type=int, default=60, help="schedule length of each profiled run (default 60)")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    parser.add_argument("--rounds", type=int, default=1,
                        help="repeat the RGB and guided runs this many times, alternating, and print each round's "
                             "ratios and their median (tables: every round's steps)")
    parser.add_argument("--variants", default="current",
                        help="comma-separated code paths profiled in this one process, runs interleaved: "
                             + ", ".join(f"{k} ({v['doc']})" for k, v in VARIANTS.items()) + " (default current)")
    parser.add_argument("--device", default="cpu",
                        help="cpu (default) or cuda: on a GPU the rasterizer is gsplat and every stage "
                             "edge waits for the GPU")


# Issue 13's speed-ups that bench-step can switch off, to measure before / after in one
# process (a shared machine's load changes between processes).
# A variant may also patch the run's TrainConfig (``overrides``): switches that change what
# is trained are measured here for speed only (their quality: docs/experiments/spike-guidance.md), and
# name module attributes to swap for the block (``patches``: {(module, name): value}).
def _norm_flow_length(f):
    return f.norm(dim=1, keepdim=True)


def _inner_only_positions_gather(model, t, idx):
    """spike_flow.inner_only_positions as before its column backward (gather + mask + evaluate)."""
    params = getattr(model.gaussians, scene_model.TRAJ_MEANS)[idx]
    inner = torch.ones(params.shape[1], dtype=torch.bool, device=params.device)
    inner[0::3] = False
    params = torch.where(inner[None, :, None], params, params.detach())
    return model.gaussians.means.detach()[idx] + trajectory.evaluate(params, model.trajectory["knots"], t)


_BEFORE_GUIDED = {  # the spike branch as before EncodedWindows and the cached occlusion maps
    (interpolation, "_flow_length"): _norm_flow_length,
    (spike_guidance, "flow_consistency"): lambda *flows: None,  # None: flow_interpolate recomputes them
}

VARIANTS = {
    "current": {"doc": "the engine as it is", "hexplane_sampler": "auto"},
    "reference": {"doc": "HexPlane sampled by grid_sample, as before the fused sampler",
                  "hexplane_sampler": "torch"},
    "guided-before": {"doc": "the spike branch before issue 13's guided-step work: every render encodes its "
                             "spike window, block-colour targets recompute their occlusion maps",
                      "hexplane_sampler": "auto",
                      "patches": {**_BEFORE_GUIDED, (spike_guidance, "FINE_ENCODER_EVERY"): 0},
                      "overrides": {"fine_frozen_encoder": False, "between_every": 1}},
    "guided-exact": {"doc": "this code with the training switches of before (trained encoder, a between-frame "
                            "render every step): the pure-speed part", "hexplane_sampler": "auto",
                     "patches": {(spike_guidance, "FINE_ENCODER_EVERY"): 1},
                     "overrides": {"fine_frozen_encoder": False, "between_every": 1}},
    "between2": {"doc": "between_every=2: a between-frame render every other step (not the default: "
                        "-0.7 dB on moving pixels, docs/experiments/spike-guidance.md)", "hexplane_sampler": "auto",
                 "overrides": {"between_every": 2}},
    "fine-nokeep": {"doc": "spike windows encoded at every render, as before EncodedWindows",
                    "hexplane_sampler": "auto", "patches": {(spike_guidance, "FINE_ENCODER_EVERY"): 0}},
    "fine-every4": {"doc": "FINE_ENCODER_EVERY=4", "hexplane_sampler": "auto",
                    "patches": {(spike_guidance, "FINE_ENCODER_EVERY"): 4}},
    "fine-frozen": {"doc": "fine_frozen_encoder (encoded once per window)", "hexplane_sampler": "auto",
                    "overrides": {"fine_frozen_encoder": True}},
    "traj-reference": {"doc": "trajectories evaluated from column slices (plain autograd), as before the "
                              "column-weight backward", "hexplane_sampler": "auto",
                       "patches": {(trajectory, "EVALUATOR"): "torch"}},
    "adam-torch": {"doc": "the Gaussians' optimizer steps with torch.optim.Adam's own (seven-pass) update, "
                          "as before FusedAdam", "hexplane_sampler": "auto",
                   "patches": {(fused_adam, "ENABLED"): False}},
    "adam-twopass": {"doc": "FusedAdam in two numba passes with torch's sqrt between them (ONE_PASS=False), as "
                            "before its one-pass kernel (same numbers)", "hexplane_sampler": "auto",
                     "patches": {(fused_adam, "ONE_PASS"): False}},
    "nn-dense": {"doc": "hidden Gaussians' nearest carried neighbour by a dense torch.cdist, as before the grid "
                        "search", "hexplane_sampler": "auto", "patches": {(scene_flow, "DENSE_SEARCH"): True}},
    "traj-before": {"doc": "all three of traj-reference, adam-torch and nn-dense: the trajectory step as on "
                           "main before this work", "hexplane_sampler": "auto",
                    "patches": {(trajectory, "EVALUATOR"): "torch", (fused_adam, "ENABLED"): False,
                                (scene_flow, "DENSE_SEARCH"): True}},
    "adam-exact": {"doc": "gaussian_adam=exact: the Gaussians' FusedAdam updates every row and column "
                          "(torch's Adam bit for bit)", "hexplane_sampler": "auto",
                   "overrides": {"gaussian_adam": "exact"}},
    "adam-selective": {"doc": "gaussian_adam=selective: only the rows the step's renders see and the curve "
                              "columns its times read (engine.scene.selective_adam)", "hexplane_sampler": "auto",
                       "overrides": {"gaussian_adam": "selective"}},
    "adam-lazy": {"doc": "gaussian_adam=lazy: the curves' touched columns only, their skipped steps caught up "
                         "(engine.scene.lazy_adam)", "hexplane_sampler": "auto",
                  "overrides": {"gaussian_adam": "lazy"}},
    "lazy-clean-at-take": {"doc": "the lazy step leaves a kept gradient buffer's read columns to grad_buffers' "
                                  "strided zeroing at the next step's first reader (lazy_adam.CLEAR_BUFFERS=False)",
                           "hexplane_sampler": "auto", "patches": {(lazy_adam, "CLEAR_BUFFERS"): False}},
    "adam-serial": {"doc": "FusedAdam's one-pass update of a large parameter on one thread (fused_adam.PARALLEL="
                           "False), as before its runs of blocks on numba's threads (same numbers)",
                    "hexplane_sampler": "auto", "patches": {(fused_adam, "PARALLEL"): False}},
    "ssim-msssim": {"doc": "the D-SSIM term by pytorch_msssim (conv2d + autograd), as before the fused SSIM",
                    "hexplane_sampler": "auto", "patches": {(fused_ssim, "ENABLED"): False}},
    "adam-ssim-before": {"doc": "gaussian_adam=exact and pytorch_msssim's D-SSIM: the optimizer and the SSIM as "
                                "before SelectiveAdam and the fused SSIM", "hexplane_sampler": "auto",
                        "overrides": {"gaussian_adam": "exact"}, "patches": {(fused_ssim, "ENABLED"): False}},
    "guided-main": {"doc": "the guided step before this round: the spike loss's between-frame render over the "
                           "whole spike view with a depth channel nobody reads, the flow term's subset positions "
                           "by gather + mask", "hexplane_sampler": "auto",
                    "patches": {(spike_guidance, "BETWEEN_DEPTH"): True,
                                (spike_flow, "inner_only_positions"): _inner_only_positions_gather}},
    "flow-gather": {"doc": "the flow term's subset positions by gather + mask + evaluate, as before their column "
                           "backward", "hexplane_sampler": "auto",
                    "patches": {(spike_flow, "inner_only_positions"): _inner_only_positions_gather}},
    "step-before": {"doc": "the RGB step before this round: the admissions' Lucas-Kanade flow in torch (box filter, "
                           "median, warp), frames re-read from disk at each admission, the residual term's "
                           "finiteness test by torch.isfinite, the curves at an instant by torch column ops",
                    "hexplane_sampler": "auto",
                    "patches": {(interpolation, "FUSED_BOX"): False, (scene_flow, "ITEM_IMAGES"): False,
                                (trajectory, "FUSED_FINITE"): False, (trajectory, "FUSED_CURVES"): False}},
    "stepcost-before": {"doc": "the step before the stepcost round: a new OpenCV DIS object per optical flow, a flow "
                               "pair's two flows one after the other, the "
                               "flow term's subset positions by per-column torch ops and row gathers, the stereo "
                               "depth term's pixels by boolean masks every step (same numbers)",
                        "hexplane_sampler": "auto",
                        "patches": {(spike_flow, "FUSED_INNER"): False, (losses, "HOIST_STEREO"): False,
                                    (scene_flow, "REUSE_DIS"): False, (spike_flow_pairs, "PARALLEL_PAIR"): False}},
    "sink-off": {"doc": "every reader of the curves returns its own full [N, K, C] gradient and autograd sums "
                        "them, as before trajectory.gradient_sink (same numbers)", "hexplane_sampler": "auto",
                 "patches": {(trajectory, "SINK"): False}},
    "grad-fresh": {"doc": "the curves' gradient a fresh full [N, K, C] tensor at every step's first reader, as "
                          "before engine.scene.grad_buffers (same numbers)", "hexplane_sampler": "auto",
                   "patches": {(grad_buffers, "ENABLED"): False}},
    "rows-copied": {"doc": "births, densification and pruning rebuild every per-Gaussian tensor and Adam moment "
                           "(torch.cat, t[keep]) and give a new curve a fresh gradient buffer, as before "
                           "engine.scene.row_store and grad_buffers.carry (same numbers)",
                    "hexplane_sampler": "auto",
                    "patches": {(row_store, "ENABLED"): False, (grad_buffers, "CARRY"): False}},
    "quiet-mask": {"doc": "the quiet curves held at zero by multiplying each curve by a mask its size, built at "
                          "every mask refresh, as before engine.train.guidance._quiet_kernels (same numbers)",
                   "hexplane_sampler": "auto", "patches": {(quiet_curves, "FUSED"): False}},
    "curves-serial": {"doc": "the curve and residual kernels on one thread, as before their row-parallel drivers "
                             "(trajectory.PARALLEL; same numbers)", "hexplane_sampler": "auto",
                      "patches": {(trajectory, "PARALLEL"): False}},
    "refresh-before": {"doc": "the guided step's per-run caches refreshed as before: the flow term's visible-surface "
                              "sets every 10 steps, the quiet curves' mask every 10 (spike_flow.SURFACE_EVERY, "
                              "quiet_curves.REFRESH; now 30 and 50)", "hexplane_sampler": "auto",
                       "patches": {(spike_flow, "SURFACE_EVERY"): 10, (quiet_curves, "REFRESH"): 10}},
    "flow-inline": {"doc": "PREFETCH=0: the flow term's DIS flows computed in the step that first needs "
                           "them, as before the background worker (engine.train.guidance.spike_flow_cache; same flows)",
                    "hexplane_sampler": "auto", "patches": {(spike_flow_cache, "PREFETCH"): 0}},
    "spike-flow-off": {"doc": "spike_flow_weight=0: without the spike-view optical-flow term on the curves "
                              "(issue 11; on by default)", "hexplane_sampler": "auto",
                       "overrides": {"spike_flow_weight": 0.0}},
    "read-moments": {"doc": "a read's catch-up also decays and writes the moments (lazy_adam.READ_VALUES_ONLY="
                            "False), as first built (same numbers)", "hexplane_sampler": "auto",
                     "patches": {(lazy_adam, "READ_VALUES_ONLY"): False}},
    "rgb-dense": {"doc": "LAZY_RGB_ONLY=False: an RGB-only run's curves under LAZY_MIN_COLUMNS steps whole by "
                         "FusedAdam, as before the read catch-up (dense Adam to rounding either way)",
                  "hexplane_sampler": "auto", "patches": {(scene_gaussians, "LAZY_RGB_ONLY"): False}},
    "reads-stale": {"doc": "a render reads a lazy curve column where its last touch left it, the skipped steps' "
                           "momentum landing at the next touch (lazy_adam.READ_CATCH_UP=False), as before",
                    "hexplane_sampler": "auto", "patches": {(lazy_adam, "READ_CATCH_UP"): False}},
}
VARIANTS["long-before"] = {"doc": "grad-fresh and curves-serial together: the curves' step before the work for long "
                                  "captures (same numbers)", "hexplane_sampler": "auto",
                           "patches": {k: v for name in ("grad-fresh", "curves-serial")
                                       for k, v in VARIANTS[name]["patches"].items()}}


@contextmanager
def variant(name: str):
    """Switch the engine to code path ``name`` of :data:`VARIANTS` for the block."""
    spec = VARIANTS[name]
    old = HexPlane.sampler
    HexPlane.sampler = spec["hexplane_sampler"]
    saved = [(mod, attr, getattr(mod, attr)) for mod, attr in spec.get("patches", {})]
    for (mod, attr), value in spec.get("patches", {}).items():
        setattr(mod, attr, value)
    try:
        yield
    finally:
        HexPlane.sampler = old
        for mod, attr, value in reversed(saved):
            setattr(mod, attr, value)


def _profile_run(cap, steps: int, preset: str, overrides: dict | None, rgb_only: bool,
                 prof: "StepProfiler", device: str = "cpu") -> int:
    """One profiled run (RGB only or guided) into ``prof``; returns its final Gaussian count."""
    cfg = get_preset(preset, {**(overrides or {}), "iterations": int(steps)})
    tr = Trainer(cap, cfg, device=device, rgb_only=rgb_only)
    tr.init_model()
    deform = "rgb_deform" if rgb_only else "guided_deform"
    with prof:
        for i in range(int(steps)):
            stage = tr.stage_of(i)
            if i in (0, tr.static_steps) or (stage == "static" and not rgb_only):
                tr.step(i)  # a stage's set-up step, or the guided run's (identical) static stage
                continue
            prof.run_step(tr, i, "static" if stage == "static" else deform)
    spike_flow.close_flow_worker(tr.run)  # its prefetch worker must not run into the next run
    enc = getattr(tr.model.deformation, "fine_encoder", None)
    if enc is not None and hasattr(enc, "encoded"):  # spike windows encoded / shared / reused stale
        e = enc.encoded
        prof.fine_stats = {"computed": e.computed, "shared": e.shared, "stale": e.stale}
    return tr.model.gaussians.num_gaussians


def merged(profs: list["StepProfiler"]) -> "StepProfiler":
    """One profiler whose tables are over every step of ``profs`` (each label's times and
    step counts summed); ``rounds`` keeps the parts, in order."""
    out = StepProfiler()
    for p in profs:
        for label, acc in p.by_label.items():
            dst = out._acc(label)
            for c in CATEGORIES:
                dst["totals"][c] += acc["totals"][c]
            dst["steps"] += acc["steps"]
            dst["seconds"] += acc["seconds"]
        out.fine_stats = p.fine_stats or out.fine_stats
    out.rounds = list(profs)
    return out


def compare_runs(capture, steps: int, preset: str = "fast", overrides: dict | None = None,
                 spike: bool = True, variants=("current",), device: str = "cpu",
                 rounds: int = 1) -> tuple[dict, dict]:
    """Profile an RGB-only run (and, with ``spike``, a guided run) of ``steps`` steps for
    each code path of ``variants`` (:data:`VARIANTS`), interleaved: RGB runs of every
    variant, then guided runs; ``rounds`` times over (RGB, guided, RGB, guided, ...), so that
    a ratio of the two runs can be read per round: on a shared VM the guided / RGB ratio of
    one pair moved 1.64-1.90x between processes. Returns ({variant: StepProfiler over every
    round, its ``rounds`` the per-round profilers}, {variant: Gaussian counts of the last round})."""
    if rounds < 1:
        raise ValueError("bench-step: rounds must be >= 1")
    cap = load_capture(capture) if not hasattr(capture, "frames") else capture
    global _SYNC_CUDA
    on_cpu = torch.device(device).type == "cpu"
    warm_up_runtime(device)
    per_round = {v: [StepProfiler() for _ in range(int(rounds))] for v in variants}
    counts: dict = {v: {} for v in variants}
    threads = torch.get_num_threads()
    if on_cpu:
        torch.set_num_threads(1)  # as engine.train.train does on the CPU
    else:  # the first gsplat call loads (or builds) its extension: not a step's time
        from engine.raster import gsplat_backend

        if not gsplat_backend.available():
            raise SystemExit("bench-step --device cuda: gsplat unusable: " + gsplat_backend.unavailable_reason())
    _SYNC_CUDA = torch.device(device).type == "cuda"
    try:
        for r in range(int(rounds)):
            for rgb_only in ((True, False) if spike else (True,)):
                for v in variants:
                    with variant(v):
                        n = _profile_run(cap, steps, preset,
                                         {**(overrides or {}), **VARIANTS[v].get("overrides", {})},
                                         rgb_only, per_round[v][r], device)
                    counts[v]["rgb_deform" if rgb_only else "guided_deform"] = n
    finally:
        torch.set_num_threads(threads)
        _SYNC_CUDA = False
    return {v: merged(per_round[v]) for v in variants}, counts


def profile_runs(capture, steps: int, preset: str = "fast", overrides: dict | None = None,
                 spike: bool = True) -> tuple["StepProfiler", dict]:
    """Profile an RGB-only run (and, with ``spike``, a guided run) of ``steps`` steps.
    Returns the profiler (labels static / rgb_deform / guided_deform) and Gaussian counts."""
    profs, counts = compare_runs(capture, steps, preset, overrides, spike)
    return profs["current"], counts["current"]


def ratios(prof: "StepProfiler", clock: str = "wall") -> dict:
    rgb, guided = prof.table("rgb_deform", clock), prof.table("guided_deform", clock)
    raster = rgb["ms"]["raster_fwd"] + rgb["ms"]["raster_bwd"]
    out = {"rgb_step_over_raster": rgb["step_ms"] / raster if raster else float("nan")}
    if guided["steps"]:
        out["guided_step_over_rgb_step"] = guided["step_ms"] / rgb["step_ms"] if rgb["step_ms"] else float("nan")
    return out


def round_ratios(prof: "StepProfiler", clock: str = "wall") -> str:
    """The two ratios of each round of ``prof`` (:func:`merged`) and their medians."""
    per = [ratios(p, clock) for p in prof.rounds]
    lines = []
    for key, name in (("rgb_step_over_raster", "RGB step / rasterizer"),
                      ("guided_step_over_rgb_step", "guided / RGB step")):
        vals = [r[key] for r in per if key in r]
        if vals:
            lines.append(f"{name} by round: " + ", ".join(f"{v:.2f}x" for v in vals)
                         + f"; median {float(np.median(vals)):.2f}x")
    return "\n".join(lines)


def markdown(prof: "StepProfiler", clock: str = "wall") -> str:
    labels = [lb for lb in ("static", "rgb_deform", "guided_deform") if prof.table(lb)["steps"]]
    tabs = {lb: prof.table(lb, clock) for lb in labels}
    steps = " | ".join(f"{tabs[lb]['step_ms']:.1f} ({tabs[lb]['steps']} steps)" for lb in labels)
    lines = [f"| part ({clock} ms) | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels),
             f"| step ms | {steps} |"]
    for c in CATEGORIES:
        lines.append(f"| {c} | " + " | ".join(f"{tabs[lb]['ms'][c]:.1f} ({100 * tabs[lb]['share'][c]:.0f}%)"
                                             for lb in labels) + " |")
    return "\n".join(lines)


def main(args) -> int:
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown or not variants:
        raise SystemExit(f"bench-step: unknown variant(s) {unknown}; choose from {', '.join(VARIANTS)}")
    load0 = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    t0 = time.perf_counter()
    profs, counts = compare_runs(args.capture, args.steps, args.preset, parse_overrides(args.set),
                                 variants=variants, device=args.device, rounds=args.rounds)
    load1 = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    for v in variants:
        prof = profs[v]
        for clock in CLOCKS:
            print(f"### {v} ({VARIANTS[v]['doc']}), {clock} time\n")
            print(markdown(prof, clock))
            r = ratios(prof, clock)
            print()
            print(f"RGB deformation step / rasterizer fwd+bwd: {r['rgb_step_over_raster']:.2f}x (target <= 1.6x)")
            if "guided_step_over_rgb_step" in r:
                print(f"guided step / RGB step: {r['guided_step_over_rgb_step']:.2f}x (target <= 1.6x)")
            if len(prof.rounds) > 1:
                print(round_ratios(prof, clock))
            print()
        print(f"Gaussians at the end ({v}): {counts[v]}")
        if getattr(prof, "fine_stats", None):
            print(f"spike windows encoded / shared / reused stale ({v}): {prof.fine_stats}")
    if len(variants) > 1:
        base = profs[variants[0]]
        for v in variants[1:]:
            for clock in CLOCKS:
                parts = []
                for lb in ("rgb_deform", "guided_deform"):
                    a, b = base.table(lb, clock), profs[v].table(lb, clock)
                    if a["steps"] and b["steps"]:
                        parts.append(f"{lb} {a['step_ms'] / b['step_ms']:.2f}x")
                print(f"step speed-up of {v} over {variants[0]} ({clock}): " + ", ".join(parts))
    print(f"{time.perf_counter() - t0:.0f} s; load average start/end {load0:.1f} / {load1:.1f} "
          f"(cores: {os.cpu_count()})")
    return 0
