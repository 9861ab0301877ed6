"""A trained 4D scene: canonical Gaussians + deformation field, rendered at any instant.

* :class:`Model4D` (torch) is shared by training and inference: ``attributes(t)`` gives the
  deformed Gaussians at capture time ``t`` (seconds, continuous), ``render(...)`` rasterizes
  them with :func:`engine.raster.rasterization`.
* :func:`load_run` opens a run directory and returns a :class:`Scene4D` (numpy in, numpy out)
  -- what the Blender side, the render CLI and the exporter call. ``Scene4D.sample`` gives
  the Gaussians at K capture times, the arrays the Blender side stores as mesh attributes.
  The per-time npz cache is written by :mod:`engine.export.npz`.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..cameras import View
from ..errors import RunError
from ..io.checkpoint import load_checkpoint, read_run_json
from ..raster import rasterization
from ..raster.holes import fill_uncovered
from . import trajectory as traj
from .deformation import DeformationField
from .gaussians import GaussianModel, num_sh_bases

# per-Gaussian trajectory parameters (GaussianModel extras, issue 11): [N, K, 3] position
# offsets and [N, K, 4] quaternion residuals (engine.scene.trajectory)
TRAJ_MEANS, TRAJ_QUATS = "traj_means", "traj_quats"
# temporal opacity (Spacetime Gaussians, Li et al. CVPR 2024, eq. 3 as a Gaussian in time):
# [N, 1] centre (capture seconds) and log standard deviation; only Gaussians born at an
# admitted instant (engine.train.motion.births) have a short life, the rest get exp(30) s
TIME_CENTER, TIME_LOG_SCALE = "time_center", "time_log_scale"
ALWAYS_LOG_SCALE = 30.0  # log std (s) of Gaussians not born at an instant: factor 1 at any t
BORN_LOG_SCALE_BELOW = 10.0  # a log std under this (e^10 s) marks a Gaussian born at an instant


def born_mask(gaussians) -> torch.Tensor:
    """bool [N]: the Gaussians born at an admitted instant (a temporal log std under
    :data:`BORN_LOG_SCALE_BELOW`); all False when no Gaussian has a temporal opacity."""
    if TIME_LOG_SCALE not in gaussians.extra_lrs:
        return torch.zeros(gaussians.num_gaussians, dtype=torch.bool, device=gaussians.means.device)
    return getattr(gaussians, TIME_LOG_SCALE).detach()[:, 0] < BORN_LOG_SCALE_BELOW


def temporal_opacity(center: torch.Tensor, log_scale: torch.Tensor, t: float) -> torch.Tensor:
    """[N] factor ``exp(-((t - center) / exp(log_scale))^2 / 2)`` on the opacities at ``t``."""
    return torch.exp(-0.5 * ((float(t) - center[:, 0]) * torch.exp(-log_scale[:, 0])) ** 2)


def default_device(device=None) -> torch.device:
    if device is None or device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def view_tensors(view: View, device) -> dict:
    """Rasterizer inputs of one View: viewmat [1,4,4], K [1,3,3], campos [3], size, time."""
    vm = torch.as_tensor(view.viewmat, dtype=torch.float32, device=device)[None]
    K = torch.as_tensor(view.K, dtype=torch.float32, device=device)[None]
    return {"viewmat": vm, "K": K, "width": int(view.intrinsics.width), "height": int(view.intrinsics.height),
            "campos": torch.as_tensor(view.center, dtype=torch.float32, device=device), "time": float(view.time)}


def scaled_view(item: dict, scale: float) -> dict:
    """A trainer view dict (viewmat, K, width, height, ...) at ``scale`` x its resolution
    (same field of view), without the image. Scales that do not divide the size evenly are
    rounded to whole pixels."""
    vt = {k: v for k, v in item.items() if k != "image"}
    if scale == 1.0:
        return vt
    w, h = max(1, int(round(item["width"] * scale))), max(1, int(round(item["height"] * scale)))
    sx, sy = w / item["width"], h / item["height"]
    K = item["K"].clone()
    K[..., 0, 0] *= sx
    K[..., 0, 2] *= sx
    K[..., 1, 1] *= sy
    K[..., 1, 2] *= sy
    vt.update(K=K, width=w, height=h)
    return vt


def near_plane_for_extent(extent: float) -> float:
    """gsplat's 0.01 near plane for scenes of metres, scaled down with tiny scenes so that a
    capture of extent 1e-3 is not culled whole (found by the stress suite)."""
    return float(min(0.01, 1e-3 * max(float(extent), 1e-9)))


class Model4D(nn.Module):
    """Canonical Gaussians (+ optional deformation field)."""

    def __init__(self, gaussians: GaussianModel, deformation: DeformationField | None = None,
                 background=(0.0, 0.0, 0.0), static_mask: torch.Tensor | None = None,
                 near_plane: float = 0.01):
        super().__init__()
        self.near_plane = float(near_plane)
        self.gaussians = gaussians
        self.deformation = deformation
        self.background = tuple(float(b) for b in background)
        self.use_deformation = deformation is not None
        self.static_mask = static_mask  # optional bool [N]: Gaussians frozen in time
        # optional ``(canonical means [N,3]) -> bool [N]``: Gaussians a motion prior holds
        # static (the spike branch: never any change where they project in the spike view);
        # recomputed at every render so densification needs no bookkeeping; its last value
        # is saved as ``prior_mask`` (a render node has no spike stream to recompute it)
        self.static_prior = None
        self.prior_mask: torch.Tensor | None = None  # the prior's last value, as saved
        # per-Gaussian trajectories (issue 11): {"knots": [F] seconds} when the Gaussians
        # carry TRAJ_MEANS / TRAJ_QUATS; applied before the deformation field (a residual)
        self.trajectory: dict | None = None
        # engine.scene.dropout.GaussianDropout while a training step renders (set by the trainer)
        self.dropout = None

    def add_trajectories(self, knots, lr_means: float, lr_quats: float) -> None:
        """Give every Gaussian a (static) trajectory over ``knots`` (the RGB instants)."""
        g = self.gaussians
        knots = traj.default_knots(knots)
        k = traj.num_controls(len(knots))
        n = g.num_gaussians
        g.add_extra(TRAJ_MEANS, torch.zeros(n, k, 3, device=g.means.device), lr_means)
        g.add_extra(TRAJ_QUATS, torch.zeros(n, k, 4, device=g.means.device), lr_quats)
        self.trajectory = {"knots": knots}
        _mark_curves(g)

    def trajectory_at(self, t: float, mask: torch.Tensor | None = None):
        """(position offsets [N,3], quaternion residuals [N,4]) at ``t``; rows where the bool
        ``mask`` is True (static Gaussians) are zero. None without trajectories."""
        if self.trajectory is None:
            return None
        g = self.gaussians
        knots = self.trajectory["knots"]
        dm = traj.evaluate(getattr(g, TRAJ_MEANS), knots, t)
        dq = traj.evaluate(getattr(g, TRAJ_QUATS), knots, t)
        if mask is not None:
            keep = (~mask).to(dm.dtype)[:, None]
            dm, dq = dm * keep, dq * keep
        return dm, dq

    def attributes(self, t: float, campos=None, fine: torch.Tensor | None = None) -> dict:
        """Deformed Gaussians at ``t``: means, quats, scales (linear), opacities, colors."""
        g = self.gaussians
        means, quats, log_scales, opac = g.means, g.quats, g.log_scales, g.opacity_logits
        color_delta = None
        if self.use_deformation and self.trajectory is not None:
            dm, dq = self.trajectory_at(t, self.effective_static_mask())
            means, quats = means + dm, quats + dq
        if self.use_deformation and self.deformation is not None:
            static = self.effective_static_mask()
            mask = None if static is None else ~static
            d = self.deformation(means, quats, log_scales, opac, t, fine=fine, mask=mask)
            means, quats, log_scales, opac = d["means"], d["quats"], d["log_scales"], d["opacity_logits"]
            color_delta = d["color_delta"]
        colors = g.colors(means, campos)
        if color_delta is not None:
            colors = (colors + color_delta).clamp_min(0.0)
        opacities = torch.sigmoid(opac)
        if self.use_deformation and TIME_CENTER in g.extra_lrs:
            c, s = getattr(g, TIME_CENTER), getattr(g, TIME_LOG_SCALE)
            opacities = opacities * temporal_opacity(c, s, t)
        return {"means": means, "quats": quats, "scales": torch.exp(log_scales),
                "opacities": opacities, "colors": colors}

    def render(self, vt: dict, t: float | None = None, *, background=None, fine=None, backend="auto",
               render_depth: bool = True, grad_rows: torch.Tensor | None = None,
               grad_attrs: tuple | None = None):
        """Render one view (``view_tensors`` dict) at time ``t`` (default: the view's time).

        ``grad_rows`` (bool [N]): only these Gaussians' attributes carry a gradient from this
        render; the others are drawn but enter detached. ``grad_attrs``: only these of
        :meth:`attributes`' keys (means, quats, scales, opacities, colors) carry one; "size"
        (without "scales"): the scales' common factor does, their ratios do not.
        Returns (rgb [1,H,W,3], alpha [1,H,W,1], meta, attributes).
        """
        t = vt["time"] if t is None else float(t)
        attrs = self.attributes(t, campos=vt["campos"], fine=fine)
        if grad_attrs is not None:
            kept = {k: v if k in grad_attrs else v.detach() for k, v in attrs.items()}
            if "size" in grad_attrs and "scales" not in grad_attrs:
                # the shape detached, its overall size trained: one factor on all three axes
                m = attrs["scales"].log().mean(-1, keepdim=True)
                kept["scales"] = kept["scales"] * torch.exp(m - m.detach())
            attrs = kept
        if grad_rows is not None:
            keep = grad_rows.to(attrs["means"].device)
            attrs = {k: torch.where(keep.reshape(-1, *([1] * (v.dim() - 1))), v, v.detach()) for k, v in attrs.items()}
        bg = self.background if background is None else background
        bgs = torch.as_tensor(bg, dtype=torch.float32, device=attrs["means"].device).reshape(1, 3)
        opacities = attrs["opacities"]
        if self.dropout is not None and torch.is_grad_enabled():
            opacities = self.dropout(opacities)
        rgb, alpha, meta = rasterization(
            attrs["means"], attrs["quats"], attrs["scales"], opacities, attrs["colors"],
            vt["viewmat"], vt["K"], vt["width"], vt["height"], backgrounds=bgs, render_depth=render_depth,
            near_plane=self.near_plane, backend=backend)
        note = getattr(self.gaussians.optimizer, "note_visible", None)  # engine.scene.selective_adam
        if note is not None and torch.is_grad_enabled() and meta.get("radii") is not None:
            note(meta["radii"])
        return rgb, alpha, meta, attrs

    def effective_static_mask(self) -> torch.Tensor | None:
        """bool [N]: ``static_mask`` (when it matches the Gaussian count) OR the static prior."""
        n = self.gaussians.num_gaussians
        mask = self.static_mask if self.static_mask is not None and self.static_mask.shape[0] == n else None
        prior = self.prior_static()
        if prior is not None:
            mask = prior if mask is None else (mask | prior)
        return mask

    def prior_static(self) -> torch.Tensor | None:
        """bool [N] of the static prior: live when one is attached, else as saved."""
        n = self.gaussians.num_gaussians
        if self.static_prior is not None:
            with torch.no_grad():
                self.prior_mask = self.static_prior(self.gaussians.means.detach())
            return self.prior_mask
        if self.prior_mask is not None and self.prior_mask.shape[0] == n:
            return self.prior_mask
        return None

    # ------------------------------------------------------------------ (de)serialisation
    def state(self) -> dict:
        return {
            "gaussians": self.gaussians.state(),
            "deformation": None if self.deformation is None else {
                "config": self.deformation.config(), "state_dict": self.deformation.state_dict(),
                "fine_windows": _fine_windows(self.deformation)},
            "use_deformation": self.use_deformation,
            "background": list(self.background),
            "near_plane": self.near_plane,
            "static_mask": _cpu_or_none(self.static_mask),
            "prior_mask": _cpu_or_none(self.prior_static()),
            "trajectory": None if self.trajectory is None else dict(self.trajectory),
        }

    @classmethod
    def from_state(cls, state: dict, cfg=None, device="cpu") -> "Model4D":
        """``cfg``: the Gaussians' settings (``GaussianConfig``) to set up their optimiser (training), or None."""
        g = GaussianModel.from_state(state["gaussians"], cfg, device=device)
        deform = None
        if state.get("deformation") is not None:
            deform = DeformationField.from_config(state["deformation"]["config"])
            sd = dict(state["deformation"]["state_dict"])
            # an extension's fine encoder (Eq. 10) is rebuilt by that extension: its weights
            # wait in ``pending_fine_state`` for it
            deform.pending_fine_state = {k[len("fine_encoder."):]: sd.pop(k) for k in list(sd)
                                         if k.startswith("fine_encoder.")}
            deform.pending_fine_windows = state["deformation"].get("fine_windows")
            deform.load_state_dict(sd)
            deform.to(device)
        m = cls(g, deform, background=state.get("background", (0, 0, 0)),
                near_plane=state.get("near_plane", 0.01))
        m.use_deformation = bool(state.get("use_deformation", deform is not None))
        sm = state.get("static_mask")
        m.static_mask = None if sm is None else sm.to(device)
        pm = state.get("prior_mask")
        m.prior_mask = None if pm is None else pm.to(device)
        tj = state.get("trajectory")
        if tj is not None:
            if not hasattr(g, TRAJ_MEANS) or not hasattr(g, TRAJ_QUATS):
                raise ValueError("the model has trajectories but the Gaussians lack their parameters")
            m.trajectory = {"knots": [float(x) for x in tj["knots"]]}
            m.use_deformation = bool(state.get("use_deformation", True))
            _mark_curves(g)
        return m


def _mark_curves(g: GaussianModel) -> None:
    """Tell a selective optimizer (engine.scene.selective_adam) which groups are curves."""
    curves = getattr(g.optimizer, "curves", None)
    if curves is not None:
        curves.update((TRAJ_MEANS, TRAJ_QUATS))


def _fine_windows(field) -> dict | None:
    """The spike fine branch's windows (issue 11: a run renders without its capture)."""
    enc = getattr(field, "fine_encoder", None)
    if enc is not None and hasattr(enc, "windows_state"):
        return enc.windows_state()
    return getattr(field, "pending_fine_windows", None)


SAMPLE_KEYS = ("means", "quats", "scales", "opacities", "colors")  # Scene4D.sample arrays


def auto_num_samples(duration: float, num_gaussians: int, per_second: float = 150.0,
                     max_points: int = 4_000_000, max_samples: int = 300) -> int:
    """A default number of time samples K: ``per_second`` per capture second, at least 2, and
    at most ``max_points`` stored points (N*K) in all."""
    k = int(math.ceil(max(duration, 0.0) * per_second)) + 1
    k = min(k, max_samples, max(2, max_points // max(1, num_gaussians)))
    return max(2, k)


def _cpu_or_none(t):
    return None if t is None else t.cpu()


class Scene4D:
    """A trained run, ready to sample and render (numpy interface)."""

    def __init__(self, model: Model4D, run_dir: Path, info: dict, device="cpu"):
        self.model = model.eval()
        self.run_dir = Path(run_dir)
        self.info = info
        self.device = torch.device(device)
        tr = info.get("time_range")
        if tr is None and model.deformation is not None:
            tr = model.deformation.time_range
        self.time_range = tuple(float(x) for x in (tr or (0.0, 0.0)))

    @property
    def num_gaussians(self) -> int:
        return self.model.gaussians.num_gaussians

    @property
    def background(self):
        return self.model.background

    def prune(self, mask) -> int:
        """Drop the Gaussians where the bool ``mask`` [N] is True (with their trajectories
        and static / prior masks); the deformation field is per position and stays. In
        memory only. Returns how many were dropped."""
        m = self.model
        mask = torch.as_tensor(np.asarray(mask, bool), device=m.gaussians.means.device)
        if mask.shape != (self.num_gaussians,):
            raise ValueError(f"prune mask of shape {tuple(mask.shape)} for {self.num_gaussians} Gaussians")
        n = int(mask.sum())
        if n:
            keep = ~mask
            for name in ("static_mask", "prior_mask"):
                v = getattr(m, name)
                if v is not None and v.shape[0] == mask.shape[0]:
                    setattr(m, name, v[keep.to(v.device)])
            m.gaussians.prune(mask)
        return n

    def gaussians_at(self, t: float) -> dict:
        """Gaussians at capture time ``t`` as float32 numpy arrays.

        means [N,3], quats [N,4] wxyz normalised, scales [N,3] linear, opacities [N],
        colors [N,3] sRGB-encoded (from the SH DC term), sh [N,K,3].
        """
        with torch.no_grad():
            a = self.model.attributes(float(t), campos=None)
            q = a["quats"] / a["quats"].norm(dim=-1, keepdim=True).clamp_min(1e-12)
            g = self.model.gaussians
            sh = g.sh[:, : num_sh_bases(g.active_sh_degree)]
            return {"means": _np(a["means"]), "quats": _np(q), "scales": _np(a["scales"]),
                    "opacities": _np(a["opacities"]), "colors": _np(a["colors"].clamp(0, 1)),
                    "sh": _np(sh)}

    def sample(self, num_samples: int = 0, time_range=None) -> dict:
        """The Gaussians at K evenly spaced capture times ``t_k = t0 + k (t1 - t0) / (K - 1)``
        (what the Blender side stores as one mesh of N*K points).

        ``num_samples`` K (< 2: :func:`auto_num_samples`); ``time_range`` (t0, t1), default
        :attr:`time_range`. Returns float32 arrays ``means [K,N,3]``, ``quats [K,N,4]``,
        ``scales [K,N,3]``, ``opacities [K,N]``, ``colors [K,N,3]`` (sRGB-encoded, as
        :meth:`gaussians_at`) and ``times [K]`` (float64)."""
        t0, t1 = time_range if time_range is not None else self.time_range
        k = int(num_samples) if num_samples and num_samples >= 2 else auto_num_samples(t1 - t0, self.num_gaussians)
        times = np.linspace(float(t0), float(t1), k)
        per_time = [self.gaussians_at(float(t)) for t in times]
        out = {key: np.stack([np.asarray(g[key], dtype=np.float32) for g in per_time]) for key in SAMPLE_KEYS}
        out["times"] = times
        return out

    def render(self, views: list[View], background=None, time: float | None = None,
               fill_holes: bool = False) -> list[dict]:
        """Render each View at its own time (or ``time``): rgb [H,W,3] sRGB-encoded, alpha, depth.

        ``fill_holes``: where alpha < 1, show the colour the covered neighbourhood implies
        instead of the background (:func:`engine.raster.holes.fill_uncovered`, issue 14);
        rgb is then no longer premultiplied, alpha unchanged."""
        out = []
        with torch.no_grad():
            for v in views:
                vt = view_tensors(v, self.device)
                rgb, alpha, meta, _ = self.model.render(vt, time, background=background)
                if fill_holes:
                    bg = self.model.background if background is None else background
                    rgb = fill_uncovered(rgb[0], alpha[0], bg)[None]
                depth = meta.get("depths")
                out.append({
                    "rgb": _np(rgb[0].clamp(0, 1)),
                    "alpha": _np(alpha[0, ..., 0]),
                    "depth": _np(depth[0, ..., 0]) if depth is not None else np.zeros(alpha.shape[1:3], np.float32),
                })
        return out


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().to("cpu", torch.float32).numpy()


def load_run(run_dir, device="cpu") -> Scene4D:
    """Open a run directory (``engine.train`` output); RunError if missing or corrupt."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunError(run_dir, "run directory does not exist")
    device = default_device(device)
    state = load_checkpoint(run_dir, map_location=device)
    try:
        model = Model4D.from_state(state["model"], None, device=device)
    except (KeyError, RuntimeError, TypeError, ValueError) as exc:
        raise RunError(run_dir / "checkpoint.pt", f"checkpoint does not hold a usable model: {exc}") from exc
    try:
        info = read_run_json(run_dir)
    except RunError:
        info = {}
    info = {**info, "time_range": state.get("time_range", info.get("time_range")),
            "step": state.get("step"), "total_steps": state.get("total_steps")}
    return Scene4D(model, run_dir, info, device=device)
