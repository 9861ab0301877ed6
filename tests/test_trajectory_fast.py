"""The trajectories' column-weight evaluation and its hand-written backward (issue 13)
against the slice-by-slice reference (engine.scene.trajectory.evaluate_reference)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from engine.scene import trajectory as traj
from engine.scene.trajectory import (
    evaluate,
    evaluate_reference,
    inner_residual_sq,
    inner_residuals,
    num_controls,
    segment_weights,
)

KNOT_SETS = {
    "one": [0.25],
    "two": [0.0, 0.2],
    "three": [0.0, 0.05, 0.2],
    "uneven": [0.0, 1 / 30, 2 / 30, 0.1, 0.15],
    "seven": [k / 30 for k in range(7)],
}


def _times(knots):
    k = np.asarray(knots)
    lo, hi = k[0], k[-1]
    span = max(hi - lo, 0.1)
    inner = np.linspace(lo, hi, 23)
    mids = (k[:-1] + k[1:]) / 2 if len(k) > 1 else k
    return [float(t) for t in np.concatenate([k, mids, inner, [lo - span, hi + span, lo - 1e-9, hi + 1e-9]])]


def _params(knots, n=7, c=3, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, num_controls(len(knots)), c, generator=g, dtype=dtype)


@pytest.mark.parametrize("name", list(KNOT_SETS))
@pytest.mark.parametrize("channels", [3, 4])
def test_fast_matches_reference_in_value_and_gradient(name, channels):
    knots = KNOT_SETS[name]
    p = _params(knots, c=channels)
    for t in _times(knots):
        a = p.clone().requires_grad_(True)
        b = p.clone().requires_grad_(True)
        w = torch.randn(p.shape[0], channels, dtype=p.dtype)
        fa, fb = evaluate(a, knots, t), evaluate_reference(b, knots, t)
        torch.testing.assert_close(fa, fb, rtol=1e-12, atol=1e-12)
        (fa * w).sum().backward()
        (fb * w).sum().backward()
        torch.testing.assert_close(a.grad, b.grad, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", ["one", "two", "uneven", "seven"])
def test_weights_are_the_curve(name):
    """``sum w params[:, col]`` is the curve; the junctions' weights sum to 1 (equal
    junctions and zero residuals: a constant curve)."""
    knots = KNOT_SETS[name]
    p = _params(knots)
    for t in _times(knots):
        sw = segment_weights(knots, t)
        cols = [c for c, _ in sw]
        assert cols == sorted(set(cols)) and all(w != 0.0 for _, w in sw)
        assert sum(w for c, w in sw if c % 3 == 0) == pytest.approx(1.0, abs=1e-12)
        direct = sum(w * p[:, c] for c, w in sw)
        torch.testing.assert_close(direct, evaluate_reference(p, knots, t), rtol=1e-12, atol=1e-12)
        i, _ = traj.segment_of(knots, t)
        assert set(cols) <= {3 * (i - 1), 3 * i, 3 * i + 1, 3 * i + 2, 3 * (i + 1), 3 * (i + 2)}


def test_at_the_knots_one_column_and_bit_for_bit_in_float32():
    knots = KNOT_SETS["seven"]
    p = _params(knots, n=257, c=4, dtype=torch.float32)
    for j, t in enumerate(knots):
        assert segment_weights(knots, t) == [(3 * j, 1.0)]
        a = p.clone().requires_grad_(True)
        b = p.clone().requires_grad_(True)
        fa, fb = evaluate(a, knots, t), evaluate_reference(b, knots, t)
        assert torch.equal(fa, fb)
        w = torch.randn_like(fa)
        (fa * w).sum().backward()
        (fb * w).sum().backward()
        assert torch.equal(a.grad, b.grad)


def test_gradcheck():
    for name in ("two", "uneven"):
        knots = KNOT_SETS[name]
        p = _params(knots, n=3).requires_grad_(True)
        for t in _times(knots)[::3]:
            assert torch.autograd.gradcheck(lambda x, t=t: evaluate(x, knots, t), (p,))
    p = _params(KNOT_SETS["uneven"], n=3).requires_grad_(True)
    assert torch.autograd.gradcheck(inner_residual_sq, (p,))


def test_gradient_reaches_only_the_touched_columns():
    knots = KNOT_SETS["seven"]
    p = _params(knots).requires_grad_(True)
    t = 0.5 * (knots[2] + knots[3])
    evaluate(p, knots, t).sum().backward()
    touched = set(torch.nonzero(p.grad.abs().sum((0, 2))).flatten().tolist())
    assert touched == {3, 6, 7, 8, 9, 12}  # X_1..X_4 (tangents), D_20, D_21


def test_residual_square_is_bit_for_bit_the_expression():
    knots = KNOT_SETS["seven"]
    p = _params(knots, n=301, c=3, dtype=torch.float32, seed=3) * 1e-2
    a = p.clone().requires_grad_(True)
    b = p.clone().requires_grad_(True)
    qa, qb = inner_residual_sq(a), (inner_residuals(b) ** 2).sum(-1)
    assert torch.equal(qa, qb)
    (qa.mean() / 0.37 ** 2).backward()
    (qb.mean() / 0.37 ** 2).backward()
    assert torch.equal(a.grad, b.grad)
    assert inner_residual_sq(_params(KNOT_SETS["one"])).shape == (7, 0, 2)


def test_reference_switch(monkeypatch):
    knots = KNOT_SETS["uneven"]
    p = _params(knots).requires_grad_(True)
    monkeypatch.setattr(traj, "EVALUATOR", "torch")
    out = evaluate(p, knots, 0.05)
    assert "CurveAt" not in type(out.grad_fn).__name__
    monkeypatch.setattr(traj, "EVALUATOR", "fast")
    assert "CurveAt" in type(evaluate(p, knots, 0.05).grad_fn).__name__


def test_bad_shapes_are_refused():
    knots = KNOT_SETS["uneven"]
    with pytest.raises(ValueError, match="knots need"):
        evaluate(torch.zeros(3, 5, 3), knots, 0.0)
    with pytest.raises(ValueError, match="knots need"):
        evaluate(torch.zeros(3, num_controls(len(knots))), knots, 0.0)


def test_residual_square_with_zero_residuals_adds_no_gradient_tensor():
    """All residuals zero (RGB-only training): no gradient from the term, the same numbers
    as the expression's all-zero gradient added to the curves' gradient; a residual whose
    square underflows still gets its gradient."""
    knots = KNOT_SETS["seven"]
    p = _params(knots, n=50, c=3, dtype=torch.float32, seed=4)
    p[:, 1::3] = 0.0
    p[:, 2::3] = 0.0
    for tiny in (0.0, 1e-30):
        p[7, 4, 1] = tiny
        a = p.clone().requires_grad_(True)
        b = p.clone().requires_grad_(True)
        w = torch.randn(50, 3)
        ((evaluate(a, knots, knots[2]) * w).sum() + inner_residual_sq(a).mean() / 0.37 ** 2).backward()
        ((evaluate_reference(b, knots, knots[2]) * w).sum() + (inner_residuals(b) ** 2).sum(-1).mean()
         / 0.37 ** 2).backward()
        assert torch.equal(a.grad, b.grad)
        assert (a.grad[7, 4, 1] != 0) == (tiny != 0.0)


def test_finite_check_of_the_residual_term_is_torchs():
    """The residual term's backward tests its incoming gradient in one numba pass
    (trajectory._all_finite): the same answer as torch.isfinite(...).all(), and an inf
    gradient on all-zero residuals still gives torch's NaN gradient (inf * 0)."""
    from engine.scene import trajectory

    for x in (torch.zeros(5, 6, 2), torch.randn(7, 3, 2), torch.randn(4, 2, 2, dtype=torch.float64)):
        for bad in (None, float("inf"), float("-inf"), float("nan")):
            y = x.clone()
            if bad is not None:
                y.view(-1)[-1] = bad
            assert trajectory._all_finite(y) == bool(torch.isfinite(y).all())
    knots = KNOT_SETS["seven"]
    p = torch.zeros(4, num_controls(len(knots)), 3, requires_grad=True)
    q = p.detach().clone().requires_grad_(True)
    (inner_residual_sq(p) * float("inf")).sum().backward()
    ((inner_residuals(q) ** 2).sum(-1) * float("inf")).sum().backward()
    torch.testing.assert_close(p.grad, q.grad, rtol=0, atol=0, equal_nan=True)


@pytest.mark.parametrize("c,dtype", [(3, torch.float32), (4, torch.float32), (3, torch.float64)])
def test_curve_kernels_are_the_column_ops_bit_for_bit(c, dtype, monkeypatch):
    """_CurveAt's numba forward / backward (trajectory.FUSED_CURVES) against its torch column
    ops: values and gradients equal at knots, between them and clamped outside."""
    from engine.scene import trajectory

    knots = KNOT_SETS["seven"]
    g = torch.Generator().manual_seed(c)
    p0 = torch.randn(300, num_controls(len(knots)), c, generator=g, dtype=dtype)
    p0 *= 10.0 ** torch.randint(-4, 4, p0.shape, generator=g).to(dtype)
    w = torch.randn(300, c, generator=g, dtype=dtype)
    for t in (knots[0], knots[3], 0.5 * (knots[1] + knots[2]), knots[4] + 1e-4, knots[-1], knots[-1] + 1.0, -1.0):
        got = []
        for fused in (False, True):
            monkeypatch.setattr(trajectory, "FUSED_CURVES", fused)
            p = p0.clone().requires_grad_(True)
            out = evaluate(p, knots, t)
            (out * w).sum().backward()
            got.append((out.detach(), p.grad))
        assert torch.equal(got[0][0], got[1][0]) and torch.equal(got[0][1], got[1][1]), t
    # a non-contiguous tensor keeps the torch path (same numbers)
    q = p0.transpose(0, 1).contiguous().transpose(0, 1)
    assert not q.is_contiguous() and torch.equal(evaluate(q, knots, 0.05), evaluate(p0, knots, 0.05))


@pytest.mark.parametrize("c,dtype", [(3, torch.float32), (4, torch.float64)])
def test_threaded_curve_and_residual_kernels_are_the_serial_ones_bit_for_bit(c, dtype, monkeypatch):
    """The row-parallel drivers (trajectory.PARALLEL, curves of PARALLEL_MIN floats and more):
    the curves' values and gradients, written fresh and summed in place (gradient_sink), and
    the residual term's value and gradient equal the serial kernels' bit for bit."""
    from engine.scene import trajectory

    knots = KNOT_SETS["seven"]
    g = torch.Generator().manual_seed(c)
    p0 = torch.randn(501, num_controls(len(knots)), c, generator=g, dtype=dtype)
    p0 *= 10.0 ** torch.randint(-4, 4, p0.shape, generator=g).to(dtype)
    w = torch.randn(501, c, generator=g, dtype=dtype)
    module = trajectory.KERNELS.load()
    called = []
    for name in ("curve_at_rows", "curve_at_backward_rows", "residual_sq_rows", "residual_sq_backward_rows"):
        real = getattr(module, name)
        monkeypatch.setattr(module, name, lambda *a, _r=real, _n=name: (called.append(_n), _r(*a))[1])
    monkeypatch.setattr(trajectory, "PARALLEL_MIN", 0)
    got = []
    for threaded in (False, True):
        monkeypatch.setattr(trajectory, "PARALLEL", threaded)
        outs = []
        for sink in (False, True):
            p = p0.clone().requires_grad_(True)
            loss = sum((evaluate(p, knots, t) * w).sum() for t in (0.5 * (knots[1] + knots[2]), knots[3], 0.11))
            sq = inner_residual_sq(p)
            loss = loss + (sq * torch.arange(sq.numel(), dtype=dtype).reshape(sq.shape)).sum()
            with trajectory.gradient_sink() if sink else torch.enable_grad():
                loss.backward()
            outs += [sq.detach(), p.grad]
        got.append(outs)
    assert set(called) == {"curve_at_rows", "curve_at_backward_rows", "residual_sq_rows", "residual_sq_backward_rows"}
    for a, b in zip(*got):
        assert torch.equal(a, b)
