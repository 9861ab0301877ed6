"""Coarse 4D deformation field (paper Eq. 1 and 5; 4D Gaussians, Wu et al. 2024).

``f_c = phi_d(H(x, t))``: a multi-resolution HexPlane ``H`` over (x, y, z, t) -- six planes
xy, xz, yz, xt, yt, zt, sampled bilinearly, multiplied across planes and concatenated across
resolutions -- followed by a small MLP ``phi_d``. A multi-head decoder ``D`` turns the feature
into per-Gaussian residuals: position (always), rotation (quaternion residual, always),
and optionally log-scale, opacity logit and colour (off by default; DynTCG found that
scale deformation rarely pays).

Fine-scale hook (paper Eq. 10): ``f = f_c + f_f``. Pass ``fine=`` to :meth:`forward` (a
tensor [N, feature_dim]) or set ``field.fine_encoder`` to a module called as
``fine_encoder(xyz_normalised [N,3], t: float) -> [N, feature_dim]``; its output is added
to the coarse feature before the decoder. The spike branch plugs in there.

Coordinates: xyz are normalised to the field's bounds (an AABB fixed when the deformation
stage starts), t (capture seconds, continuous) to the capture's time range, both to
[-1, 1]; samples outside are clamped to the border.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ..spike.features import SpikeWindowCache
from . import hexplane_fused
from .fine_deformation import SpikeFineEncoder


# (a, b) coordinate indices of the six planes; 3 is time.
@dataclass
class HexPlaneConfig:
    """The HexPlane deformation field's settings (the training configuration's ``hexplane`` group)."""

    resolution: int = 24              # base spatial resolution of each plane axis
    features: int = 16                # channels per plane
    mlp_width: int = 64               # hidden width of the decoder phi_d
    deform_scale: bool = False        # DynTCG: no scale deformation unless it pays
    deform_opacity: bool = False
    deform_color: bool = False
    lr_grid: float = 5e-2             # decays to LR_GRID_FINAL
    lr_mlp: float = 5e-3              # decays to LR_MLP_FINAL
    time_smooth_weight: float = 1e-3  # second difference along t of the time planes (RGB-only)


MULTIRES = (1, 2)             # resolution multipliers of the planes
MLP_DEPTH = 1                 # hidden layers of phi_d
TIME_CELLS_PER_FRAME = 1.0    # time cells per RGB instant (6 with spike guidance: TIME_CELLS_PER_FRAME_GUIDED)
TIME_CELLS_PER_FRAME_GUIDED = 6.0
LR_GRID_FINAL = 1.6e-3
LR_MLP_FINAL = 1.6e-4
TV_WEIGHT = 2e-4              # spatial plane total variation
TIME_L1_WEIGHT = 1e-4         # time planes close to 1 (static by default)

PLANES = ((0, 1), (0, 2), (1, 2), (0, 3), (1, 3), (2, 3))
SPATIAL = (0, 1, 2)
TEMPORAL = (3, 4, 5)


class HexPlane(nn.Module):
    """Multi-resolution HexPlane: features [N, features * len(multires)] at (x, y, z, t).

    Per resolution level the three spatial planes (xy, xz, yz) are stored stacked as one
    tensor [3, C, R, R] and the three time planes (xt, yt, zt) as [3, C, T, R] (rows: time),
    so each level costs two batched ``grid_sample`` calls instead of six.
    """

    def __init__(self, features: int = 16, resolution: int = 24, multires=(1, 2), time_resolution: int = 8,
                 seed: int = 0):
        super().__init__()
        gen = torch.Generator().manual_seed(seed)
        self.features = int(features)
        self.resolutions = []
        self.spatial = nn.ParameterList()
        self.temporal = nn.ParameterList()
        for m in multires:
            r, t = int(resolution * m), max(2, int(time_resolution))
            self.resolutions.append([r, r, r, t])
            # grid_sample: grid x (coordinate a) indexes width, grid y (coordinate b) indexes height
            self.spatial.append(nn.Parameter(torch.rand((3, self.features, r, r), generator=gen) * 0.4 + 0.1))
            # time planes start at 1: the product is then the static feature
            self.temporal.append(nn.Parameter(torch.ones(3, self.features, t, r)))

    @property
    def out_dim(self) -> int:
        return self.features * len(self.resolutions)

    def plane(self, level: int, index: int) -> torch.Tensor:
        """Plane ``index`` (order of PLANES) of ``level`` as [1, C, H, W]."""
        src = self.spatial[level] if index < 3 else self.temporal[level]
        return src[index % 3: index % 3 + 1]

    # "auto": the fused numba sampler (engine.scene.hexplane_fused) for CPU tensors when
    # numba is available, else ``grid_sample``; "torch": always ``grid_sample`` (the
    # reference the fused path is tested against); "fused": the fused one where it can run.
    sampler = "auto"

    def forward(self, xyzt: torch.Tensor) -> torch.Tensor:
        """``xyzt`` [N, 4] in [-1, 1] -> [N, out_dim]."""
        if self.sampler != "torch" and hexplane_fused.supports(xyzt, [*self.spatial, *self.temporal]):
            return hexplane_fused.hexplane_sample(xyzt, self.spatial, self.temporal)
        return self.reference(xyzt)

    def reference(self, xyzt: torch.Tensor) -> torch.Tensor:
        """:meth:`forward` by ``F.grid_sample`` (two batched calls per level)."""
        n = xyzt.shape[0]
        gs = torch.stack([xyzt[:, PLANES[i]] for i in SPATIAL]).reshape(3, 1, n, 2)
        gt = torch.stack([xyzt[:, PLANES[i]] for i in TEMPORAL]).reshape(3, 1, n, 2)
        outs = []
        for sp, tp in zip(self.spatial, self.temporal):
            fs = F.grid_sample(sp, gs, mode="bilinear", padding_mode="border", align_corners=True)
            ft = F.grid_sample(tp, gt, mode="bilinear", padding_mode="border", align_corners=True)
            f = (fs * ft).reshape(3, self.features, n)
            outs.append((f[0] * f[1] * f[2]).t())
        return torch.cat(outs, dim=1)

    # ---- regularisers (4D Gaussians) ---------------------------------------------------
    def tv_loss(self) -> torch.Tensor:
        """Total variation of the spatial planes (mean squared neighbour differences)."""
        total = 0.0
        for p in self.spatial:
            total = total + 3 * (((p[..., 1:, :] - p[..., :-1, :]) ** 2).mean()
                                 + ((p[..., :, 1:] - p[..., :, :-1]) ** 2).mean())
        return total

    def time_smoothness_loss(self) -> torch.Tensor:
        """Squared second difference along t of the time planes (smooth motion)."""
        total = 0.0
        for p in self.temporal:
            if p.shape[-2] < 3:
                continue
            d2 = p[..., 2:, :] - 2 * p[..., 1:-1, :] + p[..., :-2, :]
            total = total + 3 * (d2 ** 2).mean()
        return total

    def time_l1_loss(self) -> torch.Tensor:
        """Time planes stay close to 1 (no motion) unless the data asks for it."""
        total = 0.0
        for p in self.temporal:
            total = total + 3 * (1.0 - p).abs().mean()
        return total


def _head(width: int, out: int) -> nn.Sequential:
    head = nn.Sequential(nn.ReLU(), nn.Linear(width, width), nn.ReLU(), nn.Linear(width, out))
    nn.init.zeros_(head[-1].weight)  # start at the identity deformation
    nn.init.zeros_(head[-1].bias)
    return head


class DeformationField(nn.Module):
    """Coarse deformation field: (canonical Gaussians, t) -> deformed Gaussians."""

    def __init__(self, bounds_min, bounds_max, time_range, *, features: int = 16, resolution: int = 24,
                 multires=(1, 2), time_resolution: int = 8, width: int = 64, depth: int = 1,
                 deform_scale: bool = False, deform_opacity: bool = False, deform_color: bool = False,
                 seed: int = 0):
        super().__init__()
        bmin = torch.as_tensor(bounds_min, dtype=torch.float32).reshape(3)
        bmax = torch.as_tensor(bounds_max, dtype=torch.float32).reshape(3)
        bmax = torch.maximum(bmax, bmin + 1e-6)
        self.register_buffer("bounds_min", bmin)
        self.register_buffer("bounds_max", bmax)
        t0, t1 = float(time_range[0]), float(time_range[1])
        if not t1 > t0:
            t1 = t0 + 1.0
        self.time_range = (t0, t1)
        # position residuals are decoded in units of the bounds' half-diagonal
        self.pos_scale = float(torch.linalg.norm(bmax - bmin) / 2)
        self.options = dict(features=features, resolution=resolution, multires=tuple(multires),
                            time_resolution=int(time_resolution), width=width, depth=depth,
                            deform_scale=deform_scale, deform_opacity=deform_opacity,
                            deform_color=deform_color, seed=seed)
        torch.manual_seed(seed)
        self.grid = HexPlane(features, resolution, multires, time_resolution, seed=seed)
        layers: list[nn.Module] = [nn.Linear(self.grid.out_dim, width)]
        for _ in range(depth - 1):
            layers += [nn.ReLU(), nn.Linear(width, width)]
        self.phi = nn.Sequential(*layers)
        self.feature_dim = width
        self.pos_head = _head(width, 3)
        self.rot_head = _head(width, 4)
        self.scale_head = _head(width, 3) if deform_scale else None
        self.opacity_head = _head(width, 1) if deform_opacity else None
        self.color_head = _head(width, 3) if deform_color else None
        self.fine_encoder: nn.Module | None = None  # Eq. 10 hook (spike branch)
        self.fine_spec: dict | None = None  # spec of a checkpoint's spike fine encoder
        self.pending_fine_state: dict = {}  # fine_encoder weights found in a checkpoint (see engine.scene.model)
        self.pending_fine_windows: dict | None = None  # its stored spike windows (SpikeWindowCache.state)

    # ---- coordinates ------------------------------------------------------------------
    def normalize_xyz(self, xyz: torch.Tensor) -> torch.Tensor:
        return (xyz - self.bounds_min) / (self.bounds_max - self.bounds_min) * 2.0 - 1.0

    def normalize_time(self, t: float) -> float:
        t0, t1 = self.time_range
        return (float(t) - t0) / (t1 - t0) * 2.0 - 1.0

    # ---- parameters by learning-rate group ------------------------------------------------
    def grid_parameters(self):
        return list(self.grid.parameters())

    def mlp_parameters(self):
        ids = {id(p) for p in self.grid.parameters()}
        if self.fine_encoder is not None:
            ids |= {id(p) for p in self.fine_encoder.parameters()}
        return [p for p in self.parameters() if id(p) not in ids]

    # ---- forward ------------------------------------------------------------------------
    def features(self, means: torch.Tensor, t: float, fine: torch.Tensor | None = None) -> torch.Tensor:
        """Multi-scale deformation feature f_d^m = phi_d(H(x, t)) [+ f_fine], [N, feature_dim]."""
        xyz = self.normalize_xyz(means)
        tn = torch.full((means.shape[0], 1), self.normalize_time(t), dtype=means.dtype, device=means.device)
        f = self.phi(self.grid(torch.cat([xyz, tn], dim=1)))
        if self.fine_encoder is None and self.fine_spec is not None:
            self.restore_fine_encoder()
        if fine is None and self.fine_encoder is not None:
            fine = self.fine_encoder(xyz, t)
        if fine is not None:
            f = f + fine
        return f

    def forward(self, means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor,
                opacity_logits: torch.Tensor, t: float, fine: torch.Tensor | None = None,
                mask: torch.Tensor | None = None) -> dict:
        """Deformed attributes at capture time ``t`` (seconds).

        Returns dict(means, quats, log_scales, opacity_logits, color_delta or None).
        ``mask`` (bool [N]) restricts the deformation to some Gaussians (others are static).
        """
        if mask is not None:
            idx = mask.nonzero(as_tuple=True)[0]
            sub = self.forward(means[idx], quats[idx], log_scales[idx], opacity_logits[idx], t,
                               None if fine is None else fine[idx])
            out = {"means": means.index_copy(0, idx, sub["means"]),
                   "quats": quats.index_copy(0, idx, sub["quats"]),
                   "log_scales": log_scales.index_copy(0, idx, sub["log_scales"]),
                   "opacity_logits": opacity_logits.index_copy(0, idx, sub["opacity_logits"]),
                   "color_delta": None}
            if sub["color_delta"] is not None:
                out["color_delta"] = torch.zeros_like(means).index_copy(0, idx, sub["color_delta"])
            return out
        f = self.features(means, t, fine)
        out = {
            "means": means + self.pos_head(f) * self.pos_scale,
            "quats": quats + self.rot_head(f),
            "log_scales": log_scales + self.scale_head(f) if self.scale_head is not None else log_scales,
            "opacity_logits": (opacity_logits + self.opacity_head(f)[:, 0] if self.opacity_head is not None
                               else opacity_logits),
            "color_delta": self.color_head(f) if self.color_head is not None else None,
        }
        return out

    def regularization(self, tv_weight: float, time_smooth_weight: float, time_l1_weight: float) -> torch.Tensor:
        return (tv_weight * self.grid.tv_loss() + time_smooth_weight * self.grid.time_smoothness_loss()
                + time_l1_weight * self.grid.time_l1_loss())

    # ---- (de)serialisation ----------------------------------------------------------------
    def config(self) -> dict:
        cfg = {"bounds_min": self.bounds_min.tolist(), "bounds_max": self.bounds_max.tolist(),
               "time_range": list(self.time_range), **{k: (list(v) if isinstance(v, tuple) else v)
                                                        for k, v in self.options.items()}}
        spec = getattr(self.fine_encoder, "spec", None) or self.fine_spec
        if spec is not None:  # spike fine branch (engine.train.guidance.spike_guidance.SpikeFineEncoder)
            cfg["fine"] = spec
        return cfg

    def restore_fine_encoder(self) -> None:
        """Rebuild the spike fine encoder of a loaded checkpoint from its spec (config
        "fine") and the weights waiting in ``pending_fine_state``."""
        if self.fine_encoder is not None or self.fine_spec is None:
            return
        enc = SpikeFineEncoder(self.feature_dim, self.fine_spec).to(self.bounds_min.device)
        if self.pending_fine_windows is not None:  # stored spike windows: no capture needed
            enc.attach(SpikeWindowCache.from_state(self.pending_fine_windows, device=self.bounds_min.device))
            self.pending_fine_windows = None
        if self.pending_fine_state:
            enc.load_state_dict(self.pending_fine_state)
            self.pending_fine_state = {}
        self.fine_encoder = enc

    @classmethod
    def from_config(cls, cfg: dict) -> "DeformationField":
        c = dict(cfg)
        fine = c.pop("fine", None)
        field = cls(c.pop("bounds_min"), c.pop("bounds_max"), c.pop("time_range"), **c)
        field.fine_spec = fine  # the encoder itself is rebuilt lazily (restore_fine_encoder)
        return field


def time_resolution_for(frame_times, per_frame: float) -> int:
    """Time cells of the HexPlane: about ``per_frame`` cells per distinct RGB instant."""
    n = len({round(float(t), 9) for t in frame_times})
    return max(2, int(math.ceil(n * per_frame)) + 1)


def make_field(cfg: HexPlaneConfig, bounds_min, bounds_max, time_range, frame_times, seed: int = 0,
               time_cells_per_frame: float = TIME_CELLS_PER_FRAME) -> DeformationField:
    """Build a field from its settings (:class:`HexPlaneConfig`)."""
    return DeformationField(
        bounds_min, bounds_max, time_range, features=cfg.features, resolution=cfg.resolution,
        multires=MULTIRES, time_resolution=time_resolution_for(frame_times, time_cells_per_frame),
        width=cfg.mlp_width, depth=MLP_DEPTH, deform_scale=cfg.deform_scale,
        deform_opacity=cfg.deform_opacity, deform_color=cfg.deform_color, seed=seed)
