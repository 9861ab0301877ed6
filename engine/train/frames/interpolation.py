"""Frame interpolation for the block colour loss (paper Eq. 18-20) and the baselines.

RIFE weights are not available offline, so two stand-ins:

* :func:`linear_blend` — ``(1 - eps) * C1 + eps * C2``;
* :func:`flow_interpolate` — dense optical flow both ways (coarse-to-fine Lucas-Kanade,
  :func:`lk_flow`, in plain torch), intermediate flows by the Super-SloMo linear-motion
  approximation, backward warping of both frames and an occlusion-aware blend (forward /
  backward flow consistency).

Images are channel-last float tensors ``[H, W, C]`` or ``[B, H, W, C]`` (the rasterizer's
layout); flows are ``[B, 2, H, W]`` in pixels (x, y). The flow convention is backward:
``a(p) ~ b(p + flow_ab(p))``.

:func:`block_colour_loss` is Eq. 20: L1 between ``k x k`` average-pooled images (k = 4).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ...numba_cache import LazyKernels

KERNELS = LazyKernels(__package__, "_flow_kernels")  # lk_flow's box filter, median, warp (torch's numbers)
# False: the Lucas-Kanade flow's box filter, median and warp run in torch, as before their
# numba kernels (bench-step's "step-before" variant switches it)
FUSED_BOX = True

__all__ = ["linear_blend", "lk_flow", "warp", "flow_consistency", "flow_interpolate",
           "interpolate", "block_colour_loss", "avg_pool_blocks", "resample_area"]


def _to_bchw(img: torch.Tensor) -> tuple[torch.Tensor, bool]:
    single = img.dim() == 3
    x = img[None] if single else img
    return x.permute(0, 3, 1, 2).contiguous(), single


def _from_bchw(x: torch.Tensor, single: bool) -> torch.Tensor:
    y = x.permute(0, 2, 3, 1)
    return y[0] if single else y


def linear_blend(a: torch.Tensor, b: torch.Tensor, eps: float) -> torch.Tensor:
    """Linear interpolation between frames ``a`` (eps = 0) and ``b`` (eps = 1)."""
    return a * (1.0 - eps) + b * eps


def warp(img: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Backward warp: ``out(p) = img(p + flow(p))``; img [B, C, H, W], flow [B, 2, H, W]
    (pixels). Bilinear, border-clamped. On CPU float32 without autograd by
    :func:`engine.train.frames._flow_kernels.warp_border` where it equals this function's torch
    path bit for bit (:func:`fused_warp_exact`, checked once per process)."""
    if _fused_flow(img, flow) and flow.shape == (img.shape[0], 2, *img.shape[2:]):
        img, flow = img.contiguous(), flow.contiguous()
        out = torch.empty_like(img)
        if KERNELS.module.warp_border(img.numpy(), flow.numpy(), out.numpy()):
            return out
    return _warp_torch(img, flow)


_WARP_EXACT: bool | None = None


def _on_kernels(*tensors) -> bool:
    """The numba kernels may take over: CPU float32 [B, C, H, W] tensors without autograd
    (the box filter's, the median's; the warp's also needs :func:`fused_warp_exact`)."""
    return (FUSED_BOX and all(t.device.type == "cpu" and t.dtype == torch.float32 and t.dim() == 4
                              and not t.requires_grad for t in tensors) and KERNELS.load() is not None)


def _fused_flow(*tensors) -> bool:
    """The numba warp may take over: :func:`_on_kernels`, and it equals ``F.grid_sample`` here."""
    return _on_kernels(*tensors) and fused_warp_exact()


def fused_warp_exact() -> bool:
    """True when the numba warp gives ``F.grid_sample``'s numbers here (checked once on
    random images and flows, awkward sizes; False without numba)."""
    global _WARP_EXACT
    if _WARP_EXACT is None:
        _WARP_EXACT = False
        if KERNELS.load() is not None:
            try:
                gen = torch.Generator().manual_seed(4242)
                ok = True
                for shape in ((1, 1, 23, 37), (3, 3, 9, 8), (2, 1, 1, 5)):
                    img = torch.rand(shape, generator=gen) * 4.0 - 1.0
                    flow = torch.randn(shape[0], 2, *shape[2:], generator=gen) * 6.0
                    out = torch.empty_like(img)
                    ok &= bool(KERNELS.module.warp_border(img.numpy(), flow.numpy(), out.numpy()))
                    ok &= torch.equal(out, _warp_torch(img, flow))
                    ref = torch.rand(shape, generator=gen)
                    sad = img.new_empty(shape[0], 1, *shape[2:])
                    ok &= bool(KERNELS.module.warped_sad(ref.numpy(), img.numpy(), flow.numpy(), sad.numpy()))
                    ok &= torch.equal(sad, (ref - _warp_torch(img, flow)).abs().sum(1, keepdim=True))
                _WARP_EXACT = bool(ok)
            except Exception:  # a numba / llvmlite that cannot compile the kernel: torch's path
                _WARP_EXACT = False
    return _WARP_EXACT


def _warp_torch(img: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    B, _, H, W = img.shape
    ys, xs = torch.meshgrid(torch.arange(H, dtype=img.dtype, device=img.device),
                            torch.arange(W, dtype=img.dtype, device=img.device), indexing="ij")
    gx = (xs[None] + flow[:, 0] + 0.5) / W * 2 - 1
    gy = (ys[None] + flow[:, 1] + 0.5) / H * 2 - 1
    grid = torch.stack([gx, gy], -1)
    return F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False)


def _gray(x: torch.Tensor) -> torch.Tensor:
    return x.mean(1, keepdim=True) if x.shape[1] > 1 else x


def _grad(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    gx = F.pad(x, (1, 1, 0, 0), mode="replicate")
    gy = F.pad(x, (0, 0, 1, 1), mode="replicate")
    return (gx[..., 2:] - gx[..., :-2]) * 0.5, (gy[..., 2:, :] - gy[..., :-2, :]) * 0.5


def _box(x: torch.Tensor, win: int) -> torch.Tensor:
    """Box mean over ``win x win`` (odd) with replicated borders, [B, C, H, W] -> same shape.
    On CPU float32 by :func:`engine.train.frames._flow_kernels.box_replicate`: the same numbers
    as the torch pooling below, bit for bit (tests/test_flow_kernels.py)."""
    if win % 2 == 1 and _on_kernels(x):
        x = x.contiguous()
        out = torch.empty_like(x)
        KERNELS.module.box_replicate(x.view(-1, *x.shape[-2:]).numpy(), win // 2,
                                     out.view(-1, *x.shape[-2:]).numpy())
        return out
    return _box_torch(x, win)


def _box_torch(x: torch.Tensor, win: int) -> torch.Tensor:
    return F.avg_pool2d(F.pad(x, (win // 2,) * 4, mode="replicate"), win, stride=1)


def _median3(x: torch.Tensor) -> torch.Tensor:
    """3x3 median filter per channel (replicate border). On CPU float32 by
    :func:`engine.train.frames._flow_kernels.median3_replicate` (the same values: a selection)."""
    if _on_kernels(x):
        x = x.contiguous()
        out = torch.empty_like(x)
        KERNELS.module.median3_replicate(x.view(-1, *x.shape[-2:]).numpy(), out.view(-1, *x.shape[-2:]).numpy())
        return out
    return _median3_torch(x)


def _median3_torch(x: torch.Tensor) -> torch.Tensor:
    B, C, H, W = x.shape
    p = F.unfold(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3)  # [B, C*9, H*W]
    return p.reshape(B, C, 9, H * W).median(2).values.reshape(B, C, H, W)


def _block_match(A: torch.Tensor, Bm: torch.Tensor, flow: torch.Tensor, radius: int, win: int) -> torch.Tensor:
    """Discrete search: per pixel, the flow among ``flow + (dx, dy)``, |dx|,|dy| <= radius,
    and the zero flow, minimising the window-averaged absolute difference.

    The ``(2 radius + 1)^2`` candidates are warped and box-filtered as one batch (issue 13:
    the trajectories' admissions spend most of their time in this flow; one call each
    instead of 25 took a 160x120 ``lk_flow`` from 101 to 93 ms), then compared in the
    candidates' order as before: the same numbers as one candidate at a time
    (tests/test_interpolation.py)."""
    best_cost = _box((A - Bm).abs().sum(1, keepdim=True), win)
    best = torch.zeros_like(flow)
    offsets = [(dx, dy) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)]
    n, b = len(offsets), flow.shape[0]
    shift = torch.tensor(offsets, dtype=flow.dtype, device=flow.device).repeat_interleave(b, 0)
    cands = flow.repeat(n, 1, 1, 1)
    cands += shift[:, :, None, None]
    if _fused_flow(A, Bm, cands):  # the same numbers in three numba passes (_flow_kernels)
        k = KERNELS.module
        A, Bm, best_cost = A.contiguous(), Bm.contiguous(), best_cost.contiguous()
        sad = A.new_empty(n * b, 1, *A.shape[-2:])
        if k.warped_sad(A.numpy(), Bm.numpy(), cands.numpy(), sad.numpy()):
            k.select_best(_box(sad, win).numpy(), cands.numpy(), n, best_cost.numpy(), best.numpy())
            return best
    costs = _box((A.repeat(n, 1, 1, 1) - warp(Bm.repeat(n, 1, 1, 1), cands)).abs().sum(1, keepdim=True), win)
    for k in range(n):
        cand, cost = cands[k * b:(k + 1) * b], costs[k * b:(k + 1) * b]
        take = cost < best_cost - 1e-7
        best = torch.where(take, cand, best)
        best_cost = torch.where(take, cost, best_cost)
    return best


@torch.no_grad()
def lk_flow(a: torch.Tensor, b: torch.Tensor, *, levels: int | None = None, iters: int = 3,
            win: int = 9, reg: float = 1e-2, radius: int = 2, match_win: int = 5) -> torch.Tensor:
    """Dense coarse-to-fine flow from ``a`` to ``b`` ([B, C, H, W]) -> [B, 2, H, W] with
    ``a(p) ~ b(p + flow(p))``: block matching + Lucas-Kanade refinement.

    At each pyramid level (coarsest first, factor 2): a discrete search (``radius`` pixels
    around the flow propagated from the coarser level, plus the zero flow; SAD over a
    ``match_win`` window on all channels) recovers from gross errors of the coarse level
    (motion boundaries); then ``iters`` Lucas-Kanade Gauss-Newton steps on the grey
    brightness-constancy residual give sub-pixel flow (structure tensor summed over a
    ``win x win`` window, Tikhonov term ``reg`` x its mean trace, so textureless areas keep
    the matched flow), and a 3x3 median removes isolated outliers.
    """
    H, W = a.shape[-2:]
    if levels is None:
        levels = max(1, min(6, int(torch.log2(torch.tensor(min(H, W) / 8.0)).floor().item()) + 1))
    pa, pb = [a], [b]
    for _ in range(levels - 1):
        pa.append(F.avg_pool2d(pa[-1], 2, ceil_mode=True))
        pb.append(F.avg_pool2d(pb[-1], 2, ceil_mode=True))
    flow = torch.zeros(a.shape[0], 2, *pa[-1].shape[-2:], dtype=a.dtype, device=a.device)
    for lvl in range(levels - 1, -1, -1):
        Ac, Bc = pa[lvl], pb[lvl]
        if flow.shape[-2:] != Ac.shape[-2:]:
            flow = F.interpolate(flow, size=Ac.shape[-2:], mode="bilinear", align_corners=False) * 2.0
        if radius > 0:
            flow = _block_match(Ac, Bc, flow, radius, match_win)
        A, Bm = _gray(Ac), _gray(Bc)
        for _ in range(iters):
            bw = warp(Bm, flow)
            ix, iy = _grad(0.5 * (A + bw))
            it = bw - A
            sxx, syy, sxy = _box(ix * ix, win), _box(iy * iy, win), _box(ix * iy, win)
            sxt, syt = _box(ix * it, win), _box(iy * it, win)
            r = reg * (sxx + syy).mean(dim=(-2, -1), keepdim=True) + 1e-9
            sxx, syy = sxx + r, syy + r
            det = sxx * syy - sxy * sxy
            du = -(syy * sxt - sxy * syt) / det
            dv = -(sxx * syt - sxy * sxt) / det
            flow = flow + torch.cat([du, dv], 1).clamp(-1.0, 1.0)
        flow = _median3(flow)
    return flow


def _flow_length(f: torch.Tensor) -> torch.Tensor:
    """|f| per pixel of a flow [B, 2, H, W] -> [B, 1, H, W]. (``Tensor.norm(dim=1)`` over the
    channel axis is a strided reduction that took ~75 % of a 320x240 interpolation here.)"""
    return torch.sqrt(f[:, 0:1] * f[:, 0:1] + f[:, 1:2] * f[:, 1:2])


def flow_consistency(f_ab: torch.Tensor, f_ba: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward-backward inconsistency (pixels) of each source flow, [B, 1, H, W] each: large
    where a pixel is occluded in the other frame. Independent of the interpolation time, so
    a caller interpolating one pair at several times computes it once (``consistency=``)."""
    return _flow_length(f_ab + warp(f_ba, f_ab)), _flow_length(f_ba + warp(f_ab, f_ba))


def _intermediate_flows(f_ab: torch.Tensor, f_ba: torch.Tensor, t: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Super-SloMo: flows from the intermediate frame at ``t`` back to a (t0) and forward to b (t1)."""
    f_t0 = -(1 - t) * t * f_ab + t * t * f_ba
    f_t1 = (1 - t) * (1 - t) * f_ab - t * (1 - t) * f_ba
    return f_t0, f_t1


def flow_interpolate(a: torch.Tensor, b: torch.Tensor, eps: float, *, flows=None,
                     return_flows: bool = False, consistency=None, **lk):
    """Flow-based interpolation at ``eps`` in [0, 1] between channel-last frames ``a``, ``b``.

    ``flows`` = (flow_ab, flow_ba) reuses precomputed flows (several eps per pair), and
    ``consistency`` = :func:`flow_consistency` of those flows their occlusion maps.
    """
    xa, single = _to_bchw(a)
    xb, _ = _to_bchw(b)
    if flows is None:
        f_ab = lk_flow(xa, xb, **lk)
        f_ba = lk_flow(xb, xa, **lk)
    else:
        f_ab, f_ba = flows
    t = float(eps)
    f_t0, f_t1 = _intermediate_flows(f_ab, f_ba, t)
    wa = warp(xa, f_t0)
    wb = warp(xb, f_t1)
    # occlusion: forward-backward consistency of each source flow at the sampled location
    cons_a, cons_b = flow_consistency(f_ab, f_ba) if consistency is None else consistency
    va = torch.exp(-warp(cons_a, f_t0) ** 2 / 2.0)
    vb = torch.exp(-warp(cons_b, f_t1) ** 2 / 2.0)
    w0 = (1 - t) * (va + 1e-3)  # the floor keeps the endpoints exact where both are occluded
    w1 = t * (vb + 1e-3)
    out = (w0 * wa + w1 * wb) / (w0 + w1).clamp(min=1e-6)
    out = _from_bchw(out, single)
    return (out, (f_ab, f_ba)) if return_flows else out


def interpolate(a: torch.Tensor, b: torch.Tensor, eps: float, method: str = "flow", **kw) -> torch.Tensor:
    """``method``: 'linear' or 'flow'."""
    if method == "linear":
        return linear_blend(a, b, eps)
    if method == "flow":
        return flow_interpolate(a, b, eps, **kw)
    raise ValueError(f"unknown interpolation method {method!r} (linear, flow)")


def avg_pool_blocks(img: torch.Tensor, k: int = 4) -> torch.Tensor:
    """Channel-last [.., H, W, C] -> k x k block means [.., H/k, W/k, C] (ceil, edge blocks
    averaged over what they cover)."""
    x, single = _to_bchw(img if img.dim() >= 3 else img[..., None])
    y = F.avg_pool2d(x, k, stride=k, ceil_mode=True, count_include_pad=False)
    return _from_bchw(y, single)


def resample_area(img: torch.Tensor, size_hw) -> torch.Tensor:
    """Channel-last [.., H, W, C] -> [.., h, w, C] by area averaging (``size_hw`` = (h, w));
    each output pixel is the mean of the input pixels it overlaps (adaptive average pooling),
    so a downscale keeps the mean colour of every region."""
    x, single = _to_bchw(img)
    h, w = int(size_hw[0]), int(size_hw[1])
    if tuple(x.shape[-2:]) == (h, w):
        return img
    return _from_bchw(F.interpolate(x, size=(h, w), mode="area"), single)


def block_colour_loss(pred: torch.Tensor, target: torch.Tensor, k: int = 4,
                      mask: torch.Tensor | None = None, k_target: int | None = None) -> torch.Tensor:
    """Paper Eq. 20: ``|| AvgPool_k(target) - AvgPool_k(pred) ||_1`` (mean).

    ``k_target``: block size on the target when it has another resolution than ``pred``
    (e.g. a half-resolution render with ``k=2`` against a full-resolution frame with
    ``k_target=4``: the same blocks). Any sizes work: where the two block grids differ
    (sizes not divisible by the block, rounded render sizes), ``target`` -- a frame or
    its blocks, showing the same field of view as ``pred`` -- is area-resampled onto the
    render's pixel grid first (:func:`resample_area`)."""
    pb = avg_pool_blocks(pred, k)
    target = target.to(pred.dtype)
    tb = avg_pool_blocks(target, k if k_target is None else k_target)
    if tb.shape[-3:-1] != pb.shape[-3:-1]:
        # e.g. a 161x121 frame (41x31 blocks of 4) against its half-resolution render
        # 80x60 (40x30 blocks of 2): both show the same field of view, so the target is
        # area-resampled onto the render's pixel grid and pooled with the render's blocks
        tb = avg_pool_blocks(resample_area(target, pred.shape[-3:-1]), k)
    d = (pb - tb).abs()
    if mask is not None:
        m = avg_pool_blocks(mask.to(pred.dtype)[..., None] if mask.dim() == pred.dim() - 1 else mask, k)
        return (d * m).sum() / (m.sum() * d.shape[-1]).clamp(min=1e-6)
    return d.mean()


def warmup() -> float:
    """Compile (first run on a machine) or load the Lucas-Kanade flow's kernels and run the
    warp's exactness check now (engine.train.loop.budget.warm_up_runtime); seconds taken."""
    import time

    t0 = time.perf_counter()
    if fused_warp_exact():
        a = torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(0))
        lk_flow(a, a.flip(-1))
    return time.perf_counter() - t0
