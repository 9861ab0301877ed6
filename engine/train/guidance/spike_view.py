"""Pinhole geometry at one camera for the spike-view flow terms (engine.train.guidance.spike_flow):
project and lift points, sample image-like maps at pixels, and the least-squares fit of a
curve segment's inner control points to target positions. Pure tensor functions."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ...raster.projection import pinhole_project as project  # world points -> (uv, z)

__all__ = ["sample_map", "project", "lift", "projected_flow_loss", "segment_basis", "fit_inner_residuals"]


def sample_map(img: torch.Tensor, uv: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """Values [M, C] of ``img`` [h, w, C] at continuous pixel coordinates ``uv`` [M, 2]
    (corner of the image at (0, 0), pixel (i, j)'s centre at (j + 0.5, i + 0.5): the
    convention of :func:`engine.cameras.project_points`); borders clamp."""
    h, w = img.shape[:2]
    grid = torch.stack([uv[:, 0] / w * 2.0 - 1.0, uv[:, 1] / h * 2.0 - 1.0], -1).reshape(1, 1, -1, 2)
    src = img.permute(2, 0, 1)[None].to(grid.dtype)
    out = F.grid_sample(src, grid, mode=mode, padding_mode="border", align_corners=False)
    return out[0, :, 0].T


def projected_flow_loss(uv_t: torch.Tensor, target: torch.Tensor, beta: float = 1.0) -> torch.Tensor:
    """Mean smooth-L1 (knee ``beta`` px) of the 2D error ``|uv_t - target|`` [M] in pixels
    (``target`` detached)."""
    err = torch.linalg.vector_norm(uv_t - target.detach(), dim=-1)
    return F.smooth_l1_loss(err, torch.zeros_like(err), beta=float(beta))


def segment_basis(u: torch.Tensor) -> torch.Tensor:
    """[J, 2]: the Bezier weights ``3 (1-u)^2 u`` and ``3 (1-u) u^2`` of a segment's two inner
    control points at local parameters ``u`` [J] (a curve moves by ``a D0 + b D1`` when its
    residuals move by ``D0, D1``; engine.scene.trajectory)."""
    v = 1.0 - u
    return torch.stack([3.0 * v * v * u, 3.0 * v * u * u], -1)


def fit_inner_residuals(current: torch.Tensor, targets: torch.Tensor, weights: torch.Tensor, u: torch.Tensor,
                        ridge: float = 1e-3) -> torch.Tensor:
    """Least-squares change ``dD`` [M, 2, 3] of one segment's inner residuals so that the
    curves pass through ``targets``: ``current[j] + a(u_j) dD0 + b(u_j) dD1 ~ targets[j]``
    weighted by ``weights`` [J, M] (0 = no observation). ``current``, ``targets`` [J, M, 3];
    ``ridge`` (x the summed weight) keeps poorly observed curves near where they are."""
    B = segment_basis(u.to(current))  # [J, 2]
    w = weights.to(current)
    AtA = torch.einsum("jm,ja,jb->mab", w, B, B)
    AtA = AtA + ridge * w.sum(0).clamp_min(1e-6)[:, None, None] * torch.eye(2, dtype=current.dtype,
                                                                             device=current.device)
    Atr = torch.einsum("jm,ja,jmc->mac", w, B, targets - current)
    return torch.linalg.solve(AtA, Atr)


def lift(uv: torch.Tensor, z: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """World points [N, 3] at pixels ``uv`` [N, 2] and camera depth ``z`` [N] (inverse of :func:`project`)."""
    cam = torch.stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z, z], -1)
    return (cam - viewmat[:3, 3]) @ viewmat[:3, :3]
