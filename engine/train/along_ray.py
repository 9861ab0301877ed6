"""Along-ray prior for the spike guidance (issue 11, Build 2, "along-ray prior").

Between RGB instants only the spike camera watches the scene, and one viewpoint sees only
image-plane motion: the spike loss (Eq. 17) is blind to a Gaussian sliding along the
spike camera's ray through it. Left free, the field explains in-between spike images with
such motion, which the eval camera then sees as a drift (novel scene, RGB-only trajectory
runs: the ball's Gaussians 685 mm mean / 50.6 mm median off along the ray,
``scripts/trajectory_error.py``).

This prior pins the unobserved component: at a between-frame instant ``t`` of the RGB
interval ``[T_k, T_k+1]``, for the Gaussians the spike loss touches (visible in that
step's between-frame render at the spike camera's co-located view, and not held static),
the distance from the spike camera's centre ``rho(x) = |x - c|`` must follow a smooth
curve through its values at the neighbouring RGB instants, where both train cameras see
the scene:

* ``along_ray_curve="hermite"`` (default): cubic Hermite in ``rho`` with Catmull-Rom
  tangents from ``T_k-1 .. T_k+2`` (one-sided at the ends of the admitted time window);
* ``"linear"``: linear in ``rho`` between ``T_k`` and ``T_k+1``.

The positions at the RGB instants are evaluated without gradient (targets), and the
canonical Gaussians enter detached, so only the motion (deformation field and / or the
per-Gaussian trajectories) is trained by this term. Since ``d rho / d x`` is the unit ray
direction through ``x``, the gradient is exactly along the ray: the image-plane component
of the motion stays the spike loss's to move (tests/test_along_ray.py checks both).

Loss: mean over those Gaussians of the smooth L1 (Huber, ``along_ray_beta`` x extent) of
``(rho(x(t)) - rho*(t)) / extent``; weight ``lambda_along_ray`` (0: off, the term is not
even built). Works with ``motion=hexplane``, ``trajectory`` and ``trajectory+hexplane``.
Listed in :data:`engine.train.trainer.LOSS_FACTORIES` after the spike guidance (whose
between-frame render it reuses); nothing without a spike stream or with ``rgb_only``.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..scene import trajectory as traj
from ..scene.model import TRAJ_MEANS, TRAJ_QUATS, Model4D
from .losses import LossTerm
from .spike_guidance import admitted_time, spike_view_guidance

__all__ = ["along_ray_factory", "along_ray_loss", "along_ray_target", "motion_frames", "motion_positions", "ray_depth"]

CURVES = ("hermite", "linear")


# ------------------------------------------------------------------------------ functional
def ray_depth(x: torch.Tensor, center: torch.Tensor) -> torch.Tensor:
    """Distance of points ``x`` [N, 3] from the camera centre ``center`` [3] -> [N]; its
    gradient is the unit viewing ray through each point."""
    return torch.linalg.vector_norm(x - center.reshape(1, 3), dim=-1)


def along_ray_target(times, depths, t: float, curve: str = "hermite") -> torch.Tensor:
    """``rho*(t)`` [N] from ray depths at up to four consecutive RGB instants.

    ``times``: ``[T_k-1?, T_k, T_k+1, T_k+2?]`` with ``T_k <= t <= T_k+1``, given as a dict
    ``{"prev"?, "a", "b", "next"?}`` -> seconds; ``depths``: the same keys -> [N]. ``linear``
    uses ``a`` and ``b`` only; ``hermite`` (cubic Hermite, Catmull-Rom tangents) uses
    ``prev`` / ``next`` where given (one-sided differences otherwise).
    """
    if curve not in CURVES:
        raise ValueError(f"unknown along_ray_curve {curve!r}; choose one of {', '.join(CURVES)}")
    ta, tb = float(times["a"]), float(times["b"])
    h = tb - ta
    if h <= 0:
        raise ValueError(f"RGB instants must increase: {ta} .. {tb}")
    s = min(1.0, max(0.0, (float(t) - ta) / h))
    ra, rb = depths["a"], depths["b"]
    if curve == "linear":
        return (1.0 - s) * ra + s * rb
    slope = (rb - ra) / h
    ma = (rb - depths["prev"]) / (tb - float(times["prev"])) if "prev" in depths else slope
    mb = (depths["next"] - ra) / (float(times["next"]) - ta) if "next" in depths else slope
    s2, s3 = s * s, s * s * s
    h00, h10, h01, h11 = 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2
    return h00 * ra + h10 * h * ma + h01 * rb + h11 * h * mb


def along_ray_loss(x_t: torch.Tensor, center: torch.Tensor, target: torch.Tensor, scale: float,
                   beta: float = 0.01) -> torch.Tensor:
    """Mean smooth-L1 of ``(|x_t - c| - target) / scale`` (``beta`` in the same units).
    ``x_t`` [N, 3] (with gradient), ``target`` [N] (detached here)."""
    r = (ray_depth(x_t, center) - target.detach()) / float(scale)
    return F.smooth_l1_loss(r, torch.zeros_like(r), beta=float(beta))


def motion_positions(model: Model4D, t: float, idx: torch.Tensor, static: torch.Tensor | None | str = "model"
                     ) -> torch.Tensor:
    """Positions [M, 3] of the Gaussians ``idx`` [M] at capture time ``t``, with the canonical
    attributes detached (only the motion -- trajectories and / or deformation field -- keeps
    a gradient), as :meth:`Model4D.attributes` computes them (static rows do not move).
    ``static``: bool [N] of the static rows (default: the model's, recomputed)."""
    return motion_frames(model, t, idx, static)[0]


def motion_frames(model: Model4D, t: float, idx: torch.Tensor, static: torch.Tensor | None | str = "model"
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """(positions [M, 3], quaternions [M, 4], unnormalised) of the Gaussians ``idx`` at ``t``:
    :func:`motion_positions` with the rotations too (engine.train.between_rigidity)."""
    g = model.gaussians
    means, quats = g.means.detach()[idx], g.quats.detach()[idx]
    if isinstance(static, str):
        static = model.effective_static_mask()
    moving = None if static is None else ~static[idx]
    if model.use_deformation and model.trajectory is not None:
        knots = model.trajectory["knots"]
        cols = [c for c, _ in traj.segment_weights(knots, t)]
        for name in (TRAJ_MEANS, TRAJ_QUATS):  # row subsets: the whole curves' read hook (lazy Adam)
            traj.before_read(getattr(g, name), cols)
        dm = traj.evaluate(getattr(g, TRAJ_MEANS)[idx], knots, t)
        dq = traj.evaluate(getattr(g, TRAJ_QUATS)[idx], knots, t)
        if moving is not None:
            keep = moving.to(dm.dtype)[:, None]
            dm, dq = dm * keep, dq * keep
        means, quats = means + dm, quats + dq
    if model.use_deformation and model.deformation is not None and (moving is None or bool(moving.any())):
        d = model.deformation(means, quats, g.log_scales.detach()[idx], g.opacity_logits.detach()[idx], t,
                              mask=moving)
        means, quats = d["means"], d["quats"]
    return means, quats


# ------------------------------------------------------------------------------ trainer term
class AlongRayPrior:
    """Per-run state of the term: the spike guidance it rides on and the RGB instants."""

    def __init__(self, trainer, guidance):
        self.trainer = trainer
        self.guidance = guidance
        self.cfg = trainer.cfg
        if self.cfg.along_ray_curve not in CURVES:
            raise ValueError(f"unknown along_ray_curve {self.cfg.along_ray_curve!r}; choose one of {', '.join(CURVES)}")
        self.times = list(trainer.frame_times)
        self.last: dict = {}  # diagnostics of the last evaluation (gaussians, mean |residual| in extent units)

    def center(self, device) -> torch.Tensor:
        """The spike camera's centre: the stream's pose, else its co-located RGB camera's."""
        g = self.guidance
        stream = g.stream
        if stream is not None and getattr(stream, "c2w", None) is not None:
            c = torch.as_tensor(stream.view(0.0).center, dtype=torch.float32)
        else:
            c = self.trainer.items[g.by_cam[g.colocated][0]]["campos"]
        return c.to(device).reshape(3)

    def bracket(self, t: float, t_admitted: float):
        """({"prev"?, "a", "b", "next"?} -> seconds) around ``t``, only with instants the time
        curriculum has admitted; None when the right end is not admitted yet."""
        ts = self.times
        k = max(i for i, v in enumerate(ts) if v <= t + 1e-12) if ts and ts[0] <= t else None
        if k is None or k + 1 >= len(ts) or ts[k + 1] > t_admitted + 1e-9:
            return None
        out = {"a": ts[k], "b": ts[k + 1]}
        if k >= 1:
            out["prev"] = ts[k - 1]
        if k + 2 < len(ts) and ts[k + 2] <= t_admitted + 1e-9:
            out["next"] = ts[k + 2]
        return out

    def __call__(self, ctx):
        hit = self.guidance.deforming_spike_view(ctx)
        if hit is None:
            return None
        b, model = hit
        tr = ctx.trainer
        t = float(b["instant"].time)
        admitted = admitted_time(ctx, self.times[-1])
        times = self.bracket(t, admitted)
        if times is None:
            return None
        visible = b["meta"]["radii"][0] > 0 if "meta" in b else None
        if visible is None:
            return None
        static = model.effective_static_mask()
        touched = visible if static is None else visible & ~static
        idx = touched.nonzero(as_tuple=True)[0]
        cap = int(self.cfg.along_ray_max_gaussians)
        if cap > 0 and idx.numel() > cap:  # a random subset bounds the cost per step
            gen = torch.Generator(device="cpu").manual_seed(tr.seed * 7919 + ctx.step)
            idx = idx[torch.randperm(idx.numel(), generator=gen)[:cap].to(idx.device)]
        if idx.numel() == 0:
            return None
        c = self.center(idx.device)
        curve = self.cfg.along_ray_curve
        keys = ("a", "b") if curve == "linear" else tuple(times)
        with torch.no_grad():
            depths = {k: ray_depth(motion_positions(model, times[k], idx, static), c) for k in keys}
        target = along_ray_target({k: times[k] for k in keys}, depths, t, curve)
        x_t = motion_positions(model, t, idx, static)
        extent = max(float(tr.extent), 1e-9)
        loss = along_ray_loss(x_t, c, target, extent, float(self.cfg.along_ray_beta))
        with torch.no_grad():
            res = (ray_depth(x_t, c) - target).abs().mean() / extent
        self.last = {"gaussians": int(idx.numel()), "residual": float(res) if math.isfinite(float(res)) else None}
        return loss


def along_ray_factory(trainer) -> list:
    """The along-ray term for a (non rgb_only) run with ``lambda_along_ray > 0`` and a spike
    loss (it needs the spike guidance's between-frame render); nothing otherwise."""
    cfg = trainer.cfg
    guid = spike_view_guidance(trainer)
    if cfg.lambda_along_ray <= 0 or guid is None:
        return []
    prior = AlongRayPrior(trainer, guid)
    trainer.along_ray = prior
    return [LossTerm("along_ray", float(cfg.lambda_along_ray), prior, stages=("deform",))]
