"""Freezing static Gaussians (CPOStream-style prediction + observation modules).

CPOStream (Fig. 2 of its paper) splits Gaussians into *to-be-frozen* and
*to-be-optimised* before each frame: the **prediction module** freezes a Gaussian that was
*inactive* (its displacement below a threshold) in each of the last ``K`` checks; the
**observation module** wakes frozen Gaussians that fall into regions that suddenly change.
Here the same two modules decide which Gaussians skip the 4D deformation field:

* a frozen Gaussian is rendered with its canonical attributes at every instant -- it costs
  nothing in the deformation field and cannot flicker (its render is time-invariant);
* :class:`Freezer` holds the state; it knows nothing about the run. ``update(motion)``
  takes per-Gaussian motion measured at a periodic check (deltas [N,3] or magnitudes [N]),
  ``wake(mask)`` / ``observe(scores)`` un-freeze, ``resize_on_densify`` follows clone /
  split / prune, ``state_dict`` / ``load_state_dict`` checkpoint it;
* :func:`deformation_motion` measures the motion (world units, or pixels through the train
  cameras) of every Gaussian under a deformation field over sample instants;
* :func:`residual_scores` projects an image residual back to Gaussians through ``means2d``
  (the observation module); :func:`abrupt_mask` is CPOStream's "moving now but not in the
  last K checks" mask;
* the flicker that freezing removes is measured by :mod:`engine.evaluate.flicker`.

:class:`TrainFreezer` is the run's side (``TrainConfig.freeze_static``): it runs the
periodic checks in the deformation stage, sets ``Model4D.static_mask`` and is checkpointed
with the run.
"""
from __future__ import annotations

import numpy as np
import torch

# ----------------------------------------------------------------------------- state

class Freezer:
    """Per-Gaussian frozen flags from motion measured at periodic checks.

    ``k_checks``: a Gaussian freezes after ``k_checks`` consecutive checks with motion
    <= ``motion_eps`` (CPOStream's K). ``wake_residual``: :meth:`observe` wakes frozen
    Gaussians whose observation score is above it. Non-finite motion counts as motion (a
    Gaussian is never frozen on a NaN).
    """

    def __init__(self, num_gaussians: int, k_checks: int = 3, motion_eps: float = 0.1,
                 wake_residual: float = 0.1, device="cpu"):
        if k_checks < 1:
            raise ValueError("k_checks must be >= 1")
        self.k_checks = int(k_checks)
        self.motion_eps = float(motion_eps)
        self.wake_residual = float(wake_residual)
        self.device = torch.device(device)
        n = int(num_gaussians)
        self.streak = torch.zeros(n, dtype=torch.int32, device=self.device)  # consecutive quiet checks
        self.frozen = torch.zeros(n, dtype=torch.bool, device=self.device)
        self.checks = 0
        self.total_woken = 0
        self.last_motion: torch.Tensor | None = None

    # -------------------------------------------------------------- basic properties
    @property
    def num_gaussians(self) -> int:
        return int(self.frozen.shape[0])

    @property
    def num_frozen(self) -> int:
        return int(self.frozen.sum())

    @property
    def fraction_frozen(self) -> float:
        return self.num_frozen / max(1, self.num_gaussians)

    # -------------------------------------------------------------- prediction module
    @staticmethod
    def motion_magnitude(motion) -> torch.Tensor:
        """[N] magnitudes from deltas [N,D] (L2 norm) or magnitudes [N]."""
        m = torch.as_tensor(motion)
        if m.dim() == 2:
            m = m.float().norm(dim=-1)
        elif m.dim() != 1:
            raise ValueError(f"motion must be [N] or [N,D], got shape {tuple(m.shape)}")
        return m.float()

    def update(self, motion) -> dict:
        """One check: Gaussians with motion <= eps extend their quiet streak, others reset it;
        a streak of ``k_checks`` freezes. Returns counts (frozen, newly_frozen, unfrozen, active)."""
        m = self.motion_magnitude(motion).to(self.device)
        if m.shape[0] != self.num_gaussians:
            raise ValueError(f"motion has {m.shape[0]} entries but the freezer tracks {self.num_gaussians} "
                             "Gaussians (call resize_on_densify after densification)")
        active = ~(m <= self.motion_eps)  # NaN compares False -> active
        self.streak = torch.where(active, torch.zeros_like(self.streak), self.streak + 1)
        new_frozen = self.streak >= self.k_checks
        newly = int((new_frozen & ~self.frozen).sum())
        unfrozen = int((self.frozen & ~new_frozen).sum())
        self.frozen = new_frozen
        self.checks += 1
        self.last_motion = m.detach()
        return {"frozen": self.num_frozen, "newly_frozen": newly, "unfrozen": unfrozen,
                "active": int(active.sum()), "check": self.checks}

    # -------------------------------------------------------------- observation module
    def wake(self, mask) -> int:
        """Un-freeze Gaussians where ``mask`` (bool [N]) is True; their quiet streak restarts."""
        mask = torch.as_tensor(mask, dtype=torch.bool, device=self.device)
        if mask.shape[0] != self.num_gaussians:
            raise ValueError(f"wake mask has {mask.shape[0]} entries, expected {self.num_gaussians}")
        woken = int((mask & self.frozen).sum())
        self.frozen = self.frozen & ~mask
        self.streak = torch.where(mask, torch.zeros_like(self.streak), self.streak)
        self.total_woken += woken
        return woken

    def observe(self, scores) -> int:
        """Wake frozen Gaussians whose observation score (e.g. :func:`residual_scores`) is
        above ``wake_residual``. Returns how many woke."""
        s = torch.as_tensor(scores, dtype=torch.float32, device=self.device)
        return self.wake(~(s <= self.wake_residual))  # non-finite scores wake too

    # -------------------------------------------------------------- densification
    def resize_on_densify(self, keep_mask=None, num_new: int | None = None, *, new_count: int | None = None,
                          parent_index=None) -> None:
        """Follow a densification step.

        ``keep_mask`` (bool [N_old]): surviving old rows, in order; ``num_new`` rows appended
        after them. ``parent_index`` (long [num_new], indices into the OLD rows): new rows
        inherit their parent's state (clones of a frozen Gaussian stay frozen); without it
        new rows start active. ``new_count`` alone (no mask): rows only appended (or, if it
        equals the current count, nothing changed); shrinking needs a mask.
        """
        n_old = self.num_gaussians
        if keep_mask is None:
            if new_count is None and num_new is None:
                raise ValueError("give keep_mask, num_new or new_count")
            target = int(new_count) if new_count is not None else n_old + int(num_new)
            if target < n_old:
                raise ValueError(f"cannot shrink from {n_old} to {target} Gaussians without a keep_mask")
            keep = torch.ones(n_old, dtype=torch.bool, device=self.device)
            add = target - n_old
        else:
            keep = torch.as_tensor(keep_mask, dtype=torch.bool, device=self.device)
            if keep.shape[0] != n_old:
                raise ValueError(f"keep_mask has {keep.shape[0]} entries, expected {n_old}")
            add = int(num_new or 0)
            if new_count is not None and int(keep.sum()) + add != int(new_count):
                raise ValueError(f"keep_mask keeps {int(keep.sum())} + {add} new != new_count {new_count}")
        if parent_index is not None:
            pi = torch.as_tensor(parent_index, dtype=torch.long, device=self.device)
            if pi.shape[0] != add:
                raise ValueError(f"parent_index has {pi.shape[0]} entries, expected {add}")
            new_streak, new_frozen = self.streak[pi], self.frozen[pi]
        else:
            new_streak = torch.zeros(add, dtype=torch.int32, device=self.device)
            new_frozen = torch.zeros(add, dtype=torch.bool, device=self.device)
        self.streak = torch.cat([self.streak[keep], new_streak])
        self.frozen = torch.cat([self.frozen[keep], new_frozen])
        if self.last_motion is not None:
            self.last_motion = torch.cat([self.last_motion[keep], torch.full((add,), float("nan"), device=self.device)])

    # -------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict:
        return {"k_checks": self.k_checks, "motion_eps": self.motion_eps, "wake_residual": self.wake_residual,
                "streak": self.streak.cpu(), "frozen": self.frozen.cpu(), "checks": self.checks,
                "total_woken": self.total_woken}

    def load_state_dict(self, state: dict) -> None:
        self.k_checks = int(state["k_checks"])
        self.motion_eps = float(state["motion_eps"])
        self.wake_residual = float(state["wake_residual"])
        self.streak = torch.as_tensor(state["streak"], dtype=torch.int32).to(self.device)
        self.frozen = torch.as_tensor(state["frozen"], dtype=torch.bool).to(self.device)
        if self.streak.shape != self.frozen.shape:
            raise ValueError("freezer state: streak and frozen have different lengths")
        self.checks = int(state.get("checks", 0))
        self.total_woken = int(state.get("total_woken", 0))
        self.last_motion = None

    @classmethod
    def from_state_dict(cls, state: dict, device="cpu") -> "Freezer":
        f = cls(0, device=device)
        f.load_state_dict(state)
        return f


# ----------------------------------------------------------------------------- motion

def _quat_angle(q0: torch.Tensor, q1: torch.Tensor) -> torch.Tensor:
    """Rotation angle (rad) between raw (unnormalised) wxyz quaternions, safely."""
    a = q0 / q0.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    b = q1 / q1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    dot = (a * b).sum(-1).abs().clamp(max=1.0)
    return 2.0 * torch.acos(dot)


@torch.no_grad()
def deformed_over_time(field, means, quats, log_scales, opacity_logits, times) -> dict:
    """Deformed means [T,N,3], unit quats [T,N,4] and scales [T,N,3] at each of ``times``."""
    ms, qs, ss = [], [], []
    for tt in times:
        d = field(means.detach(), quats.detach(), log_scales.detach(), opacity_logits.detach(), float(tt))
        ms.append(d["means"])
        q = d["quats"]
        qs.append(q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12))
        ss.append(torch.exp(d["log_scales"]))
    return {"means": torch.stack(ms), "quats": torch.stack(qs), "scales": torch.stack(ss)}


@torch.no_grad()
def deformation_motion(field, means, quats, log_scales, opacity_logits, times, *, viewmats=None, Ks=None,
                       relative: str = "mean", chunk: int = 65536) -> torch.Tensor:
    """Per-Gaussian motion under a deformation field over ``times``.

    ``relative="mean"`` (default): the temporal spread -- max over ``times`` of
    ``|mean(t) - mean_avg| + angle(q(t), q_avg) * max_scale + max|scale(t) - scale_avg|``
    -- so a time-independent offset (a Gaussian the field merely moved once) counts as
    static; ``relative="canonical"``: the same against the canonical attributes. World
    units, or pixels when ``viewmats [C,4,4]`` / ``Ks [C,3,3]`` are given (world motion x
    fx / depth, max over the cameras; cameras the Gaussian is behind are ignored).
    """
    if relative not in ("mean", "canonical"):
        raise ValueError("relative must be 'mean' or 'canonical'")
    means = means.detach()
    n = means.shape[0]
    out = torch.zeros(n, dtype=torch.float32, device=means.device)
    if len(times) == 0 or n == 0:
        return out
    for s in range(0, n, chunk):
        sl = slice(s, min(n, s + chunk))
        d = deformed_over_time(field, means[sl], quats[sl], log_scales[sl], opacity_logits[sl], times)
        if relative == "mean":
            m0 = d["means"].mean(0)
            q0 = d["quats"][len(times) // 2]
            s0 = d["scales"].mean(0)
        else:
            m0 = means[sl]
            q0 = quats[sl].detach()
            s0 = torch.exp(log_scales[sl].detach())
        max_scale = s0.max(dim=-1).values
        mv = (d["means"] - m0[None]).norm(dim=-1)                                     # [T,n]
        mv = mv + _quat_angle(q0[None].expand_as(d["quats"]), d["quats"]) * max_scale[None]
        mv = mv + (d["scales"] - s0[None]).abs().max(dim=-1).values
        out[sl] = torch.nan_to_num(mv.float(), nan=float("inf")).max(dim=0).values
    if viewmats is not None:
        R = viewmats[:, :3, :3].to(means.dtype)
        t = viewmats[:, :3, 3].to(means.dtype)
        z = torch.einsum("cij,nj->cni", R, means)[..., 2] + t[:, None, 2]         # [C,N]
        f = Ks[:, 0, 0].to(means.dtype)[:, None]
        pix = torch.where(z > 1e-6, f / z.clamp_min(1e-6), torch.zeros_like(z)).max(dim=0).values
        out = out * pix.float()
    return out


@torch.no_grad()
def bake_static(gaussians, field, mask, times) -> int:
    """Write the time-averaged deformation of the Gaussians in ``mask`` into their canonical
    parameters (means, quats, log-scales), so that freezing them (skipping the field) does
    not make them jump. Returns how many were baked."""
    idx = torch.as_tensor(mask, dtype=torch.bool).nonzero(as_tuple=True)[0]
    if idx.numel() == 0 or len(times) == 0:
        return 0
    g = gaussians
    d = deformed_over_time(field, g.means[idx], g.quats[idx], g.log_scales[idx], g.opacity_logits[idx], times)
    g.means.data[idx] = d["means"].mean(0).to(g.means.dtype)
    g.quats.data[idx] = d["quats"][len(times) // 2].to(g.quats.dtype)
    g.log_scales.data[idx] = torch.log(d["scales"].mean(0).clamp_min(1e-30)).to(g.log_scales.dtype)
    return int(idx.numel())


# ----------------------------------------------------------------------------- observation

def blur_box(img: torch.Tensor, radius: int) -> torch.Tensor:
    """Box blur of [H,W] (mean over a (2r+1)^2 window, zero-padded, normalised)."""
    if radius <= 0:
        return img
    x = img[None, None].float()
    k = 2 * radius + 1
    num = torch.nn.functional.avg_pool2d(x, k, stride=1, padding=radius, count_include_pad=False)
    return num[0, 0]


def residual_map(rendered, target, blur: int = 1) -> torch.Tensor:
    """Per-pixel photometric residual [H,W]: mean |rendered - target| over channels, box-blurred."""
    r = torch.as_tensor(rendered).float()
    g = torch.as_tensor(target).float()
    while r.dim() > 3:
        r, g = r[0], g[0]
    res = (r - g).abs().mean(-1) if r.dim() == 3 else (r - g).abs()
    return blur_box(res, blur)


def residual_scores(residual: torch.Tensor, means2d: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """Project a residual map [H,W] back to Gaussians: the residual at each visible
    Gaussian's projected centre (``means2d`` [N,2] px, ``radii`` [N], 0 = culled -> score 0)."""
    res = torch.as_tensor(residual).float()
    H, W = res.shape
    m = means2d.detach().reshape(-1, 2)
    r = radii.detach().reshape(-1)
    x = torch.nan_to_num(m[:, 0], nan=-1.0).floor().long()
    y = torch.nan_to_num(m[:, 1], nan=-1.0).floor().long()
    inside = (r > 0) & (x >= 0) & (x < W) & (y >= 0) & (y < H)
    out = torch.zeros(m.shape[0], dtype=torch.float32, device=res.device)
    out[inside] = res[y[inside], x[inside]]
    return out


def abrupt_mask(current: torch.Tensor, history: list, threshold: float) -> torch.Tensor:
    """CPOStream Eq. 6: pixels above ``threshold`` now and in none of the ``history`` maps."""
    now = torch.as_tensor(current) > threshold
    for h in history:
        now = now & ~(torch.as_tensor(h) > threshold)
    return now


# ----------------------------------------------------------------------------- run side

# the observation module wakes a frozen Gaussian under a larger residual; the motion checks are spread
# over the deformation stage, the first after START_FRACTION of it
WAKE_RESIDUAL = 0.15
CHECKS_PER_STAGE = 20
START_FRACTION = 0.3

class TrainFreezer:
    """The freezing switch of :mod:`engine.train.loop.trainer` (``TrainConfig.freeze_static``): a
    :class:`Freezer` run by the run it belongs to, in the deformation stage.

    The run calls :meth:`after_step` after each optimiser step (before densification)
    and :meth:`maybe_check` after it. Together they:

    * every ``check_every`` steps (default: ``checks_per_stage`` checks over the deformation
      stage) after ``start_fraction`` of the deformation stage, measure each Gaussian's
      motion in pixels over the train frame times (:func:`deformation_motion`) -- the frozen
      ones are measured too, through the field, so that the prediction module can also
      release them -- and ``update`` the freezer;
    * every step (once something is frozen), wake frozen Gaussians under a high photometric
      residual of the step's frame (observation module);
    * bake the time-averaged deformation of newly frozen Gaussians into their canonical
      parameters (:func:`bake_static`), so freezing does not make them jump;
    * keep ``Model4D.static_mask`` equal to the frozen mask (frozen Gaussians skip the
      deformation field: ``DeformationField.forward(mask=...)``);
    * follow densification and pruning (:meth:`follow`: keep mask + new rows; the run
      routes the Gaussians' ``_replace`` through it).

    :meth:`state_dict` / :meth:`load_state_dict` go into the run's checkpoint, so a
    resumed run freezes exactly as an uninterrupted one. Statistics are in :attr:`log`.
    """

    LOG_KEEP = 50

    def __init__(self, run, *, k_checks: int = 3, motion_eps_px: float = 0.3, wake_residual: float = 0.15,
                 check_every: int | None = None, checks_per_stage: int = 20, start_fraction: float = 0.3,
                 max_times: int = 8, observe: bool = True, bake: bool = True):
        self.run = run
        self.k_checks = int(k_checks)
        self.motion_eps_px = float(motion_eps_px)
        self.wake_residual = float(wake_residual)
        # None: a fixed number of checks per deformation stage (schedules are step-count relative)
        self.check_every = None if check_every is None else max(1, int(check_every))
        self.checks_per_stage = max(1, int(checks_per_stage))
        self.start_fraction = float(start_fraction)
        self.max_times = int(max_times)
        self.observe_enabled = bool(observe)
        self.bake = bool(bake)
        self.freezer: Freezer | None = None
        self.log: list[dict] = []
        self.num_checks = 0
        self.woken = 0

    @classmethod
    def from_config(cls, run, cfg) -> "TrainFreezer":
        return cls(run, k_checks=cfg.skip.freeze_k_checks, motion_eps_px=cfg.skip.freeze_motion_eps_px,
                   wake_residual=WAKE_RESIDUAL, checks_per_stage=CHECKS_PER_STAGE, start_fraction=START_FRACTION)

    # -------------------------------------------------------------- bookkeeping
    def _active(self) -> bool:
        m = self.run.model
        # not with per-Gaussian trajectories (issue 11): freezing bakes the field's motion
        # only, a frozen Gaussian would lose its trajectory offset
        return (m is not None and m.deformation is not None and m.use_deformation
                and getattr(m, "trajectory", None) is None)

    def _ensure(self) -> Freezer:
        g = self.run.model.gaussians
        if self.freezer is None or self.freezer.num_gaussians != g.num_gaussians:
            self.freezer = Freezer(g.num_gaussians, self.k_checks, self.motion_eps_px, self.wake_residual,
                                   device=g.means.device)
        return self.freezer

    def follow(self, keep, n_new: int) -> None:
        """The Gaussians were replaced: ``keep`` (bool over the old rows, None = all) survive,
        ``n_new`` rows were appended (they start active)."""
        f = self.freezer
        if f is None:
            return
        n_old = f.num_gaussians if keep is None else int(keep.shape[0])
        if n_old != f.num_gaussians:  # lost track: start over
            self.freezer = None
        else:
            f.resize_on_densify(keep, int(n_new))
        self.sync_mask()

    def sync_mask(self) -> None:
        model = self.run.model
        if self.freezer is None or self.freezer.num_frozen == 0:
            model.static_mask = None
        else:
            model.static_mask = self.freezer.frozen.clone()

    def _times(self):
        ts = list(self.run.frame_times)
        if len(ts) > self.max_times:
            idx = np.linspace(0, len(ts) - 1, self.max_times).round().astype(int)
            ts = [ts[i] for i in idx]
        return ts

    def schedule(self) -> tuple[int, int]:
        """(first check, steps between checks) in the run's virtual steps (engine.train.loop.schedule)."""
        tr = self.run
        s0 = tr.schedule.static_end(tr.cfg.schedule.static_fraction)
        deform_steps = max(1, tr.schedule.nominal - s0)
        start = s0 + int(self.start_fraction * deform_steps)
        every = self.check_every or max(1, deform_steps // self.checks_per_stage)
        return start, every

    # -------------------------------------------------------------- per step
    @torch.no_grad()
    def after_step(self, step: int, item: dict, rgb: torch.Tensor, meta: dict) -> None:
        """Observation module on this step's render (before densification changes the rows)."""
        if not self._active():
            return
        f = self._ensure()
        if self.observe_enabled and f.num_frozen and meta.get("means2d") is not None:
            means2d, radii = meta["means2d"][0], meta["radii"][0]
            if means2d.shape[0] == f.num_gaussians:
                res = residual_map(rgb.detach(), item["image"], blur=1)
                woken = f.observe(residual_scores(res, means2d, radii))
                self.woken += woken
                if woken and self.log:
                    self.log[-1]["woken"] = self.log[-1].get("woken", 0) + woken
        self.sync_mask()

    @torch.no_grad()
    def maybe_check(self, step: int) -> dict | None:
        """Prediction module: a motion check at the scheduled steps. Returns its record."""
        if not self._active():
            return None
        start, every = self.schedule()
        if self.run.schedule.mark_at(step, start, every) is None:
            return None
        f = self._ensure()
        tr = self.run
        g = tr.model.gaussians
        field = tr.model.deformation
        views = {}
        for it in tr.items:
            views.setdefault(it["camera"], it)
        vm = torch.cat([v["viewmat"] for v in views.values()])
        K = torch.cat([v["K"] for v in views.values()])
        times = self._times()
        motion = deformation_motion(field, g.means, g.quats, g.log_scales, g.opacity_logits, times,
                                    viewmats=vm, Ks=K)
        before = f.frozen.clone()
        info = f.update(motion)
        if self.bake:
            info["baked"] = bake_static(g, field, f.frozen & ~before, times)
        info.update(step=step, num_gaussians=g.num_gaussians, fraction=round(f.fraction_frozen, 4))
        self.num_checks += 1
        self.log.append(info)
        del self.log[:-self.LOG_KEEP]
        self.sync_mask()
        return info

    # -------------------------------------------------------------- checkpoints / report
    def state_dict(self) -> dict:
        return {"freezer": None if self.freezer is None else self.freezer.state_dict(), "log": list(self.log),
                "num_checks": self.num_checks, "woken": self.woken}

    def load_state_dict(self, state: dict) -> None:
        fs = state.get("freezer")
        dev = self.run.model.gaussians.means.device if self.run.model is not None else "cpu"
        self.freezer = None if fs is None else Freezer.from_state_dict(fs, device=dev)
        self.log = list(state.get("log", []))
        self.num_checks = int(state.get("num_checks", len(self.log)))
        self.woken = int(state.get("woken", 0))

    def summary(self) -> dict:
        f = self.freezer
        return {"checks": self.num_checks, "frozen": 0 if f is None else f.num_frozen,
                "num_gaussians": 0 if f is None else f.num_gaussians,
                "fraction_frozen": 0.0 if f is None else round(f.fraction_frozen, 4),
                "woken": self.woken,
                "mean_fraction_frozen": (round(float(np.mean([r["fraction"] for r in self.log])), 4) if self.log
                                         else 0.0)}


def frozen_deformation_cost(num_gaussians: int, num_frozen: int) -> float:
    """Fraction of the deformation field's per-step work left when ``num_frozen`` skip it."""
    return (num_gaussians - num_frozen) / max(1, num_gaussians) if num_gaussians else 0.0


__all__ = ["Freezer", "TrainFreezer", "deformation_motion", "deformed_over_time", "bake_static", "residual_map",
           "residual_scores", "abrupt_mask", "blur_box", "frozen_deformation_cost"]
