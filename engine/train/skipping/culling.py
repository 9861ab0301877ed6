"""Frustum culling: prune Gaussians that no train camera sees (the ``cull_frustum`` switch
of :class:`engine.train.config.TrainConfig`)."""
from __future__ import annotations

import numpy as np
import torch

from ...raster.projection import project_gaussians

__all__ = ["FrustumCuller", "frustum_cull_mask"]


def frustum_cull_mask(run, margin_px: float = 0.0, times=None) -> torch.Tensor:
    """bool [N]: Gaussians invisible (radius 0: behind, beyond the image box, or below 1/255
    opacity) in every train view, at the canonical positions and -- once the deformation
    field exists -- at ``times`` (default: the train frame times) as well."""
    model = run.model
    g = model.gaussians
    views = {}
    for it in run.items:
        key = tuple(np.round(it["viewmat"][0].cpu().numpy().ravel(), 6)) + (it["width"], it["height"])
        views.setdefault(key, it)
    with torch.no_grad():
        positions = [g.means.detach()]
        if model.deformation is not None and model.use_deformation:
            for t in (times if times is not None else run.frame_times):
                d = model.deformation(g.means, g.quats, g.log_scales, g.opacity_logits, float(t))
                positions.append(d["means"].detach())
        if model.trajectory is not None and model.use_deformation:  # per-Gaussian curves (issue 11)
            for t in (times if times is not None else run.frame_times):
                positions.append(model.attributes(float(t))["means"].detach())
        visible = torch.zeros(g.num_gaussians, dtype=torch.bool, device=g.means.device)
        scales = torch.exp(g.log_scales.detach())
        opac = torch.sigmoid(g.opacity_logits.detach())
        for it in views.values():
            w, h = it["width"] + 2 * margin_px, it["height"] + 2 * margin_px
            K = it["K"].clone()
            K[:, 0, 2] += margin_px
            K[:, 1, 2] += margin_px
            for pos in positions:
                proj = project_gaussians(pos, g.quats.detach(), scales, opac, it["viewmat"], K, int(w), int(h))
                visible |= proj.radii[0] > 0
    return ~visible


class FrustumCuller:
    """Prune Gaussians outside every train frustum (:func:`frustum_cull_mask`). The run
    calls it after the first step, after the first deformation step and right after each
    densification (whose statistics were just reset, so pruning then does not disturb them);
    never below ``min_keep`` Gaussians."""

    EVENTS_KEEP = 50

    def __init__(self, min_keep: int = 16):
        self.min_keep = int(min_keep)
        self.pruned = 0
        self.events: list[dict] = []

    def __call__(self, run, step: int) -> int:
        g = run.model.gaussians
        mask = frustum_cull_mask(run)
        n = int(mask.sum())
        if not n or g.num_gaussians - n < self.min_keep:
            return 0
        g.prune(mask)
        if run.part("freeze") is None:
            run.model.static_mask = None
        self.pruned += n
        self.events.append({"step": int(step), "pruned": n, "left": g.num_gaussians})
        del self.events[:-self.EVENTS_KEEP]
        return n

    def state_dict(self) -> dict:
        return {"pruned": self.pruned, "events": list(self.events)}

    def load_state_dict(self, state: dict) -> None:
        self.pruned = int(state.get("pruned", 0))
        self.events = list(state.get("events", []))

    def summary(self) -> dict:
        return {"pruned": self.pruned, "events": list(self.events)}
