"""Gaussian dropout for training renders: DropGaussian (Park, Ryu and Kim, CVPR 2025).

Each training render leaves out a random share of the Gaussians and lifts the others'
opacity by 1 / (1 - rate), so that the expected opacity is unchanged. With two train
cameras a few degrees apart the Gaussians otherwise co-adapt to those two views; a render
that may miss any one of them makes each carry the surface on its own. The trainer drops
while densification runs (``densify.stop``) and trains every Gaussian together after it:
dropout to the end blurred the result (LPIPS up to +0.03), docs/experiments/gaussian-dropout.md.
Evaluation and export renders (no gradient) keep every Gaussian.
"""
from __future__ import annotations

import torch

# the step's seed: a resumed run draws the same masks as an uninterrupted one
_STEP_SEED = 15485863


class GaussianDropout:
    """The masks of one training step's renders (their order within the step is fixed)."""

    def __init__(self, rate: float, seed: int, step: int):
        if not 0.0 <= rate < 1.0:
            raise ValueError(f"gaussians.drop_rate must lie in [0, 1), got {rate}")
        self.rate = float(rate)
        self.generator = torch.Generator(device="cpu").manual_seed(int(seed) * _STEP_SEED + int(step))

    @classmethod
    def for_step(cls, rate: float, seed: int, step: int, densifying: bool = True) -> "GaussianDropout | None":
        """The step's dropout, or None when ``rate`` is 0 or the step is past the densification window
        (the schedule's, virtual steps included: the last steps train every Gaussian together, which keeps LPIPS)."""
        return cls(rate, seed, step) if rate > 0 and densifying else None

    def __call__(self, opacities: torch.Tensor) -> torch.Tensor:
        """opacities [N] -> the same with a share ``rate`` zeroed and the rest / (1 - rate)."""
        keep = torch.rand(opacities.shape, generator=self.generator) >= self.rate
        scale = keep.to(opacities.dtype) / (1.0 - self.rate)
        return opacities * scale.to(opacities.device)
