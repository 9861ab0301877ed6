"""The spike branch's between-frame render skips the depth channel (spike_guidance.BETWEEN_DEPTH):
the same colours and gradients as a render with depth, bit for bit."""
from __future__ import annotations

import torch

from engine.raster import rasterization


def _view(width=64, height=48, f=60.0):
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])[None]
    return {"viewmat": torch.eye(4)[None], "K": K, "width": width, "height": height}


def _gaussians(n=300, seed=0, spread=0.35):
    gen = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=gen) * 2 - 1
    means[:, :2] *= spread  # well inside the view: the projection's FoV clamp never applies
    means[:, 2] = 3.0 + means[:, 2]
    q = torch.randn(n, 4, generator=gen)
    return {"means": means, "quats": q / q.norm(dim=-1, keepdim=True),
            "scales": torch.rand(n, 3, generator=gen) * 0.05 + 0.01,
            "opacities": torch.rand(n, generator=gen) * 0.8 + 0.1, "colors": torch.rand(n, 3, generator=gen)}


def test_render_without_depth_has_the_same_colours_and_gradients_bit_for_bit():
    g = _gaussians(n=1000, spread=0.9)
    vt = _view()
    w = torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(4))
    outs = []
    for depth in (True, False):
        leaf = {k: v.clone().requires_grad_(True) for k, v in g.items()}
        rgb, _, meta = rasterization(leaf["means"], leaf["quats"], leaf["scales"], leaf["opacities"],
                                     leaf["colors"], vt["viewmat"], vt["K"], 64, 48, render_depth=depth)
        (rgb * w).sum().backward()
        assert ("depths" in meta) == depth
        outs.append((rgb.detach(), [leaf[k].grad for k in sorted(leaf)]))
    assert torch.equal(outs[0][0], outs[1][0])
    assert all(torch.equal(a, b) for a, b in zip(outs[0][1], outs[1][1]))
