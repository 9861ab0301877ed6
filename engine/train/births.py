"""Births: new Gaussians at an admitted RGB instant, where the render still misses the frame.

Why: on the fast scene the per-Gaussian curves of a fast, rotating object do not reach its
new place at late instants, and the optimiser answers with lower opacity (ghosts: README
"Motion representation", time-curriculum table). Densification only clones existing
Gaussians, curves included, so nothing can start at the new place. Spacetime Gaussians
(Li et al., CVPR 2024) give each Gaussian a temporal opacity and add points per frame; here,
when the time curriculum admits RGB instant ``t`` (after the carry has moved the curves
there), every train view at ``t`` is rendered, and at pixels where the render misses the
frame by more than ``birth_error`` (max over channels) and the per-instant stereo depth is
known, a Gaussian is born at the back-projected point with the frame's colour, a zero
(static) curve and a temporal opacity centred on ``t`` (std ``birth_lifespan`` x the frame
interval; the other Gaussians get an effectively infinite one, so they are unchanged).
Training then moves, widens or fades it like any other parameter.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..scene.gaussians import inverse_sigmoid, rgb_to_sh
from ..scene.model import TIME_CENTER, TIME_LOG_SCALE, view_tensors
from .scene_flow import backproject_pixels, frame_image, instant_depth_priors

__all__ = ["ALWAYS_LOG_SCALE", "birth_candidates", "ensure_temporal_opacity", "spawn_at_instant"]

ALWAYS_LOG_SCALE = 30.0  # log std (s) of Gaussians not born at an instant: factor 1 at any t
LR_TIME_CENTER = 5e-4    # s per step: a born Gaussian's centre can drift a few frames in 100 steps
LR_TIME_LOG_SCALE = 1e-2


def ensure_temporal_opacity(gaussians) -> None:
    """Give every Gaussian the temporal-opacity extras (once): centre 0, log std 30."""
    if TIME_CENTER in gaussians.extra_lrs:
        return
    n, dev = gaussians.num_gaussians, gaussians.means.device
    gaussians.add_extra(TIME_CENTER, torch.zeros(n, 1, device=dev), LR_TIME_CENTER)
    gaussians.add_extra(TIME_LOG_SCALE, torch.full((n, 1), ALWAYS_LOG_SCALE, device=dev), LR_TIME_LOG_SCALE)


def birth_candidates(render: np.ndarray, image: np.ndarray, depth: np.ndarray, depth_ok: np.ndarray,
                     threshold: float, stride: int, limit: int, rng: np.random.Generator):
    """Pixels (rows, cols) where ``render`` [H,W,3] misses ``image`` by more than ``threshold``
    (max over channels) and ``depth_ok``, on a ``stride`` grid, at most ``limit`` (random)."""
    miss = np.abs(render - image).max(axis=-1) > threshold
    grid = np.zeros_like(miss)
    grid[::stride, ::stride] = True
    rows, cols = np.nonzero(miss & depth_ok & grid & np.isfinite(depth) & (depth > 0))
    if len(rows) > limit:
        keep = np.sort(rng.choice(len(rows), size=limit, replace=False))
        rows, cols = rows[keep], cols[keep]
    return rows, cols


def spawn_at_instant(trainer, frames, t: float) -> dict:
    """Births at the train frames of instant ``t`` (see the module docstring). Returns the
    record ``{"birth_at", "born", "total"}``, also appended to ``trainer.birth_info`` (run.json's
    ``births``)."""
    cfg, model = trainer.cfg, trainer.model
    g = model.gaussians
    pri = instant_depth_priors(trainer, frames)
    knots = model.trajectory["knots"]  # births follow the carry, which only curves have
    dt = float(np.median(np.diff(knots))) if len(knots) > 1 else 1.0 / 30.0
    rng = np.random.default_rng(int(trainer.seed) * 7919 + int(round(t * 1e6)))
    pts, cols, sizes = [], [], []
    for f in frames:
        if abs(float(f.time) - t) > 1e-6 or id(f) not in pri:
            continue
        view = trainer.capture.view(f)
        vt = view_tensors(view, trainer.device)
        with torch.no_grad():
            rgb = model.render(vt, t, render_depth=False)[0][0].clamp(0, 1).cpu().numpy()
        img = frame_image(trainer, f)
        depth, ok = pri[id(f)]
        r, c = birth_candidates(rgb, img, depth, ok, cfg.birth_error, int(cfg.birth_stride), int(cfg.birth_max), rng)
        if len(r) == 0:
            continue
        z = depth[r, c].astype(np.float64)
        pts.append(backproject_pixels(view, np.stack([c + 0.5, r + 0.5], 1), z))
        cols.append(img[r, c])
        sizes.append(z / view.intrinsics.fx * cfg.birth_stride * 0.5)  # half the grid step, in metres
    records = trainer.__dict__.setdefault("birth_info", [])
    if not pts:
        records.append({"birth_at": float(t), "born": 0, "total": g.num_gaussians})
        return records[-1]
    ensure_temporal_opacity(g)
    dev = g.means.device
    means = torch.as_tensor(np.concatenate(pts), dtype=torch.float32, device=dev)
    m = means.shape[0]
    quats = torch.zeros(m, 4, device=dev)
    quats[:, 0] = 1.0
    rows = {n: torch.zeros((m, *getattr(g, n).shape[1:]), device=dev) for n in g.param_names}  # static curves
    rows.update({
        "means": means,
        "log_scales": torch.log(torch.as_tensor(np.concatenate(sizes), dtype=torch.float32, device=dev)
                                .clamp_min(1e-6))[:, None].repeat(1, 3),
        "quats": quats,
        "opacity_logits": inverse_sigmoid(torch.full((m,), float(cfg.birth_opacity), device=dev)),
        "sh_dc": rgb_to_sh(torch.as_tensor(np.concatenate(cols), dtype=torch.float32, device=dev))[:, None, :],
        TIME_CENTER: torch.full((m, 1), float(t), device=dev),
        TIME_LOG_SCALE: torch.full((m, 1), math.log(max(cfg.birth_lifespan * dt, 1e-6)), device=dev),
    })
    g.append(rows)
    if model.static_mask is not None and model.static_mask.shape[0] == g.num_gaussians - m:
        model.static_mask = torch.cat([model.static_mask, torch.zeros(m, dtype=torch.bool, device=dev)])
    records.append({"birth_at": float(t), "born": int(m), "total": g.num_gaussians})
    return records[-1]
