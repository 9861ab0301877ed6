"""Per-frame stereo depth priors for training (issue 14): the fused SGBM depth of
:mod:`engine.geometry.stereo` at every RGB instant, or nothing when the cameras are not a
usable pair (the message is returned so that the trainer records it in run.json)."""
from __future__ import annotations

from ..init_points import rgb_cameras
from .stereo import StereoUnavailable, fused_depth_priors


def stereo_depth_priors(capture, frames, *, min_pixels: int = 16) -> dict:
    """{id(frame): (depth [H,W] float32, mask [H,W] bool)} for frames of the stereo pair with
    at least ``min_pixels`` known depths; ``{}`` plus a ``"_unavailable"`` message when the
    cameras are not a pair."""
    try:
        priors = fused_depth_priors(capture, frames, rgb_cameras(capture))
    except StereoUnavailable as err:
        return {"_unavailable": str(err)}
    return {k: v for k, v in priors.items() if int(v[1].sum()) >= min_pixels}
