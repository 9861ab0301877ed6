"""The training configuration: one dataclass per part of the method, and three presets.

Schedules are fractions of the schedule's step count (``schedule.iterations``, fewer when a
wall-clock budget ``train(..., seconds=N)`` cannot buy them); a run with more steps than that
settles after the schedule (engine.train.loop.schedule). A setting is named ``group.field``
(``--set densify.max_gaussians=40000``); the names of the flat configuration that came before
(``max_gaussians``) are still accepted, so old run folders load and old scripts keep working.
Engineering constants (cache refresh intervals, search radii, kernel sizes) live in the
module that uses them; the measurements behind every default are in docs/experiments/.
"""
from __future__ import annotations

import dataclasses
import difflib
from dataclasses import dataclass, field, fields

from ..scene.deformation import HexPlaneConfig
from ..scene.gaussians import GaussianConfig

__all__ = ["TrainConfig", "ScheduleConfig", "InitConfig", "GaussianConfig", "DensifyConfig", "HexPlaneConfig",
           "MotionConfig", "BirthConfig", "LossConfig", "SkipConfig", "SpikeConfig", "SpikeFlowConfig",
           "BaselineConfig", "PRESETS", "get_preset", "apply_overrides", "block_weight", "opacity_decay_window",
           "setting_names"]


@dataclass
class ScheduleConfig:
    iterations: int = 1000            # the schedule's steps (static warm-up + deformation); longer runs settle after it
    steps: int = 0                    # steps of a run without a budget (0: iterations); those past iterations settle
    static_fraction: float = 0.3      # warm-up share: canonical Gaussians only, no motion
    time_curriculum: float = 0.5      # share of the deformation stage over which frames are admitted in time order
    checkpoint_every_s: float = 30.0  # seconds between checkpoints


@dataclass
class InitConfig:
    method: str = "auto"              # auto (points.ply, else stereo, else random) | ply | stereo | planesweep | random
    max_points: int = 6000            # stereo points kept for the initial cloud
    random_points: int = 3000         # random points when there is neither a point cloud nor a stereo pair
    backdrop: float = 0.3             # points beyond each image border (this share wide) on the dominant planes
    planes: bool = True               # stereo holes take the dominant planes' depth where it agrees


@dataclass
class DensifyConfig:
    start: float = 0.05               # first densification, share of the steps
    stop: float = 0.7                 # last densification (and its opacity prune)
    every: int = 100                  # steps between densifications
    grad_threshold: float = 2e-4      # mean view-space gradient that clones or splits a Gaussian
    percent_dense: float = 0.01       # clone if the largest scale <= this x extent, else split
    prune_opacity: float = 0.005      # prune below this opacity
    max_gaussians: int = 20000        # no densification beyond this count at 160x120 (up to 4x for larger frames)


@dataclass
class MotionConfig:
    representation: str = "trajectory"  # trajectory (per-Gaussian curves) | hexplane (Eq. 1, 5) | trajectory+hexplane
    lr_traj: float = 1.6e-3           # x extent: curve control points, decays to lr_traj_final
    lr_traj_final: float = 1.6e-5
    lr_traj_quats: float = 1e-3       # the rotation residual curve
    carry: str = "flow"               # an admitted RGB instant starts from: flow (stereo + flow) | velocity | hold
    inner_weight: float = 1.0         # prior on the curves' in-between bends (mean squared / extent^2)


@dataclass
class BirthConfig:
    error: float = 0.15               # new Gaussians where the render misses an admitted frame by more (0: off)
    lifespan: float = 0.5             # their temporal std, x the RGB frame interval
    static_lifespan: float = 16.0     # ... where a neighbouring RGB frame repeats the pixel's colour (static surface)
    depth_guard: float = 0.8          # no static birth where stereo lies in front of an opaque render by this ratio
    motion: str = "none"              # motion before their instant: none | lk | dis | nearest | match


@dataclass
class LossConfig:
    dssim: float = 0.2                # D-SSIM share of the frame loss (paper Eq. 22)
    block: float = 0.5                # L1 of 4x4 average-pooled frames (paper Eq. 20)
    depth: float = 0.1                # relative L1 to the fused stereo depth at every RGB instant
    background: tuple = (0.0, 0.0, 0.0)
    opacity_decay: float = 0.995      # x opacity of the Gaussians a step sees (1: off); floaters fade and are pruned
    opacity_decay_until: float | None = None  # share of the steps the decay lasts (None: densify.stop)
    cover: float = 0.5                # cracks at a virtual view ~20 deg off the step's frame (0: off)
    flat: float = 0.02                # Gaussians on the stereo surface lie flat in its local plane (0: off)
    cover_grad: str = "all"           # what it trains: all | "+"-joined means, quats, scales, size, opacities, colors


@dataclass
class SkipConfig:
    freeze_static: bool = False       # CPOStream: Gaussians still for freeze_k_checks checks skip the motion model
    freeze_k_checks: int = 3
    freeze_motion_eps_px: float = 0.3  # still: motion over the train frames <= this (px)
    early_stop: bool = False          # stop when held-back train frames stop improving (never the eval frames)
    early_stop_patience: int = 3      # proxy evaluations without a gain before stopping
    cull_frustum: bool = False        # prune Gaussians outside every train camera's frustum


@dataclass
class SpikeConfig:
    fine_deformation: bool = True     # the spike feature added to the HexPlane feature (Eq. 6-10)
    fine_per_gaussian: bool = False   # per-Gaussian spike features (else one per instant)
    fine_frozen_encoder: bool = True  # the conv texture encoder stays at its seeded init (windows encoded once)
    fine_k_sub: int = 8               # sub-windows (attention tokens) per RGB interval
    fine_d_model: int = 64            # attention width of the fine branch
    fine_channels: int = 32           # conv channels of the spike texture encoder
    loss_weight: float = 1.0          # the spike loss (Eq. 17)
    window: int = 32                  # m: spike frames per rendered window (paper: 32)
    loss_mode: str = "counts"         # counts (expected counts) | if (m-step integrate-and-fire, surrogate gradient)
    block_loss_weight: float | None = None  # Eq. 20 between frames (None: 1 for the HexPlane field alone, else 0)
    block_interp: str = "flow"        # the block loss's interpolated frame: flow | linear
    between_every: int = 1            # a between-frame render every k deformation steps (0: never)
    between_colocated_p: float = 0.75  # share of between-frame renders at the spike camera's view
    between_scale: float = 0.5        # between-frame renders at this share of the RGB resolution
    time_smooth_weight: float = 0.1   # the HexPlane's time smoothness with guidance (finer time cells)
    between_curriculum: bool = True   # between-frame instants only up to the time curriculum's front
    static_prior: bool = True         # Gaussians where the spike view never changes skip the HexPlane field
    skip_static: bool = True          # no between-frame renders in spike windows without change
    fine_change_gate: bool = True     # fine feature only where / when the spike view changes
    quiet_curves: bool = True         # where the spike view saw no change: no in-between bend, no between-frame grad


@dataclass
class SpikeFlowConfig:
    weight: float = 1.0               # the spike view's optical flow on the curves (0: off)
    warm: bool = True                 # each grid instant's flow starts from its neighbour's
    fit: bool = True                  # once per interval, the curves' inner points fitted to the flow
    junctions: str = "all"            # the curves' place at the next RGB instant from the flow: all | born | none


@dataclass
class BaselineConfig:
    kind: str = ""                    # training data (paper Table 1): repeat | interp-linear | interp-flow | spike2img
    instants: str = "all"             # synthetic frames as RGB instants ("all") or as between-frame targets ("real")
    weight: float = 1.0               # frame-loss weight of a synthetic frame


# the groups in the order a reader meets the method
GROUPS = {"schedule": ScheduleConfig, "init": InitConfig, "gaussians": GaussianConfig, "densify": DensifyConfig,
          "motion": MotionConfig, "hexplane": HexPlaneConfig, "births": BirthConfig, "losses": LossConfig,
          "skip": SkipConfig, "spike": SpikeConfig, "spike_flow": SpikeFlowConfig, "baseline": BaselineConfig}


@dataclass
class TrainConfig:
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    init: InitConfig = field(default_factory=InitConfig)
    gaussians: GaussianConfig = field(default_factory=GaussianConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    hexplane: HexPlaneConfig = field(default_factory=HexPlaneConfig)
    births: BirthConfig = field(default_factory=BirthConfig)
    losses: LossConfig = field(default_factory=LossConfig)
    skip: SkipConfig = field(default_factory=SkipConfig)
    spike: SpikeConfig = field(default_factory=SpikeConfig)
    spike_flow: SpikeFlowConfig = field(default_factory=SpikeFlowConfig)
    baseline: BaselineConfig = field(default_factory=BaselineConfig)

    def to_dict(self) -> dict:
        return {g: {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(getattr(self, g)).items()}
                for g in GROUPS}

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """A config from ``to_dict``'s nested form or the flat form of older run folders; names
        that are no longer settings are ignored (their values are module constants now)."""
        flat = {}
        for k, v in d.items():
            if k in GROUPS and isinstance(v, dict):
                flat.update({f"{k}.{n}": x for n, x in v.items() if n in _FIELDS[k]})
            elif k in FLAT_NAMES:
                flat[FLAT_NAMES[k]] = v
        return apply_overrides(cls(), flat)

    def replace(self, **changes) -> "TrainConfig":
        """A copy with settings replaced; keys are ``group__field`` or the old flat names."""
        return apply_overrides(self, {k.replace("__", "."): v for k, v in changes.items()})


_FIELDS = {g: {f.name: f for f in fields(c)} for g, c in GROUPS.items()}

# the flat names of the configuration before the redesign -> their place now
FLAT_NAMES = {
    "iterations": "schedule.iterations", "static_fraction": "schedule.static_fraction",
    "time_curriculum": "schedule.time_curriculum",
    "checkpoint_every_s": "schedule.checkpoint_every_s",
    "init": "init.method", "init_max_points": "init.max_points", "init_random_points": "init.random_points",
    "init_backdrop": "init.backdrop", "init_planes": "init.planes",
    "sh_degree": "gaussians.sh_degree", "sh_step_fraction": "gaussians.sh_step_fraction",
    "lr_means": "gaussians.lr_means", "lr_means_final": "gaussians.lr_means_final",
    "lr_scales": "gaussians.lr_scales", "lr_quats": "gaussians.lr_quats", "lr_opacities": "gaussians.lr_opacities",
    "lr_sh_dc": "gaussians.lr_sh_dc", "init_opacity": "gaussians.init_opacity",
    "gaussian_adam": "gaussians.optimizer",
    "densify_from": "densify.start", "densify_until": "densify.stop", "densify_every": "densify.every",
    "densify_grad_threshold": "densify.grad_threshold", "percent_dense": "densify.percent_dense",
    "prune_opacity": "densify.prune_opacity", "max_gaussians": "densify.max_gaussians",
    "motion": "motion.representation", "lr_traj": "motion.lr_traj", "lr_traj_final": "motion.lr_traj_final",
    "lr_traj_quats": "motion.lr_traj_quats", "traj_carry": "motion.carry", "traj_inner_weight": "motion.inner_weight",
    "hex_resolution": "hexplane.resolution", "hex_features": "hexplane.features", "mlp_width": "hexplane.mlp_width",
    "deform_scale": "hexplane.deform_scale", "deform_opacity": "hexplane.deform_opacity",
    "deform_color": "hexplane.deform_color", "lr_grid": "hexplane.lr_grid", "lr_mlp": "hexplane.lr_mlp",
    "time_smooth_weight": "hexplane.time_smooth_weight",
    "birth_error": "births.error", "birth_lifespan": "births.lifespan",
    "birth_static_lifespan": "births.static_lifespan", "birth_depth_guard": "births.depth_guard",
    "birth_motion": "births.motion",
    "lambda_dssim": "losses.dssim", "lambda_block": "losses.block", "lambda_depth": "losses.depth",
    "background": "losses.background", "opacity_decay": "losses.opacity_decay",
    "opacity_decay_until": "losses.opacity_decay_until", "lambda_cover": "losses.cover",
    "cover_grad": "losses.cover_grad",
    "freeze_static": "skip.freeze_static", "freeze_k_checks": "skip.freeze_k_checks",
    "freeze_motion_eps_px": "skip.freeze_motion_eps_px", "early_stop": "skip.early_stop",
    "early_stop_patience": "skip.early_stop_patience", "cull_frustum": "skip.cull_frustum",
    "fine_deformation": "spike.fine_deformation", "fine_per_gaussian": "spike.fine_per_gaussian",
    "fine_frozen_encoder": "spike.fine_frozen_encoder", "fine_k_sub": "spike.fine_k_sub",
    "fine_d_model": "spike.fine_d_model", "fine_channels": "spike.fine_channels",
    "spike_loss_weight": "spike.loss_weight", "spike_window": "spike.window", "spike_loss_mode": "spike.loss_mode",
    "block_loss_weight": "spike.block_loss_weight", "block_interp": "spike.block_interp",
    "between_every": "spike.between_every", "between_colocated_p": "spike.between_colocated_p",
    "between_scale": "spike.between_scale", "spike_time_smooth_weight": "spike.time_smooth_weight",
    "between_curriculum": "spike.between_curriculum",
    "spike_static_prior": "spike.static_prior", "spike_skip_static": "spike.skip_static",
    "fine_change_gate": "spike.fine_change_gate", "quiet_curves": "spike.quiet_curves",
    "spike_flow_weight": "spike_flow.weight", "spike_flow_warm": "spike_flow.warm", "spike_flow_fit": "spike_flow.fit",
    "spike_flow_junctions": "spike_flow.junctions",
    "baseline": "baseline.kind", "baseline_instants": "baseline.instants", "baseline_weight": "baseline.weight",
}


def setting_names() -> list[str]:
    """Every ``group.field`` name, in the groups' order."""
    return [f"{g}.{n}" for g in GROUPS for n in _FIELDS[g]]


def _resolve(key: str) -> tuple[str, str]:
    """(group, field) of a ``group.field`` or an old flat name; a clear KeyError otherwise."""
    name = FLAT_NAMES.get(key, key)
    group, _, leaf = name.partition(".")
    if group in _FIELDS and leaf in _FIELDS[group]:
        return group, leaf
    near = difflib.get_close_matches(key, setting_names() + list(FLAT_NAMES), n=3, cutoff=0.6)
    hint = f"; did you mean {' or '.join(repr(n) for n in near)}?" if near else ""
    raise KeyError(f"unknown training option {key!r}{hint} (every option: "
                   "python -c 'from engine.train.config import setting_names; print(setting_names())')")


def _coerce(f: dataclasses.Field, v):
    default = f.default
    if isinstance(default, tuple) and isinstance(v, list):
        return tuple(v)
    if isinstance(default, bool):
        if isinstance(v, str):
            if v.lower() not in ("1", "0", "true", "false", "yes", "no", "on", "off"):
                raise ValueError(f"{f.name}: expected true or false, got {v!r}")
            return v.lower() in ("1", "true", "yes", "on")
        return bool(v)
    if isinstance(default, int):
        return int(v)
    if isinstance(default, float) or (default is None and v is not None and "float" in str(f.type)):
        return float(v)  # an optional float (None: decided by other settings) given a value
    return v


def apply_overrides(cfg: TrainConfig, overrides: dict | None) -> TrainConfig:
    """A copy of ``cfg`` with settings replaced (``group.field`` or old flat names); an unknown
    name raises ``KeyError`` with the closest names, a value of the wrong type ``ValueError``."""
    groups = {g: dataclasses.replace(getattr(cfg, g)) for g in GROUPS}
    for k, v in (overrides or {}).items():
        g, leaf = _resolve(k)
        try:
            setattr(groups[g], leaf, _coerce(_FIELDS[g][leaf], v))
        except (TypeError, ValueError) as err:
            raise ValueError(f"training option {g}.{leaf}: {err}") from None
    return TrainConfig(**groups)


# the presets: what each changes of the defaults (fast). balanced: more steps and Gaussians with fast's
# motion model (a larger HexPlane collapsed on the demo); quality: more still (at 6000 steps it overfit
# both scenes: a budget that buys more steps settles after the schedule, engine.train.loop.schedule).
# docs/experiments/benchmark-history.md ("Quality preset: what was wrong") and docs/benchmarks.md
PRESET_CHANGES = {
    "fast": {},
    "balanced": {"schedule.iterations": 2500, "schedule.checkpoint_every_s": 60.0,
                 "gaussians.sh_degree": 1, "init.max_points": 10000, "densify.max_gaussians": 30000},
    "quality": {"schedule.iterations": 3000, "schedule.checkpoint_every_s": 120.0,
                "gaussians.sh_degree": 1, "init.max_points": 12000, "densify.every": 150,
                "densify.max_gaussians": 40000, "hexplane.resolution": 32, "hexplane.mlp_width": 96},
}
PRESETS = tuple(PRESET_CHANGES)
# where the command line and the Blender panel both start (bt4d_addon/properties.py lists it first):
# the preset every published figure uses
DEFAULT_PRESET = "fast"


def get_preset(name: str = "fast", overrides: dict | None = None) -> TrainConfig:
    if name not in PRESET_CHANGES:
        raise KeyError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return apply_overrides(apply_overrides(TrainConfig(), PRESET_CHANGES[name]), overrides)


def block_weight(cfg: TrainConfig) -> float:
    """The block colour loss's weight between frames (Eq. 20): ``spike.block_loss_weight``, or
    when it is None 1.0 for the HexPlane field alone and 0 for per-Gaussian trajectories."""
    if cfg.spike.block_loss_weight is not None:
        return float(cfg.spike.block_loss_weight)
    return 1.0 if cfg.motion.representation == "hexplane" else 0.0


def opacity_decay_window(cfg: TrainConfig) -> tuple[float, float]:
    """(from, until) of the opacity decay as shares of the schedule: from the start until
    ``losses.opacity_decay_until``, or when it is None ``densify.stop``, so the decay ends where
    densification's opacity prune does."""
    until = cfg.losses.opacity_decay_until
    return 0.0, float(cfg.densify.stop if until is None else until)
