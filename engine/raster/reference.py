"""The obviously-correct dense compositor: every pixel against every Gaussian, plain torch.

Memory is O(C * H * W * N): for tests and tiny images only. Autograd gives the gradients.
Same rules as the fast path: front-to-back in depth order, alpha = min(alpha_max,
opacity * exp(-power)), alpha < 1/255 skipped, a Gaussian that would bring the
transmittance to <= 1e-4 stops the pixel (it and everything behind are left out).
"""
from __future__ import annotations

import torch

from .projection import ALPHA_THRESHOLD, TRANSMITTANCE_STOP


def composite_lists(pix: torch.Tensor, means2d: torch.Tensor, conics: torch.Tensor,
                    opacities: torch.Tensor, feats: torch.Tensor, valid: torch.Tensor | None = None,
                    alpha_max: float = 0.99) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite B groups of pixels against B front-to-back lists of Gaussians.

    pix [B,P,2] pixel centres, means2d [B,K,2], conics [B,K,3], opacities [B,K],
    feats [B,K,D], valid [B,K] (False = padding) -> (features [B,P,D], alphas [B,P,1]).
    """
    d = means2d[:, None] - pix[:, :, None]                                 # [B,P,K,2] mean - pixel
    dx, dy = d[..., 0], d[..., 1]
    a, b, c = (conics[:, None, :, j] for j in range(3))
    power = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    ok = power >= 0
    if valid is not None:
        ok = ok & valid[:, None]
    power = torch.where(ok, power, torch.zeros_like(power))        # no inf in the unused branch
    alpha = torch.clamp_max(opacities[:, None] * torch.exp(-power), alpha_max)
    zero = torch.zeros_like(alpha)
    alpha = torch.where(ok & (alpha >= ALPHA_THRESHOLD), alpha, zero)
    t_incl = torch.cumprod(1.0 - alpha, dim=-1)
    alpha = torch.where(t_incl > TRANSMITTANCE_STOP, alpha, zero)
    one_minus = 1.0 - alpha
    t_excl = torch.cumprod(torch.cat([torch.ones_like(one_minus[..., :1]), one_minus[..., :-1]], -1), -1)
    w = alpha * t_excl                                                      # [B,P,K]
    return w @ feats, 1.0 - torch.prod(one_minus, dim=-1, keepdim=True)


def pixel_centres(width: int, height: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """[H*W, 2] (x, y) pixel centres, row-major."""
    ys, xs = torch.meshgrid(torch.arange(height, device=device, dtype=dtype) + 0.5,
                            torch.arange(width, device=device, dtype=dtype) + 0.5, indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)


def composite_dense(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                    feats: torch.Tensor, depths: torch.Tensor, radii: torch.Tensor,
                    width: int, height: int, alpha_max: float = 0.99
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """means2d [C,N,2], conics [C,N,3], opacities [C,N], feats [C,N,D], depths [C,N] (sort
    key), radii [C,N] (0 = culled) -> (features [C,H,W,D], alphas [C,H,W,1])."""
    C, N = radii.shape
    D = feats.shape[-1]
    pix = pixel_centres(width, height, means2d.device, means2d.dtype)
    out_f, out_a = [], []
    for c in range(C):
        idx = torch.nonzero(radii[c] > 0).reshape(-1)
        if idx.numel() == 0:  # keep the graph connected (zero gradients) for an empty view
            z = 0.0 * (means2d.sum() + conics.sum() + opacities.sum() + feats.sum())
            out_f.append(feats.new_zeros(height * width, D) + z)
            out_a.append(feats.new_zeros(height * width, 1) + z)
            continue
        order = idx[torch.argsort(depths[c, idx].detach(), stable=True)]
        f, a = composite_lists(pix[None], means2d[c, order][None], conics[c, order][None],
                               opacities[c, order][None], feats[c, order][None],
                               alpha_max=alpha_max)
        out_f.append(f[0])
        out_a.append(a[0])
    return (torch.stack(out_f).reshape(C, height, width, D),
            torch.stack(out_a).reshape(C, height, width, 1))
