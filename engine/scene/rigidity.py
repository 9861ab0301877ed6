"""Local rigidity priors over k nearest neighbours (Luiten et al., "Dynamic 3D Gaussians",
3DV 2024, Sec. 4: rigidity, rotation similarity, isometry).

What one camera (the spike view) sees of a rigid part should move the whole part: each
Gaussian's neighbours keep their offsets in its local frame, their relative rotations and
their distances between a reference instant and the current one.

Shapes: ``means_*`` [N, 3], ``quats_*`` [N, 4] wxyz (any norm), ``nbr`` [N, k] int64
indices of each Gaussian's neighbours, ``w`` [N, k] weights (Luiten: exp(-lambda d^2) of
the canonical distance). Returns scalars (weighted means).
"""
from __future__ import annotations

import torch

from .gaussians import quat_to_rotmat

__all__ = ["knn_neighbours", "rigidity_losses"]


@torch.no_grad()
def knn_neighbours(points: torch.Tensor, k: int = 8, chunk: int = 2048,
                   weight_scale: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(indices [N, k], weights [N, k]) of the ``k`` nearest other points; weights
    ``exp(-d^2 / (2 s^2))`` with ``s`` the median neighbour distance (or ``weight_scale``)."""
    n = points.shape[0]
    k = max(1, min(int(k), n - 1))
    idx = torch.empty(n, k, dtype=torch.long, device=points.device)
    dist = torch.empty(n, k, dtype=points.dtype, device=points.device)
    for s in range(0, n, chunk):
        d = torch.cdist(points[s:s + chunk], points)
        d[torch.arange(d.shape[0]), torch.arange(s, s + d.shape[0])] = float("inf")
        v, i = d.topk(k, dim=1, largest=False)
        idx[s:s + chunk], dist[s:s + chunk] = i, v
    scale = float(weight_scale) if weight_scale is not None else float(dist.median().clamp_min(1e-12))
    return idx, torch.exp(-(dist ** 2) / (2 * scale ** 2))


def rigidity_losses(means_ref: torch.Tensor, quats_ref: torch.Tensor, means_t: torch.Tensor, quats_t: torch.Tensor,
                    nbr: torch.Tensor, w: torch.Tensor) -> dict:
    """Luiten's three terms between a reference instant and ``t``:

    * ``rigid``: ``|| (mu_j,ref - mu_i,ref) - R_i,ref R_i,t^T (mu_j,t - mu_i,t) ||`` -- the
      neighbour offsets rotate with the Gaussian's own frame;
    * ``rot``: ``|| q_j,t q_j,ref^-1 - q_i,t q_i,ref^-1 ||`` -- neighbours rotate alike;
    * ``iso``: ``| ||mu_j,ref - mu_i,ref|| - ||mu_j,t - mu_i,t|| |`` -- distances are kept.
    """
    wsum = w.sum().clamp_min(1e-12)
    off_ref = means_ref[nbr] - means_ref[:, None]  # [N, k, 3]
    off_t = means_t[nbr] - means_t[:, None]
    R_ref, R_t = quat_to_rotmat(quats_ref), quat_to_rotmat(quats_t)
    rel = R_ref @ R_t.transpose(1, 2)  # [N, 3, 3]: frame at t -> frame at ref
    back = torch.einsum("nab,nkb->nka", rel, off_t)
    rigid = ((off_ref - back).norm(dim=-1) * w).sum() / wsum
    qr = quats_ref / quats_ref.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    qt = quats_t / quats_t.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    d = _qmul(qt, _qconj(qr))  # [N, 4] rotation from ref to t
    d = d * torch.sign(d[:, :1] + 1e-12)  # q and -q are the same rotation
    rot = ((d[nbr] - d[:, None]).norm(dim=-1) * w).sum() / wsum
    iso = ((off_ref.norm(dim=-1) - off_t.norm(dim=-1)).abs() * w).sum() / wsum
    return {"rigid": rigid, "rot": rot, "iso": iso}


def _qconj(q: torch.Tensor) -> torch.Tensor:
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def _qmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)
