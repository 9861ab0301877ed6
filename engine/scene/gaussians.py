"""Canonical 3D Gaussians: parameters, activation, optimiser, 3DGS densification.

Storage follows 3DGS: means, log-scales, raw quaternions (normalised when used), opacity
logits, SH coefficients (DC + rest). Colours live in sRGB-encoded display space:
``colour = 0.5 + SH(dirs)`` clamped at 0, exactly like 3DGS, so images are trained on as
loaded. The optimiser is one Adam with one parameter group per attribute; densification
rebuilds the tensors and carries Adam's moments (new rows start at zero), as 3DGS's
``cat_tensors_to_optimizer`` / ``_prune_optimizer`` do, but in place: rows are appended into
spare storage rows and pruned by moving the kept ones forward (``engine.scene.row_store``),
so a birth round does not rewrite a long capture's curves and moments.
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from . import grad_buffers, row_store
from .fused_adam import FusedAdam
from .lazy_adam import LazyCurveAdam
from .selective_adam import SelectiveAdam

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)

@dataclass
class GaussianConfig:
    """The Gaussians' settings and their optimiser's (the training configuration's ``gaussians`` group)."""

    sh_degree: int = 0                # final SH degree, grown one band per sh_step_fraction of the steps
    sh_step_fraction: float = 0.15
    lr_means: float = 1.6e-3          # x scene extent, decays exponentially to lr_means_final
    lr_means_final: float = 1.6e-5
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacities: float = 5e-2
    lr_sh_dc: float = 2.5e-3          # the higher SH bands learn at SH_REST_LR_RATIO of it
    init_opacity: float = 0.1
    drop_rate: float = 0.1            # share of Gaussians a render leaves out while densifying (DropGaussian; 0: off)
    # exact (FusedAdam: torch's Adam bit for bit) | selective (only rows and curve columns a step
    # touched) | lazy (the curves' touched columns, skipped steps caught up) | auto (lazy for long curves)
    optimizer: str = "auto"


SH_REST_LR_RATIO = 1 / 20   # 3DGS: the higher SH bands at 1/20 of the DC colour's lr
# optimizer=auto: curves of at least this many control-point columns (K = 3 (F - 1) + 1 for F RGB
# instants) take the lazy step (engine.scene.lazy_adam), shorter ones FusedAdam's ...
LAZY_MIN_COLUMNS = 40
# ... and every curve of a model whose renders are all at RGB instants (``instants_only``): its inner
# columns are never read, so the lazy step with the read catch-up is dense Adam to rounding
LAZY_RGB_ONLY = True

PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def rgb_to_sh(rgb):
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh_dc):
    return sh_dc * SH_C0 + 0.5


def eval_sh(degree: int, sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate real SH (3DGS convention) of ``degree`` -> [N, 3]; ``sh`` is [N, K, 3]."""
    result = SH_C0 * sh[:, 0]
    if degree < 1:
        return result
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    x, y, z = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    result = result - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
    if degree < 2:
        return result
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    result = (result + SH_C2[0] * xy * sh[:, 4] + SH_C2[1] * yz * sh[:, 5]
              + SH_C2[2] * (2.0 * zz - xx - yy) * sh[:, 6] + SH_C2[3] * xz * sh[:, 7]
              + SH_C2[4] * (xx - yy) * sh[:, 8])
    if degree < 3:
        return result
    return (result + SH_C3[0] * y * (3 * xx - yy) * sh[:, 9] + SH_C3[1] * xy * z * sh[:, 10]
            + SH_C3[2] * y * (4 * zz - xx - yy) * sh[:, 11]
            + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
            + SH_C3[4] * x * (4 * zz - xx - yy) * sh[:, 13] + SH_C3[5] * z * (xx - yy) * sh[:, 14]
            + SH_C3[6] * x * (xx - 3 * yy) * sh[:, 15])


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """wxyz quaternions (any norm) -> [N, 3, 3] rotation matrices."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def knn_mean_distance(points: torch.Tensor, k: int = 3, chunk: int = 2048) -> torch.Tensor:
    """Mean distance to the ``k`` nearest other points (3DGS's scale initialisation)."""
    n = points.shape[0]
    if n <= 1:
        return torch.ones(n, dtype=points.dtype, device=points.device)
    k = min(k, n - 1)
    out = torch.empty(n, dtype=points.dtype, device=points.device)
    for s in range(0, n, chunk):
        d = torch.cdist(points[s:s + chunk], points)
        d[torch.arange(d.shape[0]), torch.arange(s, s + d.shape[0])] = float("inf")
        out[s:s + chunk] = d.topk(k, dim=1, largest=False).values.mean(dim=1)
    return out


def inverse_sigmoid(x):
    return torch.log(x / (1 - x))


# GaussianModel -> [weak bound methods]: on_settle's callbacks, outside the module (deepcopy)
_SETTLE_HOOKS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


class GaussianModel(nn.Module):
    """Canonical Gaussians with their own Adam optimiser and densification statistics."""

    def __init__(self, means, colors=None, *, sh_degree: int = 0, init_opacity: float = 0.1,
                 scales=None, device="cpu"):
        super().__init__()
        means = torch.as_tensor(np.asarray(means), dtype=torch.float32, device=device)
        n = means.shape[0]
        if colors is None:
            colors = torch.full((n, 3), 0.5)
        colors = torch.as_tensor(np.asarray(colors), dtype=torch.float32, device=device).clamp(0, 1)
        if scales is None:
            dist = knn_mean_distance(means).clamp_min(1e-7)
            if n >= 20:  # isolated outliers would start as screen-filling splats: cap them
                dist = dist.clamp_max(float(torch.quantile(dist, 0.9)) * 2.0)
            log_scales = torch.log(dist)[:, None].repeat(1, 3)
        else:
            log_scales = torch.log(torch.as_tensor(np.asarray(scales), dtype=torch.float32, device=device))
        quats = torch.zeros(n, 4, device=device)
        quats[:, 0] = 1.0
        k = num_sh_bases(sh_degree)
        self.max_sh_degree = int(sh_degree)
        self.active_sh_degree = 0
        self.means = nn.Parameter(means.clone())
        self.log_scales = nn.Parameter(log_scales)
        self.quats = nn.Parameter(quats)
        self.opacity_logits = nn.Parameter(inverse_sigmoid(torch.full((n,), float(init_opacity), device=device)))
        self.sh_dc = nn.Parameter(rgb_to_sh(colors)[:, None, :].contiguous())
        self.sh_rest = nn.Parameter(torch.zeros(n, k - 1, 3, device=device))
        self.optimizer: torch.optim.Adam | None = None
        self.extent = 1.0
        self.extra_lrs: dict[str, float] = {}  # per-Gaussian extra parameters (add_extra)
        self._reset_stats()

    # ------------------------------------------------------------------ attributes
    @property
    def num_gaussians(self) -> int:
        return self.means.shape[0]

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def sh(self) -> torch.Tensor:
        return torch.cat([self.sh_dc, self.sh_rest], dim=1)

    def colors(self, means: torch.Tensor | None = None, campos=None, sh: torch.Tensor | None = None) -> torch.Tensor:
        """View-dependent sRGB-encoded colours [N, 3] (3DGS: 0.5 + SH, clamped at 0)."""
        sh = self.sh if sh is None else sh
        deg = self.active_sh_degree
        if deg == 0 or campos is None:
            rgb = SH_C0 * sh[:, 0]
        else:
            means = self.means if means is None else means
            campos = torch.as_tensor(campos, dtype=means.dtype, device=means.device)
            rgb = eval_sh(deg, sh[:, : num_sh_bases(deg)], means - campos)
        return (rgb + 0.5).clamp_min(0.0)

    @property
    def param_names(self) -> tuple:
        """The per-Gaussian parameters: 3DGS's plus the extras (e.g. trajectories)."""
        return PARAM_NAMES + tuple(getattr(self, "extra_lrs", {}))

    def params(self) -> dict[str, nn.Parameter]:
        return {name: getattr(self, name) for name in self.param_names}

    def add_extra(self, name: str, value: torch.Tensor, lr: float, *, position_like: bool = False) -> None:
        """A per-Gaussian parameter [N, ...] (e.g. trajectory control points, issue 11) that
        densification clones / splits / prunes with the rows, saved with the model and
        optimised in its own Adam group (``lr`` x extent and decayed like the means when
        ``position_like``)."""
        if name in PARAM_NAMES or not name.isidentifier():
            raise ValueError(f"bad extra parameter name {name!r}")
        if value.shape[0] != self.num_gaussians:
            raise ValueError(f"extra parameter {name!r} has {value.shape[0]} rows for {self.num_gaussians} Gaussians")
        setattr(self, name, nn.Parameter(value.detach().to(self.means.device).float().contiguous()))
        self.extra_lrs[name] = float(lr)
        self.extra_position_like = set(getattr(self, "extra_position_like", set()))
        if position_like:
            self.extra_position_like.add(name)
        if self.optimizer is not None:
            self.optimizer.add_param_group({"params": [getattr(self, name)], "lr": self._extra_lr(name), "name": name})

    def _extra_lr(self, name: str, scale: float = 1.0) -> float:
        lr = self.extra_lrs[name]
        return lr * self.extent * scale if name in getattr(self, "extra_position_like", set()) else lr

    # ------------------------------------------------------------------ optimiser
    # Set by the trainer before setup_optimizer: every render that trains this model is at an RGB
    # instant (an RGB-only run without synthetic frames), so the curves' inner control points get no
    # gradient and stay zero (no prior acts on them), and gaussian_adam=auto with lazy_rgb_only
    # steps every curve lazily (engine.scene.lazy_adam), whatever its length
    instants_only = False

    def setup_optimizer(self, cfg: GaussianConfig, extent: float) -> None:
        self.extent = float(extent)
        lrs = {"means": cfg.lr_means * self.extent, "log_scales": cfg.lr_scales, "quats": cfg.lr_quats,
               "opacity_logits": cfg.lr_opacities, "sh_dc": cfg.lr_sh_dc, "sh_rest": cfg.lr_sh_dc * SH_REST_LR_RATIO}
        groups = [{"params": [getattr(self, n)], "lr": lrs[n], "name": n} for n in PARAM_NAMES]
        self._base_lrs = lrs  # what scale_constant_lrs scales
        groups += [{"params": [getattr(self, n)], "lr": self._extra_lr(n), "name": n} for n in self.extra_lrs]
        # FusedAdam: torch's Adam bit for bit; SelectiveAdam: only the rows the step's renders
        # saw (and the curve columns they read) move (engine.scene.selective_adam)
        # LazyCurveAdam: the curves' touched columns only, their skipped steps caught up; "auto"
        # for curves of at least LAZY_MIN_COLUMNS columns (engine.scene.lazy_adam)
        opt = cfg.optimizer
        if opt not in ("exact", "selective", "lazy", "auto"):
            raise ValueError(f"unknown gaussians.optimizer {opt!r}; choose exact, selective, lazy or auto")
        if opt in ("lazy", "auto"):
            least = int(LAZY_MIN_COLUMNS) if opt == "auto" else 0
            below = least if self.instants_only and LAZY_RGB_ONLY else 0
            # below: the inner columns are never read, so lazy with read catch-up is dense Adam to rounding
            self.optimizer = LazyCurveAdam(groups, min_columns=0 if below else least, dense_inner_below=below,
                                           lr=0.0, eps=1e-15)
        else:
            self.optimizer = (SelectiveAdam if opt == "selective" else FusedAdam)(groups, lr=0.0, eps=1e-15)
        self._lr_means = (cfg.lr_means * self.extent, cfg.lr_means_final * self.extent)

    def update_learning_rate(self, progress: float) -> float:
        """Exponential decay of the means' lr over ``progress`` in [0, 1]; returns it."""
        lr0, lr1 = self._lr_means
        p = min(max(progress, 0.0), 1.0)
        lr = math.exp(math.log(lr0) * (1 - p) + math.log(lr1) * p)
        for g in self.optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = lr
            elif g["name"] in getattr(self, "extra_position_like", set()):
                g["lr"] = self._extra_lr(g["name"], lr / lr0)
        return lr

    def scale_constant_lrs(self, factor: float) -> None:
        """Every lr no schedule decays (all but the means' and position-like extras') at ``factor`` x its
        configured value: the settle stage after the schedule (engine.train.loop.schedule)."""
        for g in self.optimizer.param_groups:
            n = g["name"]
            if n != "means" and n not in getattr(self, "extra_position_like", set()):
                g["lr"] = (self._base_lrs[n] if n in self._base_lrs else self._extra_lr(n)) * factor

    def oneup_sh_degree(self) -> None:
        if self.active_sh_degree < self.max_sh_degree:
            self.active_sh_degree += 1

    # ------------------------------------------------------------------ densification
    def _reset_stats(self) -> None:
        n = self.num_gaussians
        dev = self.means.device
        self.grad_accum = torch.zeros(n, device=dev)
        self.grad_count = torch.zeros(n, device=dev)

    def add_densification_stats(self, means2d_grad: torch.Tensor, radii: torch.Tensor,
                                width: int, height: int) -> None:
        """Accumulate the view-space gradient norm (3DGS NDC units) of visible Gaussians.

        ``means2d_grad`` is [C, N, 2] in pixels, ``radii`` [C, N] (0 = culled).
        """
        if means2d_grad is None:
            return
        g = means2d_grad.detach().clone()
        c = g.shape[0]
        g[..., 0] *= width / 2.0 * c
        g[..., 1] *= height / 2.0 * c
        visible = radii > 0
        norms = g.norm(dim=-1)
        self.grad_accum += (norms * visible).sum(0)
        self.grad_count += visible.sum(0).to(self.grad_count.dtype)

    def _replace(self, new_tensors: dict[str, torch.Tensor], keep: torch.Tensor | None, n_new: int) -> None:
        """Swap in new parameter tensors and rebuild the optimiser state.

        ``keep`` (bool mask over the old rows or None = all) selects which old rows survive;
        ``n_new`` rows appended at the end start with zero Adam moments.
        """
        opt = self.optimizer
        for name in self.param_names:
            old = getattr(self, name)
            new = nn.Parameter(new_tensors[name].contiguous())
            if opt is not None:
                group = next(g for g in opt.param_groups if g["name"] == name)
                state = opt.state.pop(old, None)
                if state is not None:
                    for key in ("exp_avg", "exp_avg_sq"):
                        v = state[key]  # the old parameter's: its rows may be overwritten (row_store)
                        if keep is not None:
                            v = row_store.compact_rows(v, keep)
                        if n_new:
                            v = row_store.append_rows(v, torch.zeros((n_new, *v.shape[1:]), dtype=v.dtype,
                                                                     device=v.device))
                        state[key] = v
                    opt.state[new] = state
                group["params"] = [new]
            grad_buffers.carry(old, new, keep, n_new)  # a long curve's kept gradient buffer, grown in place
            setattr(self, name, new)

    def densify_and_prune(self, *, grad_threshold: float, percent_dense: float, min_opacity: float,
                          max_world_scale: float, max_gaussians: int, generator: torch.Generator | None = None) -> dict:
        """3DGS clone / split / prune. Returns counts {cloned, split, pruned, total}."""
        self.settle()  # the new rows copy the parameters: a lazy optimiser's skipped moves first
        with torch.no_grad():
            grads = self.grad_accum / self.grad_count.clamp_min(1)
            big = self.scales.max(dim=1).values > percent_dense * self.extent
            cand = grads >= grad_threshold
            budget = max(0, max_gaussians - self.num_gaussians)
            if int(cand.sum()) > budget:  # keep the strongest candidates (splits add one row net)
                order = torch.argsort(grads, descending=True)
                cand = torch.zeros_like(cand)
                cand[order[:budget]] = True
                cand &= grads >= grad_threshold
            clone = cand & ~big
            split = cand & big
            names = self.param_names
            p = {n: getattr(self, n).detach() for n in names}

            # clone: same parameters (3DGS)
            add = {n: p[n][clone] for n in names}
            # split: two samples from each big Gaussian, scale / 1.6, replace the original
            ns = int(split.sum())
            if ns:
                stds = self.scales.detach()[split].repeat(2, 1)
                noise = torch.randn(stds.shape, generator=generator, device=stds.device) if generator is not None \
                    else torch.randn_like(stds)
                rots = quat_to_rotmat(p["quats"][split]).repeat(2, 1, 1)
                new_means = torch.bmm(rots, (noise * stds)[..., None])[..., 0] + p["means"][split].repeat(2, 1)
                split_add = {
                    "means": new_means,
                    "log_scales": torch.log(self.scales.detach()[split] / 1.6).repeat(2, 1),
                    "quats": p["quats"][split].repeat(2, 1),
                    "opacity_logits": p["opacity_logits"][split].repeat(2),
                    "sh_dc": p["sh_dc"][split].repeat(2, 1, 1),
                    "sh_rest": p["sh_rest"][split].repeat(2, 1, 1),
                }
                for n in self.extra_lrs:  # trajectories etc.: both halves follow the parent's
                    split_add[n] = p[n][split].repeat(2, *([1] * (p[n].dim() - 1)))
                add = {n: torch.cat([add[n], split_add[n]]) for n in names}
            n_add = add["means"].shape[0]

            # prune: low opacity, huge in world space, split originals, non-finite
            opac = torch.sigmoid(p["opacity_logits"])
            prune = (opac < min_opacity) | split
            prune |= self.scales.detach().max(dim=1).values > max_world_scale * self.extent
            prune |= ~torch.isfinite(p["means"]).all(dim=1)
            keep = ~prune
            if int(keep.sum()) + n_add == 0:  # never prune everything
                keep = torch.ones_like(keep)
            # in place (row_store): ``p``'s tensors are the parameters' own rows, overwritten here
            new = {n: row_store.append_rows(row_store.compact_rows(p[n], keep), add[n]) for n in names}
            self._replace(new, keep, n_add)
            self._reset_stats()
            return {"cloned": int(clone.sum()), "split": ns, "pruned": int(prune.sum()) - ns,
                    "total": self.num_gaussians}

    def append(self, rows: dict[str, torch.Tensor]) -> int:
        """Add Gaussians: ``rows`` holds every name of :attr:`param_names` as [M, ...]. They
        start with zero Adam moments and densification statistics; the old rows keep theirs."""
        m = int(rows["means"].shape[0])
        if m == 0:
            return 0
        self.settle()
        with torch.no_grad():
            new = {n: row_store.append_rows(getattr(self, n), rows[n]) for n in self.param_names}
            self._replace(new, None, m)
            zeros = torch.zeros(m, device=self.grad_accum.device, dtype=self.grad_accum.dtype)
            self.grad_accum = torch.cat([self.grad_accum, zeros])
            self.grad_count = torch.cat([self.grad_count, zeros])
        return m

    def prune(self, mask: torch.Tensor) -> None:
        """Remove rows where ``mask`` is True."""
        self.settle()
        keep = ~mask
        new = {n: row_store.compact_rows(getattr(self, n), keep) for n in self.param_names}
        self._replace(new, keep, 0)
        self._reset_stats()

    def reset_opacity(self, value: float = 0.01) -> None:
        """3DGS opacity reset: clamp opacities to ``value`` and zero their Adam moments."""
        with torch.no_grad():
            new = torch.minimum(self.opacity_logits.detach(), inverse_sigmoid(torch.tensor(value)))
            self.opacity_logits.data.copy_(new)
            if self.optimizer is not None:
                st = self.optimizer.state.get(self.opacity_logits)
                if st:
                    st["exp_avg"].zero_()
                    st["exp_avg_sq"].zero_()

    # ------------------------------------------------------------------ (de)serialisation
    def settle(self) -> None:
        """Bring a lazy optimiser's curves up to its last step (engine.scene.lazy_adam): before
        anything reads or writes the parameters other than a training step's renders. Then, when
        it moved something, the :meth:`on_settle` callbacks (a constraint to re-apply: QuietCurves)."""
        settle = getattr(self.optimizer, "settle", None)
        if settle is None or not settle():  # nothing moved (every curve dense, or all current): as before
            return
        for ref in list(_SETTLE_HOOKS.get(self, ())):
            fn = ref()
            if fn is not None:
                fn(self)

    def trim(self) -> None:
        """Give every parameter and Adam moment storage of its own size (``row_store.exact``): one
        tensor copied at a time, the spare rows freed with it. Before the state is saved
        (``torch.save`` writes a tensor's whole storage, spare rows included; copies of the whole
        state at once would have doubled a long capture's peak memory at every checkpoint)."""
        opt = self.optimizer
        for n in self.param_names:
            p = getattr(self, n)
            p.data = row_store.exact(p.data)
            st = opt.state.get(p) if opt is not None else None
            for key in ("exp_avg", "exp_avg_sq"):
                if st and isinstance(st.get(key), torch.Tensor):
                    st[key] = row_store.exact(st[key])

    def on_settle(self, fn) -> None:
        """Call the bound method ``fn(gaussians)`` after every :meth:`settle` (held weakly, and
        not by the model: a deep copy of it, the budget probe's, carries none)."""
        hooks = _SETTLE_HOOKS.setdefault(self, [])
        if not any(r() == fn for r in hooks):
            hooks.append(weakref.WeakMethod(fn))

    def state(self) -> dict:
        """Everything needed to rebuild the model and its optimiser exactly."""
        self.settle()
        self.trim()
        return {
            "params": {n: getattr(self, n).detach().cpu() for n in self.param_names},
            "extra_lrs": dict(self.extra_lrs),
            "extra_position_like": sorted(getattr(self, "extra_position_like", set())),
            "max_sh_degree": self.max_sh_degree,
            "active_sh_degree": self.active_sh_degree,
            "extent": self.extent,
            "grad_accum": self.grad_accum.cpu(),
            "grad_count": self.grad_count.cpu(),
            "optimizer": self.optimizer.state_dict() if self.optimizer is not None else None,
            "lr_means": getattr(self, "_lr_means", None),
            "instants_only": bool(self.instants_only),
        }

    @classmethod
    def from_state(cls, state: dict, cfg=None, device="cpu") -> "GaussianModel":
        p = state["params"]
        m = cls.__new__(cls)
        nn.Module.__init__(m)
        for n in PARAM_NAMES:
            setattr(m, n, nn.Parameter(p[n].to(device).float()))
        m.extra_lrs = {str(k): float(v) for k, v in (state.get("extra_lrs") or {}).items()}
        m.extra_position_like = set(state.get("extra_position_like") or [])
        for n in m.extra_lrs:
            setattr(m, n, nn.Parameter(p[n].to(device).float()))
        m.max_sh_degree = int(state["max_sh_degree"])
        m.active_sh_degree = int(state["active_sh_degree"])
        m.extent = float(state.get("extent", 1.0))
        m.optimizer = None
        m._reset_stats()
        m.instants_only = bool(state.get("instants_only", False))
        if state.get("grad_accum") is not None and state["grad_accum"].shape[0] == m.num_gaussians:
            m.grad_accum = state["grad_accum"].to(device)
            m.grad_count = state["grad_count"].to(device)
        if cfg is not None:
            m.setup_optimizer(cfg, m.extent)
            if state.get("optimizer") is not None:
                m.optimizer.load_state_dict(state["optimizer"])
            if state.get("lr_means") is not None:
                m._lr_means = tuple(state["lr_means"])
        return m
