"""Quiet curves: no in-between bend where the spike view saw nothing change (issue 11).

With per-Gaussian trajectories (engine.scene.trajectory) the RGB frames fix each curve's
junctions; its inner control points (residuals from the Catmull-Rom spline) are moved only
by the between-frame terms of the spike branch (the spike loss, Eq. 17, and the spike-view
flow term and its fit, engine.train.guidance.spike_flow). Those terms see one greyscale 80x60 view
with shot noise, and bend the curves of Gaussians that never moved: on the demo capture
(1000 fast steps, seed 0) 13.5k of 24.5k Gaussians had a residual above 1 % of the scene
extent (mean 3.7 %: 16 cm) where RGB-only holds them all at zero, and the full model lost
0.25 dB to RGB-only between RGB frames at the eval camera while it gained 0.37 dB at the RGB
instants. Setting every residual back to zero after training put it +0.52 dB above RGB-only
between frames (the bends cost the demo, whose motion 30 FPS samples smoothly), but on the
``between`` scene (motion 30 FPS cannot sample) the same reset cost 1.2 dB: the bends are
the spike branch's gain there. The HexPlane model has the same guard as a prior
(``SpikeGuidance.static_prior``, ``spike_static_prior``); the trajectories had none.

This switch (``quiet_curves``) holds at zero the segment-``k`` inner residuals (positions
and rotations) of the Gaussians that, at both ends of segment ``k`` (RGB instants ``T_k``,
``T_{k+1}``), project inside the spike view onto blocks where the spike stream did not
change during interval ``k`` (:class:`engine.spike.change.SpikeChange`, dilated by
``DILATE`` blocks): what the spike view saw there is still, so the curve between
the two RGB instants is the smooth one the RGB frames give. Gaussians outside the spike view
or over a change keep their bends. Applied after every optimiser step (a projection onto
the constraint, also undoing the flow fit's changes there); the mask is recomputed when the
Gaussian count changes and every ``REFRESH`` steps (junctions move slowly).

Holding the junctions joined by quiet segments at their mean as well (quiet junctions) was
measured and dropped (docs/experiments/quiet-curves.md).

Still Gaussians between frames (issue 47): the Gaussians quiet over an interval take no gradient
from the between-frame renders in it either (:meth:`QuietCurves.still_at`, read by
``SpikeGuidance.trainable_between``): held curves alone left their colours, shapes and places to the
spike loss, whose count noise and sensor mismatch at one greyscale viewpoint repainted the static
world (on random scenes static pixels 0.2-0.4 dB under RGB-only; the spike loss off recovered them).
docs/experiments/still-gaussians-between-frames.md has the figures.

Rotation bends (issue 47): where the spike view changed, the spike terms bend the rotation
curves as well as the positions. The greyscale spike view places a surface; it cannot say how
a Gaussian turns, and the rotation bends are not motion the eval camera can use: set to zero
after training, 18 finished runs (random scenes, ours, 1000 and 2000 steps) lost at most 0.02 dB
and gained up to 0.11 (seed 211: +0.08, static pixels between RGB instants +0.48, the static
drift 0.0057 -> 0.0032), with a lower static drift on 17. Training without them is no
better (mean +0.01 dB, ``between`` at 2000 steps -0.10 / -0.15): during training they take up
what the spike loss cannot place. So a finished run flattens them (:meth:`QuietCurves.finish`,
run.json ``quiet_curves``); docs/experiments/quiet-curves.md "Rotation bends".

Small bends: a position bend smaller than its own Gaussian's largest axis moves the Gaussian
less than its size: the static world's wander under the spike loss, not motion. Flattened at
the same time (segment by segment), measured on 17 finished runs: -0.01 to +0.07 dB (fast, demo
+0.07), the static drift lower on 15 (docs/experiments/quiet-curves.md "Small bends").

Measured (docs/experiments/quiet-curves.md "Quiet curves"; 1000 fast steps, seeds 0 / 1, full - RGB-only between RGB
frames at the eval cameras, off -> on): demo -0.24 / -0.27 -> +0.30 / +0.24 dB, fast +0.13 /
+0.11 -> +0.20 / +0.43, ``between`` +1.53 / +1.26 -> +1.47 / +1.38 (moving pixels +2.49 / +2.15
-> +2.28 / +2.15). Dilation 1 block: post hoc (curves flattened after training) 2 / 1 / 0
blocks gave the demo 21.74 / 21.95 / 22.05 dB and ``between`` 21.80 / 21.83 / 21.69 (0 clips
the moving objects' edges). Cost: ~23 ms CPU per mask (36k Gaussians, 9 intervals), ~3 ms per
step to apply it with :func:`inner_keep`'s mask. On the CPU :func:`zero_quiet_columns` is a kernel
(``engine.train.guidance._quiet_kernels``) that writes the quiet rows' entries alone for a lazy step's few
columns and for whole applications to curves of ``MASK_MAX_BYTES`` or more: no mask the size of the
curves (on a 1 s capture, 70k Gaussians x 91 columns: 178 MB for the two curves, rebuilt at every
refresh); smaller curves keep the mask, whose multiply is the faster there. The same numbers.
"""
from __future__ import annotations

import numpy as np
import torch

from ...numba_cache import LazyKernels
from ...scene import trajectory as traj
from ...scene.fine_deformation import project_to_grid
from ...scene.model import TRAJ_MEANS, TRAJ_QUATS
from .spike_guidance import CHANGE_BLOCK, spike_stream_info

# change-map blocks added around the changed ones (2 / 1 / 0: 1 keeps the moving objects' edges) and
# steps a quiet mask (~14 ms at 23k Gaussians) is reused while the Gaussian count is unchanged
# (10 -> 50: within noise; docs/experiments/quiet-curves.md)
DILATE = 1
REFRESH = 50

__all__ = ["quiet_segments", "segment_intervals", "inner_keep", "zero_inner", "segment_bends", "zero_quiet_columns",
           "QuietCurves", "quiet_curves_factory", "warmup"]

KERNELS = LazyKernels(__package__, "_quiet_kernels")
# False: the mask multiply below (inner_keep) on every device, as before the kernel (bench-step "quiet-mask")
FUSED = True
# Curves below this many bytes keep the mask for a whole application: built once per refresh and in
# the cache, its vectorised multiply is the fastest (demo, 22k x 19 x 3: 0.06 ms against the segment
# kernel's 0.22); above, the mask's memory and rebuilds cost more (70k x 91 x 4: 102 MB, 24 ms a build)
MASK_MAX_BYTES = 32 << 20


def quiet_segments(means: torch.Tensor, junctions: torch.Tensor, change, intervals, viewmat: torch.Tensor,
                   K: torch.Tensor, width: int, height: int, dilate: int = 2) -> torch.Tensor:
    """bool [N, F-1]: segment ``k`` of Gaussian ``i`` is quiet when its positions at both
    junctions, ``means [N,3] + junctions[:, k]`` and ``+ junctions[:, k+1]`` (``junctions``
    [N, F, 3]), project inside the spike view (``viewmat`` [4,4], ``K`` [3,3], ``width`` x
    ``height``) onto no change of the spike interval ``intervals[k]`` (``change``:
    :class:`SpikeChange`, its map dilated by ``dilate`` blocks; ``intervals[k]`` None: the
    spike stream does not cover segment ``k``, never quiet)."""
    n, f = junctions.shape[:2]
    out = torch.zeros(n, max(0, f - 1), dtype=torch.bool, device=means.device)
    if n == 0 or f < 2:
        return out
    grids, vis = [], []
    for j in range(f):
        gr, v = project_to_grid(means + junctions[:, j], viewmat, K, width, height)
        grids.append(gr)
        vis.append(v)
    for k in range(f - 1):
        if k >= len(intervals) or intervals[k] is None:
            continue
        still = [change.gate(int(intervals[k]), grids[j], dilate=dilate).to(means.device) <= 0 for j in (k, k + 1)]
        out[:, k] = vis[k] & vis[k + 1] & still[0] & still[1]
    return out


def segment_intervals(knots, rgb_times, num_intervals: int) -> list:
    """Per curve segment between ``knots``: the spike interval ``i`` (between ``rgb_times[i]``
    and ``rgb_times[i + 1]``, ``i < num_intervals``) holding the segment's midpoint, or None."""
    out = []
    for a, b in zip(knots[:-1], knots[1:]):
        mid = 0.5 * (float(a) + float(b))
        ks = [i for i in range(len(rgb_times) - 1) if rgb_times[i] <= mid < rgb_times[i + 1]]
        out.append(ks[0] if ks and ks[0] < num_intervals else None)
    return out


def inner_keep(quiet: torch.Tensor, channels: int = 1) -> torch.Tensor:
    """float [N, K, channels] (K = 3 (F-1) + 1), contiguous: 0 at the inner control points
    ``3k+1, 3k+2`` of the rows where ``quiet`` [N, F-1] holds for segment ``k``, 1 elsewhere
    (junctions always 1). Built once per mask: multiplying by it is one plain elementwise pass
    (36k Gaussians x 28 columns: ~0.3 ms, against ~3 ms broadcast from one channel or ~6 ms
    by boolean row indexing per segment)."""
    n, s = quiet.shape
    keep = torch.ones(n, 3 * s + 1, device=quiet.device)
    inner = (~quiet).float()
    keep[:, 1::3] = inner
    keep[:, 2::3] = inner
    return keep[..., None].expand(n, 3 * s + 1, int(channels)).contiguous()


@torch.no_grad()
def zero_inner(params: torch.Tensor, quiet: torch.Tensor, keep: torch.Tensor | None = None) -> None:
    """Set the inner control points ``3k+1, 3k+2`` of ``params`` [N, K, C] to zero in the rows
    where ``quiet`` [N, F-1] holds for segment ``k`` (in place; ``keep``: its
    :func:`inner_keep`, when already built)."""
    params.data.mul_(inner_keep(quiet) if keep is None else keep)


def segment_bends(params: torch.Tensor) -> torch.Tensor:
    """[N, F-1]: the larger norm of segment ``k``'s two inner points ``3k+1, 3k+2`` of ``params``
    [N, K, C] (how far the curve bends off its smooth spline there; 0: not at all)."""
    n, segs = params.shape[0], (params.shape[1] - 1) // 3
    return params.detach()[:, :3 * segs].reshape(n, segs, 3, -1)[:, :, 1:].norm(dim=-1).amax(-1)


@torch.no_grad()
def zero_quiet_columns(params: torch.Tensor, quiet: torch.Tensor, cols=None, keeps: dict | None = None) -> None:
    """:func:`zero_inner` restricted to the columns ``cols`` (int array; None: all) of ``params``
    [N, K, C], in place. On the CPU a kernel writes the quiet rows' entries alone for a step's few
    columns, and for every column of a curve of :data:`MASK_MAX_BYTES` or more; otherwise the mask
    of :func:`inner_keep` ([N, K, C] floats: 100 MB for a 1 s capture's 70k rotation curves, built
    at every mask refresh) is multiplied in (kept in ``keeps`` by channel count). The same numbers
    either way (zero times the entry, as the mask's multiply)."""
    n, k, c = params.shape
    cols = np.arange(k) if cols is None else np.asarray(cols, np.int64)
    cols = cols[cols % 3 != 0]
    data = params.data
    every = cols.size == k - (k + 2) // 3  # every inner column
    kern = None
    if (FUSED and data.device.type == "cpu" and data.is_contiguous() and data.dtype in (torch.float32, torch.float64)
            and not (every and data.numel() * data.element_size() < MASK_MAX_BYTES)):
        kern = KERNELS.load()
    if kern is not None:
        if cols.size and n:
            rows, q = data.view(n, k * c).numpy(), quiet.cpu().numpy()
            if every:
                kern.zero_quiet_segments(rows, q, c)
            else:
                kern.zero_quiet_inner(rows, q, cols.astype(np.int64), c)
        return
    keeps = {} if keeps is None else keeps
    if c not in keeps:
        keeps[c] = inner_keep(quiet, c)
    if every:  # one pass
        zero_inner(params, quiet, keeps[c])
        return
    for col in cols.tolist():  # column by column: a view each (an index tensor's copy and scatter: ~8 ms)
        data[:, col].mul_(keeps[c][:, col])


def warmup() -> float:
    """Compile (first run on a machine) or load the kernel now; seconds taken."""
    import time

    t0 = time.perf_counter()
    if KERNELS.load() is not None:
        zero_quiet_columns(torch.ones(2, 4, 3), torch.tensor([[True], [False]]))
    return time.perf_counter() - t0


class QuietCurves:
    """Post-step hook of a run (see the module doc)."""

    def __init__(self, run, stream, change, rgb_times):
        self.cfg = run.cfg
        self.rgb_times = [float(t) for t in rgb_times]  # the change maps' intervals run between these
        view = stream.view(0.0)
        self.viewmat = torch.as_tensor(view.viewmat, dtype=torch.float32)
        self.K = torch.as_tensor(stream.intrinsics.K, dtype=torch.float32)
        self.size = (int(stream.width), int(stream.height))
        self.change = change
        # (step, N, quiet [N, F-1], {channels: inner_keep(quiet, channels)}, id of the curves' tensor)
        self._mask: tuple | None = None
        self._applied: tuple | None = None  # (mask, optimiser settles) of the last whole application
        self.last: dict = {}

    def intervals(self, knots) -> list:
        """Per segment between ``knots``: :func:`segment_intervals` of this run's spike stream."""
        return segment_intervals(knots, self.rgb_times, self.change.num_intervals)

    def mask(self, model, step: int) -> torch.Tensor:
        g = model.gaussians
        params = getattr(g, TRAJ_MEANS)
        hit = self._mask
        refresh = max(1, int(REFRESH))
        if not self._fits(params) or step - hit[0] >= refresh or step < hit[0]:
            quiet = self._quiet(model)
            self._mask = hit = (step, params.shape[0], quiet, {}, id(params))
            self.last = {"step": int(step), "quiet_fraction": float(quiet.float().mean()) if quiet.numel() else 0.0}
        return hit[2]

    def _fits(self, params: torch.Tensor) -> bool:
        """Whether the stored mask belongs to these curves (``TRAJ_MEANS``): the same Gaussian count
        and the same tensor (the budget probe steps a copy of the model through this hook)."""
        hit = self._mask
        return hit is not None and hit[1] == params.shape[0] and hit[4] == id(params)

    def _quiet(self, model) -> torch.Tensor:
        """:func:`quiet_segments` of ``model``'s Gaussians and curves as they are now."""
        g = model.gaussians
        params = getattr(g, TRAJ_MEANS)
        dev = params.device
        return quiet_segments(g.means.detach(), params.detach()[:, 0::3], self.change,
                              self.intervals(model.trajectory["knots"]), self.viewmat.to(dev),
                              self.K.to(dev), *self.size, dilate=int(DILATE))

    def still_at(self, model, t: float) -> torch.Tensor | None:
        """bool [N]: the Gaussians whose curve segment holding time ``t`` is quiet (the spike view saw
        them still over that interval), or None (no curves, or ``t`` outside them). The mask the last
        step's hook applied while it fits the curves; after the Gaussian count changed, one computed for
        this render alone: the run's mask is replaced only by the hook, which zeroes what it calls quiet
        before a render reads it."""
        if model is None or model.trajectory is None or not model.use_deformation:
            return None
        quiet = self._mask[2] if self._fits(getattr(model.gaussians, TRAJ_MEANS)) else self._quiet(model)
        k, _ = traj.segment_of(model.trajectory["knots"], t)
        return quiet[:, k] if 0 <= k < quiet.shape[1] else None

    def __call__(self, tr, step, item, meta) -> None:
        model = tr.model
        if model is None or model.trajectory is None or not model.use_deformation:
            return
        self.mask(model, step)
        g = model.gaussians
        # a lazy optimiser (engine.scene.lazy_adam) moved only the columns its step updated since
        # the mask was last applied whole, unless a settle moved them all: zero those alone
        settles = getattr(g.optimizer, "settles", None)
        now = (self._mask[0], self._mask[1], self._mask[4], settles)
        self._apply(g, local=settles is not None and self._applied == now)
        self._applied = now
        if settles is not None:
            g.on_settle(self.after_settle)
        if hasattr(g.optimizer, "on_catch_up"):
            g.optimizer.on_catch_up(self.after_catch_up)

    def after_settle(self, g) -> None:
        """A lazy optimiser's settle moved every column (the skipped steps' momentum): hold the
        quiet segments at zero again before anyone reads them (a checkpoint, densification)."""
        if self._fits(getattr(g, TRAJ_MEANS)):
            self._apply(g, local=False)

    def after_catch_up(self, params: torch.Tensor, cols) -> None:
        """A lazy optimiser brought columns ``cols`` of a curve up to its last step before a render
        reads them (the skipped steps' momentum): hold their quiet segments at zero first, as the
        dense step's mask application would have."""
        hit = self._mask
        if hit is None or hit[1] != params.shape[0]:
            return
        zero_quiet_columns(params, hit[2], cols, hit[3])

    @torch.no_grad()
    def finish(self, model) -> dict:
        """At the end of a finished run: every rotation curve's inner points to zero, and a
        position bend smaller than its Gaussian's largest axis (the module doc, "Rotation bends"
        and "Small bends"); what a cancelled run saves to resume from keeps them."""
        g = model.gaussians
        g.settle()  # a lazy optimiser's skipped moves land first
        rotations, positions = getattr(g, TRAJ_QUATS), getattr(g, TRAJ_MEANS)
        bent = segment_bends(rotations).amax(1) > 0
        bend = segment_bends(positions)
        small = (bend > 0) & (bend < g.log_scales.detach().exp().amax(-1)[:, None])
        zero_inner(rotations, torch.ones_like(small))
        zero_inner(positions, small)
        return {"rotation_bends_flattened": int(bent.sum()), "small_bends_flattened": int(small.sum()),
                "position_bends_kept": int((bend > 0).sum() - small.sum())}

    def _apply(self, g, local: bool) -> None:
        quiet, keeps = self._mask[2], self._mask[3]
        for params in (getattr(g, TRAJ_MEANS), getattr(g, TRAJ_QUATS)):
            cols = g.optimizer.last_columns(params) if local else None
            zero_quiet_columns(params, quiet, cols, keeps)


def quiet_curves_factory(run) -> list:
    """Registers the :class:`QuietCurves` post-step hook for a (non rgb_only) run with
    ``quiet_curves`` on, per-Gaussian trajectories and a calibrated spike stream whose spike
    guidance exists (its change maps); adds no loss term. Listed after the spike-flow factory
    so the hook runs after the flow fit."""
    cfg = run.cfg
    guid = run.part("spike_guidance")
    hooks = getattr(run, "post_step_hooks", None)
    if not cfg.spike.quiet_curves or guid is None or hooks is None or "trajectory" not in cfg.motion.representation:
        return []
    info = spike_stream_info(run.capture)
    stream = guid.stream
    if info is None or stream is None or stream.c2w is None or stream.intrinsics is None:
        return []
    cache = guid.window_cache()
    if cache is None:
        return []
    term = QuietCurves(run, stream, cache.change(int(CHANGE_BLOCK)), cache.rgb_times)
    run.parts["quiet_curves"] = term
    hooks.append(term)
    return []
