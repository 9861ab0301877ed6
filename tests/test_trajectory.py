"""Per-Gaussian piecewise cubic Bezier trajectories (engine.scene.trajectory, issue 11)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from engine.scene.trajectory import (
    bezier_controls,
    evaluate,
    extrapolate_junctions,
    inner_residuals,
    junctions,
    num_controls,
    num_knots,
    segment_of,
)


def _reference(params: np.ndarray, knots: np.ndarray, t: float) -> np.ndarray:
    """Plain numpy: cubic Hermite with Catmull-Rom tangents + inner-point residuals, as
    Bezier control points evaluated by de Casteljau."""
    F = len(knots)
    X = params[:, 0::3]
    t = min(max(t, knots[0]), knots[-1])
    i = min(int(np.searchsorted(knots, t, side="right")) - 1, F - 2)
    h = knots[i + 1] - knots[i]
    u = (t - knots[i]) / h

    def vel(j):
        a, b = max(j - 1, 0), min(j + 1, F - 1)
        return (X[:, b] - X[:, a]) / (knots[b] - knots[a])

    P = [X[:, i], X[:, i] + vel(i) * h / 3 + params[:, 3 * i + 1],
         X[:, i + 1] - vel(i + 1) * h / 3 + params[:, 3 * i + 2], X[:, i + 1]]
    while len(P) > 1:  # de Casteljau
        P = [(1 - u) * a + u * b for a, b in zip(P[:-1], P[1:])]
    return P[0]


KNOTS = np.array([0.0, 1 / 30, 2 / 30, 0.1, 0.15])  # non-uniform on purpose


def test_shapes_and_counts():
    assert num_controls(1) == 1 and num_controls(7) == 19 and num_knots(19) == 7
    with pytest.raises(ValueError):
        num_knots(5)
    p = torch.randn(6, num_controls(len(KNOTS)), 3)
    assert evaluate(p, KNOTS, 0.05).shape == (6, 3)
    assert junctions(p).shape == (6, 5, 3) and inner_residuals(p).shape == (6, 4, 2, 3)
    assert bezier_controls(p, KNOTS).shape == p.shape
    with pytest.raises(ValueError):
        evaluate(p[:, :-1], KNOTS, 0.0)
    with pytest.raises(ValueError):
        evaluate(p, [0.0, 0.0, 1.0, 2.0, 3.0], 0.5)
    assert segment_of(KNOTS, -1.0) == (0, 0.0) and segment_of(KNOTS, 9.0) == (3, 1.0)


@pytest.mark.parametrize("channels", [3, 4])
def test_matches_numpy_reference_and_passes_through_junctions(channels):
    rng = np.random.default_rng(0)
    p = rng.normal(size=(5, num_controls(len(KNOTS)), channels))
    pt = torch.from_numpy(p)
    for t in np.concatenate([np.linspace(-0.02, 0.17, 41), KNOTS]):
        np.testing.assert_allclose(evaluate(pt, KNOTS, float(t)).numpy(), _reference(p, KNOTS, float(t)),
                                   rtol=1e-10, atol=1e-10)
    for i, tk in enumerate(KNOTS):  # exact at the RGB instants: the junction value
        np.testing.assert_allclose(evaluate(pt, KNOTS, float(tk)).numpy(), p[:, 3 * i], atol=1e-12)
    # the controls reproduce the curve through the Bernstein form
    c = bezier_controls(pt, KNOTS).numpy()
    u = 0.3
    t = KNOTS[2] + u * (KNOTS[3] - KNOTS[2])
    b = ((1 - u) ** 3 * c[:, 6] + 3 * (1 - u) ** 2 * u * c[:, 7] + 3 * (1 - u) * u ** 2 * c[:, 8] + u ** 3 * c[:, 9])
    np.testing.assert_allclose(evaluate(pt, KNOTS, t).numpy(), b, atol=1e-12)


def test_zero_residuals_give_a_c1_curve_and_linear_motion_is_exact():
    # junctions on a straight line at constant velocity: the curve is exactly that motion
    vel = np.array([1.0, -2.0, 0.5])
    p = np.zeros((1, num_controls(len(KNOTS)), 3))
    p[0, 0::3] = KNOTS[:, None] * vel
    pt = torch.from_numpy(p)
    for t in np.linspace(0, 0.15, 31):
        np.testing.assert_allclose(evaluate(pt, KNOTS, float(t)).numpy()[0], t * vel, atol=1e-12)
    # C1 at an inner knot for random junctions (zero residuals)
    rng = np.random.default_rng(1)
    p = np.zeros((3, num_controls(len(KNOTS)), 3))
    p[:, 0::3] = rng.normal(size=(3, len(KNOTS), 3))
    pt = torch.from_numpy(p)
    e = 1e-7
    tk = float(KNOTS[2])
    left = (evaluate(pt, KNOTS, tk) - evaluate(pt, KNOTS, tk - e)) / e
    right = (evaluate(pt, KNOTS, tk + e) - evaluate(pt, KNOTS, tk)) / e
    np.testing.assert_allclose(left.numpy(), right.numpy(), rtol=1e-3, atol=1e-3)  # finite differences


def test_gradcheck():
    p = torch.randn(4, num_controls(len(KNOTS)), 3, dtype=torch.float64, requires_grad=True)
    for t in (0.0, 0.01, 0.05, 0.12, 0.15):
        assert torch.autograd.gradcheck(lambda x: evaluate(x, KNOTS, t), (p,))
    assert torch.autograd.gradcheck(lambda x: bezier_controls(x, KNOTS), (p,))


def test_between_instants_move_only_their_segment():
    """A loss between two RGB instants reaches the two junctions around it, their
    neighbours (tangents) and that segment's residuals -- nothing further away."""
    p = torch.zeros(1, num_controls(len(KNOTS)), 3, requires_grad=True)
    evaluate(p, KNOTS, 0.5 * (KNOTS[1] + KNOTS[2])).sum().backward()
    g = p.grad[0].abs().sum(-1)
    touched = set(torch.nonzero(g).flatten().tolist())
    assert {3, 4, 5, 6} <= touched  # X_1, D_10, D_11, X_2
    assert touched <= {0, 3, 4, 5, 6, 9}
    # at an RGB instant only that junction gets a gradient
    p.grad = None
    evaluate(p, KNOTS, float(KNOTS[3])).sum().backward()
    assert set(torch.nonzero(p.grad[0].abs().sum(-1)).flatten().tolist()) == {9}


def test_extrapolate_junctions():
    p = torch.zeros(2, num_controls(len(KNOTS)), 3)
    p[:, 0] = 0.0
    p[:, 3] = torch.tensor([1.0, 0.0, 0.0])  # moved 1 in 1/30 s: 30 /s
    p[:, 7] = 5.0  # a stale residual of a segment not trained yet
    extrapolate_junctions(p, KNOTS, last=1, first_new=2)
    X = junctions(p)
    np.testing.assert_allclose(X[0, 2].numpy(), [2.0, 0, 0], atol=1e-5)
    np.testing.assert_allclose(X[0, 4].numpy(), [30 * 0.15, 0, 0], atol=1e-5)
    assert float(p[:, 7].abs().max()) == 0.0
    q = torch.zeros_like(p)
    q[:, 0] = 2.0
    extrapolate_junctions(q, KNOTS, last=0, first_new=1, mode="velocity")  # first knot: hold
    assert torch.equal(junctions(q), torch.full_like(junctions(q), 2.0))
