"""Fused HexPlane sampler (issue 13): numba forward and hand-derived backward of
:meth:`engine.scene.deformation.HexPlane.forward` on CPU tensors.

``hexplane_sample(xyzt, spatial, temporal)`` returns what the reference path (two batched
``F.grid_sample`` per level, bilinear, border padding, align_corners=True, product over the
six planes, concatenation over levels) returns, and the same gradients: into every plane
and, when ``xyzt`` requires it, into the coordinates (the trainer's canonical means get
a gradient through the field this way, so it is kept). The kernels are in
:mod:`engine.scene._hexplane_kernels`; numba is imported lazily, ``available()`` says
whether it can be used (the reference path is the fallback).

Why: in a deformation step the field's backward was the largest part (40-42 %,
docs/experiments/benchmark-history.md "Where a training step goes"): ``grid_sample``'s CPU backward scatters one
point and one
channel plane at a time and computes the coordinate gradient through a separate pass
per plane; here one pass per level reads each texel's C channels contiguously (planes
stored channels-last) and writes the plane and coordinate gradients together.
"""
from __future__ import annotations

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from ..numba_cache import LazyKernels

KERNELS = LazyKernels(__package__, "_hexplane_kernels")  # numba compiles / loads its cache on first use

MIN_CHUNK = 512  # points per parallel chunk at least (a chunk owns a whole gradient grid)


def _load():
    return KERNELS.load()


def available() -> bool:
    return KERNELS.available()


def supports(xyzt: torch.Tensor, planes) -> bool:
    """True when the fused path can take these tensors: CPU, float32 or float64, one dtype."""
    if xyzt.device.type != "cpu" or xyzt.dtype not in (torch.float32, torch.float64):
        return False
    if any(p.device.type != "cpu" or p.dtype != xyzt.dtype for p in planes):
        return False
    return available()


def _chunks(n: int) -> int:
    import numba

    return int(max(1, min(numba.get_num_threads(), n // MIN_CHUNK)))


def _channels_last(p: torch.Tensor) -> np.ndarray:
    """[3, C, H, W] -> [3, H, W, C] contiguous numpy (a copy: the planes are small)."""
    return np.ascontiguousarray(p.detach().permute(0, 2, 3, 1).numpy())


class _HexPlaneFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, xyzt, *planes):
        k = _load()
        levels = len(planes) // 2
        C = planes[0].shape[1]
        x = np.ascontiguousarray(xyzt.detach().numpy())
        n = x.shape[0]
        out = np.empty((n, levels * C), x.dtype)
        chunks = _chunks(n)
        grids = []
        for lv in range(levels):
            sp, tp = _channels_last(planes[2 * lv]), _channels_last(planes[2 * lv + 1])
            grids.append((sp, tp))
            if n:
                k.hexplane_fwd(x, sp, tp, out, lv * C, chunks)
        ctx.save_for_backward(xyzt, *planes)
        ctx.grids = grids
        ctx.x = x
        return torch.from_numpy(out)

    @staticmethod
    @once_differentiable
    def backward(ctx, gout):
        k = _load()
        xyzt, *planes = ctx.saved_tensors
        x = ctx.x
        n = x.shape[0]
        C = planes[0].shape[1]
        want_coords = bool(ctx.needs_input_grad[0])
        g = np.ascontiguousarray(gout.detach().to(xyzt.dtype).numpy())
        gx = np.zeros((n, 4), x.dtype)
        chunks = _chunks(n)
        grads = []
        for lv, (sp, tp) in enumerate(ctx.grids):
            gsp = np.zeros((chunks,) + sp.shape, x.dtype)
            gtp = np.zeros((chunks,) + tp.shape, x.dtype)
            if n:
                k.hexplane_bwd(x, sp, tp, g, lv * C, chunks, gsp, gtp, gx, want_coords)
            for buf in (gsp, gtp):  # chunks summed in order: independent of thread scheduling
                grads.append(torch.from_numpy(np.ascontiguousarray(buf.sum(0).transpose(0, 3, 1, 2))))
        grads = [gr if ctx.needs_input_grad[1 + i] else None for i, gr in enumerate(grads)]
        return (torch.from_numpy(gx) if want_coords else None, *grads)


def hexplane_sample(xyzt: torch.Tensor, spatial, temporal) -> torch.Tensor:
    """``xyzt`` [N, 4] in [-1, 1]; ``spatial[l]`` [3, C, R, R] (planes xy, xz, yz),
    ``temporal[l]`` [3, C, T, R] (planes xt, yt, zt; rows are time) -> [N, C * levels]:
    per level the product over the six planes of their bilinear samples (border padding,
    align_corners=True), levels concatenated. CPU float32 / float64 (:func:`supports`)."""
    planes = []
    for sp, tp in zip(spatial, temporal):
        planes += [sp, tp]
    return _HexPlaneFunction.apply(xyzt, *planes)


def warmup() -> float:
    """Compile (first run on a machine) or load the float32 kernels now; seconds taken."""
    import time

    t0 = time.perf_counter()
    if not available():
        return 0.0
    sp = torch.rand(3, 2, 3, 3, requires_grad=True)
    tp = torch.rand(3, 2, 2, 3, requires_grad=True)
    xyzt = (torch.rand(5, 4) * 2 - 1).requires_grad_(True)
    hexplane_sample(xyzt, [sp], [tp]).sum().backward()
    return time.perf_counter() - t0
