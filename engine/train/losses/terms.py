"""The training objective: a list of :class:`LossTerm` evaluated on a :class:`StepContext`.

:func:`default_loss_terms` is the RGB frame loss (L1 + lambda * D-SSIM, paper Eq. 22) plus
the block L1 (Eq. 20), the stereo depth prior and the deformation regularisers; the spike
branch adds its terms through the loss factories listed in :mod:`engine.train.loop.trainer`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import torch
import torch.nn.functional as F
from pytorch_msssim import ssim

from ...scene.deformation import TIME_L1_WEIGHT, TV_WEIGHT
from ...scene.model import TRAJ_MEANS
from ...scene.trajectory import inner_residual_sq
from ..config import TrainConfig
from .fused_ssim import fused_ssim
from .geometry_losses import geometry_loss_terms

__all__ = ["LossTerm", "StepContext", "default_loss_terms", "frame_item_fields", "BLOCK_SIZE"]

BLOCK_SIZE = 4  # side of the block loss's average pooling (paper Eq. 20: 4x4)

def frame_item_fields(frame, cfg: TrainConfig, device) -> dict:
    """The run item's fields that say how a train frame is supervised: ``synthetic``
    (a baseline's generated frame, engine.train.frames.baselines), ``knot`` (its instant is an RGB
    instant: trajectory knot, scene-flow carry, spike intervals; the frame's ``knot``, from
    ``cfg.baseline.instants``), and for synthetic frames ``loss_scale`` (``cfg.baseline.weight``)."""
    synthetic = bool(getattr(frame, "extra", {}).get("synthetic"))
    out = {"synthetic": synthetic, "knot": bool(getattr(frame, "knot", True))}
    if synthetic:
        out["loss_scale"] = float(cfg.baseline.weight)
    return out


def _frame_target(ctx: "StepContext"):
    """(target image [1, H, W, 3], weight) of the frame loss (a synthetic frame's ``loss_scale``)."""
    item = ctx.item
    return item["image"], item.get("loss_scale", 1.0)


@dataclass
class LossTerm:
    """One term of the training objective: ``weight * fn(ctx)``; ``fn`` may return None."""

    name: str
    weight: float
    fn: Callable[["StepContext"], torch.Tensor | None]
    stages: tuple = ("static", "deform")


@dataclass
class StepContext:
    run: Any          # the RunContext of the run (engine.train.run_context)
    step: int
    stage: str
    item: dict            # the train frame: view tensors + "image" [1,H,W,3] + "index"
    rgb: torch.Tensor     # rendered [1,H,W,3]
    alpha: torch.Tensor   # [1,H,W,1]
    meta: dict
    attrs: dict           # deformed Gaussians used for the render


def _l1(ctx: StepContext):
    target, w = _frame_target(ctx)
    return (ctx.rgb - target).abs().mean() * w


def _dssim(ctx: StepContext):
    target, w = _frame_target(ctx)
    d = dssim(ctx.rgb, target)
    return None if d is None else d * w


def dssim(rgb: torch.Tensor, target: torch.Tensor) -> torch.Tensor | None:
    """1 - SSIM of two [1, H, W, 3] images (None under 11 px a side)."""
    fused = fused_ssim(rgb, target)  # the same SSIM in two numba passes (issue 13)
    if fused is not None:
        return 1.0 - fused
    pred = rgb.permute(0, 3, 1, 2)
    gt = target.permute(0, 3, 1, 2)
    if min(pred.shape[-2:]) < 11:
        return None
    return 1.0 - ssim(pred, gt, data_range=1.0, size_average=True)


def _block_l1(ctx: StepContext):
    """L1 between 4x4 average-pooled images (the paper's block supervision, Eq. 20): a
    wider basin of attraction for displaced objects than per-pixel L1."""
    k = BLOCK_SIZE
    pred = ctx.rgb.permute(0, 3, 1, 2)
    if min(pred.shape[-2:]) < 2 * k:
        return None
    target, w = _frame_target(ctx)
    gt = target.permute(0, 3, 1, 2)
    return (F.avg_pool2d(pred, k) - F.avg_pool2d(gt, k)).abs().mean() * w


def _stereo_depth(ctx: StepContext):
    """Relative L1 between the rendered expected depth and confident stereo depth (the
    calibrated pair sees every RGB instant twice: geometry the eval viewpoint relies on)."""
    target = ctx.item.get("stereo_depth")
    depth = ctx.meta.get("depths")
    if target is None or depth is None:
        return None
    m = ctx.item["stereo_mask"]
    if not HOIST_STEREO or depth.shape[0] != 1 or m.shape != depth.shape[1:3] or m.device != depth.device:
        gt = target[m]
        return ((depth[0, ..., 0][m] - gt).abs() / gt).mean()
    # the item's mask and target are fixed for the run: their confident pixels' flat indices and
    # target values once per (mask, target), then one index_select a step instead of two boolean
    # gathers (each a nonzero over the image); same values, and the same gradient (0 + g per pixel)
    cache = ctx.run.memo.setdefault("stereo_pixels", {})
    hit = cache.get(id(m))
    if hit is None or hit[0] is not m or hit[1] is not target:
        flat = m.reshape(-1).nonzero(as_tuple=True)[0]
        hit = cache[id(m)] = (m, target, flat, target[m])
    _, _, flat, gt = hit
    return ((depth[0, ..., 0].reshape(-1).index_select(0, flat) - gt).abs() / gt).mean()


# False: the stereo depth term gathers its pixels by boolean masks every step (bench-step's
# "stereo-mask" variant)
HOIST_STEREO = True


def _deform_reg(ctx: StepContext):
    d = ctx.run.model.deformation
    cfg = ctx.run.cfg
    if d is None or not ctx.run.model.use_deformation:
        return None
    smooth = cfg.spike.time_smooth_weight if ctx.run.guided else cfg.hexplane.time_smooth_weight
    return d.regularization(TV_WEIGHT, smooth, TIME_L1_WEIGHT)


def _traj_reg(ctx: StepContext):
    """Mean squared inner-point residual of the trajectories / extent^2 (engine.scene.trajectory):
    with zero residuals the in-between motion is the Catmull-Rom curve through the RGB
    instants; only the between-frame losses have a reason to bend it."""
    m = ctx.run.model
    if m.trajectory is None or not m.use_deformation:
        return None
    opt, curve = m.gaussians.optimizer, getattr(m.gaussians, TRAJ_MEANS)
    if getattr(opt, "lazy_for", None) is not None and opt.lazy_for(curve):
        # a lazy optimiser adds the prior's gradient on the columns it updates (engine.scene.lazy_adam)
        opt.inner_decay[TRAJ_MEANS] = float(ctx.run.cfg.motion.inner_weight) / ctx.run.extent ** 2
        return None
    sq = inner_residual_sq(curve)
    if sq.numel() == 0:
        return None
    return sq.mean() / ctx.run.extent ** 2


MOTIONS = ("hexplane", "trajectory", "trajectory+hexplane")


def renders_at_instants_only(cfg: TrainConfig, items, rgb_only: bool) -> bool:
    """Whether every render that trains a run is at an RGB instant: RGB-only (no spike terms) and no
    synthetic frames between the instants (the Interpolate baseline's). Then no loss reads the curves'
    inner control points (``GaussianModel.instants_only``)."""
    return bool(rgb_only) and all(it.get("knot", True) for it in items)


def default_loss_terms(cfg: TrainConfig) -> list[LossTerm]:
    terms = [LossTerm("l1", 1.0 - cfg.losses.dssim, _l1)]
    if cfg.losses.dssim > 0:
        terms.append(LossTerm("dssim", cfg.losses.dssim, _dssim))
    if cfg.losses.block > 0:
        terms.append(LossTerm("block_l1", cfg.losses.block, _block_l1))
    if cfg.losses.depth > 0:
        terms.append(LossTerm("stereo_depth", cfg.losses.depth, _stereo_depth))
    terms.extend(geometry_loss_terms(cfg, LossTerm))  # issue 14 (engine.train.losses.geometry_losses)
    terms.append(LossTerm("deform_reg", 1.0, _deform_reg, stages=("deform",)))
    if "trajectory" in cfg.motion.representation and cfg.motion.inner_weight > 0:
        terms.append(LossTerm("traj_reg", cfg.motion.inner_weight, _traj_reg, stages=("deform",)))
    return terms
