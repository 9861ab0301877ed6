"""Coarse-to-fine for large frames (issue 43): the static warm-up renders and scores a train frame
at most :data:`COARSE_MAX_WIDTH` wide; the deformation stage uses the full frame.

The warm-up fits colours and the static geometry's large-scale layout, which half the pixels carry
as well; every step of it costs a fraction at 1080x720. Frames no wider than the limit are used as
they are (every capture of the test suite and the published figures).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ...scene.model import scaled_view
from .interpolation import resample_area

COARSE_MAX_WIDTH = 540  # half the paper's 1080-px RGB frames


def coarse_item(item: dict, max_width: int = COARSE_MAX_WIDTH) -> dict:
    """``item`` (a trainer frame: view tensors, image [1, H, W, 3], optional stereo depth, mask and
    local planes [H, W(, 3)]) at most ``max_width`` wide: the camera scaled (same field of view), the image
    area-averaged, the depth prior and planes sampled nearest (no depth between two surfaces). The item
    itself when it is no wider."""
    if item["width"] <= max_width:
        return item
    out = scaled_view(item, max_width / item["width"])
    h, w = out["height"], out["width"]
    out["image"] = resample_area(item["image"], (h, w)).contiguous()
    if "stereo_depth" in item:
        d = item["stereo_depth"][None, None].float()
        m = item["stereo_mask"][None, None].float()
        out["stereo_depth"] = F.interpolate(d, size=(h, w), mode="nearest")[0, 0]
        out["stereo_mask"] = F.interpolate(m, size=(h, w), mode="nearest")[0, 0] > 0.5
    if "stereo_normal" in item:  # the local planes of engine.train.losses.geometry_losses.lie_flat
        n = item["stereo_normal"].permute(2, 0, 1)[None]
        out["stereo_normal"] = F.interpolate(n, size=(h, w), mode="nearest")[0].permute(1, 2, 0).contiguous()
        out["stereo_offset"] = F.interpolate(item["stereo_offset"][None, None], size=(h, w), mode="nearest")[0, 0]
    return out


class CoarseItems:
    """Each frame's coarse item, made once."""

    def __init__(self, max_width: int | None = None):
        self.max_width = int(max_width if max_width is not None else COARSE_MAX_WIDTH)
        self._items: dict[int, dict] = {}

    def __call__(self, item: dict) -> dict:
        if item["width"] <= self.max_width:
            return item
        key = int(item["index"])
        if key not in self._items:
            with torch.no_grad():
                self._items[key] = coarse_item(item, self.max_width)
        return self._items[key]
