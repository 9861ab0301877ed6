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


def depth_normals(depth: np.ndarray, mask: np.ndarray, K: np.ndarray, *, window: int | None = None,
                  flatness: float = 0.05, grazing: float = 0.1, jump: float = 0.05) -> tuple:
    """Local plane fits to a depth map: camera-space unit normals [H,W,3] float32, where one was
    kept [H,W] bool, and the plane's offset [H,W] float32 (the plane is n . x = offset).

    ``depth`` [H,W] planar depth (OpenCV camera: x right, y down, z forward), ``mask`` its known
    pixels, ``K`` [3,3]. Each pixel's normal is the least-variance direction of the back-projected
    known points in a ``window`` x ``window`` box (default: the image width / 16, odd, >= 5: at
    320x240 a 21-pixel box puts half of a 2 m set's stereo normals within 5 degrees of the truth,
    a 7-pixel one within 14); it is kept where at least half the box is known, no depth jump
    (neighbours differing by more than ``jump``, relative) lies in the box, the fit is flat
    (smallest eigenvalue / trace <= ``flatness``: stereo scatter is not) and the surface is not
    seen edge-on (|cos| of its angle to the ray >= ``grazing``). Normals face the camera."""
    import cv2

    H, W = depth.shape
    win = window or max(5, int(W / 16) | 1)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    z = np.where(mask, depth, 0.0).astype(np.float64)
    p = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
    m = mask.astype(np.float64)

    def box(a):
        return cv2.boxFilter(a, -1, (win, win), normalize=False, borderType=cv2.BORDER_CONSTANT)

    n = box(m)
    safe = np.maximum(n, 1.0)
    mean = np.stack([box(p[..., i] * m) for i in range(3)], -1) / safe[..., None]
    cov = np.empty((H, W, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[..., i, j] = cov[..., j, i] = box(p[..., i] * p[..., j] * m) / safe - mean[..., i] * mean[..., j]
    ev, vec = np.linalg.eigh(cov)
    normal = vec[..., :, 0]
    normal *= -np.sign(np.einsum("hwi,hwi->hw", normal, mean))[..., None]
    flat = ev[..., 0] <= flatness * np.maximum(ev.sum(-1), 1e-12)
    facing = -np.einsum("hwi,hwi->hw", normal, mean) >= grazing * np.linalg.norm(mean, axis=-1)
    zn = np.where(mask, depth, np.nan)
    ratio = np.ones((H, W))
    for a, b in ((zn[:, 1:], zn[:, :-1]), (zn[1:], zn[:-1])):
        r = np.nan_to_num(np.maximum(a / b, b / a), nan=1.0)
        pad = ((0, 0), (0, 1)) if a.shape[1] < W else ((0, 1), (0, 0))
        ratio = np.maximum(ratio, np.pad(r, pad, constant_values=1.0))
    near_jump = box((ratio > 1 + jump).astype(np.float64)) > 0  # the box around each pixel (a jump's left/top pixel)
    ok = mask & ~near_jump & (n >= 0.5 * win * win) & flat & facing & np.isfinite(normal).all(-1)
    normal = np.where(ok[..., None], normal, 0.0)
    return normal.astype(np.float32), ok, np.einsum("hwi,hwi->hw", normal, mean).astype(np.float32)


PLANES_MAX_WIDTH = 400  # local planes are fitted on every k-th pixel above this width (1080x720: 1.4 s a frame)


def world_planes(depth: np.ndarray, mask: np.ndarray, K: np.ndarray, viewmat: np.ndarray,
                 max_width: int = PLANES_MAX_WIDTH) -> tuple:
    """:func:`depth_normals` in world space: (normals [H,W,3], offsets [H,W]) float32, the local plane
    at each pixel being n . x = offset (zero normals where there is none); ``viewmat`` [4,4] is the
    OpenCV world-to-camera matrix (x_cam = R x_world + t). A depth map wider than ``max_width`` is
    fitted on every k-th pixel (the box keeps its share of the width) and each plane is given to the
    k x k pixels around its sample: the planes are metres across, the fit costs a 3x3 eigen-problem
    per pixel."""
    K = np.asarray(K, dtype=np.float64)
    H, W = depth.shape
    k = max(1, -(-W // int(max_width)))
    if k > 1:  # pixel i of the subsample is pixel k i + k // 2 of the frame
        Ks = K.copy()
        Ks[0, 0], Ks[1, 1] = K[0, 0] / k, K[1, 1] / k
        Ks[0, 2], Ks[1, 2] = (K[0, 2] - k // 2 - 0.5) / k + 0.5, (K[1, 2] - k // 2 - 0.5) / k + 0.5
        n, _, off = depth_normals(depth[k // 2::k, k // 2::k], mask[k // 2::k, k // 2::k], Ks)
        n = np.repeat(np.repeat(n, k, 0), k, 1)[:H, :W]
        off = np.repeat(np.repeat(off, k, 0), k, 1)[:H, :W]
        if n.shape[:2] != (H, W):  # fewer than H / k samples: pad with "no plane"
            n = np.pad(n, ((0, H - n.shape[0]), (0, W - n.shape[1]), (0, 0)))
            off = np.pad(off, ((0, H - off.shape[0]), (0, W - off.shape[1])))
    else:
        n, _, off = depth_normals(depth, mask, K)
    vm = np.asarray(viewmat, dtype=np.float64)
    return (n @ vm[:3, :3]).astype(np.float32), (off - n @ vm[:3, 3]).astype(np.float32)
