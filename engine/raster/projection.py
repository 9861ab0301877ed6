"""Projection of 3D Gaussians to the image plane and SH colour evaluation (vectorised torch).

Shared by every CPU backend. Autograd differentiates these O(N) operations; only the
per-pixel compositing has a hand-written backward (``engine.raster.cpu``).

Rules follow gsplat: near/far culling *before* dividing by z (the culled entries divide
by a safe 1), x/z and y/z clamped to 1.3x the field of view when building the Jacobian,
``eps2d`` px^2 added to the 2D covariance, determinant clamped at 1e-10, per-axis radius
``ceil(extent * sigma)`` with ``extent = min(3.33, sqrt(2 ln(255 * opacity)))`` (beyond it
alpha < 1/255 and the pixel would be skipped anyway), Gaussians with opacity < 1/255,
a zero radius or a box entirely off the image are culled (radius 0).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

ALPHA_THRESHOLD = 1.0 / 255.0
TRANSMITTANCE_STOP = 1e-4
EXTENT_MAX = 3.33
DET_MIN = 1e-10

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


@dataclass
class Projected:
    """Per camera, per Gaussian screen-space quantities ([C, N, ...])."""

    means2d: torch.Tensor   # [C,N,2] px, differentiable
    conics: torch.Tensor    # [C,N,3] (a, b, c) of the inverse 2D covariance, differentiable
    depths: torch.Tensor    # [C,N] camera z (1 where culled by depth), differentiable
    z: torch.Tensor         # [C,N] camera z as is (also for culled Gaussians)
    radii: torch.Tensor     # [C,N] int32, max of the per-axis radii; 0 = culled
    radii_xy: torch.Tensor  # [C,N,2] int32 per-axis radii (binning box); 0 where culled


def pinhole_project(x: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pinhole projection of world points ``x`` [N, 3] -> (uv [N, 2], z [N]); ``viewmat``
    [4, 4] world-to-camera, ``K`` [3, 3] (as :func:`engine.cameras.project_points`; z clamped at
    1e-6 for the division only)."""
    cam = x @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    zs = z.clamp_min(1e-6)
    uv = torch.stack([K[0, 0] * cam[:, 0] / zs + K[0, 2], K[1, 1] * cam[:, 1] / zs + K[1, 2]], -1)
    return uv, z


def normalize_quats(quats: torch.Tensor) -> torch.Tensor:
    """wxyz quaternions -> unit quaternions; a zero quaternion becomes the identity safely."""
    n2 = (quats * quats).sum(-1, keepdim=True)
    safe = n2 > 1e-24
    ident = torch.zeros_like(quats)
    ident[..., 0] = 1.0
    q = torch.where(safe, quats, ident)
    n2 = torch.where(safe, n2, torch.ones_like(n2))
    return q * torch.rsqrt(n2)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Unit wxyz quaternions [N,4] -> rotation matrices [N,3,3]."""
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(q.shape[:-1] + (3, 3))


def camera_centers(viewmats: torch.Tensor) -> torch.Tensor:
    """World-space camera centres [C,3] from world-to-camera matrices."""
    R = viewmats[:, :3, :3]
    t = viewmats[:, :3, 3]
    return -(R.transpose(1, 2) @ t[..., None])[..., 0]


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Real SH basis (3DGS sign convention) for unit directions [...,3] -> [..., (degree+1)^2]."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz,
                SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, -1)


def eval_colors(means: torch.Tensor, colors: torch.Tensor, viewmats: torch.Tensor,
                sh_degree: int | None, combine=None) -> torch.Tensor:
    """Per-camera RGB [C,N,3]: plain colours broadcast, or SH evaluated towards each camera
    (``max(SH + 0.5, 0)``, the 3DGS convention). ``combine(basis [C,N,K], coeffs [N,K,3])``
    may replace the torch basis-coefficient product (the cpu backend passes a numba one)."""
    C = viewmats.shape[0]
    if sh_degree is None:
        if colors.dim() != 2 or colors.shape[-1] != 3:
            raise ValueError(f"colors must be [N,3] without sh_degree, got {tuple(colors.shape)}")
        return colors[None].expand(C, -1, -1)
    if not 0 <= int(sh_degree) <= 3:
        raise ValueError(f"sh_degree must be 0..3, got {sh_degree}")
    sh_degree = int(sh_degree)
    K = (sh_degree + 1) ** 2
    if colors.dim() != 3 or colors.shape[-1] != 3 or colors.shape[1] < K:
        raise ValueError(f"colors must be [N,K>={K},3] for sh_degree={sh_degree}, "
                         f"got {tuple(colors.shape)}")
    coeffs = colors[:, :K]
    if sh_degree == 0:
        rgb = (SH_C0 * coeffs[:, 0])[None].expand(C, -1, -1)
    else:
        d = means[None] - camera_centers(viewmats)[:, None]          # [C,N,3]
        n2 = (d * d).sum(-1, keepdim=True)
        d = d * torch.rsqrt(n2.clamp_min(1e-20))
        basis = sh_basis(d, sh_degree)                                # [C,N,K]
        if combine is not None:
            rgb = combine(basis, coeffs)
        else:
            rgb = (basis[..., None] * coeffs[None]).sum(-2)
    return torch.clamp_min(rgb + 0.5, 0.0)


def project_gaussians(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                      opacities: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor,
                      width: int, height: int, near_plane: float = 0.01, far_plane: float = 1e10,
                      eps2d: float = 0.3) -> Projected:
    """EWA splatting of 3D Gaussians into C pinhole cameras (OpenCV convention)."""
    R = viewmats[:, :3, :3].to(means.dtype)                  # [C,3,3]
    t = viewmats[:, :3, 3].to(means.dtype)                   # [C,3]
    Ks = Ks.to(means.dtype)
    pc = torch.einsum("cij,nj->cni", R, means) + t[:, None]  # [C,N,3]
    x, y, z = pc.unbind(-1)
    in_depth = (z > near_plane) & (z < far_plane)
    zs = torch.where(in_depth, z, torch.ones_like(z))        # safe divisor: culled -> 1
    inv_z = 1.0 / zs
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]           # [C,1]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    u, v = x * inv_z, y * inv_z
    means2d = torch.stack([fx * u + cx, fy * v + cy], -1)   # [C,N,2]

    # Jacobian of the projection, with x/z, y/z clamped to 1.3x the field of view (gsplat).
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    uc = torch.minimum(torch.maximum(u, -(cx / fx + 0.3 * tan_x)), (width - cx) / fx + 0.3 * tan_x)
    vc = torch.minimum(torch.maximum(v, -(cy / fy + 0.3 * tan_y)), (height - cy) / fy + 0.3 * tan_y)
    j00, j02 = fx * inv_z, -fx * uc * inv_z
    j11, j12 = fy * inv_z, -fy * vc * inv_z
    # rows of J @ R: [C,N,3]
    T0 = j00[..., None] * R[:, None, 0] + j02[..., None] * R[:, None, 2]
    T1 = j11[..., None] * R[:, None, 1] + j12[..., None] * R[:, None, 2]
    # Sigma = M M^T with M = Rq diag(s); cov2d = (T M)(T M)^T, exactly PSD.
    M = quat_to_rotmat(normalize_quats(quats)) * scales[:, None, :]   # [N,3,3]
    a_vec = (T0[..., :, None] * M[None]).sum(-2)            # [C,N,3] = T0 @ M
    b_vec = (T1[..., :, None] * M[None]).sum(-2)
    cov_a = (a_vec * a_vec).sum(-1) + eps2d
    cov_b = (a_vec * b_vec).sum(-1)
    cov_c = (b_vec * b_vec).sum(-1) + eps2d
    det = torch.clamp_min(cov_a * cov_c - cov_b * cov_b, DET_MIN)
    inv_det = 1.0 / det
    conics = torch.stack([cov_c * inv_det, -cov_b * inv_det, cov_a * inv_det], -1)

    with torch.no_grad():
        op = opacities.detach().to(means.dtype)[None].expand_as(z)
        ok = in_depth & (op >= ALPHA_THRESHOLD)
        extent = torch.sqrt(2.0 * torch.log(torch.clamp_min(op, ALPHA_THRESHOLD) / ALPHA_THRESHOLD))
        extent = torch.clamp_max(extent, EXTENT_MAX)
        rx = torch.ceil(extent * torch.sqrt(cov_a.detach()))
        ry = torch.ceil(extent * torch.sqrt(cov_c.detach()))
        mx, my = means2d.detach().unbind(-1)
        ok &= (rx > 0) & (ry > 0) & torch.isfinite(rx) & torch.isfinite(ry)
        ok &= (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height)
        lim = float(2 ** 30)  # keeps int32 radii from overflowing; binning clamps to the image
        rx = torch.where(ok, rx.clamp_max(lim), torch.zeros_like(rx)).to(torch.int32)
        ry = torch.where(ok, ry.clamp_max(lim), torch.zeros_like(ry)).to(torch.int32)
        radii_xy = torch.stack([rx, ry], -1)
        radii = torch.maximum(rx, ry)
    # depth-culled Gaussians: zero centre and conic (as gsplat's packed=False outputs)
    keep = in_depth[..., None]
    means2d = torch.where(keep, means2d, torch.zeros_like(means2d))
    conics = torch.where(keep, conics, torch.zeros_like(conics))
    return Projected(means2d=means2d, conics=conics, depths=zs, z=z, radii=radii, radii_xy=radii_xy)
