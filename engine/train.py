"""Coarse-stage 4D Gaussian training on the train cameras' RGB frames.

Two stages (4D Gaussians, Wu et al.; paper's "coarse DSR + L_frame"):

1. static warm-up: canonical Gaussians only, trained on every RGB frame;
2. deformation: a HexPlane deformation field (``engine.deformation``) deforms the
   canonical Gaussians to each frame's capture time; both are optimised jointly.

Each step renders one random train frame (a per-epoch permutation, seeded by ``seed``) and
minimises a list of loss terms (:class:`LossTerm`): L1 + lambda * D-SSIM on the RGB frame
plus the deformation regularisers. The spike branch adds its own terms through
:func:`register_loss_factory` (ignored with ``rgb_only=True``).

The schedule is a function of the total step count only (``engine.presets``). With a
wall-clock budget (``seconds``), the step count is chosen up front from the measured cost of
a few throw-away steps on a copy of the model, then re-estimated once from the rate of the
real steps after ~5% of the run (the loaded-machine case), while the run is still in the
static stage so that every schedule stays consistent (both estimates are in run.json); the
budget is also enforced as a hard stop (reported as ``stopped_by_budget``).

Skipping what a scene does not need (issue 6; switches of :class:`TrainConfig`, all off
by default, checkpointed with the run so that cancel + resume equals an uninterrupted run):

* ``freeze_static``: CPOStream freezing (:class:`engine.freezing.TrainFreezer`): Gaussians
  that stay still for K motion checks skip the deformation field;
* ``early_stop``: stop (status ``finished``, ``stopped_early`` in the summary and run.json)
  when the PSNR on a few held-out eval frames (train frames when the capture has none)
  stops improving (:class:`EarlyStop`);
* ``cull_frustum``: prune Gaussians outside every train frustum after the first step, at
  the start of the deformation stage and after each densification (:func:`frustum_cull_mask`).
"""
from __future__ import annotations

import contextlib
import copy
import datetime as _dt
import math
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from .checkpoint import CHECKPOINT, load_checkpoint, save_checkpoint, update_run_json
from .deformation import make_field
from .errors import RunError
from .freezing import TrainFreezer
from .gaussians import GaussianModel
from .init_points import initial_points, stereo_depth_priors
from .model import TRAJ_MEANS, TRAJ_QUATS, Model4D, default_device, near_plane_for_extent, view_tensors
from .presets import TrainConfig, get_preset

# ---------------------------------------------------------------------------------- losses


@dataclass
class LossTerm:
    """One term of the training objective: ``weight * fn(ctx)``; ``fn`` may return None."""

    name: str
    weight: float
    fn: Callable[["StepContext"], torch.Tensor | None]
    stages: tuple = ("static", "deform")


@dataclass
class StepContext:
    trainer: "Trainer"
    step: int
    stage: str
    item: dict            # the train frame: view tensors + "image" [1,H,W,3] + "index"
    rgb: torch.Tensor     # rendered [1,H,W,3]
    alpha: torch.Tensor   # [1,H,W,1]
    meta: dict
    attrs: dict           # deformed Gaussians used for the render


_LOSS_FACTORIES: list[Callable[["Trainer"], list[LossTerm]]] = []


def register_loss_factory(factory: Callable[["Trainer"], list[LossTerm]]) -> None:
    """Add a factory ``(trainer) -> [LossTerm]`` called when a (non rgb_only) run starts."""
    if factory not in _LOSS_FACTORIES:
        _LOSS_FACTORIES.append(factory)


@contextlib.contextmanager
def loss_factory_registered(factory):
    """``with loss_factory_registered(f): train(...)`` -- ``f`` takes part in every (non
    rgb_only) run started in the block and is removed afterwards, even on error."""
    register_loss_factory(factory)
    try:
        yield factory
    finally:
        with contextlib.suppress(ValueError):
            _LOSS_FACTORIES.remove(factory)


def _l1(ctx: StepContext):
    return (ctx.rgb - ctx.item["image"]).abs().mean()


def _dssim(ctx: StepContext):
    from pytorch_msssim import ssim

    pred = ctx.rgb.permute(0, 3, 1, 2)
    gt = ctx.item["image"].permute(0, 3, 1, 2)
    if min(pred.shape[-2:]) < 11:
        return None
    return 1.0 - ssim(pred, gt, data_range=1.0, size_average=True)


def _block_l1(ctx: StepContext):
    """L1 between 4x4 average-pooled images (the paper's block supervision, Eq. 20): a
    wider basin of attraction for displaced objects than per-pixel L1."""
    k = ctx.trainer.cfg.block_size
    pred = ctx.rgb.permute(0, 3, 1, 2)
    if min(pred.shape[-2:]) < 2 * k:
        return None
    gt = ctx.item["image"].permute(0, 3, 1, 2)
    return (F.avg_pool2d(pred, k) - F.avg_pool2d(gt, k)).abs().mean()


def _stereo_depth(ctx: StepContext):
    """Relative L1 between the rendered expected depth and confident stereo depth (the
    calibrated pair sees every RGB instant twice: geometry the eval viewpoint relies on)."""
    target = ctx.item.get("stereo_depth")
    depth = ctx.meta.get("depths")
    if target is None or depth is None:
        return None
    m = ctx.item["stereo_mask"]
    gt = target[m]
    return ((depth[0, ..., 0][m] - gt).abs() / gt).mean()


def _deform_reg(ctx: StepContext):
    d = ctx.trainer.model.deformation
    cfg = ctx.trainer.cfg
    if d is None or not ctx.trainer.model.use_deformation:
        return None
    smooth = cfg.spike_time_smooth_weight if ctx.trainer.guided else cfg.time_smooth_weight
    return d.regularization(cfg.tv_weight, smooth, cfg.time_l1_weight)


def _traj_reg(ctx: StepContext):
    """Mean squared inner-point residual of the trajectories / extent^2 (engine.scene.trajectory):
    with zero residuals the in-between motion is the Catmull-Rom curve through the RGB
    instants; only the between-frame losses have a reason to bend it."""
    from .scene.trajectory import inner_residuals

    m = ctx.trainer.model
    if m.trajectory is None or not m.use_deformation:
        return None
    d = inner_residuals(getattr(m.gaussians, TRAJ_MEANS))
    if d.numel() == 0:
        return None
    return (d ** 2).sum(-1).mean() / ctx.trainer.extent ** 2


def _rigidity(ctx: StepContext):
    """Luiten et al.'s local rigidity (rigidity + rotation similarity + isometry over kNN,
    engine.scene.rigidity) between the canonical Gaussians and the render's instant; the
    neighbours are recomputed when the Gaussians change (densification) or every 100 steps."""
    from .scene.rigidity import knn_neighbours, rigidity_losses

    tr, g = ctx.trainer, ctx.trainer.model.gaussians
    cache = getattr(tr, "_rigidity_nbrs", None)
    if cache is None or cache[0] != g.num_gaussians or ctx.step - cache[1] >= 100:
        nbr, w = knn_neighbours(g.means.detach(), int(tr.cfg.rigidity_k))
        cache = tr._rigidity_nbrs = (g.num_gaussians, ctx.step, nbr, w)
    parts = rigidity_losses(g.means.detach(), g.quats.detach(), ctx.attrs["means"], ctx.attrs["quats"],
                            cache[2], cache[3])
    return (parts["rigid"] + parts["rot"] + parts["iso"]) / tr.extent


MOTIONS = ("hexplane", "trajectory", "trajectory+hexplane")


def default_loss_terms(cfg: TrainConfig) -> list[LossTerm]:
    terms = [LossTerm("l1", 1.0 - cfg.lambda_dssim, _l1)]
    if cfg.lambda_dssim > 0:
        terms.append(LossTerm("dssim", cfg.lambda_dssim, _dssim))
    if cfg.lambda_block > 0:
        terms.append(LossTerm("block_l1", cfg.lambda_block, _block_l1))
    if cfg.lambda_depth > 0:
        terms.append(LossTerm("stereo_depth", cfg.lambda_depth, _stereo_depth))
    terms.append(LossTerm("deform_reg", 1.0, _deform_reg, stages=("deform",)))
    if cfg.rigidity_weight > 0:
        terms.append(LossTerm("rigidity", cfg.rigidity_weight, _rigidity, stages=("deform",)))
    if "trajectory" in getattr(cfg, "motion", "hexplane") and cfg.traj_inner_weight > 0:
        terms.append(LossTerm("traj_reg", cfg.traj_inner_weight, _traj_reg, stages=("deform",)))
    return terms


# ---------------------------------------------------------------------------------- helpers
def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _load_capture(capture):
    if isinstance(capture, (str, os.PathLike)):
        from .capture import load_capture

        return load_capture(capture)
    return capture


def _capture_path(capture) -> str | None:
    root = getattr(capture, "root", None)
    return str(Path(root).resolve()) if root is not None else None


def train_frames(capture) -> list:
    """The RGB frames of cameras with role 'train'."""
    out = []
    for f in capture.frames:
        cam = capture.cameras.get(f.camera) if hasattr(capture, "cameras") else None
        if cam is not None and getattr(cam, "role", "train") != "train":
            continue
        out.append(f)
    return out


def scene_extent(points: np.ndarray, centers: np.ndarray) -> float:
    """Scene radius: the larger of 3DGS's camera radius and the points' robust half-diagonal."""
    cam = 0.0
    if len(centers):
        c = centers.mean(0)
        cam = float(np.linalg.norm(centers - c, axis=1).max()) * 1.1
    pts = 0.0
    if len(points) >= 4:
        lo, hi = np.percentile(points, 2, axis=0), np.percentile(points, 98, axis=0)
        pts = float(np.linalg.norm(hi - lo)) / 2
    return max(cam, pts, 1e-3)


def robust_bounds(points: np.ndarray, margin: float = 0.1):
    lo, hi = np.percentile(points, 1, axis=0), np.percentile(points, 99, axis=0)
    pad = (hi - lo) * margin + 1e-6
    return lo - pad, hi + pad


def _config_key(cfg: TrainConfig, seed: int, rgb_only: bool, capture_path: str | None) -> dict:
    d = cfg.to_dict()
    for k in ("checkpoint_every_s", "log_every", "expected_seconds"):
        d.pop(k, None)
    return {"config": d, "seed": int(seed), "rgb_only": bool(rgb_only), "capture": capture_path}


# ---------------------------------------------------------------------------------- trainer
class Trainer:
    """Holds the data, model and optimisers of one run; :meth:`step` does one iteration."""

    def __init__(self, capture, cfg: TrainConfig, *, device, seed: int = 0, rgb_only: bool = False,
                 total_steps: int | None = None):
        self.capture = capture
        self.cfg = cfg
        self.device = torch.device(device)
        self.seed = int(seed)
        self.rgb_only = bool(rgb_only)
        self.total_steps = int(total_steps or cfg.iterations)
        frames = train_frames(capture)
        if not frames:
            raise RunError(_capture_path(capture) or "capture", "the capture has no train RGB frames")
        self.items = []
        for i, f in enumerate(frames):
            vt = view_tensors(capture.view(f), self.device)
            img = np.asarray(f.load_rgb(), dtype=np.float32)[..., :3]
            if img.shape[:2] != (vt["height"], vt["width"]):
                raise RunError(getattr(f, "path", "frame"), f"image is {img.shape[1]}x{img.shape[0]} but its camera "
                               f"says {vt['width']}x{vt['height']}")
            vt["image"] = torch.from_numpy(np.ascontiguousarray(img)).to(self.device)[None]
            vt["index"] = i
            vt["camera"] = f.camera
            vt["synthetic"] = bool(getattr(f, "extra", {}).get("synthetic"))  # baseline frames
            self.items.append(vt)
        if cfg.lambda_depth > 0:
            priors = stereo_depth_priors(capture, frames)
            for f, it in zip(frames, self.items):
                if id(f) in priors and priors[id(f)][1].sum() >= 16:
                    d, ok = priors[id(f)]
                    it["stereo_depth"] = torch.from_numpy(d).to(self.device)
                    it["stereo_mask"] = torch.from_numpy(ok).to(self.device)
        self.frame_times = sorted({round(float(f.time), 9) for f in frames})
        tr = getattr(capture, "time_range", None)
        self.time_range = (float(tr[0]), float(tr[1])) if tr else (min(self.frame_times), max(self.frame_times))
        self.model: Model4D | None = None
        self.deform_opt: torch.optim.Adam | None = None
        self.loss_terms = default_loss_terms(cfg)
        # extension hooks (the spike branch): called with the trainer once the deformation
        # field exists (new run or resumed), e.g. to set ``field.fine_encoder`` and call
        # :meth:`add_deformation_parameters`; ``fine_provider(item) -> [N, W] | None`` feeds
        # the Eq. 10 fine feature of each step's render.
        self.deformation_hooks: list[Callable[["Trainer"], None]] = []
        self.fine_provider: Callable[[dict], torch.Tensor | None] | None = None
        if not self.rgb_only:
            for factory in _LOSS_FACTORIES:
                self.loss_terms.extend(factory(self) or [])
        self.init_info: dict = {}
        self.extent = 1.0
        self.last_losses: dict = {}
        self._carried_to = -math.inf  # latest frame time whose motion was carried forward
        self.carry_info: list[dict] = []  # trajectories carried by scene flow (traj_carry="flow")
        # skipping (issue 6): owned by the trainer, checkpointed in state()
        self.freeze: TrainFreezer | None = TrainFreezer.from_config(self, cfg) if cfg.freeze_static else None
        self.early_stop: EarlyStop | None = EarlyStop.for_trainer(self) if cfg.early_stop else None
        self.cull: FrustumCuller | None = FrustumCuller() if cfg.cull_frustum else None

    # ---- schedule (a pure function of total_steps) --------------------------------------
    @property
    def static_steps(self) -> int:
        return int(round(self.cfg.static_fraction * self.total_steps))

    def stage_of(self, step: int) -> str:
        return "static" if step < self.static_steps else "deform"

    def densify_schedule(self):
        lo = int(self.cfg.densify_from * self.total_steps)
        hi = int(self.cfg.densify_until * self.total_steps)
        every = max(1, min(self.cfg.densify_every, max(1, (hi - lo) // 3)))
        return lo, hi, every

    def time_window(self, step: int) -> float:
        """Latest capture time trained on at ``step`` (time curriculum of the deformation stage).

        The static warm-up sees the first RGB instant only (``static_frames="first"``, the
        canonical scene is the scene at t0) or every frame (``"all"``). The deformation stage
        then widens the window from t0 to the last frame over ``time_curriculum`` of its steps,
        so each newly admitted frame starts from the motion of the frames before it (fast
        objects move less than their size between neighbouring frames, so gradients find them).
        """
        t0, t1 = self.frame_times[0], self.frame_times[-1]
        if self.stage_of(step) == "static":
            return t0 if self.cfg.static_frames == "first" and self.cfg.static_fraction < 1.0 else t1
        if self.cfg.time_curriculum <= 0:
            return t1
        s0 = self.static_steps
        p = (step - s0) / max(1, self.total_steps - s0)
        return t0 + (t1 - t0) * min(1.0, p / self.cfg.time_curriculum)

    def frame_pool(self, step: int) -> list[int]:
        t_max = self.time_window(step) + 1e-9
        pool = [i for i, it in enumerate(self.items) if it["time"] <= t_max]
        return pool or list(range(len(self.items)))

    def frame_index(self, step: int) -> int:
        pool = self.frame_pool(step)
        if len(pool) == len(self.items):  # every frame once per epoch
            n = len(pool)
            epoch, k = divmod(step, n)
            return int(np.random.default_rng([self.seed, epoch]).permutation(n)[k])
        return pool[int(np.random.default_rng([self.seed, step, 7]).integers(len(pool)))]

    # ---- setup --------------------------------------------------------------------------
    def init_model(self) -> None:
        torch.manual_seed(self.seed)
        cfg = self.cfg
        pts = initial_points(self.capture, cfg.init, max_points=cfg.init_max_points, n_random=cfg.init_random_points,
                             seed=self.seed, fill_stride=cfg.init_fill_stride)
        self.init_info = {"method": pts.method, **pts.info, "num_points": int(len(pts.xyz))}
        centers = np.stack([np.linalg.inv(it["viewmat"][0].cpu().numpy().astype(np.float64))[:3, 3] for it in self.items])
        self.extent = scene_extent(pts.xyz, centers)
        g = GaussianModel(pts.xyz, pts.rgb, sh_degree=cfg.sh_degree, init_opacity=cfg.init_opacity, device=self.device)
        g.setup_optimizer(cfg, self.extent)
        self.model = Model4D(g, None, background=cfg.background, near_plane=near_plane_for_extent(self.extent))
        self.model.use_deformation = False
        self._watch_gaussians()

    def _watch_gaussians(self) -> None:
        """With freezing on, route the Gaussians' ``_replace`` (densify, prune, cull) through
        the freezer so that its per-Gaussian state follows the rows."""
        g = self.model.gaussians
        if self.freeze is None or "_replace" in vars(g):
            return
        freeze, replace = self.freeze, type(g)._replace

        def _replace(new_tensors, keep, n_new, _g=g):
            replace(_g, new_tensors, keep, n_new)
            freeze.follow(keep, n_new)

        g._replace = _replace

    def start_deformation(self) -> None:
        """Start the motion of ``cfg.motion``: per-Gaussian trajectories (issue 11,
        engine.scene.trajectory) and / or the deformation field around the current canonical
        Gaussians (with both, the field is a residual on top of the trajectories)."""
        motion = self.cfg.motion
        if motion not in MOTIONS:
            raise ValueError(f"unknown motion representation {motion!r}; choose one of {', '.join(MOTIONS)}")
        self.model.use_deformation = True
        if "trajectory" in motion:
            self.model.add_trajectories(self.frame_times, self.cfg.lr_traj * self.extent, self.cfg.lr_traj_quats)
        if "hexplane" not in motion:
            return
        g = self.model.gaussians
        means = g.means.detach().cpu().numpy()
        lo, hi = robust_bounds(means)
        cfg = self.cfg
        if self.between_supervised():  # spike / block colour losses constrain the field between frames
            cfg = cfg.replace(time_resolution_per_frame=cfg.spike_time_resolution_per_frame)
        field = make_field(cfg, lo, hi, self.time_range, self.frame_times, seed=self.seed).to(self.device)
        self.model.deformation = field
        self.model.use_deformation = True
        self._make_deform_opt()
        for hook in self.deformation_hooks:
            hook(self)

    @property
    def guided(self) -> bool:
        """:meth:`between_supervised`, computed once per run."""
        if getattr(self, "_guided", None) is None:
            self._guided = self.between_supervised()
        return self._guided

    def between_supervised(self) -> bool:
        """True when the spike guidance supervises instants between the RGB frames."""
        if self.rgb_only:
            return False
        from .spike_guidance import spike_stream_info

        if spike_stream_info(self.capture) is None:  # no spikes: plain RGB training, no flag needed
            return False
        return self.cfg.spike_loss_weight > 0 or self.cfg.block_loss_weight > 0

    def _make_deform_opt(self) -> None:
        d = self.model.deformation
        groups = [{"params": d.grid_parameters(), "lr": self.cfg.lr_grid, "name": "grid"},
                  {"params": d.mlp_parameters(), "lr": self.cfg.lr_mlp, "name": "mlp"}]
        self.deform_opt = torch.optim.Adam(groups, lr=0.0)

    def _carry_forward(self, t_max: float) -> None:
        """When the time window grows past frames not trained yet, start their deformation
        from the latest trained one: copy that time cell of every time plane forward."""
        admitted = [t for t in self.frame_times if t <= t_max + 1e-9]
        t_prev = admitted[-1]
        if t_prev <= self._carried_to:
            return
        d = self.model.deformation
        last = self._carried_to
        self._carried_to = t_prev
        if last == -math.inf:
            return
        if self.model.trajectory is not None:  # later knots start from the motion so far
            from .scene.trajectory import extrapolate_junctions

            knots = self.model.trajectory["knots"]
            li = int(np.argmin([abs(k - last) for k in knots]))
            g = self.model.gaussians
            mode = "velocity" if self.cfg.traj_carry == "flow" else self.cfg.traj_carry
            extrapolate_junctions(getattr(g, TRAJ_MEANS).data, knots, li, li + 1, mode=mode)
            extrapolate_junctions(getattr(g, TRAJ_QUATS).data, knots, li, li + 1, mode="hold")
            if self.cfg.traj_carry == "flow" and li + 1 < len(knots):
                self.carry_info.append(self._carry_by_flow(knots, li, li + 1))
        if d is None:
            return
        u = (d.normalize_time(last) + 1.0) / 2.0
        with torch.no_grad():
            for p in d.grid.temporal:
                T = p.shape[-2]
                c = min(T - 1, int(math.ceil(u * (T - 1) - 1e-6)))
                if c < T - 1:
                    p[:, :, c + 1:, :] = p[:, :, c:c + 1, :]

    # ---- trajectories: scene flow from per-instant stereo + optical flow (issue 11) -----------
    def _carry_by_flow(self, knots, i: int, j: int) -> dict:
        """Move the junction ``j`` of every Gaussian that is the visible surface at knot ``i``
        in a train camera along that camera's optical flow, lifted by the stereo depth at
        ``knots[j]`` (engine.geometry.scene_flow); later knots hold it. Returns counts."""
        from .geometry.scene_flow import carry_by_flow, image_flow, propagate_to_hidden
        from .init_points import stereo_depth_priors

        frames = train_frames(self.capture)
        if getattr(self, "_stereo_priors", None) is None:
            self._stereo_priors = stereo_depth_priors(self.capture, frames)
        pri = self._stereo_priors
        g = self.model.gaussians
        with torch.no_grad():
            pos_i = self.model.attributes(knots[i])["means"].detach().cpu().numpy()
        todo = np.ones(len(pos_i), dtype=bool)
        still = np.zeros(len(pos_i), dtype=bool)
        delta = np.zeros_like(pos_i)
        by_cam: dict = {}
        for f in frames:
            by_cam.setdefault(f.camera, {})[round(float(f.time), 9)] = f
        for cam, at in by_cam.items():
            fa, fb = at.get(round(knots[i], 9)), at.get(round(knots[j], 9))
            if fa is None or fb is None or id(fa) not in pri or id(fb) not in pri:
                continue
            flow = image_flow(fa.load_rgb(), fb.load_rgb())
            new, ok, st = carry_by_flow(pos_i, self.capture.view(fa), flow, *pri[id(fa)], *pri[id(fb)],
                                        return_still=True)
            ok &= todo
            delta[ok] = new[ok] - pos_i[ok]
            todo &= ~ok
            still |= st
        n_flow = int((~todo).sum())
        if self.cfg.traj_carry_hidden > 0:  # hidden Gaussians follow their nearest decided neighbour
            delta, taken = propagate_to_hidden(pos_i, delta, ~todo | still,
                                               self.cfg.traj_carry_hidden * self.extent)
            todo &= ~(taken & (np.abs(delta).sum(1) > 0))
        carried = ~todo
        if carried.any():
            tm = getattr(g, TRAJ_MEANS).data
            idx = torch.from_numpy(np.nonzero(carried)[0]).to(tm.device)
            d = torch.from_numpy(delta[carried]).to(tm)
            for k in range(j, len(knots)):
                tm[idx, 3 * k] = tm[idx, 3 * i] + d
        return {"from": float(knots[i]), "to": float(knots[j]), "carried": int(carried.sum()),
                "by_flow": n_flow, "total": int(len(carried))}

    def add_deformation_parameters(self, params, lr: float, name: str = "extra") -> None:
        """For extensions (e.g. the spike fine encoder): optimise more parameters alongside."""
        if self.deform_opt is None:
            raise RuntimeError("the deformation stage has not started")
        self.deform_opt.add_param_group({"params": list(params), "lr": lr, "name": name})

    def _update_lrs(self, step: int) -> None:
        self.model.gaussians.update_learning_rate(step / max(1, self.total_steps - 1))
        s0 = self.static_steps
        p = min(1.0, max(0.0, (step - s0) / max(1, self.total_steps - s0 - 1)))
        if self.model.trajectory is not None:  # decays over the deformation stage, like the field
            for grp in self.model.gaussians.optimizer.param_groups:
                if grp["name"] == TRAJ_MEANS:
                    grp["lr"] = self.extent * math.exp(math.log(self.cfg.lr_traj) * (1 - p)
                                                       + math.log(self.cfg.lr_traj_final) * p)
        if self.deform_opt is not None:
            for grp in self.deform_opt.param_groups:
                if grp["name"] == "grid":
                    grp["lr"] = math.exp(math.log(self.cfg.lr_grid) * (1 - p) + math.log(self.cfg.lr_grid_final) * p)
                elif grp["name"] == "mlp":
                    grp["lr"] = math.exp(math.log(self.cfg.lr_mlp) * (1 - p) + math.log(self.cfg.lr_mlp_final) * p)

    # ---- one iteration --------------------------------------------------------------------
    def step(self, step: int) -> dict:
        cfg = self.cfg
        model = self.model
        g = model.gaussians
        stage = self.stage_of(step)
        if stage == "deform" and not model.use_deformation:
            self.start_deformation()
        if cfg.sh_degree > 0 and cfg.sh_step_fraction > 0:
            want = min(cfg.sh_degree, int(step / max(1, cfg.sh_step_fraction * self.total_steps)))
            while g.active_sh_degree < want:
                g.oneup_sh_degree()
        self._update_lrs(step)
        if stage == "deform" and self.cfg.time_curriculum > 0:
            self._carry_forward(self.time_window(step))
        item = self.items[self.frame_index(step)]
        fine = self.fine_provider(item) if (self.fine_provider is not None and stage == "deform") else None
        rgb, alpha, meta, attrs = model.render(item, fine=fine)
        means2d = meta.get("means2d")
        if means2d is not None and means2d.requires_grad:
            means2d.retain_grad()
        ctx = StepContext(self, step, stage, item, rgb, alpha, meta, attrs)
        total = 0.0
        losses = {}
        for term in self.loss_terms:
            if stage not in term.stages or term.weight == 0:
                continue
            val = term.fn(ctx)
            if val is None:
                continue
            losses[term.name] = float(val.detach())
            total = total + term.weight * val
        g.optimizer.zero_grad(set_to_none=True)
        if self.deform_opt is not None:
            self.deform_opt.zero_grad(set_to_none=True)
        total.backward()

        # densification statistics and schedule
        lo, hi, every = self.densify_schedule()
        if step < hi and means2d is not None and means2d.grad is not None:
            g.add_densification_stats(means2d.grad, meta["radii"], item["width"], item["height"])
        g.optimizer.step()
        if self.deform_opt is not None and stage == "deform":
            self.deform_opt.step()
        if self.freeze is not None and stage == "deform":  # observation module, on this render's rows
            self.freeze.after_step(step, item, rgb, meta)
        info = {}
        if lo <= step < hi and step > 0 and (step - lo) % every == 0 and step != lo:
            gen = torch.Generator(device="cpu").manual_seed(self.seed * 1000003 + step)
            info = g.densify_and_prune(grad_threshold=cfg.densify_grad_threshold, percent_dense=cfg.percent_dense,
                                       min_opacity=cfg.prune_opacity, max_world_scale=cfg.prune_big_world,
                                       max_gaussians=cfg.max_gaussians, generator=gen if self.device.type == "cpu" else None)
        if cfg.opacity_reset_every and step > 0 and step % cfg.opacity_reset_every == 0 and step < hi:
            g.reset_opacity()
        if self.cull is not None and (step == 0 or step == self.static_steps or info):
            self.cull(self, step)
        if self.freeze is not None and stage == "deform":  # prediction module (periodic motion checks)
            self.freeze.maybe_check(step)
        with torch.no_grad():
            mse = float(((rgb.detach().clamp(0, 1) - item["image"]) ** 2).mean())
        self.last_losses = losses
        return {"loss": float(total.detach()), "psnr": -10.0 * math.log10(max(mse, 1e-10)), "stage": stage,
                "losses": losses, "densify": info}

    # ---- state ------------------------------------------------------------------------------
    def state(self, step: int) -> dict:
        return {
            "model": self.model.state(),
            "deform_optimizer": None if self.deform_opt is None else self.deform_opt.state_dict(),
            "step": int(step),
            "total_steps": int(self.total_steps),
            "time_range": list(self.time_range),
            "frame_times": list(self.frame_times),
            "extent": self.extent,
            "init": self.init_info,
            "gaussians": self.model.gaussians.num_gaussians,
            "carried_to": self._carried_to,
            "skips": {"freeze": None if self.freeze is None else self.freeze.state_dict(),
                      "early_stop": None if self.early_stop is None else self.early_stop.state_dict(),
                      "cull": None if self.cull is None else self.cull.state_dict()},
        }

    def skip_summary(self) -> dict:
        """What the skip switches did (run.json / summary): only the enabled ones."""
        out = {}
        if self.freeze is not None:
            out["freeze"] = self.freeze.summary()
        if self.early_stop is not None:
            out["early_stop"] = self.early_stop.summary()
        if self.cull is not None:
            out["cull"] = self.cull.summary()
        return out

    def load_state(self, state: dict) -> int:
        self.total_steps = int(state["total_steps"])
        self.extent = float(state.get("extent", 1.0))
        self.init_info = state.get("init", {})
        self._carried_to = float(state.get("carried_to", -math.inf))
        self.model = Model4D.from_state(state["model"], self.cfg, device=self.device)
        if self.model.deformation is not None:
            self._make_deform_opt()
            for hook in self.deformation_hooks:
                hook(self)
            if state.get("deform_optimizer") is not None:
                self.deform_opt.load_state_dict(state["deform_optimizer"])
        skips = state.get("skips") or {}
        for name in ("freeze", "early_stop", "cull"):
            owner = getattr(self, name)
            if owner is not None and skips.get(name) is not None:
                owner.load_state_dict(skips[name])
        self._watch_gaussians()
        if self.freeze is not None:
            self.freeze.sync_mask()
        return int(state["step"])


# ---------------------------------------------------------------------------------- skipping
class EarlyStop:
    """Stop when the PSNR on a few held-out frames (the *proxy*) stops improving.

    The proxy is ``early_stop_proxy_frames`` eval frames of the capture, evenly spread over
    them (sorted by camera and time); a capture without eval frames falls back to as many
    train frames (``source == "train"``, noted in run.json). It is scored every
    ``early_stop_every_fraction`` of the steps (its cost counts in the run's wall time);
    training stops after ``early_stop_patience`` evaluations without a gain of
    ``early_stop_min_delta`` dB, once the deformation stage has run for
    ``early_stop_min_deform_fraction`` of its steps (before that only the best is tracked).
    """

    def __init__(self, frames: list[dict], names: list[str], source: str, *, patience: int = 3,
                 min_delta: float = 0.05, every_fraction: float = 0.05, min_deform_fraction: float = 0.25):
        self.frames = frames          # view tensors with "image" [1,H,W,3]
        self.names = names
        self.source = source          # "eval" | "train"
        self.patience = max(1, int(patience))
        self.min_delta = float(min_delta)
        self.every_fraction = float(every_fraction)
        self.min_deform_fraction = float(min_deform_fraction)
        self.history: list[dict] = []
        self.stopped_at: dict | None = None
        self.eval_seconds = 0.0
        self._next = 0
        self._best = -math.inf
        self._bad = 0

    @classmethod
    def for_trainer(cls, trainer: "Trainer") -> "EarlyStop":
        cfg, cap = trainer.cfg, trainer.capture
        n = max(1, int(cfg.early_stop_proxy_frames))
        evals = sorted(getattr(cap, "eval_frames", None) or [], key=lambda f: (f.camera, f.time))
        frames, names = [], []
        if evals:
            source = "eval"
            idx = np.linspace(0, len(evals) - 1, min(n, len(evals))).round().astype(int)
            for i in sorted(set(idx.tolist())):
                f = evals[i]
                vt = view_tensors(cap.view(f), trainer.device)
                img = np.asarray(f.load_rgb(), dtype=np.float32)[..., :3]
                vt["image"] = torch.from_numpy(np.ascontiguousarray(img)).to(trainer.device)[None]
                frames.append(vt)
                names.append(str(f.path))
        else:
            source = "train"
            order = sorted(range(len(trainer.items)), key=lambda i: (trainer.items[i]["time"], i))
            idx = np.linspace(0, len(order) - 1, min(n, len(order))).round().astype(int)
            for i in sorted(set(idx.tolist())):
                frames.append(trainer.items[order[i]])
                names.append(f"train:{trainer.items[order[i]]['camera']}@{trainer.items[order[i]]['time']:.6f}")
        return cls(frames, names, source, patience=cfg.early_stop_patience, min_delta=cfg.early_stop_min_delta,
                   every_fraction=cfg.early_stop_every_fraction,
                   min_deform_fraction=cfg.early_stop_min_deform_fraction)

    def every(self, total_steps: int) -> int:
        return max(1, int(self.every_fraction * total_steps))

    @torch.no_grad()
    def score(self, model: Model4D) -> float:
        from .metrics import psnr_from_mse

        was = model.training
        model.eval()
        ps = []
        for vt in self.frames:
            rgb = model.render(vt, render_depth=False)[0]
            ps.append(psnr_from_mse(float(((rgb.clamp(0, 1) - vt["image"]) ** 2).mean())))
        model.train(was)
        return float(np.mean(ps)) if ps else float("nan")

    def update(self, trainer: "Trainer", done: int) -> bool:
        """After ``done`` completed steps: evaluate when due; True when training should stop."""
        if self.stopped_at is not None:
            return True
        if done < self._next:
            return False
        total = trainer.total_steps
        self._next = done + self.every(total)
        s0 = trainer.static_steps
        deform_done = (done - s0) / max(1, total - s0)
        t0 = time.perf_counter()
        score = self.score(trainer.model)
        self.eval_seconds += time.perf_counter() - t0
        self.history.append({"step": done, "proxy_psnr": round(score, 4)})
        if trainer.stage_of(done - 1) != "deform" or deform_done < self.min_deform_fraction:
            self._best = max(self._best, score)
            return False
        if score > self._best + self.min_delta:
            self._best, self._bad = score, 0
            return False
        self._bad += 1
        if self._bad < self.patience:
            return False
        self.stopped_at = {"step": done, "total_steps": total, "proxy_psnr": round(score, 4),
                           "best_proxy_psnr": round(self._best, 4), "proxy": self.source}
        return True

    def state_dict(self) -> dict:
        return {"history": list(self.history), "stopped_at": self.stopped_at, "eval_seconds": self.eval_seconds,
                "next": self._next, "best": self._best, "bad": self._bad}

    def load_state_dict(self, state: dict) -> None:
        self.history = list(state.get("history", []))
        self.stopped_at = state.get("stopped_at")
        self.eval_seconds = float(state.get("eval_seconds", 0.0))
        self._next = int(state.get("next", 0))
        self._best = float(state.get("best", -math.inf))
        self._bad = int(state.get("bad", 0))

    def summary(self) -> dict:
        return {"proxy": self.source, "frames": list(self.names), "evaluations": len(self.history),
                "eval_seconds": round(self.eval_seconds, 3), "stopped_at": self.stopped_at,
                "history": list(self.history)}


def frustum_cull_mask(trainer: "Trainer", margin_px: float = 0.0, times=None) -> torch.Tensor:
    """bool [N]: Gaussians invisible (radius 0: behind, beyond the image box, or below 1/255
    opacity) in every train view, at the canonical positions and -- once the deformation
    field exists -- at ``times`` (default: the train frame times) as well."""
    from .raster.projection import project_gaussians

    model = trainer.model
    g = model.gaussians
    views = {}
    for it in trainer.items:
        key = tuple(np.round(it["viewmat"][0].cpu().numpy().ravel(), 6)) + (it["width"], it["height"])
        views.setdefault(key, it)
    with torch.no_grad():
        positions = [g.means.detach()]
        if model.deformation is not None and model.use_deformation:
            for t in (times if times is not None else trainer.frame_times):
                d = model.deformation(g.means, g.quats, g.log_scales, g.opacity_logits, float(t))
                positions.append(d["means"].detach())
        if model.trajectory is not None and model.use_deformation:  # per-Gaussian curves (issue 11)
            for t in (times if times is not None else trainer.frame_times):
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
    """Prune Gaussians outside every train frustum (:func:`frustum_cull_mask`). The trainer
    calls it after the first step, after the first deformation step and right after each
    densification (whose statistics were just reset, so pruning then does not disturb them);
    never below ``min_keep`` Gaussians."""

    EVENTS_KEEP = 50

    def __init__(self, min_keep: int = 16):
        self.min_keep = int(min_keep)
        self.pruned = 0
        self.events: list[dict] = []

    def __call__(self, trainer: "Trainer", step: int) -> int:
        g = trainer.model.gaussians
        mask = frustum_cull_mask(trainer)
        n = int(mask.sum())
        if not n or g.num_gaussians - n < self.min_keep:
            return 0
        g.prune(mask)
        if trainer.freeze is None:
            trainer.model.static_mask = None
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


# ---------------------------------------------------------------------------------- budget
def _measure_step_seconds(trainer: Trainer, n_static: int = 4, n_deform: int = 4) -> tuple[float, float]:
    """Median seconds per step in each stage, from throw-away steps on a copy of the model."""
    probe = copy.copy(trainer)
    probe.model = copy.deepcopy(trainer.model)
    vars(probe.model.gaussians).pop("_replace", None)  # the freezer's watch belongs to the real model
    probe.model.gaussians.setup_optimizer(trainer.cfg, trainer.extent)
    probe.deform_opt = None
    probe.freeze = probe.early_stop = probe.cull = None
    probe.total_steps = 10 ** 6
    times = {}
    for stage, n in (("static", n_static), ("deform", n_deform)):
        probe.cfg = copy.copy(trainer.cfg)
        probe.cfg.static_fraction = 1.0 if stage == "static" else 0.0
        # the whole capture time admitted: a step at the curriculum's start would skip the
        # spike branch's in-between render (engine.instants), and under-price every later step
        probe.cfg.time_curriculum = 0.0
        probe.cfg.densify_from = probe.cfg.densify_until = 2.0  # no densification in the probe
        times[stage] = []
        for i in range(n):
            t0 = time.perf_counter()
            probe.step(i)
            times[stage].append(time.perf_counter() - t0)
    med = lambda v: float(np.median(v[1:] if len(v) > 1 else v))  # noqa: E731 (first call warms up)
    return med(times["static"]), med(times["deform"])


def steps_for_budget(seconds: float, t_static: float, t_deform: float, cfg: TrainConfig,
                     growth: float = 1.5, reserve_s: float = 0.0) -> int:
    """Steps that fit in ``seconds`` given per-step costs (Gaussian growth factored in)."""
    per = (cfg.static_fraction * t_static + (1 - cfg.static_fraction) * t_deform) * growth
    return max(20, int((max(0.0, seconds - reserve_s)) / max(per, 1e-4)))


REESTIMATE_FRACTION = 0.05  # re-estimate the budget's step count after this share of the probe's estimate


def reestimate_at(total_steps: int) -> int:
    """Completed steps after which a budget run re-estimates its step count (>= 6, so that
    the rate excludes the first step and still averages a few)."""
    return max(6, int(math.ceil(REESTIMATE_FRACTION * total_steps)))


def reestimate_steps(trainer: Trainer, done: int, step_seconds: float, probe: dict, loop_seconds: float) -> dict:
    """The budget's step count from the measured seconds per (static) step of the real run.

    ``probe``: the up-front estimate (``static_step_s``, ``deform_step_s``); the deformation
    steps are scaled by the same factor as the static ones. Only while the run is still in
    the static stage (the schedules are fractions of the total): the new total is clamped so
    that the next step stays static. Returns the record for run.json (``total_steps`` is the
    new total, or the old one with ``skipped``)."""
    cfg = trainer.cfg
    old = trainer.total_steps
    scale = step_seconds / max(probe["static_step_s"], 1e-9)
    rec = {"at_step": int(done), "static_step_s": round(step_seconds, 5),
           "deform_step_s": round(probe["deform_step_s"] * scale, 5), "total_steps": old}
    if cfg.static_fraction <= 0 or done >= trainer.static_steps:
        rec["skipped"] = "the deformation stage has started (its schedule is a fraction of the total)"
        return rec
    new = steps_for_budget(loop_seconds, step_seconds, probe["deform_step_s"] * scale, cfg)
    new = max(new, done + 1)
    while int(round(cfg.static_fraction * new)) <= done:  # keep the next step in the static stage
        new += 1
        rec["clamped"] = True
    rec["total_steps"] = int(new)
    return rec


# ---------------------------------------------------------------------------------- train()
def train(capture, out_dir, *, preset: str = "fast", seconds: float | None = None, rgb_only: bool = False,
          resume: bool = True, device=None, seed: int = 0, progress=None, cancel=None,
          overrides: dict | None = None) -> dict:
    """Train a 4D Gaussian scene on ``capture`` (path or Capture) into ``out_dir``.

    Returns a summary dict (status finished | cancelled | failed, step, total_steps,
    train_seconds, num_gaussians, device, run_dir, final psnr/loss, init). See module doc.
    """
    dev = default_device(device)
    threads = torch.get_num_threads()
    if dev.type == "cpu":
        # Our tensors are small (N ~ 1e4): a second intra-op thread gains nothing when the
        # machine is idle and, with OpenMP spin-waits, costs 10x+ when the cores are shared.
        torch.set_num_threads(1)
    try:
        return _train(capture, out_dir, preset=preset, seconds=seconds, rgb_only=rgb_only, resume=resume, dev=dev,
                      seed=seed, progress=progress, cancel=cancel, overrides=overrides)
    finally:
        torch.set_num_threads(threads)


def _train(capture, out_dir, *, preset, seconds, rgb_only, resume, dev, seed, progress, cancel, overrides) -> dict:
    t_start = time.perf_counter()
    run_dir = Path(out_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    cap = _load_capture(capture)
    cfg = get_preset(preset, overrides)
    if cfg.baseline:  # two-stage baselines (paper Table 1): synthetic in-between training frames
        from .baselines import with_baseline

        cap = with_baseline(cap, cfg.baseline, per_interval=cfg.baseline_per_interval)
    torch.manual_seed(seed)
    np.random.seed(seed % (2 ** 32))
    cap_path = _capture_path(cap)
    key = _config_key(cfg, seed, rgb_only, cap_path)
    trainer = Trainer(cap, cfg, device=dev, seed=seed, rgb_only=rgb_only)

    start_step = 0
    prior_seconds = 0.0
    resumed = False
    ckpt_path = run_dir / CHECKPOINT
    if resume and ckpt_path.exists():
        try:
            state = load_checkpoint(run_dir, map_location=dev)
        except RunError:
            state = None
        if state is not None and state.get("config_key") == key:
            start_step = trainer.load_state(state)
            prior_seconds = float(state.get("train_seconds", 0.0))
            resumed = True
    budget_estimates = None
    if not resumed:
        trainer.init_model()
        if seconds is not None:
            t_s, t_d = _measure_step_seconds(trainer)
            elapsed = time.perf_counter() - t_start
            trainer.total_steps = steps_for_budget(seconds, t_s, t_d, cfg, reserve_s=elapsed + 1.0)
            budget_estimates = {"probe": {"static_step_s": round(t_s, 5), "deform_step_s": round(t_d, 5),
                                          "total_steps": trainer.total_steps}, "measured": None}
    total = trainer.total_steps
    budget_end = (t_start + float(seconds)) if seconds is not None else None
    skip_notes = {}
    if trainer.early_stop is not None:
        es = trainer.early_stop
        skip_notes["early_stop_proxy"] = {"source": es.source, "frames": list(es.names)}
        if es.source == "train":
            skip_notes["early_stop_proxy"]["note"] = ("the capture has no eval frames: the proxy is train frames "
                                                      "(it measures fit, not generalisation)")

    run_info = {
        "capture": cap_path, "preset": preset, "config": cfg.to_dict(), "overrides": overrides or {},
        "seed": seed, "rgb_only": rgb_only, "device": str(dev), "status": "running", "step": start_step,
        "total_steps": total, "train_seconds": prior_seconds, "created": _now(), "time_range": list(trainer.time_range),
        "init": trainer.init_info, "seconds_budget": seconds, "resumed_from": start_step if resumed else None,
        "host": platform.node(), **skip_notes,
    }
    if budget_estimates is not None:
        run_info["budget_estimates"] = budget_estimates
    if resumed:
        old = {}
        try:
            from .checkpoint import read_run_json

            old = read_run_json(run_dir)
        except RunError:
            pass
        run_info["created"] = old.get("created", run_info["created"])
    update_run_json(run_dir, **run_info)

    def snapshot(step: int, status: str, train_seconds: float) -> None:
        st = trainer.state(step)
        st.update({"config_key": key, "config": cfg.to_dict(), "train_seconds": train_seconds, "status": status,
                   "preset": preset, "seed": seed})
        save_checkpoint(run_dir, st)

    status = "finished"
    stopped_by_budget = False
    early = trainer.early_stop
    stopped_early = early.stopped_at if early is not None else None  # a resumed run that had stopped
    loop_t0 = time.perf_counter()
    last_ckpt = loop_t0
    step = start_step
    t_first = None  # after the first step of this call (the re-estimate's rate excludes it)
    reestimate_step = reestimate_at(total) if budget_estimates is not None else None
    out = {"loss": float("nan"), "psnr": float("nan")}
    try:
        while step < total and stopped_early is None:
            if cancel is not None and cancel.is_set():
                status = "cancelled"
                break
            if budget_end is not None and time.perf_counter() > budget_end and step > start_step:
                stopped_by_budget = True
                break
            out = trainer.step(step)
            step += 1
            if early is not None and early.update(trainer, step):
                stopped_early = early.stopped_at
            now = time.perf_counter()
            if t_first is None:
                t_first = now
            if step == reestimate_step:
                rec = reestimate_steps(trainer, step, (now - t_first) / max(1, step - 1), budget_estimates["probe"],
                                       budget_end - loop_t0 - 1.0)
                budget_estimates["measured"] = rec
                if rec["total_steps"] != total:
                    total = trainer.total_steps = rec["total_steps"]
                    if early is not None:
                        early._next = min(early._next, step + early.every(total))
                update_run_json(run_dir, budget_estimates=budget_estimates, total_steps=total)
            if progress is not None:
                el = now - loop_t0
                rate = el / max(1, step - start_step)
                progress({"step": step, "total_steps": total, "stage": out["stage"], "loss": out["loss"],
                          "psnr": out["psnr"], "elapsed_s": prior_seconds + (now - t_start),
                          "eta_s": rate * (total - step), "num_gaussians": trainer.model.gaussians.num_gaussians})
            if now - last_ckpt >= cfg.checkpoint_every_s and step < total:
                snapshot(step, "running", prior_seconds + now - t_start)
                update_run_json(run_dir, step=step, train_seconds=prior_seconds + now - t_start)
                last_ckpt = time.perf_counter()
    except BaseException as exc:
        train_seconds = prior_seconds + time.perf_counter() - t_start
        update_run_json(run_dir, status="failed", step=step, train_seconds=train_seconds,
                        error=f"{exc.__class__.__name__}: {exc}")
        raise
    train_seconds = prior_seconds + time.perf_counter() - t_start
    snapshot(step, status, train_seconds)
    skips = trainer.skip_summary()
    if trainer.carry_info:  # trajectories carried by scene flow (issue 11)
        update_run_json(run_dir, trajectory_carry=trainer.carry_info)
    summary = {
        "status": status, "step": step, "total_steps": total, "train_seconds": round(train_seconds, 3),
        "num_gaussians": trainer.model.gaussians.num_gaussians, "device": str(dev), "run_dir": str(run_dir.resolve()),
        "preset": preset, "loss": out.get("loss"), "psnr": out.get("psnr"), "init": trainer.init_info,
        "stopped_by_budget": stopped_by_budget, "resumed_from": start_step if resumed else None,
        "stopped_early": stopped_early, "skips": skips,
    }
    if budget_estimates is not None:
        summary["budget_estimates"] = budget_estimates
    update_run_json(run_dir, status=status, step=step, total_steps=total, train_seconds=train_seconds,
                    num_gaussians=summary["num_gaussians"], stopped_by_budget=stopped_by_budget,
                    stopped_early=stopped_early, skips=skips, finished=_now())
    return summary


def _register_spike_guidance() -> None:
    """BulletTime4D spike guidance (spike + block colour losses, fine branch): engine.spike_guidance."""
    from .spike_guidance import guidance_factory

    register_loss_factory(guidance_factory)


_register_spike_guidance()
