"""Lazy Adam for the curves: a step costs the columns it touched, not the capture's length (issue 13).

A per-Gaussian curve (``engine.scene.trajectory``) carries one control-point column per third
of an RGB interval, K = 3 (F - 1) + 1 of them, while a step's renders read at most six (one
at an RGB instant). Dense Adam (:class:`engine.scene.fused_adam.FusedAdam`) still updates
every entry of every curve at every step: an entry without a gradient keeps decaying its
moments and moving on its momentum. On a 1 s capture (K = 88) that is a third of the RGB
step; a 3 s capture triples it (docs/experiments/benchmark-history.md "A longer capture").

:class:`LazyCurveAdam` updates a curve's columns only when a step touched them, and then
first catches up on the steps they skipped, in closed form. With no gradient for ``s``
steps after step ``t0``, dense Adam takes the moments to ``beta1^s m``, ``beta2^s v`` and
moves the entry by

    sum_{j=1..s} lr_{t0+j} / bc1_{t0+j} * beta1^j m / (beta2^(j/2) sqrt(v) / bc2s_{t0+j} + eps)
      = (m / sqrt(v)) * sum_{j=1..s} a_{t0+j} r^j,   a_u = lr_u bc2s_u / bc1_u,  r = beta1 / sqrt(beta2)

(eps neglected: 1e-15 here, against sqrt(v) of any gradient that ever reached the entry).
The sum is one scalar per column (every row of a column skipped the same steps), taken from
the group's record of ``a_u``; terms beyond :data:`HORIZON` steps are below float32's
resolution (``r^HORIZON`` ~ 1e-27). So a touched column gets, in one pass, the dense
optimizer's moments and parameter up to rounding; what differs is *when* the skipped motion
lands: at the column's next touch (or :meth:`LazyCurveAdam.settle`) instead of step by step,
so a column a render reads between its touches would be where its last update left it.
Hence the read catch-up (:data:`READ_CATCH_UP`): every curve evaluation first brings the
columns it is about to read up to the last step (``trajectory.on_read``: :func:`evaluate`, the
spike-view flow term's row subsets), so a render reads, to rounding, what dense Adam would have
left there, and the touched columns' step then has nothing to catch up. What still differs
from dense Adam is the inner-residual prior (below) on the columns a step does not touch.

Whatever reads or writes the curves other than a step's renders must call
:meth:`LazyCurveAdam.settle` first (``GaussianModel.settle``, which then runs the
``on_settle`` callbacks: the quiet curves re-apply their mask): densification's row
surgery, the curriculum's carry of junctions, the spike-flow fit, births, checkpoints (so
the end of a run).

Which columns a step touched: those some :func:`engine.scene.trajectory.evaluate` (and the
spike-view flow term) read for a gradient since the last step
(:func:`engine.scene.trajectory.touched_columns`). A curve gradient with no such record
(a plain autograd reader) makes every column touched: the dense step, caught up. The
inner-residual prior (``traj_inner_weight``: w mean|D|^2 / extent^2, whose gradient reaches
every inner column at every step) is not a loss term here: the loss term hands its weight
to :attr:`LazyCurveAdam.inner_decay` and the step adds the prior's gradient to the inner
columns it updates (a column's prior acts when the column is trained; the dense prior's
forward and backward read and write every inner column: 14 ms of a guided step on a 1 s capture).

Every other parameter group is :class:`FusedAdam`'s (torch's Adam bit for bit).
"""
from __future__ import annotations

import functools
import math
import weakref

import numpy as np
import torch

from . import fused_adam, grad_buffers, trajectory
from .fused_adam import KERNELS, FusedAdam, adam_moments, torch_adam_update

# False: the columns' updates in torch ops (reference_columns), as the first version
FUSED = True
# False: a kept gradient buffer's read columns are zeroed by grad_buffers at the next take, not here
CLEAR_BUFFERS = True
# False: a render reads a lazy column where its last touch left it, the skipped steps' momentum
# landing at its next touch (the first version: train views -0.08 dB on average over eight
# 1000-step runs, docs/experiments/benchmark-history.md "Lazy curve Adam"); True: the read catches the column up first
READ_CATCH_UP = True
# False: the read's catch-up also decays the moments (and writes them), as first built; True: the
# values alone, the moments' decay left to the column's next step or settle (same numbers: the decay
# is the same product either way)
READ_VALUES_ONLY = True
HORIZON = 600  # skipped steps summed: r^600 = (0.9 / 0.9995)^600 ~ 4e-28


class LazyCurveAdam(FusedAdam):
    """FusedAdam whose [N, K, C] curve groups (``curves``: their names, set by ``Model4D``)
    are updated at the touched columns, with the skipped steps caught up (module docstring)."""

    def __init__(self, params, min_columns: int = 0, dense_inner_below: int = 0, **kwargs):
        super().__init__(params, **kwargs)
        self.curves: set[str] = set()
        # curves with fewer columns are updated whole at every step: FusedAdam bit for bit
        self.min_columns = int(min_columns)
        # a run that promised to read no inner column (GaussianModel.instants_only) steps short curves
        # lazily too; should a step read one of a curve under this many columns after all, that curve
        # class goes back to dense (settled first), since the prior would then act on untouched columns
        self.dense_inner_below = int(dense_inner_below)
        self._a: dict[str, list[float]] = {}      # group name -> a_u for u = 1, 2, .. (index u - 1)
        # id(param) -> (weakref, int64 [K]: step the column's moments are at, int64 [K]: step its values are
        # at, never behind the moments: a read catches the values up alone, the moments' decay waits for a step)
        self._cols: dict[int, tuple] = {}
        self.last_touched: int | None = None       # columns updated by the last step (tools, tests)
        # group name -> w / extent^2 of the inner-residual prior w mean|D|^2 / extent^2, whose
        # gradient on the touched inner columns the step adds itself (the loss term sets it)
        self.inner_decay: dict[str, float] = {}
        self.settles = 0                           # settle() calls (QuietCurves: then apply its mask whole)
        self._last_cols: dict[int, tuple] = {}  # id(param) -> (weakref, the columns the last step updated)
        self._foreign: set[int] = set()  # id(param) of curves a plain autograd reader reached since the last step
        self.caught_up = 0  # columns the read catch-up moved (tools, tests)
        self._catch_up_hooks: list = []  # weak fn(param, columns) after a read catch-up (QuietCurves)

    # ---- bookkeeping ----------------------------------------------------------------------
    def _column_steps(self, p: torch.Tensor, step: int) -> tuple[np.ndarray, np.ndarray]:
        """(the step each column's moments are at, the step its values are at) of curve ``p``: the
        record, made at ``step`` for a new tensor."""
        hit = self._cols.get(id(p))
        if hit is None or hit[0]() is not p or hit[1].shape[0] != p.shape[1]:
            # a new tensor (densification swaps them after settle()): every column is current
            if hit is None or hit[0]() is not p:  # once per tensor: a hook registered again would stay too
                p.register_hook(functools.partial(_foreign, weakref.ref(self), id(p)))
                trajectory.on_read(p, functools.partial(_read_hook, weakref.ref(self)))
            hit = self._cols[id(p)] = (weakref.ref(p), np.full(p.shape[1], step, np.int64),
                                       np.full(p.shape[1], step, np.int64))
        return hit[1], hit[2]

    def _group_of(self, p: torch.Tensor) -> dict | None:
        return next((grp for grp in self.param_groups if any(q is p for q in grp["params"])), None)

    def _record_a(self, g: dict, step: int) -> list[float]:
        beta1, beta2 = g["betas"]
        a = self._a.setdefault(g["name"], [])
        del a[step - 1:]  # a restart from a checkpoint rewrites the record from its step
        while len(a) < step:  # this step's a_u, after any this record missed (a restart: their lr is unknown)
            u = len(a) + 1
            a.append(float(g["lr"]) * math.sqrt(1 - beta2 ** u) / (1 - beta1 ** u))
        return a

    def _coast(self, g: dict, since: np.ndarray, upto: int, moved_to: np.ndarray) -> tuple:
        """Per column, for the steps ``since + 1 .. upto`` it skipped (its moments at ``since``): (their
        count s, the momentum factor sum_{j<=s} a_{since+j} r^j over the steps after ``moved_to``, the
        step its values are already at, beta1^s, beta2^s)."""
        beta1, beta2 = g["betas"]
        r = beta1 / math.sqrt(beta2)
        a = self._a.get(g["name"], [])
        s = (upto - since).astype(np.int64)
        total = np.zeros(s.shape[0], np.float64)
        for k in np.nonzero(s > 0)[0]:
            t0, n = int(since[k]), int(min(s[k], HORIZON))
            j0 = int(moved_to[k]) - t0 + 1  # the first step not yet moved
            if j0 > n:
                continue
            seg = np.asarray(a[t0 + j0 - 1:t0 + n], np.float64)  # a_{t0+j0} .. a_{t0+n}
            total[k] = float(np.dot(seg, r ** np.arange(j0, j0 + seg.shape[0])))
        return s, total, np.power(beta1, s.astype(np.float64)), np.power(beta2, s.astype(np.float64))

    # ---- the step -------------------------------------------------------------------------
    @torch.no_grad()
    def step(self, closure=None):
        try:
            loss = None
            if closure is not None:
                with torch.enable_grad():
                    loss = closure()
            self._lazy_step()
            return loss
        finally:
            trajectory.clear_touched()

    @torch.no_grad()
    def _lazy_step(self) -> None:
        touched_total = 0
        if self.min_columns < self.dense_inner_below and self._short_inner_read():
            self.settle()
            self.min_columns = self.dense_inner_below
        for g in self.param_groups:
            for p in g["params"]:
                if p.grad is None:
                    continue
                if not self.lazy_for(p, g):
                    self._dense(g, p)
                    continue
                state = self.state[p]
                m, v = adam_moments(state, p, "LazyCurveAdam")
                step = int(state["step"].item())
                self._record_a(g, step)
                at, moved = self._column_steps(p, step - 1)
                cols = trajectory.touched_columns(p.shape[1])
                if cols is None or id(p) in self._foreign:  # a reader that says nothing: every column
                    cols = np.arange(p.shape[1])
                cols = np.asarray(cols, np.int64)
                touched_total += cols.size
                _update_columns(p, p.grad, m, v, cols, at, moved, step, g, self, self._decay(g, p))
                self._last_cols[id(p)] = (weakref.ref(p), cols)
        self.last_touched = touched_total
        self._foreign.clear()

    def _short_inner_read(self) -> bool:
        """Whether this step read an inner column of a curve under :attr:`dense_inner_below` columns."""
        short = {p.shape[1] for g in self.param_groups if g.get("name") in self.curves for p in g["params"]
                 if p.dim() == 3 and p.shape[1] < self.dense_inner_below}
        return any(c % 3 for k in short for c in (trajectory.touched_columns(k) or ()))

    def lazy_for(self, p: torch.Tensor, g: dict | None = None) -> bool:
        """Whether ``p`` is updated at its touched columns (a curve of at least
        :attr:`min_columns` columns) rather than whole."""
        if g is None:
            g = self._group_of(p)
        return (g is not None and g.get("name") in self.curves and p.dim() == 3
                and p.shape[1] >= self.min_columns)

    def _decay(self, g: dict, p: torch.Tensor) -> float:
        """The prior's gradient factor on an inner entry: d/dD of w mean|D|^2 / extent^2 over the
        N (F - 1) 2 inner points = (w / extent^2) / (N (F - 1))."""
        coef = self.inner_decay.get(g.get("name"), 0.0)
        segments = (p.shape[1] - 1) // 3
        return coef / (p.shape[0] * segments) if coef and segments and p.shape[0] else 0.0

    def last_columns(self, p: torch.Tensor) -> np.ndarray | None:
        """The columns of curve ``p`` the last step updated (None: unknown, or all)."""
        hit = self._last_cols.get(id(p))
        return hit[1] if hit is not None and hit[0]() is p else None

    def _dense(self, g: dict, p: torch.Tensor) -> None:
        """Every entry of ``p`` (not a lazy curve): FusedAdam's update where it is exact, else
        torch's single-tensor formulas (CUDA, float64): torch's Adam either way."""
        state = self.state[p]
        m, v = adam_moments(state, p, "LazyCurveAdam")
        self._dense_update(g, p, m, v, float(state["step"].item()))

    def _dense_update(self, g: dict, p: torch.Tensor, m, v, step: float) -> None:
        lr, (beta1, beta2), eps = float(g["lr"]), g["betas"], float(g["eps"])
        if not (fused_adam.ENABLED and fused_adam.exact() and fused_adam._supported(p)):
            torch_adam_update(p.data, p.grad, m, v, step, lr, (beta1, beta2), eps)
            return
        one_pass = fused_adam.ONE_PASS and fused_adam.one_pass_exact()
        fused_adam._fused_update(p, p.grad, m, v, step, lr, float(beta1), float(beta2), eps,
                                 self._scratch_for(p.numel(), one_pass), one_pass)

    @torch.no_grad()
    def catch_up(self, p: torch.Tensor, cols) -> int:
        """Bring columns ``cols`` of lazy curve ``p`` up to the last step (the steps they skipped),
        before a render reads them; then the :meth:`on_catch_up` callbacks. Returns how many moved."""
        hit = self._cols.get(id(p))
        state = self.state.get(p)
        if hit is None or hit[0]() is not p or not state or hit[1].shape[0] != p.shape[1]:
            return 0
        step = int(state["step"].item())
        at, moved = hit[1], hit[2]
        cols = np.asarray(cols, np.int64)
        behind = np.unique(cols[moved[cols] < step])
        if not behind.size:
            return 0
        g = self._group_of(p)
        # the values alone (the read needs them): the moments' decay is left to the column's next
        # step or settle, which reads and writes them anyway (a third less memory traffic here)
        _update_columns(p, None, state["exp_avg"], state["exp_avg_sq"], behind, at, moved, step, g, self,
                        moments=not READ_VALUES_ONLY)
        self.caught_up += int(behind.size)
        for ref in list(self._catch_up_hooks):
            fn = ref()
            if fn is not None:
                fn(p, behind)
        return int(behind.size)

    def on_catch_up(self, fn) -> None:
        """Call the bound method ``fn(param, columns)`` after every read catch-up (held weakly): a
        constraint on the curves to re-apply on those columns (the quiet curves' zeros)."""
        if not any(r() == fn for r in self._catch_up_hooks):
            self._catch_up_hooks.append(weakref.WeakMethod(fn))

    @torch.no_grad()
    def settle(self) -> bool:
        """Bring every curve column up to the last step (the skipped steps' moves and decay).
        Returns whether any column moved."""
        moved = False
        for g in self.param_groups:
            for p in g["params"]:
                state = self.state.get(p)
                if not state or not self.lazy_for(p, g):
                    continue
                step = int(state["step"].item())
                at, moved_to = self._column_steps(p, step)
                behind = np.nonzero(at < step)[0]
                if behind.size:
                    _update_columns(p, None, state["exp_avg"], state["exp_avg_sq"], behind, at, moved_to, step, g, self)
                    moved = True
        self.settles += 1  # whoever settles may write next: a hook applying a mask must redo it whole
        return moved


def _foreign(opt_ref, key: int, grad) -> None:
    """Tensor hook of a lazy curve: a gradient that autograd accumulated (a reader that is not a
    curve evaluation noting its columns; None when every reader summed in place,
    ``trajectory.gradient_sink``) may be in any column, so the next step updates them all."""
    opt = opt_ref()
    if grad is not None and opt is not None:
        opt._foreign.add(key)


def _read_hook(opt_ref, p: torch.Tensor, cols) -> None:
    """``trajectory.on_read`` hook of a lazy curve: catch its read columns up (:data:`READ_CATCH_UP`)."""
    opt = opt_ref()
    if opt is not None and READ_CATCH_UP:
        opt.catch_up(p, cols)


def _update_columns(p, grad, m, v, cols: np.ndarray, at: np.ndarray, moved: np.ndarray, step: int, g: dict,
                    opt: LazyCurveAdam, decay: float = 0.0, moments: bool = True) -> None:
    """Columns ``cols`` of curve ``p``: catch up from ``at[cols]`` (the moments' step; the values
    from ``moved[cols]``) to ``step - 1`` (``grad`` given: then this step's Adam
    update, ``decay`` times the parameter added to the inner columns' gradient) or to ``step``
    (``grad`` None: settle; ``moments`` False: the values alone, a read's catch-up)."""
    beta1, beta2 = g["betas"]
    upto = step - 1 if grad is not None else step
    s, coast, d1, d2 = opt._coast(g, at[cols], upto, moved[cols])
    f32 = np.float32

    def done():
        if moments:
            at[cols] = step
        moved[cols] = step
    if grad is not None and not decay and cols.size == p.shape[1] and not (s > 0).any():
        # every column, none behind: the dense update (FusedAdam's pass: torch's Adam bit for bit)
        opt._dense_update(g, p, m, v, float(step))
        done()
        return
    k = KERNELS.load() if FUSED else None
    if k is not None and _fusable(p, grad, m, v):
        n, kk, c = p.shape
        pf, mf, vf = (t.detach().view(-1).numpy() for t in (p, m, v))
        gf = grad.detach().view(-1).numpy() if grad is not None else pf
        # a kept gradient buffer (long captures): its read columns zeroed in this pass, not by a
        # strided pass of their own at the next step's first reader (~3 ms per curve on a 1 s capture)
        clear = grad is not None and CLEAR_BUFFERS and grad_buffers.holds(p, grad)
        k.lazy_step(pf, gf, mf, vf, kk * c, c, cols, coast.astype(f32), d1.astype(f32), d2.astype(f32),
                    f32(1 - beta1), f32(beta2), f32(1 - beta2), grad is not None, f32(decay),
                    f32(math.sqrt(1 - beta2 ** step)), f32(g["eps"]), f32(-float(g["lr"]) / (1 - beta1 ** step)), clear,
                    moments)
        if clear:
            grad_buffers.cleaned(p, cols)
        done()
        return
    reference_columns(p, grad, m, v, cols, s, coast, d1, d2, step, float(g["lr"]), (beta1, beta2), float(g["eps"]),
                      decay, moments)
    done()


def _fusable(p, grad, m, v) -> bool:
    ts = (p, m, v) if grad is None else (p, grad, m, v)
    return all(t.device.type == "cpu" and t.dtype == torch.float32 and t.is_contiguous() and t.shape == p.shape
               for t in ts)


def reference_columns(p, grad, m, v, cols, s, coast, d1, d2, step: int, lr: float, betas, eps: float,
                      decay: float = 0.0, moments: bool = True) -> None:
    """Plain-torch lazy update of columns ``cols`` (the tests' reference and the fallback):
    catch-up (``s`` skipped steps, ``coast`` their summed momentum factor, ``d1``/``d2`` the
    moments' decay), then torch's single-tensor Adam formulas with ``grad`` (None: none) plus
    ``decay`` times the parameter on the inner columns."""
    beta1, beta2 = betas
    cols = np.asarray(cols, np.int64)
    idx = torch.from_numpy(cols).to(p.device)
    pc, mc, vc = p.data[:, idx], m[:, idx], v[:, idx]
    stale = pc.clone()
    if (np.asarray(s) > 0).any():
        per = lambda x: torch.as_tensor(np.asarray(x, np.float32), device=p.device)[None, :, None]  # noqa: E731
        pos = vc > 0
        pc -= per(coast) * torch.where(pos, mc / torch.where(pos, vc.sqrt(), torch.ones_like(vc)), torch.zeros_like(mc))
        mc *= per(d1)
        vc *= per(d2)
    if grad is not None:
        gc = grad[:, idx]
        if decay:
            inner = torch.from_numpy(cols % 3 != 0).to(p.device)[None, :, None]
            gc = torch.where(inner, gc + np.float32(decay) * stale, gc)
        torch_adam_update(pc, gc, mc, vc, step, lr, betas, eps)
    p.data[:, idx] = pc
    if moments:
        m[:, idx] = mc
        v[:, idx] = vc


def warmup() -> float:
    """Compile (first run on a machine) or load the lazy kernels now; seconds taken."""
    import time

    t0 = time.perf_counter()
    if KERNELS.load() is not None:
        p = torch.nn.Parameter(torch.zeros(4, 4, 3))
        opt = LazyCurveAdam([{"params": [p], "lr": 1e-3, "name": "w"}], lr=0.0, eps=1e-15)
        opt.curves.add("w")
        for cols in ([1], [2]):  # the second step catches column 1 up
            p.grad = torch.ones_like(p)
            trajectory._note_touched(4, cols)
            opt.step()
        opt.settle()
    return time.perf_counter() - t0
