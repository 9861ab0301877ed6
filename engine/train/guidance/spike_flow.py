"""Spike-view optical-flow supervision of the in-between motion (issue 11, Build 2).

The spike loss (Eq. 17) compares rendered and captured spike counts pixel by pixel. Its
basin is narrow: a part that moved several spike pixels between two RGB instants gives
gradients that do not point along its motion (``between`` scene: the visible cube
Gaussians' image-plane error 30.7 mm RGB-only -> 31.6 mm with the spike loss, the 15 Hz
vibration's own mean displacement being 31 mm; ``tools/trajectory_error.py --visible``).

This term turns the spike stream's 2D evidence into a displacement target instead. Grey
images are reconstructed from the spikes (TFP over ``spike_flow_window`` frames with the
sensor response inverted, :func:`engine.train.frames.baselines.spike_to_gray`) at an RGB instant
``T`` and at a between-frame instant ``t``; OpenCV's DIS optical flow between them, kept
where the forward and backward flows agree (occlusions, unreliable texture out), says where
the surface seen at each spike pixel at ``T`` has gone at ``t``. For the Gaussians that are
the visible surface at the spike view at ``T`` (their camera depth within
``spike_flow_depth_tol`` of the rendered depth at their pixel), the projected displacement
``pi(x(t)) - pi(x(T))`` through the spike camera must match the flow at ``pi(x(T))``::

    L = mean_i smoothL1_beta( pi(x_i(t)) - [pi(x_i(T)) + flow_{T->t}(pi(x_i(T)))] )   (spike px)

``x(T)`` is a target (no gradient); ``x(t)`` keeps a gradient only into the curves' inner
control points (the junctions belong to the RGB frames), so the term bends the in-between
motion and leaves what both cameras saw alone. ``d pi / d x`` is perpendicular to the ray:
the along-ray component stays with the curves' smoothness (``traj_inner_weight``).

Once per RGB interval (``fit_interval``, ``spike_flow_fit``) the flow also bends the visible
curves' inner control points by least squares and, with ``spike_flow_junctions`` (on: ``all``),
puts their place at the interval's right end where the flow says (``flow_junctions``: the train
cameras' 30 FPS carry misses fast jumps; docs/experiments/flow-junctions.md "The fast scene's ghost"),
where the RGB frames there agree better with the flow's place than with the carry's (``rgb_vote``).

Flows are computed once per (reference instant, between instant) pair: the between instant
is rounded to ``spike_flow_steps`` points per RGB interval and the reference is the nearer
admitted RGB instant, so a run holds at most ``2 x steps x intervals`` tiny flow maps (the
spike view is the sensor's resolution). Weight ``spike_flow_weight`` (0: off, the term is
not built). Needs per-Gaussian trajectories and a spike loss (it rides on the spike
guidance's between-frame instants); nothing with ``rgb_only`` or without a spike stream.
On by default (weight 1; docs/experiments/spike-flow.md "Spike-view optical flow on the curves": on the ``between``
scene between RGB frames +0.69 / +0.44 dB over the spike loss alone, seeds 0 / 1, the visible
cube's image-plane error 31.5 -> 11.8 mm; demo +0.14 / +0.18, fast +0.28 / +0.14, novel -0.02 / +0.56 dB).
"""
from __future__ import annotations

import numpy as np
import torch

from ...scene import trajectory as traj
from ...scene.model import TIME_CENTER, TRAJ_MEANS, Model4D, born_mask
from ..losses.terms import LossTerm
from ..motion import scene_flow
from ..motion.scene_flow import dense_flow, propagate_to_hidden
from . import spike_flow_cache
from .spike_flow_cache import FlowCache
from .spike_flow_pairs import flow_pair, forward_backward_valid, gray_to_u8, warm_flow_pair
from .spike_guidance import admitted_time, spike_view_guidance
from .spike_view import fit_inner_residuals, lift, project, projected_flow_loss, sample_map, segment_basis

# the surface a flow supervises: |z - rendered depth| <= DEPTH_TOL x depth, at most MAX_GAUSSIANS of
# it a step (0: all), its set reused for SURFACE_EVERY steps while the Gaussian count is unchanged;
# the loss's smooth-L1 knee BETA (spike px); the fit leaves curves whose median flow is below MIN_PX
DEPTH_TOL = 0.03
MAX_GAUSSIANS = 4096
SURFACE_EVERY = 30
BETA = 1.0
MIN_PX = 0.5
JUNCTION_MODES = ("none", "born", "all")  # spike_flow_junctions (SpikeFlowSupervision.flow_junctions)

__all__ = ["JUNCTION_MODES", "gray_to_u8", "dense_flow", "forward_backward_valid", "flow_pair", "warm_flow_pair",
           "sample_map", "project", "lift", "projected_flow_loss", "segment_basis", "fit_inner_residuals",
           "inner_only_positions", "subset_positions", "SpikeFlowSupervision", "spike_flow_factory",
           "close_flow_worker"]


# ------------------------------------------------------------------------------ functional
class _InnerAt(torch.autograd.Function):
    """``base + sum_j w_j params[idx, c_j]`` [M, C] (the curves of rows ``idx`` at one instant,
    ``traj.segment_weights``); the backward adds ``w_j * grad`` into rows ``idx`` of the inner
    columns (``c % 3 != 0``) of a zero [N, K, C] gradient or, in ``traj.gradient_sink``, the leaf's
    ``.grad`` (issue 13; the same numbers as gather + ``torch.where`` + ``traj.evaluate``,
    ``tests/test_spike_flow.py``). On the CPU both passes are numba (``_trajectory_kernels.inner_at``),
    the same numbers as per-column torch ops (``tests/test_step_cost.py``)."""

    @staticmethod
    def forward(ctx, params, base, idx, cols, weights):
        ctx.shape, ctx.cols, ctx.weights, ctx.leaf = params.shape, cols, weights, params if params.is_leaf else None
        ctx.save_for_backward(idx)
        ctx.fused = _fused_inner(params, base, idx)
        if ctx.fused:  # one pass over the subset's rows (_trajectory_kernels.inner_at), same numbers
            out = base.new_empty(base.shape)
            traj.KERNELS.module.inner_at(params.detach().numpy(), base.detach().numpy(), idx.numpy(),
                                         np.asarray(cols, np.int64), np.asarray(weights, _NP[params.dtype]),
                                         out.numpy())
            return out
        out = None
        for c, w in zip(cols, weights):
            term = params[idx, c] * w
            out = term if out is None else out.add_(term)
        return base + out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        (idx,) = ctx.saved_tensors
        if ctx.fused and grad.dtype in _NP and grad.device.type == "cpu":  # in place: traj.gradient_sink
            a = (grad.detach().contiguous().numpy(), idx.numpy(), np.asarray(ctx.cols, np.int64),
                 np.asarray(ctx.weights, _NP[grad.dtype]))
            return traj.sunk(ctx.leaf, lambda: traj.zeros_then(traj.KERNELS.module.inner_at_backward, ctx.shape, *a),
                             lambda g: traj.KERNELS.module.inner_at_backward(*a, g.numpy()), ctx.cols), \
                None, None, None, None
        def add(g):  # torch ops; each entry gets ``0 + grad * w``, as a zero gradient's index_add_ gives it
            for c, w in zip(ctx.cols, ctx.weights):
                if c % 3:
                    g[:, c].index_add_(0, idx, torch.mul(grad, w).add_(0.0))
            return g
        return traj.sunk(ctx.leaf, lambda: add(grad.new_zeros(ctx.shape)), add, ctx.cols), None, None, None, None


_NP = {torch.float32: np.float32, torch.float64: np.float64}
# False: _InnerAt in torch ops (a gather and a multiply per column; index_add_ per inner column
# backward), as before its numba pair (bench-step's "inner-torch" variant)
FUSED_INNER = True


def _fused_inner(params: torch.Tensor, base: torch.Tensor, idx: torch.Tensor) -> bool:
    return (FUSED_INNER and params.device.type == "cpu" and params.dtype in _NP and base.dtype == params.dtype
            and params.is_contiguous() and base.is_contiguous() and base.dim() == 2 and idx.dtype == torch.int64
            and idx.is_contiguous() and idx.device.type == "cpu" and traj.KERNELS.load() is not None)


def inner_only_positions(model: Model4D, t: float, idx: torch.Tensor) -> torch.Tensor:
    """Positions [M, 3] of Gaussians ``idx`` (distinct) at ``t`` whose gradient reaches only
    the curves' inner control points (canonical means and junctions detached). Static rows
    are not passed here by the caller."""
    g = model.gaussians
    params = getattr(g, TRAJ_MEANS)
    knots = model.trajectory["knots"]
    if traj.EVALUATOR == "torch":  # the reference path (bench-step's traj-reference variant)
        sub = params[idx]
        inner = torch.ones(sub.shape[1], dtype=torch.bool, device=sub.device)
        inner[0::3] = False
        sub = torch.where(inner[None, :, None], sub, sub.detach())
        traj.before_read(params, [c for c, _ in traj.segment_weights(knots, t)])
        return g.means.detach()[idx] + traj.evaluate(sub, knots, t)
    traj._check(params, traj._knots(knots))
    cols, weights = zip(*traj.segment_weights(knots, t))
    traj.before_read(params, cols)
    if params.requires_grad and torch.is_grad_enabled():
        traj._note_touched(params.shape[1], [c for c in cols if c % 3])  # the inner ones get its gradient
    return _InnerAt.apply(params, g.means.detach()[idx], idx, cols, weights)


@torch.no_grad()
def subset_positions(model: Model4D, t: float, idx: torch.Tensor) -> torch.Tensor:
    """Positions [M, 3] of Gaussians ``idx`` at ``t`` (no gradient):
    ``means[idx] + traj.evaluate(curves[idx], knots, t)``. On the CPU the curves' rows are read
    in place by the numba pass of :class:`_InnerAt` (all columns) instead of gathered into an
    [M, K, 3] copy first: the same numbers (issue 13, ``tests/test_step_cost.py``)."""
    g = model.gaussians
    params = getattr(g, TRAJ_MEANS)
    knots = model.trajectory["knots"]
    base = g.means.detach()[idx]
    if traj.EVALUATOR != "torch" and _fused_inner(params, base, idx):
        traj._check(params, traj._knots(knots))
        cols, weights = zip(*traj.segment_weights(knots, t))
        traj.before_read(params, cols)
        out = torch.empty_like(base)
        traj.KERNELS.module.inner_at(params.detach().numpy(), base.numpy(), idx.numpy(), np.asarray(cols, np.int64),
                                     np.asarray(weights, _NP[params.dtype]), out.numpy())
        return out
    traj.before_read(params, [c for c, _ in traj.segment_weights(knots, t)])
    return base + traj.evaluate(params.detach()[idx], knots, t)


# ------------------------------------------------------------------------------ run term
class SpikeFlowSupervision(FlowCache):
    """Per-run state of the term: flow cache (engine.train.guidance.spike_flow_cache), the spike camera
    and the RGB instants."""

    def __init__(self, run, guidance):
        self.run = run
        self.guidance = guidance
        self.cfg = run.cfg
        if self.cfg.spike_flow.junctions not in JUNCTION_MODES:
            raise ValueError(f"unknown spike_flow_junctions {self.cfg.spike_flow.junctions!r}; "
                             f"choose one of {', '.join(JUNCTION_MODES)}")
        stream = guidance.stream
        self.stream = stream
        view = stream.view(0.0)
        dev = run.device
        self.view = view
        self.viewmat = torch.as_tensor(view.viewmat, dtype=torch.float32, device=dev)
        self.K = torch.as_tensor(view.K, dtype=torch.float32, device=dev)
        self.vt = {"viewmat": self.viewmat[None], "K": self.K[None], "width": int(stream.width),
                   "height": int(stream.height), "campos": torch.as_tensor(view.center, dtype=torch.float32,
                                                                           device=dev), "time": 0.0}
        self.times = list(run.frame_times)
        self.init_flows()
        self.last: dict = {}  # diagnostics of the last evaluation
        self.fitted: dict[int, dict] = {}  # interval -> counts of its fit (spike_flow_fit)
        self._surface: dict[float, tuple] = {}  # t_ref -> (step, Gaussian count, indices)

    # --- instants ------------------------------------------------------------------------
    def instants(self, t: float, admitted: float) -> tuple[float, float] | None:
        """(reference RGB instant, quantised between instant) for a between instant ``t``,
        or None when no bracketing RGB instant is admitted yet."""
        ts = self.times
        if not ts or t <= ts[0] or t >= ts[-1]:
            return None
        a, b, q, n1 = self.grid_step(t)
        q = min(n1 - 1, max(1, q))
        tq = a + (b - a) * q / n1
        cands = [v for v in (a, b) if v <= admitted + 1e-9]
        if not cands:
            return None
        return min(cands, key=lambda v: abs(v - tq)), tq

    def surface(self, model: Model4D, t_ref: float) -> tuple[torch.Tensor, torch.Tensor]:
        """(indices [M] of the Gaussians that are the visible surface at the spike view at
        ``t_ref``, their pixels uv [M, 2]): in front, inside, not static, camera depth within
        ``spike_flow_depth_tol`` (relative) of the rendered expected depth where alpha > 0.5."""
        with torch.no_grad():
            _, alpha, meta, attrs = model.render(self.vt, t_ref, render_depth=True)
            uv, z = project(attrs["means"], self.viewmat, self.K)
            w, h = self.vt["width"], self.vt["height"]
            inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            ok = inside & (meta["radii"][0] > 0)
            static = model.effective_static_mask()
            if static is not None:
                ok &= ~static
            idx = ok.nonzero(as_tuple=True)[0]
            if idx.numel() == 0:
                return idx, uv[:0]
            uvi = uv[idx]
            d = sample_map(meta["depths"][0], uvi, "nearest")[:, 0]
            a = sample_map(alpha[0], uvi, "nearest")[:, 0]
            keep = (a > 0.5) & ((z[idx] - d).abs() <= float(DEPTH_TOL) * d)
            return idx[keep], uvi[keep]

    def cached_surface(self, model: Model4D, t_ref: float, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`surface` (a render, ~10 ms on the demo), its indices reused ``spike_flow_surface_every``
        steps while the Gaussian count is unchanged (densification re-indexes); pixels re-projected."""
        n = model.gaussians.num_gaussians
        hit = self._surface.get(t_ref)
        if hit is None or hit[1] != n or step - hit[0] >= max(1, SURFACE_EVERY) or step < hit[0]:
            idx, uv = self.surface(model, t_ref)
            self._surface[t_ref] = (step, n, idx)
            return idx, uv
        idx = hit[2]
        with torch.no_grad():
            uv, _ = project(subset_positions(model, t_ref, idx), self.viewmat, self.K)
        return idx, uv

    @torch.no_grad()
    def fit_interval(self, model: Model4D, k: int, extent: float) -> dict:
        """Bend segment ``k``'s inner control points to the flow (``spike_flow_fit``): the
        Gaussians that are the visible surface at ``T_k`` get, by least squares over the
        segment's grid instants, the residual change that puts their projections where the
        flow from ``T_k`` says (depth kept from the current curve: image-plane motion only);
        Gaussians within ``traj_carry_hidden`` x extent of them that the spike view does not
        see (inside or behind the surface) take their nearest one's change. Returns counts."""

        model.gaussians.settle()  # a lazy optimiser's skipped moves land before the fit writes
        a, b = self.times[k], self.times[k + 1]
        n = max(1, int(spike_flow_cache.FLOW_STEPS))
        us = torch.arange(1, n + 1, dtype=torch.float32) / (n + 1)
        idx, uv_ref = self.surface(model, a)
        moved = {}
        mode = self.cfg.spike_flow.junctions
        if mode != "none":  # before the inner fit, which starts from the moved curves
            moved["junctions_ahead"] = self.flow_junctions(model, k, a, b, idx, uv_ref, born_only=mode == "born")
            # those born at the right end (after the carry) take their place at the left one
            moved["junctions_back"] = self.flow_junctions(model, k, b, a, *self.surface(model, b), born_only=True)
        if idx.numel() == 0:
            return {"interval": k, "fitted": 0, **moved}
        g = model.gaussians
        params = getattr(g, TRAJ_MEANS)
        knots = model.trajectory["knots"]
        seg, _ = traj.segment_of(knots, 0.5 * (a + b))
        cur, tgt, wts, mags = [], [], [], []
        for u in us.tolist():
            t = a + (b - a) * u
            flow, valid = self.flow(a, t)
            x = subset_positions(model, t, idx)
            _, z = project(x, self.viewmat, self.K)
            f = sample_map(flow, uv_ref)
            cur.append(x)
            tgt.append(lift(uv_ref + f, z, self.viewmat, self.K))
            wts.append(sample_map(valid, uv_ref, "nearest")[:, 0])
            mags.append(f.norm(dim=-1))
        w = torch.stack(wts)
        dD = fit_inner_residuals(torch.stack(cur), torch.stack(tgt), w, us.to(params.device))
        enough = w.sum(0) >= 0.5 * n  # observed at half the instants at least
        # the flow's noise on a still surface (0.3 px at the default window, docs/experiments/spike-flow.md) is not
        # motion
        still = torch.stack(mags).median(0).values < float(MIN_PX)
        dD[still] = 0.0
        full = torch.zeros(params.shape[0], 2, 3, dtype=params.dtype, device=params.device)
        full[idx[enough]] = dD[enough].to(params.dtype)
        decided = torch.zeros(params.shape[0], dtype=torch.bool)
        decided[idx[enough].cpu()] = True
        hidden = 0
        if scene_flow.CARRY_HIDDEN > 0 and bool(decided.any()):
            pos = (g.means + traj.evaluate(params, knots, a)).cpu().numpy()
            outs = []
            for j in range(2):
                d, taken = propagate_to_hidden(pos, full[:, j].cpu().numpy(), decided.numpy(),
                                               float(scene_flow.CARRY_HIDDEN) * extent)
                outs.append(torch.as_tensor(d, device=params.device, dtype=params.dtype))
            static = model.effective_static_mask()
            keep = torch.ones(params.shape[0], dtype=torch.bool, device=params.device)
            if static is not None:
                keep &= ~static
            full = torch.where(keep[:, None, None], torch.stack(outs, 1), full)
            hidden = int(taken.sum())
        params.data[:, 3 * seg + 1] += full[:, 0]
        params.data[:, 3 * seg + 2] += full[:, 1]
        return {"interval": k, "fitted": int(enough.sum()), "still": int((enough & still).sum()), "hidden": hidden,
                **moved,
                "mean_change_mm": float(dD[enough].norm(dim=-1).mean() * 1000) if bool(enough.any()) else 0.0}

    @torch.no_grad()
    def flow_junctions(self, model: Model4D, k: int, ref: float, other: float, idx: torch.Tensor,
                       uv_ref: torch.Tensor, born_only: bool = False) -> dict:
        """Put the curves of the Gaussians that are the visible surface at ``ref`` (one end of
        interval ``k``; ``idx``, pixels ``uv_ref``) where the spike view's flow says they are at
        the interval's other end ``other`` (``spike_flow_junctions``; ``born_only``: only those
        born at ``ref``, engine.train.motion.births): the flow from ``ref`` to the cached between
        instant nearest ``other`` (``u = n / (n + 1)``), lifted at the Gaussian's camera depth at
        ``ref`` and extended linearly to ``other``; the junctions beyond ``other`` hold it.

        Why: the train cameras' carry (``traj_carry=flow``) finds the next RGB instant by a
        30 FPS optical flow that misses the fast scene's jumps (the ball ~55 px per frame), so
        the object between two RGB instants is a cross-fade of two copies (the ghost). Depth is
        the Gaussian's at ``ref`` (the curve's own at ``other`` measured worse). Only what the
        spike view sees moves: handing the change to hidden neighbours moved the static world
        near small objects (random scenes up to -1 dB; docs/experiments/flow-junctions.md
        "Random scenes"). Returns counts for run.json; ``vetoed``: moves ``rgb_vote`` refused."""
        info = {"surface": int(idx.numel()), "moved": 0}
        if idx.numel() == 0:
            return info
        g = model.gaussians
        if born_only:  # born at ``ref``: the temporal centre (trained, so it drifts) nearer ``ref`` than ``other``
            if TIME_CENTER not in g.extra_lrs:
                return info
            near = (getattr(g, TIME_CENTER).detach()[idx, 0] - ref).abs() < 0.5 * abs(other - ref)
            keep = born_mask(g)[idx] & near
            idx, uv_ref = idx[keep], uv_ref[keep]
            info["born"] = int(idx.numel())
            if idx.numel() == 0:
                return info
        n = max(1, int(spike_flow_cache.FLOW_STEPS))
        frac = n / (n + 1)
        flow, valid = self.flow(ref, ref + (other - ref) * frac)
        f = sample_map(flow, uv_ref)
        ok = (sample_map(valid, uv_ref, "nearest")[:, 0] > 0.5) & (f.norm(dim=-1) >= float(MIN_PX))
        if not bool(ok.any()):
            return info
        idx, uv, f = idx[ok], uv_ref[ok], f[ok]
        x = subset_positions(model, ref, idx)
        _, z = project(x, self.viewmat, self.K)
        d = (lift(uv + f, z, self.viewmat, self.K) - x) / frac
        # the RGB frames at ``other`` decide between the flow's place and the curve's own
        better = self.rgb_vote(x, x + d, subset_positions(model, other, idx), ref, other)
        info["vetoed"] = int((~better).sum())
        idx, d = idx[better], d[better]
        if idx.numel() == 0:
            return info
        knots = model.trajectory["knots"]
        seg, _ = traj.segment_of(knots, 0.5 * (self.times[k] + self.times[k + 1]))
        tm = getattr(g, TRAJ_MEANS).data
        if other > ref:  # ahead: junction seg + 1 and every later one
            j_ref, moved = seg, range(seg + 1, len(knots))
        else:  # back: junction seg and every earlier one
            j_ref, moved = seg + 1, range(0, seg + 1)
        new = tm[idx, 3 * j_ref] + d.to(tm)
        for j in moved:
            tm[idx, 3 * j] = new
        info["moved"] = int(idx.numel())
        return info

    def rgb_vote(self, x_ref: torch.Tensor, x_flow: torch.Tensor, x_curve: torch.Tensor, ref: float,
                 other: float) -> torch.Tensor:
        """[M] bool: where the train cameras' RGB frames at ``other`` agree better with the
        spike flow's place ``x_flow`` than with the curve's current place ``x_curve`` (from the
        train cameras' carry). Each Gaussian's 3x3 patch in the frame at ``ref`` (around its
        projection ``x_ref``) is compared, L1 summed over the cameras that have frames at both
        instants, with the patches at the two candidates in the frame at ``other``.

        Why: the spike flow finds jumps the 30 FPS carry misses (the fast scene loses 0.65 dB
        without the flow's junctions), but where the carry was right an ambiguous flow moves
        the junctions off what the RGB frames show (docs/experiments/flow-junctions.md
        "Random scenes: the hidden hand-over removed, the RGB frames' vote added")."""
        pairs = {}
        for it in self.run.items:
            if it.get("synthetic"):
                continue
            for key, t in (("ref", ref), ("other", other)):
                if abs(float(it["time"]) - t) < 1e-6:
                    pairs.setdefault(it["camera"], {})[key] = it
        off = torch.stack(torch.meshgrid(torch.arange(-1.0, 2.0), torch.arange(-1.0, 2.0), indexing="ij"), -1)
        off = off.reshape(1, 9, 2).to(x_ref)
        err_flow = torch.zeros(x_ref.shape[0], dtype=x_ref.dtype, device=x_ref.device)
        err_curve = torch.zeros_like(err_flow)
        seen = torch.zeros_like(err_flow, dtype=torch.bool)
        for cam in sorted(pairs):
            if len(pairs[cam]) < 2:
                continue
            a, b = pairs[cam]["ref"], pairs[cam]["other"]
            vm, K = a["viewmat"][0].to(x_ref), a["K"][0].to(x_ref)
            w, h = int(a["width"]), int(a["height"])

            def patches(img, pts):
                uv, z = project(pts, vm, K)
                inside = (z > 0) & (uv[:, 0] >= 1) & (uv[:, 0] < w - 1) & (uv[:, 1] >= 1) & (uv[:, 1] < h - 1)
                vals = sample_map(img[0].to(x_ref), (uv[:, None, :] + off).reshape(-1, 2))
                return vals.reshape(-1, 9 * vals.shape[-1]), inside

            p_ref, in_ref = patches(a["image"], x_ref)
            p_flow, in_flow = patches(b["image"], x_flow)
            p_curve, in_curve = patches(b["image"], x_curve)
            use = in_ref & in_flow & in_curve
            err_flow += torch.where(use, (p_flow - p_ref).abs().mean(-1), 0.0)
            err_curve += torch.where(use, (p_curve - p_ref).abs().mean(-1), 0.0)
            seen |= use
        return ~seen | (err_flow < err_curve)

    def after_step(self, tr, step, item, meta) -> None:
        """Post-step hook: the flows of the intervals the next step may admit queued
        (the static stage's steps already run beside the first ones); the interval fits
        asked for during this step."""
        if tr is self.run and callable(getattr(tr, "time_window", None)):  # not the budget's probe copy
            self.prefetch(tr.time_window(step + 1))
        if not self.cfg.spike_flow.fit:
            return
        for k, info in list(self.fitted.items()):
            if not info and tr.model is not None and tr.model.trajectory is not None:
                self.fitted[k] = self.fit_interval(tr.model, k, float(tr.extent))

    def __call__(self, ctx):
        hit = self.guidance.deforming_spike_view(ctx)
        if hit is None or hit[1].trajectory is None:
            return None
        b, model = hit
        tr = ctx.run
        admitted = admitted_time(ctx, self.times[-1])
        pair = self.instants(float(b["instant"].time), admitted)
        if pair is None:
            return None
        t_ref, tq = pair
        k = max(i for i, v in enumerate(self.times) if v <= tq)
        if self.cfg.spike_flow.fit and k not in self.fitted and self.times[k + 1] <= admitted + 1e-9:
            self.fitted[k] = {}  # fitted after this step's optimiser step (after_step), not under autograd
        idx, uv_ref = self.cached_surface(model, t_ref, ctx.step)
        flow, valid = self.flow(t_ref, tq)
        if idx.numel() == 0:
            return None
        ok = sample_map(valid, uv_ref, "nearest")[:, 0] > 0.5
        idx, uv_ref = idx[ok], uv_ref[ok]
        cap = int(MAX_GAUSSIANS)
        if cap > 0 and idx.numel() > cap:  # a random subset bounds the cost per step
            gen = torch.Generator(device="cpu").manual_seed(tr.seed * 7919 + ctx.step)
            pick = torch.randperm(idx.numel(), generator=gen)[:cap].to(idx.device)
            idx, uv_ref = idx[pick], uv_ref[pick]
        if idx.numel() == 0:
            return None
        target = uv_ref + sample_map(flow, uv_ref)
        uv_t, _ = project(inner_only_positions(model, tq, idx), self.viewmat, self.K)
        loss = projected_flow_loss(uv_t, target, float(BETA))
        with torch.no_grad():
            res = float(torch.linalg.vector_norm(uv_t - target, dim=-1).mean())
        self.last = {"gaussians": int(idx.numel()), "residual_px": res, "t_ref": t_ref, "t": tq}
        return loss


def spike_flow_factory(run) -> list:
    """The flow term for a (non rgb_only) run with ``spike_flow_weight > 0``, per-Gaussian
    trajectories and a spike loss (whose between-frame instants it uses); nothing otherwise."""
    cfg = run.cfg
    guid = spike_view_guidance(run)
    if cfg.spike_flow.weight <= 0 or guid is None:
        return []
    stream = guid.stream
    if ("trajectory" not in cfg.motion.representation or stream is None or stream.c2w is None
            or stream.intrinsics is None):
        return []
    term = SpikeFlowSupervision(run, guid)
    run.parts["spike_flow"] = term
    hooks = getattr(run, "post_step_hooks", None)
    if hooks is not None:
        hooks.append(term.after_step)
    return [LossTerm("spike_flow", float(cfg.spike_flow.weight), term, stages=("deform",))]


def close_flow_worker(run) -> None:
    """Stop the prefetch worker of ``run``'s flow term, if it has one (the end of a run, a
    benchmark's run before the next: :meth:`FlowCache.close_flows`)."""
    term = run.part("spike_flow")
    if term is not None:
        term.close_flows()
