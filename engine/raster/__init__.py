"""Differentiable Gaussian rasterizer: one functional API, several backends.

``rasterization(...)`` follows gsplat's conventions (wxyz quaternions, OpenCV
world-to-camera view matrices, pixel centres at +0.5, expected depth):

* ``"cpu"``: vectorised torch projection + SH (autograd), then numba tile binning and
  compositing with a hand-derived backward (``engine.raster.cpu``). Falls back to the
  tiled plain-torch compositor (``engine.raster.torch_tiled``) with a warning if numba
  cannot be imported.
* ``"torch"``: the tiled plain-PyTorch compositor (autograd), the no-numba fallback and
  the "plain PyTorch" baseline of ``python -m engine bench-raster``.
* ``"reference"``: dense, obviously correct, tiny cases only (tests).
* ``"gsplat"``: gsplat's CUDA kernels; imported only when CUDA is available.
* ``"auto"``: gsplat when CUDA + gsplat are usable and the tensors are on CUDA, else cpu.
"""
from __future__ import annotations

import time
import warnings

import torch

# (OMP_WAIT_POLICY is set by engine/__init__.py, imported before this package)
from . import cpu, gsplat_backend  # both load numba / gsplat only on first use
from .projection import eval_colors, project_gaussians
from .reference import composite_dense
from .torch_tiled import composite_tiles_torch

BACKENDS = ("auto", "cpu", "torch", "reference", "gsplat")
_DEPTH_EPS = 1e-6  # expected depth is 0 where alpha <= this
_warned = set()


def _warn_once(key: str, msg: str) -> None:
    if key not in _warned:
        _warned.add(key)
        warnings.warn(msg, RuntimeWarning, stacklevel=3)


def resolve_backend(backend: str, device: torch.device) -> str:
    """The backend that will actually run for ``backend`` with tensors on ``device``."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown rasterizer backend {backend!r}; choose from {BACKENDS}")
    if backend == "auto":
        if device.type == "cuda":
            if gsplat_backend.available():
                return "gsplat"
        backend = "cpu"
    if backend == "cpu":
        if device.type != "cpu":
            return "torch"  # the numba kernels work on host memory; the torch path runs anywhere
        if not cpu.available():
            _warn_once("numba", "numba unavailable (" + cpu.unavailable_reason() + "); "
                       "falling back to the slower plain-PyTorch tiled rasterizer")
            return "torch"
    return backend


def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *,
                  sh_degree=None, near_plane=0.01, far_plane=1e10, eps2d=0.3, alpha_max=0.99,
                  backgrounds=None, render_depth=True, backend="auto", tile_size=8):
    """Render N Gaussians into C cameras.

    Returns ``colors [C,H,W,3]`` (composited over ``backgrounds``, black if None),
    ``alphas [C,H,W,1]`` and ``meta`` with ``depths [C,H,W,1]`` (expected depth, 0 where
    alpha is tiny; only if render_depth), ``means2d [C,N,2]`` (non-leaf: call
    ``retain_grad()`` on it before backward for view-space gradients), ``radii [C,N]``
    int32 (0 = culled) and ``depths_gauss [C,N]`` (camera-space z).
    """
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if means.dim() != 2 or means.shape[-1] != 3:
        raise ValueError(f"means must be [N,3], got {tuple(means.shape)}")
    if viewmats.dim() != 3 or viewmats.shape[-2:] != (4, 4):
        raise ValueError(f"viewmats must be [C,4,4], got {tuple(viewmats.shape)}")
    if Ks.shape != (viewmats.shape[0], 3, 3):
        raise ValueError(f"Ks must be [C,3,3] matching viewmats, got {tuple(Ks.shape)}")
    if not 0.0 < float(alpha_max) < 1.0:
        raise ValueError(f"alpha_max must be in (0, 1), got {alpha_max}")
    tile_size = int(tile_size)
    if tile_size <= 0:
        raise ValueError("tile_size must be positive")

    which = resolve_backend(backend, means.device)
    if which == "gsplat":
        return gsplat_backend.rasterization(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height,
            sh_degree=sh_degree, near_plane=near_plane, far_plane=far_plane, eps2d=eps2d,
            alpha_max=alpha_max, backgrounds=backgrounds, render_depth=render_depth)

    C = viewmats.shape[0]
    project = cpu.project if which == "cpu" else project_gaussians
    proj = project(means, quats, scales, opacities, viewmats, Ks, width, height,
                   near_plane=near_plane, far_plane=far_plane, eps2d=eps2d)
    combine = cpu.sh_combine if which == "cpu" else None
    rgb = eval_colors(means, colors, viewmats, sh_degree, combine=combine).to(means.dtype)  # [C,N,3]
    meta = {
        "means2d": proj.means2d,
        "radii": proj.radii,
        "depths_gauss": proj.z,
        "backend": which,
    }
    if which == "cpu":
        # one autograd node from the projected Gaussians to the finished images (the
        # torch-side concatenation, blend, division and slicing cost ~5 ms of CPU at
        # 320x240 / 50k, a tenth of the forward+backward)
        out, alphas, depth = cpu.rasterize_fused(
            proj.means2d, proj.conics, opacities.to(means.dtype), rgb, proj.depths,
            proj.radii_xy, width, height, backgrounds=backgrounds, alpha_max=alpha_max,
            tile_size=tile_size, depth_eps=_DEPTH_EPS)
        if render_depth:
            meta["depths"] = depth
        return out, alphas, meta
    feats = torch.cat([rgb, proj.depths[..., None]], -1) if render_depth else rgb
    feats = feats.contiguous()
    ops = opacities.to(means.dtype)[None].expand(C, -1)

    if which == "reference":
        img, alphas = composite_dense(proj.means2d, proj.conics, ops, feats, proj.depths,
                                      proj.radii, width, height, alpha_max=alpha_max)
    elif which == "torch":
        img, alphas = composite_tiles_torch(proj.means2d, proj.conics, ops, feats, proj.depths,
                                            proj.radii_xy, width, height, alpha_max=alpha_max,
                                            tile_size=tile_size)
    else:
        raise AssertionError(which)

    out = img[..., :3]
    if backgrounds is not None:
        bg = torch.as_tensor(backgrounds, dtype=out.dtype, device=out.device).reshape(-1, 3)
        out = out + (1.0 - alphas) * bg.expand(C, 3)[:, None, None, :]
    if render_depth:
        raw = img[..., 3:4]
        ok = alphas > _DEPTH_EPS
        meta["depths"] = torch.where(ok, raw / alphas.clamp_min(_DEPTH_EPS), torch.zeros_like(raw))
    return out, alphas, meta


def warmup(backend: str = "cpu") -> float:
    """Render and differentiate a tiny scene once so that the numba kernels are compiled
    (first run on a machine: ~30 s) or loaded from numba's cache (~0.5 s) now rather than
    at the first training step. Safe to call from a worker thread. Returns seconds taken."""
    t0 = time.perf_counter()
    g = torch.Generator().manual_seed(0)
    n = 16
    params = [torch.rand(n, 3, generator=g) - 0.5 + torch.tensor([0.0, 0.0, 3.0]),
              torch.randn(n, 4, generator=g), torch.full((n, 3), 0.1),
              torch.full((n,), 0.5), torch.rand(n, 4, 3, generator=g)]
    for p in params:
        p.requires_grad_(True)
    Ks = torch.tensor([[[20.0, 0.0, 12.0], [0.0, 20.0, 10.0], [0.0, 0.0, 1.0]]])
    c, a, m = rasterization(*params, torch.eye(4)[None], Ks, 24, 20, sh_degree=1,
                            backend=backend)
    (c.sum() + a.sum() + m["depths"].sum()).backward()
    return time.perf_counter() - t0


__all__ = ["rasterization", "resolve_backend", "warmup", "BACKENDS"]
