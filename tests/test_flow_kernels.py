"""The Lucas-Kanade flow's numba kernels (engine.train.frames._flow_kernels, issue 13) give torch's
numbers bit for bit: the box filter, the 3x3 median, the warp, the block matching and a
whole ``lk_flow``; torch's paths stay where the kernels cannot take over."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from engine.train.frames import interpolation as interp


@pytest.fixture
def torch_paths(monkeypatch):
    """Run the block with the flow's torch code (as before the kernels)."""
    def switch(on: bool):
        monkeypatch.setattr(interp, "FUSED_BOX", not on)
    return switch


def _rand(shape, seed, scale=1.0):
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed)) * scale


@pytest.mark.parametrize("shape", [(1, 1, 120, 160), (25, 1, 30, 40), (2, 3, 7, 5), (1, 1, 1, 1), (1, 2, 3, 2)])
@pytest.mark.parametrize("win", [3, 5, 9])
def test_box_is_torch_pooling_bit_for_bit(shape, win):
    x = (_rand(shape, win) - 0.5) * 10.0 ** torch.randint(-3, 3, shape, generator=torch.Generator().manual_seed(1))
    assert torch.equal(interp._box(x, win), interp._box_torch(x, win))


def test_box_keeps_torch_for_what_the_kernel_does_not_cover():
    x = _rand((1, 1, 6, 7), 0).double()
    assert interp._box(x, 3).dtype == torch.float64
    assert torch.equal(interp._box(x, 3), interp._box_torch(x, 3))
    y = _rand((1, 1, 6, 7), 1).requires_grad_(True)
    interp._box(y, 3).sum().backward()  # autograd: torch's path
    assert y.grad is not None


@pytest.mark.parametrize("shape", [(1, 2, 120, 160), (2, 1, 3, 2), (1, 2, 1, 1), (1, 2, 7, 5)])
def test_median_is_torch_median_with_ties_and_nan(shape):
    x = torch.randn(shape, generator=torch.Generator().manual_seed(shape[2]))
    x[..., ::3, ::2] = 0.0  # ties
    assert torch.equal(interp._median3(x), interp._median3_torch(x))
    if shape[2] > 2:
        x[0, 0, 1, 0] = float("nan")
        torch.testing.assert_close(interp._median3(x), interp._median3_torch(x), rtol=0, atol=0, equal_nan=True)


def test_warp_is_grid_sample_bit_for_bit():
    assert interp.fused_warp_exact(), "the numba warp disagrees with F.grid_sample here"
    g = torch.Generator().manual_seed(7)
    for shape in [(1, 3, 120, 160), (4, 1, 17, 23), (1, 1, 1, 1)]:
        img = torch.rand(shape, generator=g)
        flow = torch.randn(shape[0], 2, *shape[2:], generator=g) * 4.0
        flow[..., :2, :] = torch.round(flow[..., :2, :])  # whole pixels: weights exactly 0 / 1
        flow[..., -1:, :] = 1e3  # far outside: border-clamped
        assert torch.equal(interp.warp(img, flow), interp._warp_torch(img, flow))


def test_warp_with_a_non_finite_flow_is_torchs():
    img = _rand((1, 2, 5, 6), 3)
    flow = torch.zeros(1, 2, 5, 6)
    flow[0, 0, 2, 3] = float("nan")
    flow[0, 1, 4, 4] = float("inf")
    torch.testing.assert_close(interp.warp(img, flow), interp._warp_torch(img, flow), rtol=0, atol=0,
                               equal_nan=True)


@pytest.mark.parametrize("shape", [(1, 3, 60, 80), (2, 1, 17, 23), (1, 3, 4, 5)])
def test_block_match_is_the_torch_path_bit_for_bit(shape, torch_paths):
    g = torch.Generator().manual_seed(shape[2])
    A, Bm = torch.rand(shape, generator=g), torch.rand(shape, generator=g)
    flow = torch.randn(shape[0], 2, *shape[2:], generator=g) * 2.0
    Bm[..., :3, :] = A[..., :3, :]  # exact ties with the zero flow somewhere
    for radius, win in ((2, 5), (1, 3)):
        fused = interp._block_match(A, Bm, flow, radius, win)
        torch_paths(True)
        ref = interp._block_match(A, Bm, flow, radius, win)
        torch_paths(False)
        assert torch.equal(fused, ref)


def _textured_pair(h=48, w=64, shift=(2.4, -1.3), seed=0):
    g = torch.Generator().manual_seed(seed)
    base = torch.nn.functional.interpolate(torch.rand(1, 3, h // 4, w // 4, generator=g), size=(h, w),
                                           mode="bicubic", align_corners=False)
    flow = torch.zeros(1, 2, h, w)
    flow[:, 0], flow[:, 1] = shift
    return base, interp._warp_torch(base, flow)


def test_lk_flow_is_the_torch_path_bit_for_bit(torch_paths):
    a, b = _textured_pair()
    fused = interp.lk_flow(a, b)
    torch_paths(True)
    ref = interp.lk_flow(a, b)
    assert torch.equal(fused, ref)
    assert abs(float(ref[0, 0, 24, 32]) + 2.4) < 0.5  # and it is a flow (a(p) ~ b(p + f))


@pytest.mark.slow
def test_lk_flow_on_the_demo_capture_is_the_torch_path(torch_paths):
    from pathlib import Path

    from engine.io.capture import load_capture
    from engine.train.loop.scene_setup import train_frames

    root = Path(__file__).resolve().parents[1] / "demo_capture"
    if not root.exists():
        pytest.skip("demo_capture not in this checkout")
    train = train_frames(load_capture(root))
    frames = [f for f in train if f.camera == train[0].camera]
    a, b = (torch.as_tensor(np.asarray(f.load_rgb(), np.float32)[..., :3]).permute(2, 0, 1)[None] for f in frames[:2])
    fused = interp.lk_flow(a, b)
    torch_paths(True)
    assert torch.equal(fused, interp.lk_flow(a, b))


def test_bench_kernels_reports_identical_results(demo_capture, capsys):
    from argparse import Namespace

    from tools import bench_kernels

    assert bench_kernels.main(Namespace(capture=str(demo_capture), repeats=1, pairs=1, gaussians=300)) == 0
    out = capsys.readouterr().out
    assert out.count("identical: True") == 8 and "identical: False" not in out  # 5 + the stepcost round's 3
