"""Frame interpolation (RIFE stand-ins) and the block colour loss (paper Eq. 18-20)."""
from __future__ import annotations

import pytest
import torch

from engine.train.frames.interpolation import (
    avg_pool_blocks,
    block_colour_loss,
    flow_interpolate,
    interpolate,
    linear_blend,
    lk_flow,
    resample_area,
    warp,
)


def _texture(h=64, w=80, seed=0):
    """Smooth 2-D random texture (noise at 1/4 resolution, bicubic-upsampled), RGB in ~[0,1]."""
    g = torch.Generator().manual_seed(seed)
    low = torch.rand(1, 3, h // 4 + 1, w // 4 + 1, generator=g)
    img = torch.nn.functional.interpolate(low, size=(h, w), mode="bicubic", align_corners=False)
    return img[0].permute(1, 2, 0).clamp(0, 1).double().numpy()


def _scene(dx, h=64, w=80):
    """A textured square on a textured background, square shifted by dx pixels."""
    bg = _texture(h, w, 1) * 0.5
    fg = _texture(h, w, 2)
    img = bg.copy()
    x0 = 20 + int(round(dx))
    img[20:44, x0:x0 + 24] = fg[20:44, 20:44]
    return torch.as_tensor(img, dtype=torch.float32)


def test_linear_blend_endpoints_and_midpoint():
    a, b = torch.zeros(4, 4, 3), torch.ones(4, 4, 3)
    assert torch.equal(linear_blend(a, b, 0.0), a) and torch.equal(linear_blend(a, b, 1.0), b)
    assert torch.allclose(linear_blend(a, b, 0.25), torch.full((4, 4, 3), 0.25))
    assert torch.equal(interpolate(a, b, 0.25, "linear"), linear_blend(a, b, 0.25))
    with pytest.raises(ValueError):
        interpolate(a, b, 0.5, "rife")


def test_warp_integer_shift():
    x = torch.arange(20.0).reshape(1, 1, 4, 5)
    flow = torch.zeros(1, 2, 4, 5)
    flow[:, 0] = 1.0
    y = warp(x, flow)
    assert torch.allclose(y[0, 0, :, :4], x[0, 0, :, 1:])


def test_lk_flow_recovers_a_global_translation():
    img = torch.as_tensor(_texture(), dtype=torch.float32).permute(2, 0, 1)[None]
    shift = torch.zeros(1, 2, 64, 80)
    shift[:, 0], shift[:, 1] = 5.0, -3.0
    b = warp(img, -shift)  # b(p) = a(p - s): content moved by +s, so a(p) = b(p + s)
    flow = lk_flow(img, b)
    inner = flow[..., 10:-10, 10:-10]
    assert abs(float(inner[:, 0].median()) - 5.0) < 0.3
    assert abs(float(inner[:, 1].median()) + 3.0) < 0.3


def test_flow_interpolation_beats_linear_blend_on_moving_square():
    a, b, mid = _scene(0), _scene(12), _scene(6)
    lin = linear_blend(a, b, 0.5)
    out, (f_ab, f_ba) = flow_interpolate(a, b, 0.5, return_flows=True)
    err_lin = float((lin - mid).abs().mean())
    err_flow = float((out - mid).abs().mean())
    assert out.shape == a.shape
    assert err_flow < 0.6 * err_lin
    # endpoints reproduce the frames; flows can be reused for other instants
    assert float((flow_interpolate(a, b, 0.0, flows=(f_ab, f_ba)) - a).abs().mean()) < 1e-4
    q = flow_interpolate(a, b, 0.25, flows=(f_ab, f_ba))
    assert float((q - _scene(3)).abs().mean()) < float((linear_blend(a, b, 0.25) - _scene(3)).abs().mean())
    # batched input works too
    assert flow_interpolate(a[None], b[None], 0.5).shape == (1, 64, 80, 3)


def test_block_colour_loss_ignores_detail_inside_blocks():
    torch.manual_seed(0)
    target = torch.rand(16, 16, 3)
    blocks = avg_pool_blocks(target, 4)
    assert blocks.shape == (4, 4, 3)
    # a prediction with the same 4x4 block means but different texture costs nothing
    flat = blocks.repeat_interleave(4, 0).repeat_interleave(4, 1)
    assert float(block_colour_loss(flat, target)) < 1e-6
    assert float((flat - target).abs().mean()) > 0.1
    pred = (flat + 0.1).requires_grad_(True)
    loss = block_colour_loss(pred, target)
    assert abs(float(loss.detach()) - 0.1) < 1e-5
    loss.backward()
    assert (pred.grad > 0).all()
    # batch [B,H,W,3] and non-multiple sizes
    assert block_colour_loss(torch.rand(2, 18, 14, 3), torch.rand(2, 18, 14, 3)).dim() == 0
    m = torch.zeros(16, 16)
    m[:8] = 1
    lm = block_colour_loss(flat + torch.where(torch.arange(16)[:, None, None] < 8, 0.0, 1.0), target, mask=m)
    assert float(lm) < 1e-5
    # a half-resolution render against a full-resolution target: same blocks (k=2 vs k_target=4)
    half = torch.nn.functional.avg_pool2d(flat.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0)
    assert float(block_colour_loss(half, target, 2, k_target=4)) < 1e-6
    # different block grids (k=4 on the half render vs k_target=4): the target is area-resampled
    # onto the render's grid, then pooled with the render's blocks
    coarse = avg_pool_blocks(resample_area(target, (8, 8)), 4)
    assert torch.allclose(block_colour_loss(half, target, 4, k_target=4),
                          (avg_pool_blocks(half, 4) - coarse).abs().mean())


@pytest.mark.parametrize("size", [(161, 121), (163, 119), (97, 73), (160, 120), (33, 17), (5, 9)])
@pytest.mark.parametrize("scale", [0.5, 0.25, 0.3])
def test_block_colour_loss_any_size_at_between_scale(size, scale):
    """The trainer's between-frame path (issue 11): a render at ``between_scale`` x an RGB
    frame of any size (161x121 used to raise "block grids differ") against the pooled
    frame; a render of the frame's own (area-downscaled) content costs ~nothing and a
    brighter one costs the brightness step."""
    from engine.train.guidance.spike_guidance import scaled_view

    W, H = size
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    frame = torch.stack([xx, yy, 0.5 * (xx + yy)], -1)[None]  # smooth: resampling is exact-ish
    item = {"width": W, "height": H, "K": torch.eye(3)[None], "image": frame}
    vt = scaled_view(item, scale)
    render = resample_area(frame, (vt["height"], vt["width"]))
    k = 4
    kp = max(1, int(round(k * scale)))
    target = avg_pool_blocks(frame, k)  # what SpikeGuidance.pooled_target caches (k_target=1)
    same = block_colour_loss(render, target, kp, k_target=1)
    off = block_colour_loss(render + 0.2, target, kp, k_target=1)
    assert torch.isfinite(same) and torch.isfinite(off)
    if min(W, H) >= 64:  # tiny images: a block is a large part of the gradient, the grids blur it
        assert float(same) < 0.03 and abs(float(off) - 0.2) < 0.03


def test_cached_consistency_gives_the_same_interpolation():
    """flow_consistency computed once per pair (SpikeGuidance keeps it) changes nothing."""
    from engine.train.frames.interpolation import flow_consistency

    torch.manual_seed(0)
    a = torch.rand(24, 32, 3)
    b = torch.roll(a, shifts=2, dims=1)
    _, flows = flow_interpolate(a, b, 0.5, return_flows=True)
    cons = flow_consistency(*flows)
    assert cons[0].shape == (1, 1, 24, 32) and float(cons[0].min()) >= 0
    f_ab, f_ba = flows
    # against a zero backward flow the inconsistency is the forward flow's length
    assert torch.allclose(flow_consistency(f_ab, torch.zeros_like(f_ba))[0], f_ab.norm(dim=1, keepdim=True),
                          atol=1e-6)
    for eps in (0.0, 0.3, 0.8):
        assert torch.equal(flow_interpolate(a, b, eps, flows=flows, consistency=cons),
                           flow_interpolate(a, b, eps, flows=flows))


def _block_match_one_at_a_time(A, Bm, flow, radius, win):
    """The search before issue 13 batched its candidates: the reference."""
    from engine.train.frames.interpolation import _box

    best_cost = _box((A - Bm).abs().sum(1, keepdim=True), win)
    best = torch.zeros_like(flow)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            cand = flow.clone()
            cand[:, 0] += dx
            cand[:, 1] += dy
            cost = _box((A - warp(Bm, cand)).abs().sum(1, keepdim=True), win)
            take = cost < best_cost - 1e-7
            best = torch.where(take, cand, best)
            best_cost = torch.where(take, cost, best_cost)
    return best


@pytest.mark.parametrize("shape", [(1, 3, 60, 80), (2, 1, 17, 23), (1, 3, 4, 5)])
def test_batched_block_match_is_bit_for_bit_the_loop(shape):
    from engine.train.frames.interpolation import _block_match

    g = torch.Generator().manual_seed(shape[2])
    A, Bm = torch.rand(shape, generator=g), torch.rand(shape, generator=g)
    flow = torch.randn(shape[0], 2, *shape[2:], generator=g) * 2.0
    Bm[..., :3, :] = A[..., :3, :]  # exact ties with the zero flow somewhere
    for radius, win in ((2, 5), (1, 3)):
        assert torch.equal(_block_match(A, Bm, flow, radius, win), _block_match_one_at_a_time(A, Bm, flow, radius, win))
