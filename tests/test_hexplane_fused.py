"""Fused HexPlane sampler (numba forward + hand-derived backward) against the grid_sample
reference: values, gradients into the planes and the coordinates, border semantics."""
from __future__ import annotations

import pytest
import torch

from engine.scene import hexplane_fused
from engine.scene.deformation import DeformationField, HexPlane

NEEDS_NUMBA = pytest.mark.skipif(not hexplane_fused.available(), reason="numba unavailable")


def _hexplane(features=3, resolution=4, multires=(1, 2), time_resolution=5, dtype=torch.float64, seed=0):
    h = HexPlane(features, resolution, multires, time_resolution, seed=seed).to(dtype)
    g = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():  # time planes away from their all-ones start, so that they matter
        for p in h.temporal:
            p.add_(0.3 * torch.randn(p.shape, generator=g, dtype=dtype))
    return h


def _points(n, dtype, seed=0, border=True):
    """Points inside, on and beyond the [-1, 1] border of every coordinate."""
    g = torch.Generator().manual_seed(seed)
    x = (torch.rand(n, 4, generator=g, dtype=dtype) * 2.6 - 1.3)
    if border:
        k = n // 8
        for a in range(4):
            x[a * k: a * k + k // 2, a] = 1.0
            x[a * k + k // 2: (a + 1) * k, a] = -1.0
    return x


def _fused(h, x):
    return hexplane_fused.hexplane_sample(x, h.spatial, h.temporal)


@NEEDS_NUMBA
def test_forward_and_gradients_match_reference_float64_with_border_points():
    h = _hexplane()
    x = _points(160, torch.float64).requires_grad_(True)
    ref = h.reference(x)
    out = _fused(h, x)
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-12)
    gout = torch.randn_like(ref)
    params = [x, *h.parameters()]
    g_ref = torch.autograd.grad(ref, params, gout)
    g_out = torch.autograd.grad(out, params, gout)
    for a, b in zip(g_out, g_ref):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    # on or beyond the border a coordinate gets no gradient (torch's CPU grid_sample: none)
    on = (x.detach().abs() >= 1.0)
    assert on.any() and (g_out[0][on] == 0).all()


@NEEDS_NUMBA
def test_gradcheck_float64_tiny_grid():
    h = _hexplane(features=2, resolution=3, multires=(1, 2), time_resolution=3)
    # gradcheck's finite differences need points off the texel lines and off the border;
    # beyond the border (clamped) the coordinate gradient is 0 and is checked too
    x = _points(12, torch.float64, seed=3, border=False)
    x = torch.where(x.abs() > 0.97, x.sign() * 1.2, x).requires_grad_(True)
    planes = [p.detach().clone().requires_grad_(True) for p in h.parameters()]
    spatial, temporal = planes[0::2], planes[1::2]
    assert torch.autograd.gradcheck(lambda xx, *pp: hexplane_fused.hexplane_sample(xx, pp[0::2], pp[1::2]),
                                    (x, *[q for pair in zip(spatial, temporal) for q in pair]),
                                    eps=1e-6, atol=1e-7, fast_mode=True)


@NEEDS_NUMBA
def test_float32_agreement_at_a_realistic_size():
    h = _hexplane(features=16, resolution=24, multires=(1, 2), time_resolution=43, dtype=torch.float32)
    x = _points(5000, torch.float32, seed=5)
    x[:, 3] = 0.37  # one instant, as in a training step
    x.requires_grad_(True)
    ref = h.reference(x)
    out = _fused(h, x)
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-6)
    gout = torch.randn_like(ref)
    params = [x, *h.parameters()]
    for a, b in zip(torch.autograd.grad(out, params, gout), torch.autograd.grad(ref, params, gout)):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4 * float(b.abs().max()))


@NEEDS_NUMBA
def test_gradient_only_into_what_requires_it_and_empty_input():
    h = _hexplane(dtype=torch.float32)
    x = _points(40, torch.float32)  # coordinates without requires_grad: no coordinate gradient
    out = _fused(h, x)
    out.sum().backward()
    assert x.grad is None and all(p.grad is not None for p in h.parameters())
    empty = _fused(h, torch.zeros(0, 4))
    assert tuple(empty.shape) == (0, h.out_dim)


@NEEDS_NUMBA
def test_repeatable_and_chunk_count_only_reorders_sums(monkeypatch):
    h = _hexplane(features=8, resolution=8, dtype=torch.float32)
    x = _points(3000, torch.float32, seed=7).requires_grad_(True)

    def grads():
        out = _fused(h, x)
        return torch.autograd.grad(out, [x, *h.parameters()], torch.ones_like(out))

    a, b = grads(), grads()
    for u, v in zip(a, b):
        assert torch.equal(u, v)  # deterministic: per-chunk buffers summed in order
    monkeypatch.setattr(hexplane_fused, "_chunks", lambda n: 3)
    for u, v in zip(grads(), a):
        torch.testing.assert_close(u, v, rtol=1e-5, atol=1e-5)


@NEEDS_NUMBA
def test_field_uses_the_fused_path_on_cpu_and_matches_the_torch_path(monkeypatch):
    d = DeformationField([-1, -1, -1], [1, 1, 1], (0.0, 0.2), resolution=6, multires=(1, 2), time_resolution=4,
                         features=4, width=16)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in d.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=g))
    means = (torch.rand(50, 3, generator=g) * 2.4 - 1.2).requires_grad_(True)
    quats, ls, op = torch.randn(50, 4, generator=g), torch.zeros(50, 3), torch.zeros(50)
    calls = []
    real = hexplane_fused.hexplane_sample
    monkeypatch.setattr(hexplane_fused, "hexplane_sample", lambda *a: calls.append(1) or real(*a))

    def run(sampler):
        monkeypatch.setattr(HexPlane, "sampler", sampler)
        out = d(means, quats, ls, op, 0.13)
        loss = out["means"].square().sum() + out["quats"].sum()
        return [out["means"], *torch.autograd.grad(loss, [means, *d.parameters()])]

    fused = run("auto")
    assert calls, "the CPU default is the fused sampler"
    n = len(calls)
    ref = run("torch")
    assert len(calls) == n  # "torch" never calls it
    for a, b in zip(fused, ref):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_unsupported_tensors_take_the_reference_path(monkeypatch):
    h = _hexplane(dtype=torch.float32)
    assert not hexplane_fused.supports(torch.zeros(3, 4, dtype=torch.float16), list(h.parameters()))
    assert not hexplane_fused.supports(torch.zeros(3, 4, dtype=torch.float64), list(h.parameters()))
    monkeypatch.setattr(hexplane_fused, "available", lambda: False)  # e.g. numba missing
    x = _points(20, torch.float32)
    assert not hexplane_fused.supports(x, list(h.parameters()))
    torch.testing.assert_close(h(x), h.reference(x))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_tensors_take_the_reference_path():
    h = _hexplane(dtype=torch.float32).cuda()
    x = _points(20, torch.float32).cuda()
    assert not hexplane_fused.supports(x, list(h.parameters()))
    torch.testing.assert_close(h(x), h.reference(x))
