"""The fast CPU compositor: numba tile binning + compositing with a hand-derived backward.

``composite_tiles`` has the same signature and results as ``reference.composite_dense``;
``rasterize_fused`` is what ``rasterization`` runs (compositing, background and expected
depth in one autograd node).
numba is imported lazily; ``available()`` says whether it can be used.
"""
from __future__ import annotations

import numpy as np
import torch

from ..numba_cache import LazyKernels
from .projection import Projected

KERNELS = LazyKernels(__package__, "_kernels")  # numba compiles / loads its cache on first use


def _load():
    return KERNELS.load()


def available() -> bool:
    return KERNELS.available()


def unavailable_reason() -> str:
    return KERNELS.unavailable_reason()


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def depth_order(radii_xy: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """Flat indices c * N + g [V] int64 of the visible Gaussians (radius > 0), sorted by
    camera, then float32 depth (stable). radii_xy [C*N,2] int32, depths [C,N]."""
    d32 = np.ascontiguousarray(depths, np.float32)
    return _load().depth_order(np.ascontiguousarray(radii_xy), d32.view(np.uint32))


def bin_gaussians(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                  radii_xy: torch.Tensor, depths: torch.Tensor, width: int, height: int,
                  tile_size: int):
    """Tile lists for all cameras: offsets [C*T+1] int64, ids [M] int32 (flat c*N+g, front
    to back per tile), spans [M] int32 (reachable tile rows), tiles_x, tiles_y."""
    k = _load()
    C, N = depths.shape
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    rxy = _np(radii_xy).reshape(C * N, 2)
    order = depth_order(rxy, _np(depths).reshape(C, N))
    offsets, ids, spans = k.bin_gaussians(
        _np(means2d).reshape(C * N, 2), _np(conics).reshape(C * N, 3),
        _np(opacities).reshape(C * N), rxy, order, N, C, tile_size, tiles_x, tiles_y,
        width, height)
    return offsets, ids, spans, tiles_x, tiles_y


def _composite_buffers(C: int, height: int, width: int, D: int, M: int):
    """What ``rasterize_fwd`` writes (features [C,H,W,D] and alphas [C,H,W], zero; final
    transmittance [C,H,W], one; last index [C,H,W], -1) and the packed intersections [M, 10]
    ``pack`` / ``pack_split`` fill."""
    return (np.zeros((C, height, width, D), np.float32), np.zeros((C, height, width), np.float32),
            np.ones((C, height, width), np.float32), np.full((C, height, width), -1, np.int32),
            np.empty((M, 10), np.float32))


class _RasterizeToPixels(torch.autograd.Function):
    """means2d [C,N,2], conics [C,N,3], opacities [C,N], feats [C,N,4] (float32) ->
    features [C,H,W,4], alphas [C,H,W,1]; backward by the numba kernels."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, binning, width, height, tile_size,
                alpha_max):
        k = _load()
        C, N, D = feats.shape
        offsets, ids, spans, tiles_x, tiles_y = binning
        out_feat, out_alpha, final_t, last_i, packed = _composite_buffers(C, height, width, D, ids.shape[0])
        if ids.shape[0] > 0:
            k.pack(_np(means2d).reshape(C * N, 2), _np(conics).reshape(C * N, 3),
                   _np(opacities).reshape(C * N), _np(feats).reshape(C * N, D), ids, packed)
            k.rasterize_fwd(packed, spans, offsets, C, height, width, tile_size, tiles_x,
                            tiles_y, float(alpha_max), out_feat, out_alpha, final_t, last_i)
        ctx.save_for_backward(means2d, conics, opacities, feats)
        ctx.packed = packed
        ctx.state = (offsets, ids, spans, tiles_x, tiles_y, final_t, last_i, width, height, tile_size,
                     float(alpha_max))
        return torch.from_numpy(out_feat), torch.from_numpy(out_alpha)[..., None]

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, v_feat, v_alpha):
        k = _load()
        means2d, conics, opacities, feats = ctx.saved_tensors
        offsets, ids, spans, tiles_x, tiles_y, final_t, last_i, width, height, tile_size, alpha_max = ctx.state
        C, N, D = feats.shape
        M = ids.shape[0]
        n_grad = k.N_GRAD + D
        v_gauss = np.zeros((C * N, n_grad), np.float32)
        if M > 0:
            if v_feat is None:
                v_feat = torch.zeros((C, height, width, D), dtype=torch.float32)
            if v_alpha is None:
                v_alpha = torch.zeros((C, height, width, 1), dtype=torch.float32)
            v_isect = np.empty((M, n_grad), np.float32)  # the kernels write every row
            k.rasterize_bwd(ctx.packed, spans, offsets, C, height, width, tile_size, tiles_x,
                            tiles_y, alpha_max, final_t, last_i, _np(v_feat.float()),
                            _np(v_alpha.float()).reshape(C, height, width), v_isect)
            k.scatter_grads(ids, v_isect, v_gauss)
        vg = torch.from_numpy(v_gauss).reshape(C, N, n_grad)
        return (vg[..., 0:2], vg[..., 2:5], vg[..., 5], vg[..., k.N_GRAD:],
                None, None, None, None, None)


class _RasterizeFused(torch.autograd.Function):
    """``rasterization``'s compositing in one autograd node: means2d [C,N,2], conics
    [C,N,3], opacities [N], rgb [C,N,3], z [C,N] (float32) -> colours over the background
    [C,H,W,3], alphas [C,H,W,1] and expected depth [C,H,W,1] (0 where alpha <= depth_eps).
    The feature concatenation, the per-camera opacity expansion, the background blend, the
    depth division and the output slicing ran as ~10 torch ops and their autograd nodes
    around the kernels; here they are two per-pixel loops and a gather (``pack_split``,
    ``finish_image``, ``finish_grads``)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, rgb, z, binning, bg, width, height, tile_size,
                alpha_max, depth_eps):
        k = _load()
        C, N = z.shape
        offsets, ids, spans, tiles_x, tiles_y = binning
        out_feat, out_alpha, final_t, last_i, packed = _composite_buffers(C, height, width, k.N_FEAT,
                                                                          ids.shape[0])
        if ids.shape[0] > 0:
            k.pack_split(_np(means2d).reshape(C * N, 2), _np(conics).reshape(C * N, 3),
                         _np(opacities), _np(rgb).reshape(C * N, 3), _np(z).reshape(C * N), N,
                         ids, packed)
            k.rasterize_fwd(packed, spans, offsets, C, height, width, tile_size, tiles_x,
                            tiles_y, float(alpha_max), out_feat, out_alpha, final_t, last_i)
        out_rgb = np.empty((C, height, width, 3), np.float32)
        out_depth = np.empty((C, height, width, 1), np.float32)
        k.finish_image(out_feat, final_t, bg, depth_eps, out_rgb, out_depth)
        ctx.packed = packed
        ctx.state = (offsets, ids, spans, tiles_x, tiles_y, final_t, last_i, out_depth.copy(), bg,
                     width, height, tile_size, float(alpha_max), depth_eps, C, N)
        return (torch.from_numpy(out_rgb), torch.from_numpy(out_alpha)[..., None],
                torch.from_numpy(out_depth))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, v_rgb, v_alpha, v_depth):
        k = _load()
        (offsets, ids, spans, tiles_x, tiles_y, final_t, last_i, out_depth, bg, width, height,
         tile_size, alpha_max, depth_eps, C, N) = ctx.state
        M = ids.shape[0]
        v_gauss = np.zeros((C * N, k.N_GRAD + k.N_FEAT), np.float32)
        if M > 0:
            hw = (C, height, width)
            zeros = np.zeros
            g_rgb = zeros(hw + (3,), np.float32) if v_rgb is None else _np(v_rgb.float())
            g_a = zeros(hw, np.float32) if v_alpha is None else _np(v_alpha.float()).reshape(hw)
            g_d = zeros(hw, np.float32) if v_depth is None else _np(v_depth.float()).reshape(hw)
            v_feat = np.empty(hw + (k.N_FEAT,), np.float32)
            v_alpha_raw = np.empty(hw, np.float32)
            k.finish_grads(g_rgb, g_a, g_d, out_depth, final_t, bg, depth_eps, v_feat, v_alpha_raw)
            v_isect = np.empty((M, k.N_GRAD + k.N_FEAT), np.float32)  # the kernels write every row
            k.rasterize_bwd(ctx.packed, spans, offsets, C, height, width, tile_size, tiles_x,
                            tiles_y, alpha_max, final_t, last_i, v_feat, v_alpha_raw, v_isect)
            k.scatter_grads(ids, v_isect, v_gauss)
        vg = torch.from_numpy(v_gauss).reshape(C, N, k.N_GRAD + k.N_FEAT)
        g = k.N_GRAD
        return (vg[..., 0:2], vg[..., 2:5], vg[..., 5].sum(0), vg[..., g:g + 3], vg[..., g + 3],
                None, None, None, None, None, None, None)


def rasterize_fused(means2d, conics, opacities, rgb, z, radii_xy, width: int, height: int,
                    backgrounds=None, alpha_max: float = 0.99, tile_size: int = 8,
                    depth_eps: float = 1e-6):
    """Colours over ``backgrounds`` [C,3] (black if None) [C,H,W,3], alphas [C,H,W,1] and
    expected depth [C,H,W,1] of C cameras: means2d [C,N,2], conics [C,N,3], opacities [N]
    (shared by the cameras), rgb [C,N,3], z [C,N] depths (composited, and the depth order),
    radii_xy [C,N,2]. Same results as ``composite_tiles`` of [rgb, z] followed by the
    background blend and the division by alpha, in one autograd node. A background that
    requires grad is blended by torch (its gradient is not computed by the kernels)."""
    if tile_size > 255:
        raise ValueError("tile_size must be <= 255")
    f32 = torch.float32
    dt = rgb.dtype
    C = z.shape[0]
    bg_torch = None
    bg = np.zeros((C, 3), np.float32)
    if backgrounds is not None:
        b = torch.as_tensor(backgrounds)
        if b.requires_grad:
            bg_torch = b
        else:
            bg = np.ascontiguousarray(
                np.broadcast_to(_np(b.to(f32)).reshape(-1, 3), (C, 3)), np.float32)
    binning = bin_gaussians(means2d, conics, opacities[None].expand(C, -1), radii_xy, z,
                            width, height, tile_size)
    img, alphas, depth = _RasterizeFused.apply(
        means2d.to(f32), conics.to(f32), opacities.to(f32), rgb.to(f32), z.to(f32), binning,
        bg, width, height, tile_size, alpha_max, np.float32(depth_eps))
    img, alphas, depth = img.to(dt), alphas.to(dt), depth.to(dt)
    if bg_torch is not None:
        img = img + (1.0 - alphas) * bg_torch.to(dt).reshape(-1, 3).expand(C, 3)[:, None, None, :]
    return img, alphas, depth


class _Project(torch.autograd.Function):
    """EWA projection by the numba kernels: (means, quats, scales) -> means2d [C,N,2],
    conics [C,N,3], z [C,N]; radii_xy [C,N,2] int32 is not differentiable."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, width, height, near, far,
                eps2d):
        k = _load()
        C, N = viewmats.shape[0], means.shape[0]
        dt = np.float64 if means.dtype == torch.float64 else np.float32
        m2d = np.empty((C, N, 2), dt)
        con = np.empty((C, N, 3), dt)
        z = np.empty((C, N), dt)
        radii = np.empty((C, N, 2), np.int32)
        args = (_np(means).astype(dt, copy=False), _np(quats).astype(dt, copy=False),
                _np(scales).astype(dt, copy=False), _np(viewmats).astype(np.float64),
                _np(Ks).astype(np.float64), float(width), float(height), float(near),
                float(far), float(eps2d))
        if N > 0:
            k.project_fwd(args[0], args[1], args[2], _np(opacities).astype(dt, copy=False),
                          *args[3:], m2d, con, z, radii)
        ctx.args = args
        radii_t = torch.from_numpy(radii)
        ctx.mark_non_differentiable(radii_t)
        return torch.from_numpy(m2d), torch.from_numpy(con), torch.from_numpy(z), radii_t

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, v_m2d, v_con, v_z, _v_radii):
        k = _load()
        means, quats, scales = ctx.args[:3]
        N, C = means.shape[0], ctx.args[3].shape[0]
        dt = means.dtype

        def zeros(shape, g):
            return np.zeros(shape, dt) if g is None else _np(g).astype(dt, copy=False)

        v_means = np.zeros((N, 3), dt)
        v_quats = np.zeros((N, 4), dt)
        v_scales = np.zeros((N, 3), dt)
        if N > 0:
            k.project_bwd(*ctx.args, zeros((C, N, 2), v_m2d), zeros((C, N, 3), v_con),
                          zeros((C, N), v_z), v_means, v_quats, v_scales)
        return (torch.from_numpy(v_means), torch.from_numpy(v_quats), torch.from_numpy(v_scales),
                None, None, None, None, None, None, None, None)


class _ShCombine(torch.autograd.Function):
    """rgb [C,N,3] = sum_k basis [C,N,K] * coeffs [N,K,3] (numba; torch's batched tiny
    matmul or broadcast product is several times slower for large N)."""

    @staticmethod
    def forward(ctx, basis, coeffs):
        k = _load()
        C, N, _ = basis.shape
        b, co = _np(basis), _np(coeffs)
        out = np.empty((C, N, 3), b.dtype)
        if N > 0:
            k.sh_combine_fwd(b, co.astype(b.dtype, copy=False), out)
        ctx.save_for_backward(basis, coeffs)
        return torch.from_numpy(out)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, v_out):
        k = _load()
        basis, coeffs = ctx.saved_tensors
        b, co = _np(basis), _np(coeffs).astype(_np(basis).dtype, copy=False)
        v_basis = np.zeros(b.shape, b.dtype)
        v_coeffs = np.zeros(co.shape, b.dtype)
        if b.shape[1] > 0:
            k.sh_combine_bwd(b, co, _np(v_out).astype(b.dtype, copy=False), v_basis, v_coeffs)
        return torch.from_numpy(v_basis), torch.from_numpy(v_coeffs).to(coeffs.dtype)


def sh_combine(basis: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    return _ShCombine.apply(basis.contiguous(), coeffs.contiguous())


def project(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane=0.01,
            far_plane=1e10, eps2d=0.3):
    """Numba version of ``projection.project_gaussians`` (same rules, same Projected)."""
    dt = means.dtype if means.dtype in (torch.float32, torch.float64) else torch.float32
    m2d, con, z, radii_xy = _Project.apply(means, quats.to(dt), scales.to(dt), opacities.detach(),
                                           viewmats.detach(), Ks.detach(), width, height,
                                           near_plane, far_plane, eps2d)
    return Projected(means2d=m2d, conics=con, depths=z, z=z,
                     radii=torch.maximum(radii_xy[..., 0], radii_xy[..., 1]), radii_xy=radii_xy)


def composite_tiles(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                    feats: torch.Tensor, depths: torch.Tensor, radii_xy: torch.Tensor,
                    width: int, height: int, alpha_max: float = 0.99, tile_size: int = 8
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Same contract as ``reference.composite_dense`` (radii_xy [C,N,2] per-axis radii).

    The kernels compute in float32 and render exactly 4 feature channels; other dtypes are
    cast (results come back in the input dtype) and fewer channels are zero-padded."""
    k = _load()
    dt = feats.dtype
    f32 = torch.float32
    C, N, D = feats.shape
    if D > k.N_FEAT:
        raise ValueError(f"the cpu rasterizer renders at most {k.N_FEAT} channels, got {D}")
    feats32 = feats.to(f32)
    if D < k.N_FEAT:
        feats32 = torch.cat([feats32, feats32.new_zeros(C, N, k.N_FEAT - D)], -1)
    if tile_size > 255:
        raise ValueError("tile_size must be <= 255")
    binning = bin_gaussians(means2d, conics, opacities, radii_xy, depths, width, height, tile_size)
    img, alphas = _RasterizeToPixels.apply(means2d.to(f32), conics.to(f32), opacities.to(f32),
                                           feats32.contiguous(), binning, width, height,
                                           tile_size, alpha_max)
    return img[..., :D].to(dt), alphas.to(dt)
