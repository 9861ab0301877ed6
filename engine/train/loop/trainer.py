"""The trainer: one run's data, model and optimisers; :meth:`Trainer.step` is one iteration.

Two stages (4D Gaussians, Wu et al.; the paper's "coarse DSR + L_frame"): a static warm-up of the
canonical Gaussians on the first RGB instant, then the deformation stage, which admits the RGB
instants in time order and moves the Gaussians by per-Gaussian curves and / or the HexPlane field.
Each step renders one train frame (a per-epoch permutation seeded by ``seed``) and minimises the
loss terms (:class:`engine.train.losses.terms.LossTerm`) of the frame, the geometry and the loss
factories in :data:`LOSS_FACTORIES` (the spike guidance; none with ``rgb_only=True``). The parts
of training see the run through :attr:`Trainer.run` (:class:`engine.train.run_context.RunContext`).

Every schedule reads one clock (:class:`engine.train.loop.schedule.Schedule`); the loop around the
trainer (resume, budget, checkpoints, run.json) is :mod:`engine.train.loop.run`. The skipping parts
(``skip.freeze_static``, ``skip.early_stop``, ``skip.cull_frustum``; engine.train.skipping) are
checkpointed with the run, so cancel + resume equals an uninterrupted run.
"""
from __future__ import annotations

import copy
import dataclasses
import math
from typing import Callable, Sequence

import numpy as np
import torch

from ...errors import RunError
from ...geometry.depth_priors import FusionCache, stereo_depth_priors
from ...geometry.init_points import initial_points
from ...scene.deformation import (
    LR_GRID_FINAL,
    LR_MLP_FINAL,
    TIME_CELLS_PER_FRAME,
    TIME_CELLS_PER_FRAME_GUIDED,
    make_field,
)
from ...scene.dropout import GaussianDropout
from ...scene.gaussians import GaussianModel
from ...scene.model import TRAJ_MEANS, TRAJ_QUATS, Model4D, near_plane_for_extent, view_tensors
from ...scene.trajectory import extrapolate_junctions, gradient_sink
from ..config import TrainConfig, block_weight
from ..frames.coarse import CoarseItems
from ..guidance.quiet_curves import quiet_curves_factory
from ..guidance.spike_flow import spike_flow_factory
from ..guidance.spike_guidance import guidance_factory, spike_stream_info
from ..losses.geometry_losses import attach_stereo, geometry_post_step_hooks
from ..losses.terms import (
    MOTIONS,
    LossTerm,
    StepContext,
    default_loss_terms,
    frame_item_fields,
    renders_at_instants_only,
)
from ..run_context import RunContext
from ..skipping.culling import FrustumCuller
from ..skipping.early_stop import EarlyStop, hold_back_frames
from ..skipping.freezing import TrainFreezer
from .scene_setup import capture_path, densify_cap, inside_box, robust_bounds, scene_extent, scene_points, train_frames
from .schedule import Schedule
from .settle import settle_lr

# The loss factories of a run: each ``(run context) -> [LossTerm]`` is called when a (non rgb_only) run starts. The
# spike guidance (Eq. 4-23) returns nothing without a spike stream (such captures train as RGB-only); the spike-view
# flow term and the quiet-curves hook (after the flow fit; issue 11) ride on its between instants.
LossFactory = Callable[[RunContext], "list[LossTerm] | None"]
LOSS_FACTORIES: tuple[LossFactory, ...] = (guidance_factory, spike_flow_factory, quiet_curves_factory)

PRUNE_BIG_WORLD = 0.2  # densification prunes Gaussians whose largest scale exceeds this x extent (3DGS)


# ---------------------------------------------------------------------------------- trainer
def _shared(name: str) -> property:
    """A trainer attribute that lives in its run context (what the parts of training see)."""
    return property(lambda self: getattr(self.run, name), lambda self, v: setattr(self.run, name, v),
                    doc=f"``self.run.{name}`` (engine.train.run_context.RunContext)")


class Trainer:
    """Holds the data, model and optimisers of one run; :meth:`step` does one iteration.

    The parts of training -- loss factories and terms, hooks, carries, births, skipping -- get
    :attr:`run` (a :class:`RunContext`), never the trainer itself."""

    cfg = _shared("cfg")
    capture = _shared("capture")
    device = _shared("device")
    seed = _shared("seed")
    items = _shared("items")
    frame_times = _shared("frame_times")
    time_range = _shared("time_range")
    fusion_cache = _shared("fusion_cache")
    rgb_only = _shared("rgb_only")
    schedule = _shared("schedule")
    model = _shared("model")
    extent = _shared("extent")
    deform_opt = _shared("deform_opt")
    post_step_hooks = _shared("post_step_hooks")
    deformation_hooks = _shared("deformation_hooks")
    fine_provider = _shared("fine_provider")
    guided = _shared("guided")
    init_info = property(lambda self: self.run.info.setdefault("init", {}),
                         lambda self, v: self.run.info.__setitem__("init", v), doc="run.json's init record")
    birth_info = property(lambda self: self.run.info.get("births", []), doc="run.json's births record")

    def __init__(self, capture, cfg: TrainConfig, *, device, seed: int = 0, rgb_only: bool = False,
                 total_steps: int | None = None, loss_factories: Sequence[LossFactory] = LOSS_FACTORIES):
        # one SGBM fusion (FusionCache) for init points, depth priors and the flow carry
        self.run = RunContext(cfg, capture, torch.device(device), int(seed), [], [], (0.0, 0.0), FusionCache(capture),
                              rgb_only=bool(rgb_only))
        self._bind_run()
        self.total_steps = int(total_steps or cfg.schedule.steps or cfg.schedule.iterations)
        frames = train_frames(capture)
        if not frames:
            raise RunError(capture_path(capture) or "capture", "the capture has no train RGB frames")
        # early stopping scores frames held back from training, never the eval frames that
        # every reported metric is computed on (issue 13)
        self.held_back: list = []
        if cfg.skip.early_stop:
            frames, self.held_back = hold_back_frames(frames)
        for i, f in enumerate(frames):
            vt = view_tensors(capture.view(f), self.device)
            img = np.asarray(f.load_rgb(), dtype=np.float32)[..., :3]
            if img.shape[:2] != (vt["height"], vt["width"]):
                raise RunError(getattr(f, "path", "frame"), f"image is {img.shape[1]}x{img.shape[0]} but its camera "
                               f"says {vt['width']}x{vt['height']}")
            vt["image"] = torch.from_numpy(np.ascontiguousarray(img)).to(self.device)[None]
            vt["index"] = i
            vt["camera"] = f.camera
            vt.update(frame_item_fields(f, cfg, self.device))  # synthetic (baseline) frames: knot, weight
            self.items.append(vt)
        self.coarse = CoarseItems()
        if cfg.losses.depth > 0 or cfg.losses.flat > 0:  # issue 14: fused SGBM depth at every RGB instant
            priors = stereo_depth_priors(capture, frames, fusion_cache=self.fusion_cache)
            self.depth_prior_note = priors.pop("_unavailable", None)  # recorded in run.json's init
            attach_stereo(self.items, [priors.get(id(f)) for f in frames], planes=cfg.losses.flat > 0)
        self.frame_times = sorted({round(float(it["time"]), 9) for it in self.items if it["knot"]})
        tr = getattr(capture, "time_range", None)
        self.time_range = (float(tr[0]), float(tr[1])) if tr else (min(self.frame_times), max(self.frame_times))
        self.model: Model4D | None = None
        self.deform_opt: torch.optim.Adam | None = None
        self.loss_terms = default_loss_terms(cfg)
        self.post_step_hooks = geometry_post_step_hooks(cfg)  # issue 14: (run, step, item, meta)
        # extension hooks (the spike branch): called with the run context once the deformation
        # field exists (new run or resumed), e.g. to set ``field.fine_encoder`` and call
        # :meth:`add_deformation_parameters`; ``fine_provider(item) -> [N, W] | None`` feeds
        # the Eq. 10 fine feature of each step's render.
        self.deformation_hooks: list[Callable[[RunContext], None]] = []
        self.fine_provider: Callable[[dict], torch.Tensor | None] | None = None
        self.guided = self.between_supervised()
        if not self.rgb_only:
            for factory in loss_factories:
                self.loss_terms.extend(factory(self.run) or [])
        self.init_info: dict = {}
        self.extent = 1.0
        self.field_box = None  # (lo[3], hi[3]) of the non-backdrop init points; see init_model
        self.last_losses: dict = {}
        self._carried_to = -math.inf  # latest frame time whose motion was carried forward
        self.carry_info: list[dict] = []  # trajectories carried by scene flow (traj_carry="flow")
        # skipping: owned by the trainer, checkpointed in state()
        self.freeze: TrainFreezer | None = TrainFreezer.from_config(self.run, cfg) if cfg.skip.freeze_static else None
        self.run.parts["freeze"] = self.freeze  # culling keeps the freezer's rows in step
        self.early_stop: EarlyStop | None = (EarlyStop.for_run(self.run, self.held_back) if cfg.skip.early_stop
                                            else None)
        self.cull: FrustumCuller | None = FrustumCuller() if cfg.skip.cull_frustum else None

    def _bind_run(self) -> None:
        """The run context's answers come from this trainer (its stage, its time window)."""
        self.run.stage_of = self.stage_of
        self.run.time_window = self.time_window
        self.run.add_deformation_parameters = self.add_deformation_parameters

    def probe_copy(self) -> "Trainer":
        """A shallow copy with a run context of its own (the budget's throw-away steps replace its
        model, optimisers and clock without touching this trainer's)."""
        probe = copy.copy(self)
        # its own report (births in a probe step are not the run's); the caches and hooks are shared
        probe.run = dataclasses.replace(self.run, info=copy.deepcopy(self.run.info))
        probe._bind_run()
        return probe

    def __getattr__(self, name: str):
        # the parts a factory registered (spike_guidance, spike_flow, quiet_curves) read as attributes
        run = self.__dict__.get("run")
        if run is not None and name in run.parts:
            return run.parts[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    # ---- schedule: every one reads one clock, continuous under budget re-plans (engine.train.loop.schedule) ----
    total_steps = property(lambda self: self.schedule.total,
                           lambda self, n: setattr(self, "schedule", Schedule.plan(n, self.cfg.schedule.iterations)),
                           doc="Real steps planned; setting it plans afresh (mid-run re-plans: schedule.replan)")

    static_steps = property(lambda self: self.schedule.static_steps(self.cfg.schedule.static_fraction))

    def stage_of(self, step: int) -> str:
        return "static" if step < self.static_steps else "deform"

    def time_window(self, step: int) -> float:
        """Latest capture time trained on at ``step`` (time curriculum of the deformation stage).

        The static warm-up sees the first RGB instant only (the canonical scene is the scene at
        t0; warming up on every frame was measured and dropped). The deformation stage
        then widens the window from t0 to the last frame over ``time_curriculum`` of its steps,
        so each newly admitted frame starts from the motion of the frames before it (fast
        objects move less than their size between neighbouring frames, so gradients find them).
        """
        t0, t1 = self.frame_times[0], self.frame_times[-1]
        if self.stage_of(step) == "static":
            return t0 if self.cfg.schedule.static_fraction < 1.0 else t1
        if self.cfg.schedule.time_curriculum <= 0:
            return t1
        p = self.schedule.deform_progress(step, self.cfg.schedule.static_fraction)
        return t0 + (t1 - t0) * min(1.0, p / self.cfg.schedule.time_curriculum)

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
        pts = initial_points(self.capture, cfg.init.method, max_points=cfg.init.max_points,
                             n_random=cfg.init.random_points, seed=self.seed, backdrop=cfg.init.backdrop,
                             fusion_cache=self.fusion_cache, planes=cfg.init.planes)
        self.init_info = {"method": pts.method, **pts.info, "num_points": int(len(pts.xyz)),
                          "max_gaussians": densify_cap(cfg.densify.max_gaussians, self.items)[0]}
        if getattr(self, "depth_prior_note", None):
            self.init_info["depth_prior_unavailable"] = self.depth_prior_note
        centers = np.stack([np.linalg.inv(it["viewmat"][0].cpu().numpy().astype(np.float64))[:3, 3]
                            for it in self.items])
        core = scene_points(pts.xyz, pts.info)
        self.extent = scene_extent(core, centers)
        # with a backdrop, the deformation field's bounds come from the Gaussians inside the box
        # of the points that are not backdrop (None without one: bounds as before, bit-identical)
        self.field_box = None if core is pts.xyz else (core.min(0).tolist(), core.max(0).tolist())
        g = GaussianModel(pts.xyz, pts.rgb, sh_degree=cfg.gaussians.sh_degree, init_opacity=cfg.gaussians.init_opacity,
                          device=self.device)
        g.instants_only = renders_at_instants_only(cfg, self.items, self.rgb_only)  # lazy curves: LAZY_RGB_ONLY
        g.setup_optimizer(cfg.gaussians, self.extent)
        self.model = Model4D(g, None, background=cfg.losses.background, near_plane=near_plane_for_extent(self.extent))
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
        """Start the motion of ``cfg.motion.representation``: per-Gaussian trajectories (issue 11,
        engine.scene.trajectory) and / or the deformation field around the current canonical
        Gaussians (with both, the field is a residual on top of the trajectories)."""
        motion = self.cfg.motion.representation
        if motion not in MOTIONS:
            raise ValueError(f"unknown motion representation {motion!r}; choose one of {', '.join(MOTIONS)}")
        self.model.use_deformation = True
        if "trajectory" in motion:
            self.model.add_trajectories(self.frame_times, self.cfg.motion.lr_traj * self.extent,
                                        self.cfg.motion.lr_traj_quats)
        if "hexplane" not in motion:
            return
        g = self.model.gaussians
        means = g.means.detach().cpu().numpy()
        lo, hi = robust_bounds(inside_box(means, self.field_box))
        # spike / block colour losses constrain the field between frames: finer time cells
        per_frame = TIME_CELLS_PER_FRAME_GUIDED if self.between_supervised() else TIME_CELLS_PER_FRAME
        field = make_field(self.cfg.hexplane, lo, hi, self.time_range, self.frame_times, seed=self.seed,
                           time_cells_per_frame=per_frame).to(self.device)
        self.model.deformation = field
        self.model.use_deformation = True
        self._make_deform_opt()
        for hook in self.deformation_hooks:
            hook(self.run)

    def between_supervised(self) -> bool:
        """True when the spike guidance supervises instants between the RGB frames."""
        if self.rgb_only:
            return False
        if spike_stream_info(self.capture) is None:  # no spikes: plain RGB training, no flag needed
            return False
        return self.cfg.spike.loss_weight > 0 or block_weight(self.cfg) > 0

    def _make_deform_opt(self) -> None:
        d = self.model.deformation
        groups = [{"params": d.grid_parameters(), "lr": self.cfg.hexplane.lr_grid, "name": "grid"},
                  {"params": d.mlp_parameters(), "lr": self.cfg.hexplane.lr_mlp, "name": "mlp"}]
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
            self._carry_trajectories(last)
        if d is None:
            return
        u = (d.normalize_time(last) + 1.0) / 2.0
        with torch.no_grad():
            for p in d.grid.temporal:
                T = p.shape[-2]
                c = min(T - 1, int(math.ceil(u * (T - 1) - 1e-6)))
                if c < T - 1:
                    p[:, :, c + 1:, :] = p[:, :, c:c + 1, :]

    def _carry_trajectories(self, last: float) -> None:
        """Knots after ``last`` start at constant velocity (``traj_carry=velocity``), hold (``hold``), or where
        optical flow + per-instant stereo put each Gaussian (``flow``, engine.train.motion.scene_flow; constant velocity
        for what it cannot see). A lazy optimiser's skipped moves land first (engine.scene.lazy_adam)."""
        knots, g = self.model.trajectory["knots"], self.model.gaussians
        li = int(np.argmin([abs(k - last) for k in knots]))
        g.settle()
        mode = "velocity" if self.cfg.motion.carry == "flow" else self.cfg.motion.carry
        extrapolate_junctions(getattr(g, TRAJ_MEANS).data, knots, li, li + 1, mode=mode)
        extrapolate_junctions(getattr(g, TRAJ_QUATS).data, knots, li, li + 1, mode="hold")
        frames = train_frames(self.capture)
        if self.cfg.motion.carry == "flow" and li + 1 < len(knots):
            from ..motion.scene_flow import carry_trajectories
            self.carry_info.append(carry_trajectories(self.run, frames, knots, li, li + 1))
        if self.cfg.births.error > 0 and li + 1 < len(knots):
            from ..motion.births import spawn_at_instant
            spawn_at_instant(self.run, frames, knots[li + 1])  # records in run.info["births"]

    def add_deformation_parameters(self, params, lr: float, name: str = "extra") -> None:
        """For extensions (e.g. the spike fine encoder): optimise more parameters alongside."""
        if self.deform_opt is None:
            raise RuntimeError("the deformation stage has not started")
        self.deform_opt.add_param_group({"params": list(params), "lr": lr, "name": name})

    def _update_lrs(self, step: int) -> None:
        self.model.gaussians.update_learning_rate(self.schedule.run_progress(step))
        if self.schedule.settling(step):  # past the schedule two fixed views are fitted through any freedom left
            self.model.gaussians.scale_constant_lrs(settle_lr(step, self.schedule))
        p = min(1.0, max(0.0, self.schedule.deform_progress(step, self.cfg.schedule.static_fraction, last=1)))
        if self.model.trajectory is not None:  # decays over the deformation stage, like the field
            for grp in self.model.gaussians.optimizer.param_groups:
                if grp["name"] == TRAJ_MEANS:
                    grp["lr"] = self.extent * math.exp(math.log(self.cfg.motion.lr_traj) * (1 - p)
                                                       + math.log(self.cfg.motion.lr_traj_final) * p)
        if self.deform_opt is not None:
            for grp in self.deform_opt.param_groups:
                if grp["name"] == "grid":
                    grp["lr"] = math.exp(math.log(self.cfg.hexplane.lr_grid) * (1 - p) + math.log(LR_GRID_FINAL) * p)
                elif grp["name"] == "mlp":
                    grp["lr"] = math.exp(math.log(self.cfg.hexplane.lr_mlp) * (1 - p) + math.log(LR_MLP_FINAL) * p)

    # ---- one iteration --------------------------------------------------------------------
    def step(self, step: int) -> dict:
        cfg = self.cfg
        model = self.model
        g = model.gaussians
        stage = self.stage_of(step)
        if stage == "deform" and not model.use_deformation:
            self.start_deformation()
        if cfg.gaussians.sh_degree > 0 and cfg.gaussians.sh_step_fraction > 0:
            want = self.schedule.sh_degree(step, cfg)
            while g.active_sh_degree < want:
                g.oneup_sh_degree()
        self._update_lrs(step)
        dense = self.schedule.in_densify_window(step, cfg)  # densification statistics, and this step's dropout
        model.dropout = GaussianDropout.for_step(cfg.gaussians.drop_rate, self.seed, step, densifying=dense)
        if stage == "deform" and self.cfg.schedule.time_curriculum > 0:
            self._carry_forward(self.time_window(step))
        item = self.items[self.frame_index(step)]
        if stage == "static":  # large frames warm up at half size (engine.train.frames.coarse)
            item = self.coarse(item)
        fine = self.fine_provider(item) if (self.fine_provider is not None and stage == "deform") else None
        rgb, alpha, meta, attrs = model.render(item, fine=fine)
        means2d = meta.get("means2d")
        if means2d is not None and means2d.requires_grad:
            means2d.retain_grad()
        ctx = StepContext(self.run, step, stage, item, rgb, alpha, meta, attrs)
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
        for opt in filter(None, (g.optimizer, self.deform_opt)):
            opt.zero_grad(set_to_none=True)
        with gradient_sink():  # the curves' readers sum their gradients in place (issue 13)
            total.backward()

        # densification statistics and schedule
        if dense and means2d is not None and means2d.grad is not None:
            g.add_densification_stats(means2d.grad, meta["radii"], item["width"], item["height"])
        g.optimizer.step()
        if self.deform_opt is not None and stage == "deform":
            self.deform_opt.step()
        for hook in self.post_step_hooks:
            hook(self.run, step, item, meta)
        if self.freeze is not None and stage == "deform":  # observation module, on this render's rows
            self.freeze.after_step(step, item, rgb, meta)
        info = {}
        if self.schedule.densify_due(step, cfg):
            gen = torch.Generator(device="cpu").manual_seed(self.seed * 1000003 + step)
            cap = int(self.init_info.get("max_gaussians", cfg.densify.max_gaussians))  # scaled (densify_cap)
            info = g.densify_and_prune(grad_threshold=cfg.densify.grad_threshold,
                                       percent_dense=cfg.densify.percent_dense,
                                       min_opacity=cfg.densify.prune_opacity, max_world_scale=PRUNE_BIG_WORLD,
                                       max_gaussians=cap,
                                       generator=gen if self.device.type == "cpu" else None)
        if self.cull is not None and (step == 0 or (stage == "deform" and self.stage_of(step - 1) == "static") or info):
            self.cull(self.run, step)
        if self.freeze is not None and stage == "deform":  # prediction module (periodic motion checks)
            self.freeze.maybe_check(step)
        with torch.no_grad():
            mse = float(((rgb.detach().clamp(0, 1) - item["image"]) ** 2).mean())
        self.last_losses = losses
        model.dropout = None
        return {"loss": float(total.detach()), "psnr": -10.0 * math.log10(max(mse, 1e-10)), "stage": stage,
                "losses": losses, "densify": info}

    # ---- state ------------------------------------------------------------------------------
    def state(self, step: int) -> dict:
        return {
            "model": self.model.state(),
            "deform_optimizer": None if self.deform_opt is None else self.deform_opt.state_dict(),
            "step": int(step),
            "total_steps": int(self.total_steps),
            "schedule": self.schedule.state_dict(),
            "time_range": list(self.time_range),
            "frame_times": list(self.frame_times),
            "extent": self.extent,
            "field_box": self.field_box,
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
        self.schedule = Schedule.from_state(state.get("schedule"), int(state["total_steps"]))
        self.extent = float(state.get("extent", 1.0))
        self.field_box = state.get("field_box")
        self.init_info = state.get("init", {})
        self._carried_to = float(state.get("carried_to", -math.inf))
        self.model = Model4D.from_state(state["model"], self.cfg.gaussians, device=self.device)
        if self.model.deformation is not None:
            self._make_deform_opt()
            for hook in self.deformation_hooks:
                hook(self.run)
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
