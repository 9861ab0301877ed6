"""Selective (sparse) Adam: a step updates only what the step's renders touched (issue 13).

gsplat's ``SelectiveAdam`` (``gsplat/optimizers/selective_adam.py``, its ``adam_kernel``
in ``AdamCUDA.cu``) and Taming 3DGS's sparse Adam update a Gaussian's parameters and
Adam moments only where a visibility mask [N] (``radii > 0`` of the step's renders) is
true; the others keep their moments and parameters as they are: not decayed, not moved by
momentum. With per-Gaussian trajectories (``engine.scene.trajectory``) ~133 of a
Gaussian's ~190 floats are curve control points, and a render at time ``t`` reads at most
six of a curve's ``K`` columns (one at an RGB instant), so here the curves' moments are
updated at the columns some :func:`engine.scene.trajectory.evaluate` read for a gradient
since the last step (:func:`engine.scene.trajectory.touched_columns`), too.

:class:`SelectiveAdam` is :class:`engine.scene.fused_adam.FusedAdam` (same state,
checkpoints, densification surgery) whose step runs over

* the rows visible in any render made under autograd since the last step
  (:meth:`SelectiveAdam.note_visible`, called by ``Model4D.render``), plus the rows with a
  nonzero gradient in a selected element: terms that are not renders (the spike-view flow
  term, the rigidity prior) keep their gradient, where gsplat's step would drop it;
* for the parameter groups named in :attr:`SelectiveAdam.curves` ([N, K, C]), the touched
  columns only (a curve's inner-residual prior reaches the other columns; that gradient is
  dropped, as a gsplat step drops an invisible Gaussian's).

Per element the arithmetic is FusedAdam's (torch's Adam, bias-corrected with the group's
step count, which every step advances): with every row visible and every column touched
the step is FusedAdam's bit for bit (tests). gsplat's kernel omits the bias correction;
this one keeps it so that the switch changes only which entries move. Without a render
noted since the last step (a plain ``opt.step()``) the step is FusedAdam's.
"""
from __future__ import annotations

import numpy as np
import torch

from . import fused_adam, trajectory
from .fused_adam import KERNELS, FusedAdam, adam_moments, exact, torch_adam_update


def _spans(cols: list[int] | None, shape: tuple) -> np.ndarray:
    """Element spans [S, 2] (start, stop) within one row of a [N, ...] parameter: the whole
    row, or for a [N, K, C] curve its columns ``cols`` (adjacent ones merged)."""
    d = int(np.prod(shape[1:], dtype=np.int64)) if len(shape) > 1 else 1
    if cols is None:
        return np.array([[0, d]], dtype=np.int64)
    c = int(shape[2])
    out: list[list[int]] = []
    for col in cols:
        if out and out[-1][1] == col * c:
            out[-1][1] += c
        else:
            out.append([col * c, (col + 1) * c])
    return np.array(out, dtype=np.int64).reshape(-1, 2)


class SelectiveAdam(FusedAdam):
    """FusedAdam over the rows (and curve columns) a step touched (module docstring).

    ``curves``: names of the parameter groups holding [N, K, C] curves whose untouched
    columns are left alone (``Model4D`` adds the trajectories'). Rows are the first axis
    of every parameter, the Gaussians."""

    def __init__(self, params, **kwargs):
        super().__init__(params, **kwargs)
        self.curves: set[str] = set()
        self._visible: torch.Tensor | None = None
        self.last_selected = None  # (rows updated, rows) of the last selective step, for tools

    @torch.no_grad()
    def note_visible(self, radii: torch.Tensor) -> None:
        """OR the Gaussians with ``radii > 0`` ([C, N] or [C, N, 2], a render's meta) into
        this step's rows."""
        vis = radii > 0
        if vis.dim() == 3:
            vis = vis.any(-1)
        vis = vis.any(0) if vis.dim() == 2 else vis
        if self._visible is None or self._visible.shape != vis.shape:
            self._visible = vis.clone()
        else:
            self._visible |= vis

    @torch.no_grad()
    def step(self, closure=None):
        visible, self._visible = self._visible, None
        try:
            if visible is None or not (fused_adam.ENABLED and self._plain() and exact()):
                return super().step(closure)
            loss = None
            if closure is not None:
                with torch.enable_grad():
                    loss = closure()
            self._selective_step(visible)
            return loss
        finally:
            trajectory.clear_touched()

    def _buffers(self, need: int, n: int):
        """Scratch: compact square roots (a tensor: torch's sqrt runs on it), new first
        moments and zero flags of ``need`` elements, selected rows of ``n``."""
        b = getattr(self, "_bufs", None)
        if b is None or b[0].numel() < need or b[3].shape[0] < n:
            b = self._bufs = (torch.empty(need, dtype=torch.float32), np.empty(need, np.float32),
                              np.empty(need, np.bool_), np.empty((n, 2), np.uint64))
        return b

    @torch.no_grad()
    def _selective_step(self, visible: torch.Tensor) -> None:
        vis = np.ascontiguousarray(visible.detach().cpu().numpy().astype(np.bool_))
        n = vis.shape[0]
        all_rows = bool(vis.all())
        need = max((p.numel() for g in self.param_groups for p in g["params"] if p.grad is not None), default=0)
        root_t, m_new, zero, runs = self._buffers(need, n)
        root = root_t.numpy()
        k = KERNELS.module
        f32 = np.float32
        selected = 0
        for g in self.param_groups:
            beta1, beta2 = g["betas"]
            for p in g["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                m, v = adam_moments(state, p, "SelectiveAdam")
                step, lr = float(state["step"].item()), float(g["lr"])
                cols = None
                if g.get("name") in self.curves and p.dim() == 3:
                    cols = trajectory.touched_columns(p.shape[1])  # None: no record, every column
                if p.dim() == 0 or p.shape[0] != n or (all_rows and cols is None):
                    fused_adam._fused_update(p, p.grad, m, v, step, lr, float(beta1), float(beta2),
                                             float(g["eps"]), root_t)
                    continue
                bias_correction2_sqrt = (1 - beta2 ** step) ** 0.5
                step_size = lr / (1 - beta1 ** step)
                d = p.numel() // n if n else 0
                pf, gf, mf, vf = (t.detach().view(-1).numpy() for t in (p, p.grad, m, v))
                spans = _spans(cols, tuple(p.shape))
                if runs.shape[0] < n * spans.shape[0]:
                    runs = np.empty((n * spans.shape[0], 2), np.uint64)
                n_runs, n_sel, n_el = k.select_runs(gf, d, vis, spans, runs)
                if n_el:
                    k.selective_moments(gf, mf, vf, runs, n_runs, f32(1 - beta1), f32(beta2), f32(1 - beta2),
                                        root, m_new, zero)
                    r = root_t[:n_el]
                    torch.sqrt(r, out=r)  # torch's (MKL's) rounding, as FusedAdam
                    k.selective_update(pf, runs, n_runs, root, m_new, zero, f32(bias_correction2_sqrt),
                                       f32(g["eps"]), f32(-step_size))
                selected = max(selected, int(n_sel))
        self.last_selected = (selected, n)


def reference_step(p: torch.Tensor, grad: torch.Tensor, m: torch.Tensor, v: torch.Tensor, step: int,
                   lr: float, betas=(0.9, 0.999), eps: float = 1e-8, rows: torch.Tensor | None = None,
                   cols: list[int] | None = None) -> None:
    """Plain-torch selective Adam (the tests' reference): torch's single-tensor Adam
    formulas on the entries of the selected ``rows`` (bool [N]; None: all, and the rows with a
    nonzero gradient in a selected element) and curve columns ``cols`` (None: all), in place;
    ``step``: the step count after this step."""
    n = p.shape[0]
    el = torch.zeros(p.shape, dtype=torch.bool)
    if cols is None:
        el[:] = True
    else:
        el[:, cols] = True
    r = torch.ones(n, dtype=torch.bool) if rows is None else rows.clone()
    r |= ((grad != 0) & el).reshape(n, -1).any(1)
    el &= r.reshape((n,) + (1,) * (p.dim() - 1))
    gs, ms, vs, ps = grad[el], m[el], v[el], p[el]
    torch_adam_update(ps, gs, ms, vs, step, lr, betas, eps)
    m[el], v[el], p[el] = ms, vs, ps


def warmup() -> float:
    """Compile (first run on a machine) or load the selective kernels now; seconds taken."""
    import time

    t0 = time.perf_counter()
    if exact():
        p = torch.nn.Parameter(torch.zeros(4, 4, 3))
        opt = SelectiveAdam([{"params": [p], "lr": 1e-3, "name": "w"}], lr=0.0)
        opt.curves.add("w")
        p.grad = torch.ones_like(p)
        opt.note_visible(torch.tensor([[1, 0, 1, 1]]))
        trajectory._note_touched(4, [1])
        opt.step()
    return time.perf_counter() - t0
