"""Issue 13: the curves' gradients summed in place (``trajectory.gradient_sink``) are the sums
autograd makes of every reader's full gradient, entry for entry; the sink acts only inside its
block, only on leaves whose ``.grad`` was None (training with and without it, bit for bit:
``tests/test_step_exact.py``)."""
from __future__ import annotations

import types

import pytest
import torch

from engine.scene import trajectory as traj
from engine.scene.model import TRAJ_MEANS
from engine.train.guidance import spike_flow

pytestmark = pytest.mark.skipif(not traj.KERNELS.available(), reason="numba kernels unavailable")

KNOTS = [0.0, 0.1, 0.2, 0.3]
FULL = ("curve_at_backward", "residual_sq_backward")  # a fresh full gradient
ADD = tuple(f"{k}_add" for k in FULL)  # into the leaf's .grad (inner_at_backward does either)


def _count_kernels(monkeypatch) -> list:
    """Names of the curves' backward kernels called, ``*_add`` where one added into a gradient."""
    calls = []
    k = traj.KERNELS.module
    for name in ("curve_at_backward", "residual_sq_backward", "residual_sq_backward_add", "inner_at_backward"):
        kernel = getattr(k, name)
        named = (lambda a: "curve_at_backward_add" if a[-1] else "curve_at_backward") if name == "curve_at_backward" \
            else (lambda a, _n=name: _n)
        monkeypatch.setattr(k, name, lambda *a, _k=kernel, _f=named: (calls.append(_f(a)), _k(*a))[1])
    return calls


def _loss(params: torch.Tensor, seed: int) -> torch.Tensor:
    """Every reader of the curves a guided step has, plus a plain slice (autograd's own path)."""
    gen = torch.Generator().manual_seed(seed)
    n, c = params.shape[0], params.shape[2]
    model = types.SimpleNamespace(gaussians=types.SimpleNamespace(means=torch.zeros(n, 3, dtype=params.dtype),
                                                                  **{TRAJ_MEANS: params}),
                                  trajectory={"knots": KNOTS})
    loss = (traj.evaluate(params, KNOTS, KNOTS[1]) ** 2).sum()  # an RGB render: one junction column
    loss = loss + (traj.evaluate(params, KNOTS, 0.137) * torch.randn(n, c, generator=gen, dtype=params.dtype)).sum()
    loss = loss + 0.3 * traj.inner_residual_sq(params).sum()
    if c == 3:  # the flow term's subset (position curves)
        idx = torch.randperm(n, generator=gen)[: n // 3]
        loss = loss + (spike_flow.inner_only_positions(model, 0.23, idx) ** 2).sum()
    return loss + 0.5 * params[:, 0].sum()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("channels", [3, 4])
def test_the_sink_sums_as_autograd_does(dtype, channels, monkeypatch):
    gen = torch.Generator().manual_seed(3)
    start = torch.randn(200, traj.num_controls(len(KNOTS)), channels, generator=gen, dtype=dtype)
    start[:7] = -0.0  # zero rows: readers' products of -0 and +0
    grads = {}
    calls = _count_kernels(monkeypatch)
    for sink in (False, True):
        monkeypatch.setattr(traj, "SINK", sink)
        params = torch.nn.Parameter(start.clone())
        calls.clear()
        with traj.gradient_sink():
            _loss(params, 11).backward()
        grads[sink] = params.grad
        if sink:  # one reader wrote the full gradient (the flow term's subset runs first), the rest added
            assert sum(c in FULL for c in calls) == (1 if channels == 4 else 0) and sum(c in ADD for c in calls) >= 2
        else:
            assert not any(c in ADD for c in calls)
    a, b = grads[False], grads[True]
    assert torch.equal(a, b)  # -0.0 == +0.0: an entry no later reader touched may keep its sign of zero
    bits = torch.int32 if dtype == torch.float32 else torch.int64
    nz = a != 0
    assert torch.equal(a[nz].view(bits), b[nz].view(bits)) and nz.any()


def test_outside_the_block_and_with_a_gradient_already_there_autograd_sums(monkeypatch):
    calls = _count_kernels(monkeypatch)
    params = torch.nn.Parameter(torch.randn(50, traj.num_controls(len(KNOTS)), 3))
    (g_free,) = torch.autograd.grad(_loss(params, 2), params)  # no block: readers return their gradients
    assert not any(c in ADD for c in calls) and params.grad is None
    params.grad = torch.ones_like(params)
    calls.clear()
    with traj.gradient_sink():
        _loss(params, 2).backward()
    assert not any(c in ADD for c in calls)  # a gradient from before: not the sink's to add into
    assert torch.allclose(params.grad, g_free + 1.0)


def test_a_non_leaf_reader_is_left_to_autograd(monkeypatch):
    calls = _count_kernels(monkeypatch)
    leaf = torch.nn.Parameter(torch.randn(40, traj.num_controls(len(KNOTS)), 3))
    scaled = leaf * 2.0  # not a leaf: its readers' gradients flow on through autograd
    with traj.gradient_sink():
        (traj.evaluate(scaled, KNOTS, 0.05).sum() + traj.evaluate(scaled, KNOTS, 0.25).sum()).backward()
    assert not any(c in ADD for c in calls)
    ref = torch.nn.Parameter(leaf.detach().clone())
    (traj.evaluate(ref * 2.0, KNOTS, 0.05).sum() + traj.evaluate(ref * 2.0, KNOTS, 0.25).sum()).backward()
    assert torch.equal(leaf.grad, ref.grad)
