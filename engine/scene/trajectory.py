"""Per-Gaussian parametric trajectories: piecewise cubic Bezier curves over capture time.

A HexPlane field (``engine.deformation``) shares its motion through a grid: a fast object
that moves about its own size per frame becomes a ghost (issue 11). Here every Gaussian
owns its curve, as in E-NeMF (Bezier control points, ``../shared/papers/e-nemf.txt``
Sec. 3.2, Eq. 4-5) and Spacetime Gaussians (per-Gaussian polynomial motion).

The curve is piecewise cubic Bezier with one segment per interval between *knots* (the
capture's RGB instants ``T_0 < ... < T_{F-1}``). One parameter tensor per Gaussian holds,
along its second axis (``K = 3 (F - 1) + 1`` entries, ``C`` channels):

* ``params[:, 3 i]`` -- the junction value ``X_i`` at knot ``T_i`` (what both RGB cameras
  see at that instant: the curve passes exactly through it);
* ``params[:, 3 i + 1]``, ``params[:, 3 i + 2]`` -- residuals ``D_i0, D_i1`` of segment
  ``i``'s inner control points from their Catmull-Rom defaults::

      P1 = X_i     + v_i     h_i / 3 + D_i0        v_i = (X_{i+1} - X_{i-1}) / (T_{i+1} - T_{i-1})
      P2 = X_{i+1} - v_{i+1} h_i / 3 + D_i1        (one-sided at the ends), h_i = T_{i+1} - T_i

  With zero residuals the curve is the C1 Catmull-Rom spline through the junctions, so a
  run supervised at the RGB instants only gets smooth in-between motion for free; the
  between-frame losses (spike / block colour) move the residuals: the inner control
  points of E-NeMF's curves.

For ``t`` in segment ``i`` with ``u = (t - T_i) / h_i``:
``B(u) = (1-u)^3 X_i + 3 (1-u)^2 u P1 + 3 (1-u) u^2 P2 + u^3 X_{i+1}``; ``t`` outside
``[T_0, T_{F-1}]`` is clamped (the curve holds its end values).

Shapes: ``params`` [N, K, C] (C = 3 for position offsets, 4 for quaternion residuals),
``knot_times`` [F] ascending (seconds); results [N, C]. Everything is differentiable in
``params`` (torch autograd); only the four junctions and two residuals around ``t`` are
read, so a call costs O(N) whatever the number of knots.

The curve at a fixed ``t`` is linear in ``params``: ``B(t) = sum_j w_j params[:, c_j]``
over at most six columns ``c_j`` (junctions ``X_{i-1} .. X_{i+2}``, residuals ``D_i0, D_i1``)
with scalar weights ``w_j(t)`` (:func:`segment_weights`). :func:`evaluate` computes it in
that form with a hand-written backward that writes ``w_j * grad`` into those columns
only (issue 13: built from column slices, autograd's backward materialised one full
``[N, K, C]`` zero tensor per slice, ~16 per render, and summed them).
:func:`evaluate_reference` is the slice-by-slice torch code it is tested against; at the
RGB instants (``u`` = 0 or 1) both give the junction value and its gradient bit for bit.
"""
from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import torch

from ..numba_cache import LazyKernels
from . import grad_buffers
from .curve_reads import _TOUCHED, _note_touched, before_read, clear_touched, on_read, touched_columns  # noqa: F401

KERNELS = LazyKernels(__package__, "_trajectory_kernels")  # the residual-square term's numba pair

__all__ = ["num_controls", "num_knots", "segment_of", "segment_weights", "bezier_controls", "evaluate",
           "evaluate_reference", "junctions", "extrapolate_junctions", "inner_residuals", "inner_residual_sq",
           "default_knots", "touched_columns", "clear_touched", "gradient_sink", "sunk", "zeros_then", "on_read",
           "before_read"]

# "fast": :func:`evaluate` uses the column-weight form (:class:`_CurveAt`); "torch": the
# reference slice-by-slice code (bench-step's "traj-reference" variant switches it)
EVALUATOR = "fast"

def num_controls(n_knots: int) -> int:
    """``K`` parameter entries for ``n_knots`` knots (1 knot: a constant offset)."""
    return 3 * (max(1, int(n_knots)) - 1) + 1


def num_knots(n_controls: int) -> int:
    """Inverse of :func:`num_controls`."""
    if (int(n_controls) - 1) % 3:
        raise ValueError(f"{n_controls} trajectory controls: expected 3 (F - 1) + 1")
    return (int(n_controls) - 1) // 3 + 1


def _knots(knot_times) -> list[float]:
    k = [float(x) for x in knot_times]
    if any(b <= a for a, b in zip(k, k[1:])):
        raise ValueError(f"trajectory knot times must increase strictly: {k}")
    return k


def segment_of(knot_times, t: float) -> tuple[int, float]:
    """(segment index ``i``, local parameter ``u`` in [0, 1]) of time ``t`` (clamped)."""
    k = _knots(knot_times)
    if len(k) < 2:
        return 0, 0.0
    t = min(max(float(t), k[0]), k[-1])
    i = 0
    while i < len(k) - 2 and t >= k[i + 1]:
        i += 1
    return i, (t - k[i]) / (k[i + 1] - k[i])


def junctions(params: torch.Tensor) -> torch.Tensor:
    """The curve's values at the knots: [N, F, C]."""
    return params[:, 0::3]


def inner_columns(n_controls: int) -> list[int]:
    """The inner control points' columns ``3 i + 1``, ``3 i + 2`` of a curve with ``n_controls``."""
    return [c for c in range(int(n_controls) - 1) if c % 3]


def inner_residuals(params: torch.Tensor) -> torch.Tensor:
    """The inner control points' residuals ``D``: [N, F - 1, 2, C]."""
    n, k, c = params.shape
    if k == 1:
        return params.new_zeros(n, 0, 2, c)
    inner = params[:, :-1].reshape(n, (k - 1) // 3, 3, c)
    return inner[:, :, 1:]

# ---- the curves' gradient summed in place (issue 13) ------------------------------------------
# A guided step reads the curves at several places: the RGB render's instant, the between-frame
# render's, the residual term, the flow term's subset. Autograd gives each reader's backward its
# own full [N, K, C] gradient (zeros outside the few columns it read) and sums them in full
# tensors: ~1.2 ms per full gradient and ~1.8 ms per full add of the position curves at 26k
# Gaussians (torch profiler, guided demo steps). Inside :func:`gradient_sink` (the trainer's
# ``backward()``) the first reader of a leaf still writes the full gradient and sets it as the
# leaf's ``.grad`` (what autograd's accumulation would do with it); every later reader adds its
# columns into that ``.grad`` in the order autograd runs them, so each entry is the same sum,
# with the same rounding, as autograd's (an entry no later reader touched keeps its -0.0 where
# autograd's ``x + 0`` would make it +0.0; Adam's update is the same for either zero).

# False: every reader's backward returns its full gradient to autograd (bench-step's "sink-off")
SINK = True
_SINK: dict | None = None  # id(leaf) -> leaf whose .grad the running backward created


@contextmanager
def gradient_sink():
    """Sum the curves' gradients in place during the ``backward()`` run inside this block
    (:func:`sunk`). Only around a plain ``backward()``: ``torch.autograd.grad`` must not run in
    it (it returns gradients instead of accumulating them)."""
    global _SINK
    prev, _SINK = _SINK, ({} if SINK else None)
    try:
        yield
    finally:
        _SINK = prev


def sunk(params, write_full, add_into, cols=None):
    """What a reader's backward returns for the curves ``params``: ``write_full()`` (a fresh
    full gradient) outside :func:`gradient_sink` or when ``params`` is not a CPU leaf whose
    ``.grad`` was None when this backward began; otherwise None, after setting ``.grad`` to
    the leaf's reused zero buffer with ``add_into`` applied (:mod:`engine.scene.grad_buffers`;
    ``write_full()`` when it cannot have one) for the first reader, or calling
    ``add_into(params.grad)`` (later readers). ``cols``: the columns ``add_into`` writes
    (None: any), which the buffer zeroes again before the next step's first reader."""
    state = _SINK
    if state is None or params is None or not params.is_leaf or params.device.type != "cpu":
        return write_full()
    if id(params) in state:
        grad_buffers.mark(params, cols)
        add_into(params.grad)
        return None
    if params.grad is not None:  # a gradient from before this backward: autograd sums as it would
        return write_full()
    if grad_buffers.usable(params):
        buf = grad_buffers.take(params)
        grad_buffers.mark(params, cols)
        add_into(buf)
        params.grad = buf
    else:
        params.grad = write_full()
    state[id(params)] = params
    return None


def zeros_then(kernel, shape, *args) -> torch.Tensor:
    """A zero tensor of ``shape`` (``args[0]``'s dtype) after ``kernel(*args, it)`` accumulated into it."""
    out = np.zeros(shape, args[0].dtype)
    kernel(*args, out)
    return torch.from_numpy(out)


class _ResidualSq(torch.autograd.Function):
    """``(inner_residuals(params) ** 2).sum(-1)`` [N, F - 1, 2] in one numba pass, and a
    backward that writes the gradient in one more (the reference's slices zero-fill and
    copy two full tensors: 6.9 against ~1 ms at 20k Gaussians, 7 knots, measured)."""

    @staticmethod
    def forward(ctx, params):
        k = KERNELS.module
        p = params.detach().numpy()
        out = np.empty((p.shape[0], (p.shape[1] - 1) // 3, 2), p.dtype)
        ctx.nonzero = bool((k.residual_sq_rows if _threaded(p) else k.residual_sq)(p, out))
        ctx.save_for_backward(params)
        ctx.leaf = params if params.is_leaf else None  # gradient_sink's key
        return torch.from_numpy(out)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        (params,) = ctx.saved_tensors
        if not ctx.nonzero and _all_finite(grad):
            # every residual is 0 (RGB-only training keeps them there): the gradient,
            # grad * (2 * 0), is all zeros, and None says so without a full tensor that
            # autograd would then add to the curves' gradient (x + 0 == x: same numbers)
            return None
        p, gr = params.detach().numpy(), grad.detach().to(params.dtype).numpy()

        def full():
            out = np.empty_like(p)
            # what autograd computes for ``d ** 2`` (pow's backward: grad * (2 * d)), bit for bit
            _residual_backward(p, gr, out, False)
            return torch.from_numpy(out)
        return sunk(ctx.leaf, full, lambda g: _residual_backward(p, gr, g.numpy(), True), inner_columns(p.shape[1]))


# False: the curve and residual kernels run on one thread (bench-step's "curves-serial"); True: on
# numba's threads once a curve has PARALLEL_MIN floats (the same numbers: rows are independent)
PARALLEL = True
PARALLEL_MIN = 1 << 16


def _threaded(curves: np.ndarray) -> bool:
    return PARALLEL and curves.size >= PARALLEL_MIN


def _residual_backward(p, gr, out, add: bool) -> None:
    k = KERNELS.module
    if _threaded(p):
        k.residual_sq_backward_rows(p, gr, out, add)
    else:
        (k.residual_sq_backward_add if add else k.residual_sq_backward)(p, gr, out)


def _curve_backward(gr, cols, w, out, add: bool) -> None:
    k = KERNELS.module
    (k.curve_at_backward_rows if _threaded(out) else k.curve_at_backward)(gr, cols, w, out, add)


def _all_finite(x: torch.Tensor) -> bool:
    """``bool(torch.isfinite(x).all())``; one numba pass when ``x`` is contiguous on the CPU."""
    if (FUSED_FINITE and x.device.type == "cpu" and x.is_contiguous() and x.dtype in (torch.float32, torch.float64)
            and KERNELS.load() is not None):
        return bool(KERNELS.module.all_finite(x.detach().numpy()))
    return bool(torch.isfinite(x).all())


# False: the residual term's backward tests its incoming gradient with torch.isfinite (bench-step's
# "step-before" variant switches it)
FUSED_FINITE = True


def inner_residual_sq(params: torch.Tensor) -> torch.Tensor:
    """Squared length of each inner residual, ``(inner_residuals(params) ** 2).sum(-1)``:
    [N, F - 1, 2]; value and gradient bit for bit those of that expression."""
    if (EVALUATOR == "torch" or params.shape[1] == 1 or params.device.type != "cpu" or not params.is_contiguous()
            or params.dtype not in (torch.float32, torch.float64) or KERNELS.load() is None):
        return (inner_residuals(params) ** 2).sum(-1)
    return _ResidualSq.apply(params)


def _tangent(X: torch.Tensor, k: list[float], i: int) -> torch.Tensor:
    """Catmull-Rom velocity at knot ``i`` (one-sided at the ends); X [N, F, C]."""
    a, b = max(i - 1, 0), min(i + 1, len(k) - 1)
    return (X[:, b] - X[:, a]) / (k[b] - k[a])


def _segment_controls(params: torch.Tensor, k: list[float], i: int) -> tuple:
    X = junctions(params)
    h = k[i + 1] - k[i]
    p0, p3 = X[:, i], X[:, i + 1]
    p1 = p0 + _tangent(X, k, i) * (h / 3.0) + params[:, 3 * i + 1]
    p2 = p3 - _tangent(X, k, i + 1) * (h / 3.0) + params[:, 3 * i + 2]
    return p0, p1, p2, p3


def bezier_controls(params: torch.Tensor, knot_times) -> torch.Tensor:
    """Absolute Bezier control points of every segment: [N, K, C] (entry ``3 i`` is
    ``X_i``, ``3 i + 1`` and ``3 i + 2`` the inner points of segment ``i``)."""
    k = _knots(knot_times)
    _check(params, k)
    if len(k) == 1:
        return params
    out = []
    for i in range(len(k) - 1):
        p0, p1, p2, _ = _segment_controls(params, k, i)
        out += [p0, p1, p2]
    out.append(junctions(params)[:, -1])
    return torch.stack(out, dim=1)


def _check(params: torch.Tensor, k: list[float]) -> None:
    if params.dim() != 3 or params.shape[1] != num_controls(len(k)):
        raise ValueError(f"trajectory params have shape {tuple(params.shape)}; {len(k)} knots need "
                         f"[N, {num_controls(len(k))}, C]")


def segment_weights(knot_times, t: float) -> list[tuple[int, float]]:
    """``(column, weight)`` pairs with ``evaluate(params, knot_times, t) == sum w params[:, col]``:
    the Bernstein weights of segment ``i`` around ``t`` spread onto the junctions through the
    Catmull-Rom tangents (module docstring). Columns in ascending order, each once; only
    nonzero weights (one column, weight 1.0, at a knot)."""
    k = _knots(knot_times)
    if len(k) == 1:
        return [(0, 1.0)]
    i, u = segment_of(k, t)
    v = 1.0 - u
    b0, b1, b2, b3 = v * v * v, 3.0 * v * v * u, 3.0 * v * u * u, u * u * u
    h3 = (k[i + 1] - k[i]) / 3.0
    w: dict[int, float] = {}

    def add(col: int, val: float) -> None:
        w[col] = w.get(col, 0.0) + val

    add(3 * i, b0 + b1)
    add(3 * (i + 1), b2 + b3)
    add(3 * i + 1, b1)
    add(3 * i + 2, b2)
    for j, sign, b in ((i, 1.0, b1), (i + 1, -1.0, b2)):  # the tangents at X_i and X_{i+1}
        a, c = max(j - 1, 0), min(j + 1, len(k) - 1)
        s = sign * b * h3 / (k[c] - k[a])
        add(3 * c, s)
        add(3 * a, -s)
    return [(c, float(x)) for c, x in sorted(w.items()) if x != 0.0]


class _CurveAt(torch.autograd.Function):
    """``sum_j w_j params[:, c_j]`` [N, C]; backward writes ``w_j * grad`` into the columns
    ``c_j`` of one zero [N, K, C] gradient (nothing else is materialised)."""

    @staticmethod
    def forward(ctx, params, cols, weights):
        ctx.shape, ctx.cols, ctx.weights = params.shape, cols, weights
        ctx.leaf = params if params.is_leaf else None  # gradient_sink's key
        ctx.fused = _fused_curves(params)
        if ctx.fused:  # one pass over the rows (_trajectory_kernels.curve_at), same numbers
            out = params.new_empty(params.shape[0], params.shape[2])
            p = params.detach().numpy()
            k = KERNELS.module
            (k.curve_at_rows if _threaded(p) else k.curve_at)(p, np.asarray(cols, np.int64),
                                                              np.asarray(weights, _NP_DTYPE[params.dtype]), out.numpy())
            return out
        out = None
        for c, w in zip(cols, weights):
            term = params[:, c] * w
            out = term if out is None else out.add_(term)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        if ctx.fused and grad.dtype in _NP_DTYPE and grad.device.type == "cpu":
            gr, cols = grad.detach().contiguous().numpy(), np.asarray(ctx.cols, np.int64)
            w = np.asarray(ctx.weights, _NP_DTYPE[grad.dtype])

            def full():
                g = torch.empty(ctx.shape, dtype=grad.dtype)
                _curve_backward(gr, cols, w, g.numpy(), False)
                return g
            return sunk(ctx.leaf, full, lambda g: _curve_backward(gr, cols, w, g.numpy(), True),
                        ctx.cols), \
                None, None

        def columns(g, add: bool):  # the same by torch ops: written into a zero gradient, or added
            for c, w in zip(ctx.cols, ctx.weights):
                g[:, c].add_(torch.mul(grad, w)) if add else torch.mul(grad, w, out=g[:, c])
            return g
        return sunk(ctx.leaf, lambda: columns(grad.new_zeros(ctx.shape), False), lambda g: columns(g, True),
                    ctx.cols), None, None


_NP_DTYPE = {torch.float32: np.float32, torch.float64: np.float64}
# False: _CurveAt's forward and backward in torch column ops (bench-step's "step-before" variant)
FUSED_CURVES = True


def _fused_curves(params: torch.Tensor) -> bool:
    return (FUSED_CURVES and params.device.type == "cpu" and params.dtype in _NP_DTYPE and params.is_contiguous()
            and KERNELS.load() is not None)


def evaluate(params: torch.Tensor, knot_times, t: float) -> torch.Tensor:
    """The curves at capture time ``t``: [N, C] (E-NeMF Eq. 5 with cubic segments).

    Float rounding aside the same as :func:`evaluate_reference` (bit for bit at the knots),
    in value and gradient; about a sixth of its backward's memory traffic."""
    if EVALUATOR == "torch":
        return evaluate_reference(params, knot_times, t)
    k = _knots(knot_times)
    _check(params, k)
    cols, weights = zip(*segment_weights(k, t))
    before_read(params, cols)
    if params.requires_grad and torch.is_grad_enabled():
        _note_touched(params.shape[1], cols)
    return _CurveAt.apply(params, cols, weights)


def evaluate_reference(params: torch.Tensor, knot_times, t: float) -> torch.Tensor:
    """:func:`evaluate` from column slices of ``params`` (plain torch autograd): the reference."""
    k = _knots(knot_times)
    _check(params, k)
    cols = [c for c, _ in segment_weights(k, t)]
    before_read(params, cols)
    if params.requires_grad and torch.is_grad_enabled():
        _note_touched(params.shape[1], cols)
    if len(k) == 1:
        return params[:, 0]
    i, u = segment_of(k, t)
    p0, p1, p2, p3 = _segment_controls(params, k, i)
    v = 1.0 - u
    return (v * v * v) * p0 + (3.0 * v * v * u) * p1 + (3.0 * v * u * u) * p2 + (u * u * u) * p3


@torch.no_grad()
def extrapolate_junctions(params: torch.Tensor, knot_times, last: int, first_new: int,
                          mode: str = "velocity") -> None:
    """Start knots ``first_new..`` (not trained yet) from the motion up to knot ``last`` --
    the time curriculum admits frames in order; a fast object has moved about its own size
    by the next frame, so starting it where it last was gives no overlap to follow.

    ``mode``: ``"hold"`` copies ``X_last``; ``"velocity"`` continues the last segment's
    velocity (constant-velocity prediction; ``"hold"`` when ``last`` is the first knot).
    In place on ``params``; the inner residuals of the new segments are zeroed."""
    k = _knots(knot_times)
    X = params[:, 0::3]
    if first_new >= len(k) or last < 0:
        return
    base = X[:, last].clone()
    vel = None
    if mode == "velocity" and last >= 1:
        vel = (X[:, last] - X[:, last - 1]) / (k[last] - k[last - 1])
    for j in range(first_new, len(k)):
        val = base if vel is None else base + vel * (k[j] - k[last])
        params[:, 3 * j] = val
        if j >= 1:
            params[:, 3 * (j - 1) + 1: 3 * (j - 1) + 3] = 0.0


def default_knots(frame_times) -> list[float]:
    """Distinct RGB instants (rounded to 1 ns), ascending: the curve's knots."""
    ks = sorted({round(float(t), 9) for t in frame_times})
    return ks if ks else [0.0]



def warmup() -> float:
    """Compile (first run on a machine) or load the residual-square and curve kernels now,
    in the layouts training passes them (float32, int64 rows; the gradient of a ``mean``);
    seconds taken."""
    import time

    t0 = time.perf_counter()
    if KERNELS.load() is not None:
        p = torch.zeros(3, num_controls(3), 3, requires_grad=True)
        inner_residual_sq(p).mean().backward()
        evaluate(p, [0.0, 0.5, 1.0], 0.25).sum().backward()  # the curves' forward / backward kernels
        k, x = KERNELS.module, p.detach().numpy() + np.float32(0.5)
        g, idx, cols, w = np.ones((3, 3), np.float32), np.arange(3), np.arange(3), np.ones(3, np.float32)
        k.residual_sq_backward_add(x, np.ones((3, 2, 2), np.float32), x)  # gradient_sink's in-place sums
        k.curve_at_backward(g, cols, w, x, True)
        k.inner_at(x, g, idx, cols, w, g.copy())  # the spike-view flow term's subset (spike_flow._InnerAt)
        k.inner_at_backward(g, idx, cols, w, x)
        # the threaded drivers (curves of PARALLEL_MIN floats and more)
        r = np.empty((3, 2, 2), np.float32)
        k.residual_sq_rows(x, r)
        k.residual_sq_backward_rows(x, r, x.copy(), True)
        k.curve_at_rows(x, cols, w, g)
        k.curve_at_backward_rows(g, cols, w, x, True)
    return time.perf_counter() - t0
