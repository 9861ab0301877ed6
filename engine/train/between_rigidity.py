"""Local rigidity between RGB instants (issue 11, Build 2, "local rigidity").

Between two RGB instants only the spike camera watches the scene, and what it constrains is
the image-plane motion of the surface it sees. Every Gaussian's in-between position is its
own curve (``engine.scene.trajectory``): nothing ties a Gaussian to its neighbours, so where
an object moves fast or spins (the fast scene's ball: ~55 px and a quarter turn per RGB
frame) the interpolated curves cut chords through it and the spike terms move each
Gaussian alone; from any other viewpoint the object tears apart between the frames, while
it is sharp at the RGB instants.

This term makes each part move as a rigid body between the instants where both cameras
pinned it: at the between-frame instant ``t`` of a step's between-frame render, in the RGB
interval ``[T_a, T_b]``, the Gaussians that move over the interval keep, with respect to
their positions and rotations at ``T_a`` and at ``T_b`` (evaluated without gradient), Luiten
et al.'s three relations over ``k`` nearest neighbours ("Dynamic 3D Gaussians", 3DV 2024,
Sec. 4; ``engine.scene.rigidity``): neighbour offsets that rotate with the Gaussian's frame,
neighbours that rotate alike, distances kept. The neighbours are found among the moving
Gaussians at ``T_a`` and reused for ``rigidity_between_every`` steps of the same interval
(the Gaussian set unchanged).

Only motion is trained (the canonical Gaussians enter detached; ``along_ray.motion_frames``),
so the RGB instants keep what the RGB frames say. Loss: the mean of the two instants' sums
``rigid + rot + iso`` / extent; weight ``rigidity_between_weight`` (0: off, the term is not
built). Listed in :data:`engine.train.trainer.LOSS_FACTORIES` after the spike guidance whose
between-frame render instants it uses; nothing without a spike stream or with ``rgb_only``.
"""
from __future__ import annotations

import torch

from ..scene import trajectory as traj
from ..scene.rigidity import knn_neighbours, rigidity_losses
from .along_ray import motion_frames
from .losses import LossTerm
from .spike_guidance import admitted_time

__all__ = ["BetweenRigidity", "between_rigidity_factory"]


class BetweenRigidity:
    """Per-run state of the term: the spike guidance it rides on, the RGB instants and the
    neighbour lists of the interval last used."""

    def __init__(self, trainer, guidance):
        self.trainer = trainer
        self.guidance = guidance
        self.cfg = trainer.cfg
        self.times = list(trainer.frame_times)
        self._nbrs: dict = {}  # interval k -> (step, Gaussian count, moving idx [M], nbr [M, k], w [M, k])
        self.last: dict = {}  # diagnostics of the last evaluation

    def interval(self, t: float, admitted: float) -> int | None:
        """Index k of the RGB interval [T_k, T_k+1] holding ``t`` when both ends are admitted."""
        ts = self.times
        if len(ts) < 2 or t <= ts[0] or t >= ts[-1]:
            return None
        k, _ = traj.segment_of(ts, t)
        return k if ts[k + 1] <= admitted + 1e-9 else None

    def neighbours(self, model, k: int, step: int, static):
        """(moving idx [M], nbr [M, k] into idx, weights [M, k]) for interval ``k`` (cached)."""
        n = model.gaussians.num_gaussians
        hit = self._nbrs.get(k)
        every = max(1, int(self.cfg.rigidity_between_every))
        if hit is not None and hit[1] == n and 0 <= step - hit[0] < every:
            return hit[2:]
        a, b = self.times[k], self.times[k + 1]
        with torch.no_grad():
            everyone = torch.arange(n, device=model.gaussians.means.device)
            xa, _ = motion_frames(model, a, everyone, static)
            xb, _ = motion_frames(model, b, everyone, static)
            min_move = float(self.cfg.rigidity_between_min_move) * self.trainer.extent
            move = torch.linalg.vector_norm(xb - xa, dim=-1) > min_move
            if static is not None:
                move &= ~static
            idx = move.nonzero(as_tuple=True)[0]
            cap = int(self.cfg.rigidity_between_max_gaussians)
            if cap > 0 and idx.numel() > cap:  # a random subset bounds the cost of the search and the term
                gen = torch.Generator(device="cpu").manual_seed(self.trainer.seed * 7919 + step)
                idx = idx[torch.randperm(idx.numel(), generator=gen)[:cap].to(idx.device)].sort().values
            if idx.numel() > int(self.cfg.rigidity_k):
                nbr, w = knn_neighbours(xa[idx], int(self.cfg.rigidity_k))
            else:
                nbr = w = None
        self._nbrs[k] = (step, n, idx, nbr, w)
        return idx, nbr, w

    def __call__(self, ctx):
        b = self.guidance.between(ctx)
        model = ctx.trainer.model
        if b is None or model is None or not model.use_deformation:
            return None
        tr = ctx.trainer
        t = float(b["instant"].time)
        admitted = admitted_time(ctx, self.times[-1])
        k = self.interval(t, admitted)
        if k is None:
            return None
        static = model.effective_static_mask()
        idx, nbr, w = self.neighbours(model, k, ctx.step, static)
        if nbr is None:
            return None
        x_t, q_t = motion_frames(model, t, idx, static)
        total = 0.0
        parts_sum = {"rigid": 0.0, "rot": 0.0, "iso": 0.0}
        for t_ref in (self.times[k], self.times[k + 1]):
            with torch.no_grad():
                x_r, q_r = motion_frames(model, t_ref, idx, static)
            parts = rigidity_losses(x_r, q_r, x_t, q_t, nbr, w)
            total = total + 0.5 * (parts["rigid"] + parts["rot"] + parts["iso"])
            for name in parts_sum:
                parts_sum[name] += 0.5 * float(parts[name].detach())
        self.last = {"gaussians": int(idx.numel()), "interval": k, **parts_sum}
        return total / max(float(tr.extent), 1e-9)


def between_rigidity_factory(trainer) -> list:
    """The term for a (non rgb_only) run with ``rigidity_between_weight > 0`` and a spike
    guidance that renders between RGB instants; nothing otherwise."""
    cfg = trainer.cfg
    guid = getattr(trainer, "spike_guidance", None)
    if cfg.rigidity_between_weight <= 0 or guid is None:
        return []
    term = BetweenRigidity(trainer, guid)
    trainer.between_rigidity = term
    return [LossTerm("rigidity_between", float(cfg.rigidity_between_weight), term, stages=("deform",))]
