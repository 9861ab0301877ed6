"""sRGB transfer functions and luminance, for numpy arrays and torch tensors alike.

Project convention: the engine trains on **sRGB-encoded display values in [0, 1]** (as
3DGS does). EXR inputs are linear and are encoded with :func:`linear_to_srgb` when loaded
for training; spike light (which is physical, i.e. linear) and EXR output go through
:func:`srgb_to_linear`.

Every function accepts a numpy array (or scalar) or a torch tensor and returns the same
kind. The torch paths are differentiable everywhere and give finite gradients at 0 (the
power branches are evaluated on clamped inputs, so the discarded branch of
``torch.where`` never produces inf/NaN gradients).
"""
from __future__ import annotations

import numpy as np

# IEC 61966-2-1 constants
_SRGB_KNEE = 0.04045          # encoded value where the curve changes
_LIN_KNEE = 0.0031308         # linear value where the curve changes
_REC709 = (0.2126, 0.7152, 0.0722)


def _is_torch(x) -> bool:
    mod = type(x).__module__
    return mod.startswith("torch")


def srgb_to_linear(x):
    """sRGB-encoded values -> linear light. Values <= 0 map linearly (x / 12.92)."""
    if _is_torch(x):
        import torch  # lazy: a foundation module, imported by the Blender UI where torch may be absent

        lo = x / 12.92
        hi = ((torch.clamp(x, min=_SRGB_KNEE) + 0.055) / 1.055) ** 2.4
        return torch.where(x <= _SRGB_KNEE, lo, hi)
    a = np.asarray(x)
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float32)
    lo = a / 12.92
    hi = ((np.maximum(a, _SRGB_KNEE) + 0.055) / 1.055) ** 2.4
    out = np.where(a <= _SRGB_KNEE, lo, hi).astype(a.dtype, copy=False)
    return out if out.ndim else out.item()


def linear_to_srgb(x):
    """Linear light -> sRGB-encoded values (no clipping; clip to [0, 1] yourself if needed)."""
    if _is_torch(x):
        import torch  # lazy: a foundation module, imported by the Blender UI where torch may be absent

        lo = x * 12.92
        hi = 1.055 * torch.clamp(x, min=_LIN_KNEE) ** (1.0 / 2.4) - 0.055
        return torch.where(x <= _LIN_KNEE, lo, hi)
    a = np.asarray(x)
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float32)
    lo = a * 12.92
    hi = 1.055 * np.maximum(a, _LIN_KNEE) ** (1.0 / 2.4) - 0.055
    out = np.where(a <= _LIN_KNEE, lo, hi).astype(a.dtype, copy=False)
    return out if out.ndim else out.item()


def luminance(rgb):
    """Rec.709 luminance of LINEAR RGB along the last axis ([..., 3] -> [...])."""
    r, g, b = _REC709
    if _is_torch(rgb):
        return rgb[..., 0] * r + rgb[..., 1] * g + rgb[..., 2] * b
    a = np.asarray(rgb)
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float32)
    if a.shape[-1] != 3:
        raise ValueError(f"luminance needs [..., 3] RGB, got shape {a.shape}")
    return (a[..., 0] * r + a[..., 1] * g + a[..., 2] * b).astype(a.dtype, copy=False)
