"""Issue 13: the curves' gradients summed in place (``trajectory.gradient_sink``) are the sums
autograd makes of every reader's full gradient, entry for entry; the sink acts only inside its
block, only on leaves whose ``.grad`` was None, and training runs bit for bit as without it."""
from __future__ import annotations

import types

import pytest
import torch

from engine.io.capture import load_capture
from engine.scene import trajectory as traj
from engine.scene.model import TRAJ_MEANS
from engine.train import spike_flow
from engine.train.presets import get_preset
from engine.train.trainer import Trainer

pytestmark = pytest.mark.skipif(not traj.KERNELS.available(), reason="numba kernels unavailable")

KNOTS = [0.0, 0.1, 0.2, 0.3]
FULL = ("curve_at_backward", "residual_sq_backward", "inner_at_backward")
ADD = tuple(f"{k}_add" for k in FULL)


def _count_kernels(monkeypatch) -> list:
    calls = []
    for name in FULL + ADD:
        kernel = getattr(traj.KERNELS.module, name)
        monkeypatch.setattr(traj.KERNELS.module, name, lambda *a, _k=kernel, _n=name: (calls.append(_n), _k(*a))[1])
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
        if sink:  # the first reader wrote the full gradient, every later one added its columns
            assert sum(c in FULL for c in calls) == 1 and sum(c in ADD for c in calls) == len(calls) - 1 >= 2
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


@pytest.mark.slow  # two demo trainers with the spike branch
def test_guided_training_is_bit_for_bit_without_the_sink(demo_capture, monkeypatch):
    """The fast preset's own schedule on the demo with the spike branch (every reader of a
    guided step): bench-step's ``sink-off`` and the engine as it is keep the same parameters
    after every step, and the sink did add in place."""
    from engine.train.budget import warm_up_runtime
    from tools.bench_step import variant

    warm_up_runtime("cpu")
    calls = _count_kernels(monkeypatch)
    cap = load_capture(demo_capture)
    steps = 40
    trainers = {}
    for v in ("sink-off", "current"):
        with variant(v):
            tr = Trainer(cap, get_preset("fast", {"iterations": steps}), device="cpu", rgb_only=False)
            tr.init_model()
        trainers[v] = tr
    added = 0
    for step in range(steps):
        for v, tr in trainers.items():
            calls.clear()
            with variant(v):
                tr.step(step)
            added += sum(c in ADD for c in calls) if v == "current" else 0
            assert v == "current" or not any(c in ADD for c in calls)
        a, b = (tr.model.gaussians for tr in trainers.values())
        assert a.num_gaussians == b.num_gaussians
        for name in a.param_names:
            assert torch.equal(getattr(a, name), getattr(b, name)), (step, name)
    assert added > 0
