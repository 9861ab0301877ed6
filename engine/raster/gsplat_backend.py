"""gsplat's CUDA rasterizer behind our API.

gsplat is imported only when ``torch.cuda.is_available()``: on a machine with nvcc but no
GPU, importing gsplat's CUDA backend tries to compile and fails (ImportError / OSError),
so the import is lazy, guarded and its failure remembered. Its CUDA extension is loaded
(built on first use) at the same time, so that a GPU box without nvcc falls back too.
"""
from __future__ import annotations

import torch

_gsplat = None
_error: BaseException | None = None


def _load():
    global _gsplat, _error
    if _gsplat is None and _error is None:
        if not torch.cuda.is_available():
            _error = RuntimeError("CUDA is not available")
        else:
            try:
                import gsplat  # lazy: optional, CUDA only

                _require_extension()
                _gsplat = gsplat
            except (ImportError, OSError, RuntimeError, AttributeError) as exc:
                _error = exc
    return _gsplat


def _require_extension() -> None:
    """gsplat >= 1.0 builds its CUDA extension on first use (JIT, minutes, needs nvcc) and,
    with no CUDA toolkit, only prints a warning and leaves it ``None``: every later call
    would then fail inside training. Load it here, once, so that "available" means usable
    and a missing toolkit becomes a clean fallback to the CPU path."""
    from gsplat.cuda import _backend  # lazy: this import is the (cached) build

    if getattr(_backend, "_C", None) is None:
        raise RuntimeError("gsplat is installed but its CUDA extension is not built and cannot "
                           "be built here (no CUDA toolkit / nvcc found)")


def available() -> bool:
    return _load() is not None


def unavailable_reason() -> str:
    _load()
    return "" if _error is None else f"{type(_error).__name__}: {_error}"


def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *,
                  sh_degree=None, near_plane=0.01, far_plane=1e10, eps2d=0.3, alpha_max=0.99,
                  backgrounds=None, render_depth=True):
    """Maps our arguments onto ``gsplat.rasterization`` (packed=False, classic mode).

    gsplat's alpha cap is fixed inside its kernels (0.99 or 0.999 depending on the
    version); ``alpha_max`` cannot be forwarded. Backgrounds are composited here, after
    the expected depth is taken, so they never leak into the depth channel.
    """
    gs = _load()
    if gs is None:
        raise RuntimeError("gsplat backend unavailable: " + unavailable_reason())
    C = viewmats.shape[0]
    render_colors, alphas, info = gs.rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, int(width), int(height),
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree,
        packed=False, tile_size=16, backgrounds=None,
        render_mode="RGB+ED" if render_depth else "RGB", rasterize_mode="classic")
    out = render_colors[..., :3]
    if backgrounds is not None:
        bg = torch.as_tensor(backgrounds, dtype=out.dtype, device=out.device).reshape(-1, 3)
        out = out + (1.0 - alphas) * bg.expand(C, 3)[:, None, None, :]
    radii = info["radii"]
    if radii.dim() == 3:  # gsplat >= 1.5: per-axis radii
        radii = radii.max(dim=-1).values
    meta = {
        "means2d": info["means2d"],
        "radii": radii.to(torch.int32),
        "depths_gauss": info["depths"],
        "backend": "gsplat",
    }
    if render_depth:
        depth = render_colors[..., 3:4]
        meta["depths"] = torch.where(alphas > 1e-6, depth, torch.zeros_like(depth))
    return out, alphas, meta
