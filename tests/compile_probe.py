"""Print hashes of the rasterizer's forward + backward and the fused HexPlane sampler's
forward + backward on fixed inputs (tests/test_compile_reproducible.py runs it twice on one
fresh numba cache: a cold compile, then a cache load)."""
import hashlib
import sys

import torch

sys.path.insert(0, sys.argv[1])
from engine.raster import rasterization  # noqa: E402
from engine.scene.hexplane_fused import available, hexplane_sample  # noqa: E402


def h(t):
    return hashlib.md5(t.detach().contiguous().numpy().tobytes()).hexdigest()


g = torch.Generator().manual_seed(1)
n = 4000
ps = [(torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([4.0, 3.0, 1.0]) + torch.tensor([0.0, 0.0, 4.0]),
      torch.randn(n, 4, generator=g), torch.rand(n, 3, generator=g) * 0.05 + 0.005,
      torch.rand(n, generator=g), torch.rand(n, 3, generator=g)]
for p in ps:
    p.requires_grad_(True)
K = torch.tensor([[[80.0, 0, 40], [0, 80.0, 30], [0, 0, 1]]])
c, a, m = rasterization(*ps, torch.eye(4)[None], K, 80, 60, render_depth=True)
((c * torch.rand(c.shape, generator=g)).sum() + (a * torch.rand(a.shape, generator=g)).sum()
 + m["depths"].sum()).backward()
out = ["raster", h(c), h(a), h(m["depths"])] + [h(p.grad) for p in ps]
if available():
    sp = torch.rand(3, 8, 16, 16, generator=g, requires_grad=True)
    tp = torch.rand(3, 8, 12, 16, generator=g, requires_grad=True)
    xyzt = (torch.rand(3000, 4, generator=g) * 2 - 1).requires_grad_(True)
    f = hexplane_sample(xyzt, [sp], [tp])
    (f * torch.rand(f.shape, generator=g)).sum().backward()
    out += ["hexplane", h(f), h(sp.grad), h(tp.grad), h(xyzt.grad)]
print(" ".join(out))
