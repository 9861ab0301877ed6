"""The fused SSIM (engine.train.losses.fused_ssim): pytorch_msssim's value and gradient, gradcheck
in float64, and the D-SSIM loss term using it."""
from __future__ import annotations

import pytest
import torch
from pytorch_msssim import ssim

from engine.train.losses import fused_ssim as fs
from engine.train.losses.fused_ssim import fused_ssim


def _msssim(p, t):
    return ssim(p.permute(2, 0, 1)[None], t.permute(2, 0, 1)[None], data_range=1.0, size_average=True)


@pytest.mark.parametrize("shape", [(11, 11, 3), (13, 29, 3), (40, 33, 1), (60, 80, 3)])
def test_value_and_gradient_match_pytorch_msssim(shape):
    g = torch.Generator().manual_seed(sum(shape))
    t = torch.rand(shape, generator=g)
    # a prediction near the target (a trained render) and one far from it
    for p0 in (t + 0.05 * torch.randn(shape, generator=g), torch.rand(shape, generator=g)):
        p = p0.clone().requires_grad_(True)
        a = fused_ssim(p, t)
        a.backward()
        ga = p.grad.clone()
        p.grad = None
        b = _msssim(p, t)
        b.backward()
        assert abs(float(a.detach()) - float(b.detach())) < 1e-6
        # float32 summation orders differ (conv2d vs the kernels): gradcheck in float64 below is exact
        assert torch.allclose(ga, p.grad, rtol=1e-3, atol=1e-4 * float(p.grad.abs().max()))


def test_gradcheck_float64():
    g = torch.Generator().manual_seed(3)
    p = torch.rand(14, 15, 2, dtype=torch.float64, generator=g, requires_grad=True)
    t = torch.rand(14, 15, 2, dtype=torch.float64, generator=g)
    assert torch.autograd.gradcheck(lambda q: fused_ssim(q, t), (p,))


def test_identical_images_score_one_and_batched_input():
    t = torch.rand(1, 20, 24, 3)
    assert abs(float(fused_ssim(t.clone(), t)) - 1.0) < 1e-6
    assert fused_ssim(torch.rand(2, 20, 24, 3), torch.rand(2, 20, 24, 3)) is None  # one image at a time
    assert fused_ssim(torch.rand(10, 24, 3), torch.rand(10, 24, 3)) is None  # smaller than the window


def test_dssim_term_uses_it_and_falls_back(monkeypatch):
    from types import SimpleNamespace

    from engine.train.losses.terms import _dssim

    g = torch.Generator().manual_seed(5)
    img = torch.rand(1, 30, 40, 3, generator=g)
    rgb = (img + 0.1 * torch.randn(img.shape, generator=g)).requires_grad_(True)
    ctx = SimpleNamespace(rgb=rgb, item={"image": img})
    fused = _dssim(ctx)
    monkeypatch.setattr(fs, "ENABLED", False)
    ref = _dssim(ctx)
    assert abs(float(fused.detach()) - float(ref.detach())) < 1e-6 and float(fused.detach()) > 0.01
    (ga,) = torch.autograd.grad(fused, rgb)
    (gb,) = torch.autograd.grad(ref, rgb)
    assert torch.allclose(ga, gb, rtol=1e-3, atol=1e-4 * float(gb.abs().max()))
