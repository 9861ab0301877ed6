"""FusedAdam (engine.scene.fused_adam): torch.optim.Adam's numbers bit for bit, its state
format (densification, checkpoints), and torch's own step where it cannot take over."""
from __future__ import annotations

import copy
import math

import pytest
import torch

from engine.scene import fused_adam
from engine.scene.fused_adam import FusedAdam

SIZES = [(1,), (5,), (8,), (17, 3), (20011, 19, 3), (1031, 4)]


def _params(seed=0):
    g = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(s, generator=g) * 10.0 ** (i % 4 - 2)) for i, s in enumerate(SIZES)]


def _groups(ps):
    return [{"params": [p], "lr": 10.0 ** -(i % 5 + 1), "name": f"g{i}"} for i, p in enumerate(ps)]


def _grads(steps, seed=1):
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(steps):
        # sparse-ish, wide dynamic range, some exact zeros (untouched trajectory columns)
        out.append([torch.randn(s, generator=g) * torch.rand(s, generator=g).pow(6) * 10.0
                    * (torch.rand(s, generator=g) < 0.4) for s in SIZES])
    return out


def _run(opt_cls, grads, betas=(0.9, 0.999), **kw):
    ps = _params()
    opt = opt_cls(_groups(ps), lr=0.0, eps=1e-15, betas=betas, **kw)
    for k, gs in enumerate(grads):
        for i, (p, gr) in enumerate(zip(ps, gs)):
            p.grad = None if (k + i) % 7 == 3 else gr.clone()  # some groups skip some steps
        opt.step()
    return ps, opt


@pytest.mark.parametrize("betas", [(0.9, 0.999), (0.3, 0.99)])
def test_bit_for_bit_torch_adam(betas):
    assert fused_adam.exact(), "the fused path disagrees with torch here: see engine.scene._adam_kernels"
    grads = _grads(12)
    ref, o_ref = _run(torch.optim.Adam, grads, betas=betas)
    fus, o_fus = _run(FusedAdam, grads, betas=betas)
    for a, b in zip(ref, fus):
        assert torch.equal(a, b)
        sa, sb = o_ref.state[a], o_fus.state[b]
        assert torch.equal(sa["exp_avg"], sb["exp_avg"]) and torch.equal(sa["exp_avg_sq"], sb["exp_avg_sq"])
        assert torch.equal(sa["step"], sb["step"]) and sb["step"].dtype == sa["step"].dtype


def test_state_dict_round_trips_with_torch_adam():
    grads = _grads(4)
    fus, o_fus = _run(FusedAdam, grads[:2])
    ps = [torch.nn.Parameter(p.detach().clone()) for p in fus]
    o_ref = torch.optim.Adam(_groups(ps), lr=0.0, eps=1e-15)
    o_ref.load_state_dict(copy.deepcopy(o_fus.state_dict()))  # (torch shares the step tensors)
    for gs in grads[2:]:
        for p, q, gr in zip(fus, ps, gs):
            p.grad, q.grad = gr.clone(), gr.clone()
        o_fus.step()
        o_ref.step()
    assert all(torch.equal(a, b) for a, b in zip(fus, ps))


def test_falls_back_to_torch_where_it_cannot_take_over(monkeypatch):
    calls = []
    real = fused_adam._fused_update
    monkeypatch.setattr(fused_adam, "_fused_update", lambda *a, **k: (calls.append(1), real(*a, **k)))
    p = torch.nn.Parameter(torch.randn(10, 3))
    for kw in ({"amsgrad": True}, {"weight_decay": 0.1}, {"maximize": True}):
        opt = FusedAdam([p], lr=1e-3, **kw)
        p.grad = torch.randn(10, 3)
        opt.step()
    q = torch.nn.Parameter(torch.randn(10, 3, dtype=torch.float64))
    q.grad = torch.randn(10, 3, dtype=torch.float64)
    FusedAdam([q], lr=1e-3).step()
    r = torch.nn.Parameter(torch.randn(3, 10))
    r.grad = torch.randn(10, 3).t()  # non-contiguous gradient
    FusedAdam([r], lr=1e-3).step()
    monkeypatch.setattr(fused_adam, "ENABLED", False)
    s = torch.nn.Parameter(torch.randn(10, 3))
    s.grad = torch.randn(10, 3)
    FusedAdam([s], lr=1e-3).step()
    assert calls == []
    monkeypatch.setattr(fused_adam, "ENABLED", True)
    FusedAdam([s], lr=1e-3).step()
    assert calls == [1]


def test_densification_keeps_working_with_the_fused_optimizer():
    import numpy as np

    from engine.scene.gaussians import GaussianModel
    from engine.train.config import get_preset

    rng = np.random.default_rng(0)
    g = GaussianModel(rng.normal(size=(50, 3)), rng.uniform(size=(50, 3)))
    g.setup_optimizer(get_preset("fast").gaussians, 1.0)
    assert isinstance(g.optimizer, FusedAdam)
    (g.means.sum() + g.sh_dc.sum()).backward()
    g.optimizer.step()
    g.grad_accum[:10] = 1.0
    g.grad_count[:] = 1.0
    g.densify_and_prune(grad_threshold=0.5, percent_dense=10.0, min_opacity=0.0, max_world_scale=1e9,
                        max_gaussians=1000)
    assert g.num_gaussians == 60 and g.optimizer.state[g.means]["exp_avg"].shape == (60, 3)
    g.optimizer.zero_grad()
    g.means.sum().backward()
    g.optimizer.step()


# ---- the one-pass kernel (MKL's vmsSqrt called from numba, engine.numba_vml) -------------------

def _one_pass_or_skip():
    from engine import numba_vml

    if not numba_vml.AVAILABLE:
        pytest.skip("this torch exports no vmsSqrt (built without MKL): FusedAdam keeps two passes")
    assert fused_adam.one_pass_exact(), "vmsSqrt is exported but the one-pass step differs from torch's Adam"


def test_vml_sqrt_is_torch_sqrt_bit_for_bit():
    _one_pass_or_skip()
    assert fused_adam._sqrt_probe()  # subnormals .. inf, NaN, odd offsets and lengths
    x = torch.rand(4099) * 10.0 ** torch.randint(-40, 38, (4099,)).float()
    out = torch.empty_like(x)
    fused_adam.KERNELS.module.vml_sqrt(x.numpy(), out.numpy())
    assert torch.equal(out.view(torch.int32), torch.sqrt(x).view(torch.int32))


@pytest.mark.parametrize("block", [7, 4096, None])
def test_one_pass_is_torch_adam_bit_for_bit_across_block_edges(monkeypatch, block):
    """Blocks of 7 elements split every parameter mid-row (MKL's scalar tail at every block);
    4096 cuts the (20011, 19, 3) curve-shaped parameter into ~280 blocks; None: the default."""
    _one_pass_or_skip()
    if block is not None:
        monkeypatch.setattr(fused_adam, "BLOCK", block)
    calls = []
    step = fused_adam.KERNELS.module.step
    monkeypatch.setattr(fused_adam.KERNELS.module, "step", lambda *a: (calls.append(a[-1].size), step(*a)))
    grads = _grads(6)
    ref, o_ref = _run(torch.optim.Adam, grads)
    fus, o_fus = _run(FusedAdam, grads)
    assert calls and max(calls) <= (block or fused_adam.BLOCK)  # the one-pass kernel ran, in blocks
    for a, b in zip(ref, fus):
        assert torch.equal(a, b)
        sa, sb = o_ref.state[a], o_fus.state[b]
        assert torch.equal(sa["exp_avg"], sb["exp_avg"]) and torch.equal(sa["exp_avg_sq"], sb["exp_avg_sq"])


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_threads_split_a_large_parameter_into_block_runs_bit_for_bit(monkeypatch, threads):
    """PARALLEL: the (20011, 19, 3) curve-shaped parameter (1.14M floats) is updated in runs of
    whole blocks, one per thread (numba's count, patched), the same numbers as torch's Adam
    and as one thread; the small parameters stay on one thread."""
    import numba

    _one_pass_or_skip()
    monkeypatch.setattr(numba, "get_num_threads", lambda: threads)
    n, blocks = 20011 * 57, math.ceil(20011 * 57 / fused_adam.BLOCK)
    per = math.ceil(blocks / threads) * fused_adam.BLOCK
    assert fused_adam._thread_cuts(n) == [i * per for i in range(threads)] + [n]
    assert fused_adam._thread_cuts(fused_adam.PARALLEL_MIN - 1) == [0, fused_adam.PARALLEL_MIN - 1]
    runs = []
    k = fused_adam.KERNELS.module
    step_threads = k.step_threads
    monkeypatch.setattr(k, "step_threads", lambda *a: (runs.append((a[0].size, a[-2].shape, a[-1])),
                                                        step_threads(*a))[1])
    grads = _grads(4, seed=5)
    ref, _ = _run(torch.optim.Adam, grads)
    fus, _ = _run(FusedAdam, grads)
    monkeypatch.setattr(fused_adam, "PARALLEL", False)
    one, _ = _run(FusedAdam, grads)
    assert all(torch.equal(a, b) and torch.equal(a, c) for a, b, c in zip(ref, fus, one))
    # the big parameter took the threaded pass at every step it had a gradient; nothing else did
    assert runs == ([(n, (threads, fused_adam.BLOCK), per)] * len(runs) if threads > 1 else [])
    assert len(runs) >= (3 if threads > 1 else 0)


def test_one_pass_and_two_passes_agree_and_switch(monkeypatch):
    _one_pass_or_skip()
    grads = _grads(5, seed=3)
    one, _ = _run(FusedAdam, grads)
    monkeypatch.setattr(fused_adam, "ONE_PASS", False)
    calls = []
    step = fused_adam.KERNELS.module.step
    monkeypatch.setattr(fused_adam.KERNELS.module, "step", lambda *a: (calls.append(1), step(*a)))
    two, _ = _run(FusedAdam, grads)
    assert calls == []  # ONE_PASS=False: the moments / torch.sqrt / update passes
    assert all(torch.equal(a, b) for a, b in zip(one, two))


def test_without_vmssqrt_the_two_passes_remain(monkeypatch):
    from engine import numba_vml

    monkeypatch.setattr(numba_vml, "AVAILABLE", False)
    monkeypatch.setattr(fused_adam, "_ONE_PASS_EXACT", None)
    assert fused_adam.one_pass_exact() is False
    grads = _grads(3)
    ref, _ = _run(torch.optim.Adam, grads)
    fus, _ = _run(FusedAdam, grads)
    assert all(torch.equal(a, b) for a, b in zip(ref, fus))


def test_bench_adam_times_every_parameter_and_paths_agree():
    from tools import bench_adam

    ps = _params()
    opt = FusedAdam(_groups(ps), lr=0.0, eps=1e-15)
    for p, gr in zip(ps, _grads(1)[0]):
        p.grad = gr
    opt.step()
    curve = ps[4]  # (20011, 19, 3): make its inner columns untouched, as in RGB-only training
    curve.grad[:, 1:3] = 0
    opt.state[curve]["exp_avg"][:, 1:3] = 0
    opt.state[curve]["exp_avg_sq"][:, 1:3] = 0
    rows = bench_adam.time_parameters(opt, repeats=1)
    assert [r["name"] for r in rows] == [f"g{i}" for i in range(len(SIZES))]
    assert all(r["same"] for r in rows)
    assert all(r["ms"]["torch"] < float("inf") and r["ms"]["two-pass"] < float("inf") for r in rows)
    big = rows[4]
    assert big["numel"] == 20011 * 19 * 3 and big["zero"] >= 2 / 19 - 1e-6
    assert "| **all** |" in bench_adam._table(rows)
