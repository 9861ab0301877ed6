"""Fused stereo depth as training supervision, computed once per run.

:class:`FusionCache` runs :func:`engine.geometry.stereo.capture_fusion` once per set of pair
instants; :func:`stereo_depth_priors` turns a fusion into per-frame depth targets for
``lambda_depth`` (the instant's own stereo depth, else the static depth where nothing moving
covers the pixel).
"""
from __future__ import annotations

import numpy as np

from .planesweep import rgb_cameras
from .resolution import at_size
from .stereo import StereoUnavailable, capture_fusion, pair_instants


def fused_depth_priors(capture, frames, cameras: list[str], *, fusion=None) -> dict:
    """Depth supervision for every frame of the pair: {id(frame): (depth [H,W], mask [H,W])}
    from :meth:`FusedDepth.instant_depth` (the instant's own stereo depth, else the static
    depth where nothing moving covers the pixel). ``fusion``: a precomputed (FusedDepth a,
    FusedDepth b, info). Raises :class:`StereoUnavailable`."""
    fa, fb, _ = fusion if fusion is not None else capture_fusion(capture, cameras, frames)
    out = {}
    for fused in (fa, fb):
        index = {round(float(t), 6): i for i, t in enumerate(fused.times)}
        for f in frames:
            i = index.get(round(float(f.time), 6))
            if f.camera == fused.camera and i is not None:
                d, ok = fused.instant_depth(i)
                d = np.nan_to_num(d, nan=0.0).astype(np.float32)
                k = capture.view(f).intrinsics  # a fusion at a working resolution: back at the frame's
                out[id(f)] = (at_size(d, k.height, k.width), at_size(ok, k.height, k.width))
    return out


class FusionCache:
    """:func:`capture_fusion` once per set of pair instants: the init points, the depth priors
    and the flow carry fuse the same frames, and each fusion runs SGBM on every instant (2-4 s
    on the demo). ``cache(cameras, frames=None)``; a StereoUnavailable is raised again."""

    def __init__(self, capture):
        self.capture = capture
        self._done: dict = {}

    def __call__(self, cameras: list[str], frames=None):
        a, b, inst = pair_instants(self.capture, cameras, frames)  # cheap; raises StereoUnavailable
        key = (a, b, tuple((t, id(fa), id(fb)) for t, fa, fb in inst))
        if key not in self._done:
            try:
                self._done[key] = capture_fusion(self.capture, cameras, frames)
            except StereoUnavailable as err:
                self._done[key] = err
        if isinstance(self._done[key], StereoUnavailable):
            raise self._done[key]
        return self._done[key]


def stereo_depth_priors(capture, frames, *, min_pixels: int = 16, fusion_cache: FusionCache | None = None) -> dict:
    """Depth supervision of ``lambda_depth``: {id(frame): (depth [H,W] float32, mask [H,W] bool)}
    for the pair's frames with at least ``min_pixels`` known depths (:func:`fused_depth_priors`);
    ``{"_unavailable": message}`` when the cameras are not a usable pair."""
    try:
        cams = rgb_cameras(capture)
        fusion = fusion_cache(cams, frames) if fusion_cache is not None else None
        priors = fused_depth_priors(capture, frames, cams, fusion=fusion)
    except StereoUnavailable as err:
        return {"_unavailable": str(err)}
    return {k: v for k, v in priors.items() if int(v[1].sum()) >= min_pixels}
