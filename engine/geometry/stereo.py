"""Two-view stereo between the calibrated RGB pair, with OpenCV (issue 14, build item 2).

Pipeline, per RGB instant where both cameras have a frame:

1. :func:`rectify_pair` -- ``cv2.stereoRectify`` from the two cameras' intrinsics and relative
   pose. The capture stores OpenGL camera-to-world matrices; ``View.viewmat`` is the OpenCV
   world-to-camera matrix (+Z forward, +Y down), so ``x_b = R x_a + T`` with
   ``R = R_b R_a^T`` and ``T = t_b - R t_a`` is what OpenCV expects. The engine puts pixel
   centres at ``u + 0.5`` (``u = fx x/z + cx`` from the top-left corner) and OpenCV at ``u``,
   so OpenCV's principal point is ``cx - 0.5``. A vertical pair is rectified, transposed to
   horizontal epipolar lines, matched and transposed back; the left image of the matcher is
   always the camera whose rectified centre lies left.
2. :func:`match_rectified` -- semi-global matching (``cv2.StereoSGBM``, Hirschmueller 2008) in
   both directions (the right-to-left pass matches the mirrored images), a left-right
   consistency check, SGBM's parabolic sub-pixel disparity (1/16 px), speckle filtering
   (``cv2.filterSpeckles``), the half-occluded band beside foreground edges removed
   (:mod:`.stereo_filters`) and a per-pixel confidence in [0, 1] (agreement of the two
   directions times a soft texture term).
3. :func:`pair_depths` -- the disparities mapped back to planar depth (metres along each
   original camera's axis) at every pixel of both original views.

:func:`fuse_instants` fuses the instants per camera: the background is static and moving
objects uncover it, so the static depth of a pixel is the depth most instants agree on
(ties: the farthest -- what moves is in front); each instant keeps its own depth where it
differs (what moves). :func:`fused_points` turns that into an initial point cloud.

Bad input raises :class:`StereoUnavailable` with a message saying why (one camera only,
identical poses, no overlap, no confident match); callers fall back to the next
initialisation and record the message.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .planes import plane_fill
from .resolution import resized_to, working_view
from .stereo_filters import half_occlusion_band


class StereoUnavailable(ValueError):
    """The capture's cameras do not form a usable stereo pair (message says why)."""


# SGBM settings; the block size and penalties follow OpenCV's stereo_match sample
# (P1 = 8 cn b^2, P2 = 32 cn b^2), LR tolerance 1 px (disp12MaxDiff's usual value).
# Outlier removal (docs/experiments/two-view-geometry.md; novel scene, fused over 7 instants: p90 depth
# error 24.6 -> 8.8 %, pixels off by > 5 % 29 -> 15 %; demo p90 4.9 -> 2.9 %): replicate_border
# (rectified margin = nearest border pixel, validity eroded by half a block), occlusion_margin
# (stereo_filters.half_occlusion_band, px; -1 off), clip_far (no depth beyond the rig's range).
SGBM_DEFAULTS = dict(block_size=5, uniqueness=5, speckle_window=60, speckle_range=2, lr_tolerance=1.0,
                     max_disparity_frac=0.5, replicate_border=True, occlusion_margin=3, clip_far=True)


@dataclass
class RectifiedPair:
    """Rectification of two views (a, b) as cv2.stereoRectify returns it, plus bookkeeping."""

    view_a: object
    view_b: object
    size: tuple              # (width, height) of the rectified images
    R1: np.ndarray           # 3x3 rotations original camera -> rectified camera
    R2: np.ndarray
    P1: np.ndarray           # 3x4 rectified projections (OpenCV pixel convention)
    P2: np.ndarray
    vertical: bool           # epipolar lines are vertical (transpose to match)
    a_is_left: bool          # camera a is the left image of the matcher
    baseline: float          # metres
    focal: float             # rectified focal length (px)
    maps: dict = field(default_factory=dict)


def _cv_K(view) -> np.ndarray:
    K = np.asarray(view.intrinsics.K, dtype=np.float64).copy()
    K[0, 2] -= 0.5  # engine pixel centres at u + 0.5, OpenCV's at u
    K[1, 2] -= 0.5
    return K


def relative_pose(view_a, view_b) -> tuple[np.ndarray, np.ndarray]:
    """(R, T) with ``x_b = R x_a + T`` for OpenCV camera coordinates of views a and b."""
    wa, wb = np.asarray(view_a.viewmat, np.float64), np.asarray(view_b.viewmat, np.float64)
    R = wb[:3, :3] @ wa[:3, :3].T
    T = wb[:3, 3] - R @ wa[:3, 3]
    return R, T


def overlap_fraction(view_a, view_b, depth_range: tuple[float, float], samples: int = 24) -> float:
    """Share of view a's (pixel, depth) samples over ``depth_range`` that land in view b's image
    in front of it: 0 when the frustums do not overlap in that range."""
    k = view_a.intrinsics
    u, v = np.meshgrid(np.linspace(0.5, k.width - 0.5, samples), np.linspace(0.5, k.height - 0.5, samples))
    rays = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u)], -1).reshape(-1, 3)
    depths = np.geomspace(max(depth_range[0], 1e-6), max(depth_range[1], depth_range[0] * 1.001), 8)
    R, T = relative_pose(view_a, view_b)
    kb = view_b.intrinsics
    hit = 0
    for d in depths:
        q = (rays * d) @ R.T + T
        z = q[:, 2]
        zs = np.where(z > 1e-9, z, 1e-9)
        ub, vb = kb.fx * q[:, 0] / zs + kb.cx, kb.fy * q[:, 1] / zs + kb.cy
        hit += int(((z > 1e-9) & (ub >= 0) & (ub < kb.width) & (vb >= 0) & (vb < kb.height)).sum())
    return hit / float(len(rays) * len(depths))


def scene_depth_range(view_a, view_b) -> tuple[float, float]:
    """A generous depth range for the pair: around where the optical axes meet, else from the
    baseline (a rig looks at things 2 to 100 baselines away)."""
    ca, cb = view_a.center, view_b.center
    base = float(np.linalg.norm(ca - cb))
    da = -np.asarray(view_a.c2w, np.float64)[:3, 2]
    db = -np.asarray(view_b.c2w, np.float64)[:3, 2]
    A = np.stack([da, -db], 1)
    s, *_ = np.linalg.lstsq(A, cb - ca, rcond=None)
    if np.all(s > 0) and abs(float(da @ db)) < 0.9999:
        d = float(s[0])
        return 0.25 * d, 4.0 * d
    return 2.0 * base, 100.0 * base


def rectify_pair(view_a, view_b, *, min_baseline: float = 1e-6, min_overlap: float = 0.02,
                 scale: float = 2.0) -> RectifiedPair:
    """Rectify views a and b (cv2.stereoRectify, alpha 1: every source pixel kept, images
    ``scale`` x larger: finer disparity steps, 1.26% -> 1.00% median depth error on the demo). Raises
    :class:`StereoUnavailable` for identical poses or frustums that do not overlap."""
    ka, kb = view_a.intrinsics, view_b.intrinsics
    R, T = relative_pose(view_a, view_b)
    base = float(np.linalg.norm(T))
    extent = max(1.0, float(np.linalg.norm(view_a.center)), float(np.linalg.norm(view_b.center)))
    if base < min_baseline * extent:  # relative to the coordinates' magnitude (float noise)
        raise StereoUnavailable(f"cameras {view_a.name or 'a'} and {view_b.name or 'b'} are at the same place "
                                f"(baseline {base:.3g} m): two views from one point give no depth")
    ov = overlap_fraction(view_a, view_b, scene_depth_range(view_a, view_b))
    if ov < min_overlap:
        raise StereoUnavailable(f"cameras {view_a.name or 'a'} and {view_b.name or 'b'} do not see the same "
                                f"scene ({100 * ov:.1f}% of one's view lies in the other's): no stereo overlap")
    if (ka.width, ka.height) != (kb.width, kb.height):
        raise StereoUnavailable(f"cameras {view_a.name or 'a'} ({ka.width}x{ka.height}) and {view_b.name or 'b'} "
                                f"({kb.width}x{kb.height}) differ in size; rectification needs one image size")
    size = (int(round(ka.width * scale)), int(round(ka.height * scale)))
    # T as a column: OpenCV 5 refuses a flat (3,) translation here (OpenCV 4 accepted it)
    R1, R2, P1, P2, _Q, _roi1, _roi2 = cv2.stereoRectify(_cv_K(view_a), None, _cv_K(view_b), None,
                                                        (ka.width, ka.height), R, T.reshape(3, 1),
                                                        flags=cv2.CALIB_ZERO_DISPARITY, alpha=1.0, newImageSize=size)
    vertical = abs(P2[1, 3]) > abs(P2[0, 3])
    tx = P2[1, 3] if vertical else P2[0, 3]
    focal = float(P1[0, 0])
    pair = RectifiedPair(view_a, view_b, size, R1, R2, P1, P2, bool(vertical), bool(tx < 0),
                         abs(float(tx)) / focal, focal)
    for key, K, Rr, P in (("a", _cv_K(view_a), R1, P1), ("b", _cv_K(view_b), R2, P2)):
        pair.maps[key] = cv2.initUndistortRectifyMap(K, None, Rr, P, size, cv2.CV_32FC1)
    return pair


def _to_u8(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img, np.float32)
    if img.ndim == 3:
        img = img[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32)
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def match_rectified(left: np.ndarray, right: np.ndarray, num_disparities: int, *, block_size: int = 5,
                    uniqueness: int = 5, speckle_window: int = 60, speckle_range: int = 2,
                    lr_tolerance: float = 1.0, valid_left=None, valid_right=None, occlusion_margin: int = -1,
                    edge_jump: float = 0.05, **_unused):
    """Disparity of the left image (px, float32, NaN where unknown) and its confidence [0, 1].

    ``left``/``right``: uint8 rectified grey images (epipolar lines = rows). SGBM (3-way) in
    both directions; a pixel is kept when the right image's disparity at ``x - d`` agrees
    within ``lr_tolerance`` px and its speckle region is larger than ``speckle_window``.
    ``valid_*`` (bool, optional): pixels that come from inside the original image.
    ``occlusion_margin`` >= 0 removes the half-occluded band SGBM fattens the foreground into
    (:func:`~.stereo_filters.half_occlusion_band`, jumps above ``edge_jump`` of the disparity).
    """
    nd = max(16, int(np.ceil(num_disparities / 16.0)) * 16)
    cn = 1
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=nd, blockSize=block_size,
                                 P1=8 * cn * block_size ** 2, P2=32 * cn * block_size ** 2,
                                 uniquenessRatio=uniqueness, disp12MaxDiff=-1, speckleWindowSize=0,
                                 preFilterCap=31, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    # SGBM leaves the first numDisparities columns unmatched: pad on the left, crop after
    def _sgbm(first, second):
        first, second = (cv2.copyMakeBorder(np.ascontiguousarray(x), 0, 0, nd, 0, cv2.BORDER_CONSTANT, value=0)
                         for x in (first, second))
        return np.ascontiguousarray(sgbm.compute(first, second)[:, nd:])

    dl16 = _sgbm(left, right)
    cv2.filterSpeckles(dl16, -16, speckle_window, speckle_range * 16)
    dr16 = np.ascontiguousarray(_sgbm(right[:, ::-1], left[:, ::-1])[:, ::-1])
    dl = dl16.astype(np.float32) / 16.0
    dr = dr16.astype(np.float32) / 16.0
    H, W = left.shape
    ok = dl16 > 0
    xs = np.arange(W, dtype=np.float32)[None, :] - dl
    xi = np.clip(np.round(xs).astype(np.int64), 0, W - 1)
    other = np.take_along_axis(dr, xi, axis=1)
    diff = np.abs(other - dl)
    ok &= (xs >= 0) & (other > 0) & (diff <= lr_tolerance)
    if valid_left is not None:
        ok &= valid_left
    if valid_right is not None:
        ok &= np.take_along_axis(valid_right, xi, axis=1)
    # texture along the epipolar line (the aperture problem of flat areas); soft, because
    # SGBM's smoothness carries matches across weakly textured surfaces between edges
    g = left.astype(np.float32)
    gx = np.abs(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)) / 8.0
    tex = cv2.blur(gx, (block_size, block_size))
    conf = np.clip(1.0 - diff / max(lr_tolerance, 1e-6) * 0.5, 0.0, 1.0) * (0.5 + 0.5 * np.clip(tex / 4.0, 0, 1))
    if occlusion_margin >= 0:
        ok &= ~half_occlusion_band(np.where(ok, dl, np.nan), occlusion_margin, rel_jump=edge_jump)
    disp = np.where(ok, dl, np.nan).astype(np.float32)
    return disp, np.where(ok, conf, 0.0).astype(np.float32)


def _rectified_coords(pair: RectifiedPair, which: str) -> np.ndarray:
    """Rectified pixel coordinates [H, W, 2] of every original pixel of view ``which``."""
    view = pair.view_a if which == "a" else pair.view_b
    k = view.intrinsics
    v, u = np.mgrid[0:k.height, 0:k.width].astype(np.float64)
    pts = np.stack([u, v], -1).reshape(-1, 1, 2)
    Rr, P = (pair.R1, pair.P1) if which == "a" else (pair.R2, pair.P2)
    out = cv2.undistortPoints(pts, _cv_K(view), None, R=Rr, P=P)
    return out.reshape(k.height, k.width, 2)


def pair_depths(img_a: np.ndarray, img_b: np.ndarray, pair: RectifiedPair, **options):
    """Planar depth (metres along each camera's axis) and confidence at every pixel of both
    original views: ((depth_a [H,W], conf_a [H,W]), (depth_b, conf_b)); depth NaN where
    unknown, confidence 0 there."""
    opts = {**SGBM_DEFAULTS, **options}
    # outside the source image: the nearest border pixel, not black -- a black margin is a
    # strong edge that SGBM matches between the two margins (wrong depth along the border)
    border = cv2.BORDER_REPLICATE if opts.pop("replicate_border", False) else cv2.BORDER_CONSTANT
    ra = cv2.remap(_to_u8(img_a), *pair.maps["a"], cv2.INTER_LINEAR, borderMode=border)
    rb = cv2.remap(_to_u8(img_b), *pair.maps["b"], cv2.INTER_LINEAR, borderMode=border)
    ones = np.full(np.asarray(img_a).shape[:2], 255, np.uint8)
    va = cv2.remap(ones, *pair.maps["a"], cv2.INTER_NEAREST, borderValue=0)
    vb = cv2.remap(ones, *pair.maps["b"], cv2.INTER_NEAREST, borderValue=0)
    if border == cv2.BORDER_REPLICATE:  # a block reaching into the replicated margin matches its streaks
        r = opts["block_size"] // 2 + 1
        va, vb = (cv2.erode(x, np.ones((2 * r + 1, 2 * r + 1), np.uint8)) for x in (va, vb))
    va, vb = va > 0, vb > 0
    if pair.vertical:
        ra, rb, va, vb = (np.ascontiguousarray(x.T) for x in (ra, rb, va, vb))
    left, right, vl, vr = (ra, rb, va, vb) if pair.a_is_left else (rb, ra, vb, va)
    W = left.shape[1]
    near, far = scene_depth_range(pair.view_a, pair.view_b)
    nd = int(min(opts.pop("max_disparity_frac") * W, 1.2 * pair.focal * pair.baseline / near))
    # beyond the rig's depth range (4x where the axes meet): a flat patch's near-zero disparity
    # (the bottom rows of the novel scene's floor matched at 60 m), not a surface
    min_disp = pair.focal * pair.baseline / far if opts.pop("clip_far", False) else 0.0
    lr_tol = opts["lr_tolerance"]
    dl, cl = match_rectified(left, right, nd, valid_left=vl, valid_right=vr, **opts)
    # the right view's disparity: the same matcher on the mirrored pair
    dr_m, cr_m = match_rectified(np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]), nd,
                                 valid_left=np.ascontiguousarray(vr[:, ::-1]),
                                 valid_right=np.ascontiguousarray(vl[:, ::-1]), **{**opts, "lr_tolerance": lr_tol})
    dr, cr = dr_m[:, ::-1], cr_m[:, ::-1]
    if min_disp > 0:
        dl, cl, dr, cr = (np.where(dl >= min_disp, dl, np.nan), np.where(dl >= min_disp, cl, 0.0),
                          np.where(dr >= min_disp, dr, np.nan), np.where(dr >= min_disp, cr, 0.0))
    disp_a, conf_a, disp_b, conf_b = (dl, cl, dr, cr) if pair.a_is_left else (dr, cr, dl, cl)
    if pair.vertical:
        disp_a, conf_a, disp_b, conf_b = (np.ascontiguousarray(x.T) for x in (disp_a, conf_a, disp_b, conf_b))
    out = []
    for which, disp, conf, Rr, P in (("a", disp_a, conf_a, pair.R1, pair.P1), ("b", disp_b, conf_b, pair.R2, pair.P2)):
        uv = _rectified_coords(pair, which)
        # nearest sample: interpolating across a depth edge would invent surfaces in between
        ui = np.round(uv[..., 0]).astype(np.int64)
        vi = np.round(uv[..., 1]).astype(np.int64)
        Hr, Wr = disp.shape
        inside = (ui >= 0) & (ui < Wr) & (vi >= 0) & (vi < Hr)
        ui, vi = np.clip(ui, 0, Wr - 1), np.clip(vi, 0, Hr - 1)
        d = np.where(inside, disp[vi, ui], np.nan)
        c = np.where(inside, conf[vi, ui], 0.0)
        z_rect = pair.focal * pair.baseline / np.where(d > 0, d, np.nan)
        f, cx, cy = P[0, 0], P[0, 2], P[1, 2]
        X = np.stack([(uv[..., 0] - cx) / f * z_rect, (uv[..., 1] - cy) / P[1, 1] * z_rect, z_rect], -1)
        z = X @ Rr[:, 2]  # back to the original camera: x_orig = Rr^T x_rect, so z_orig = Rr[:, 2] . x_rect
        good = np.isfinite(z) & (z > 0)
        out.append((np.where(good, z, np.nan).astype(np.float32), np.where(good, c, 0.0).astype(np.float32)))
    return out[0], out[1]


# ---------------------------------------------------------------------------------- fusion
@dataclass
class FusedDepth:
    """Per-camera fusion of the instants' depth maps (one camera of the pair)."""

    camera: str
    view: object                       # the camera's view (pose is the same at every instant)
    times: list                        # instants, sorted
    depths: np.ndarray                 # [T, H, W] float32, NaN where unknown (each instant)
    confidence: np.ndarray             # [T, H, W] float32 in [0, 1]
    images: np.ndarray                 # [T, H, W, 3] float32
    static_depth: np.ndarray           # [H, W] float32, NaN where no instant agrees
    static_support: np.ndarray         # [H, W] int: instants within tolerance of static_depth
    moving: np.ndarray                 # [T, H, W] bool: the instant's depth is in front of the static depth

    def instant_depth(self, t_index: int, colour_tolerance: float = 0.06):
        """Fused depth and mask at instant ``t_index``: the instant's own depth where it has
        one; else the static depth where the pixel shows the static scene (its colour matches
        the median over instants, so nothing moving covers it)."""
        own = self.depths[t_index]
        med = np.median(self.images, axis=0)
        static_here = np.abs(self.images[t_index] - med).max(-1) <= colour_tolerance
        use_static = ~np.isfinite(own) & np.isfinite(self.static_depth) & static_here
        d = np.where(np.isfinite(own), own, np.where(use_static, self.static_depth, np.nan)).astype(np.float32)
        return d, np.isfinite(d)


def fuse_instants(camera: str, view, times, depths, confidences, images, *, rel_tolerance: float = 0.02,
                  min_confidence: float = 0.05) -> FusedDepth:
    """Static depth per pixel = the depth most instants agree on (within ``rel_tolerance``),
    ties broken towards the farthest (moving things are in front of the static scene).
    Each instant's depth that lies in front of it by more than the tolerance is *moving*."""
    D = np.stack([np.asarray(d, np.float32) for d in depths])          # [T,H,W]
    C = np.stack([np.asarray(c, np.float32) for c in confidences])
    D = np.where(C >= min_confidence, D, np.nan)
    valid = np.isfinite(D)
    Dz = np.where(valid, D, 0.0)
    # support[i] = number of instants j whose depth agrees with instant i's
    close = np.abs(Dz[:, None] - Dz[None, :]) <= rel_tolerance * np.maximum(Dz[:, None], 1e-9)
    agree = valid[:, None] & valid[None, :] & close
    support = agree.sum(1)                                               # [T,H,W]
    far = max(float(np.nanmax(Dz)) if valid.any() else 1.0, 1e-9)
    score = np.where(valid, support.astype(np.float64) + 1e-3 * Dz / far, -1.0)  # ties: the farthest
    best = score.argmax(0)
    n_valid = valid.sum(0)
    sup_best = np.take_along_axis(support, best[None], 0)[0]
    # the median of the agreeing depths: robust and sub-pixel-averaging
    ref = np.take_along_axis(Dz, best[None], 0)[0]
    agreeing = valid & (np.abs(Dz - ref[None]) <= rel_tolerance * np.maximum(ref[None], 1e-9))
    static = np.nanmedian(np.where(agreeing, D, np.nan), axis=0) if agreeing.any() else np.full(ref.shape, np.nan)
    need = np.where(n_valid >= 3, 2, 1)  # with 3+ measurements, one alone is not a static surface
    static = np.where((n_valid > 0) & (sup_best >= need), static, np.nan).astype(np.float32)
    moving = valid & np.isfinite(static)[None] & (D < static[None] * (1 - rel_tolerance))
    moving |= valid & ~np.isfinite(static)[None]
    return FusedDepth(camera, view, list(times), D, C, np.stack(images).astype(np.float32), static,
                      np.where(np.isfinite(static), sup_best, 0).astype(np.int32), moving)


# ---------------------------------------------------------------------------------- capture level
def _same_pose(a, b, tol: float = 1e-9) -> bool:
    return np.allclose(np.asarray(a.c2w), np.asarray(b.c2w), atol=tol)


def pair_instants(capture, cameras: list[str], frames=None):
    """(camera_a, camera_b, [(time, frame_a, frame_b)]) for the first two RGB train cameras
    with frames at common instants. Raises :class:`StereoUnavailable` otherwise. Frames whose
    ``knot`` is False (a baseline's synthetic frames between the RGB instants,
    engine.train.frames.baselines) take no part: their instants are no RGB instants."""
    frames = [f for f in (capture.frames if frames is None else frames) if getattr(f, "knot", True)]
    if len(cameras) < 2:
        names = ", ".join(cameras) or "none"
        raise StereoUnavailable(f"stereo needs two RGB train cameras; the capture has {len(cameras)} ({names})")
    a, b = cameras[0], cameras[1]
    by_time: dict = {}
    for f in frames:
        if f.camera in (a, b):
            by_time.setdefault(round(float(f.time), 6), {})[f.camera] = f
    inst = [(t, p[a], p[b]) for t, p in sorted(by_time.items()) if a in p and b in p]
    if not inst:
        raise StereoUnavailable(f"cameras {a} and {b} have no RGB frame at a common instant")
    return a, b, inst


def capture_fusion(capture, cameras: list[str], frames=None, *, rel_tolerance: float = 0.02, **options):
    """Stereo depth of every common RGB instant of the pair, fused per camera.

    Returns (FusedDepth of camera a, FusedDepth of camera b, info dict). Raises
    :class:`StereoUnavailable` (pair missing, same pose, no overlap, nothing matched).
    """
    import warnings

    a, b, inst = pair_instants(capture, cameras, frames)
    va, vb = capture.view(inst[0][1]), capture.view(inst[0][2])
    va.name, vb.name = a, b
    if _same_pose(va, vb):
        raise StereoUnavailable(f"cameras {a} and {b} have identical poses: not a stereo pair")
    va, vb = working_view(va), working_view(vb)
    pair = rectify_pair(va, vb)
    da, ca, db, cb, ia, ib = [], [], [], [], [], []
    for _t, fa, fb in inst:
        img_a, img_b = resized_to(fa.load_rgb(), va), resized_to(fb.load_rgb(), vb)
        try:
            (d1, c1), (d2, c2) = pair_depths(img_a, img_b, pair, **options)
        except cv2.error as exc:  # e.g. images too small for the matcher's window
            raise StereoUnavailable(f"OpenCV could not match {a} and {b} ({fa.path.name}): "
                                    f"{str(exc).strip().splitlines()[-1]}") from None
        da.append(d1), ca.append(c1), db.append(d2), cb.append(c2), ia.append(img_a), ib.append(img_b)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels
        fa_ = fuse_instants(a, va, [t for t, *_ in inst], da, ca, ia, rel_tolerance=rel_tolerance)
        fb_ = fuse_instants(b, vb, [t for t, *_ in inst], db, cb, ib, rel_tolerance=rel_tolerance)
    cover = float(np.mean([np.isfinite(f.static_depth).mean() for f in (fa_, fb_)]))
    per_instant = float(np.mean([np.isfinite(d).mean() for d in da + db]))
    if cover < 0.01 and per_instant < 0.01:
        raise StereoUnavailable(f"stereo between {a} and {b} matched almost nothing ({100 * per_instant:.2f}% of "
                                "pixels): the views do not overlap or the images carry no texture")
    info = {"cameras": [a, b], "instants": len(inst), "baseline_m": round(pair.baseline, 6),
            "size": [va.intrinsics.width, va.intrinsics.height],
            "vertical": pair.vertical, "matched_per_instant": round(per_instant, 4),
            "static_coverage": round(cover, 4)}
    return fa_, fb_, info


def backproject(view, depth: np.ndarray) -> np.ndarray:
    """World points [H, W, 3] of a planar depth map of ``view`` (NaN stays NaN)."""
    k = view.intrinsics
    v, u = np.mgrid[0:k.height, 0:k.width].astype(np.float64)
    cam = np.stack([(u + 0.5 - k.cx) / k.fx * depth, (v + 0.5 - k.cy) / k.fy * depth, depth], -1)
    c2w = np.linalg.inv(np.asarray(view.viewmat, np.float64))
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def fused_points(fused: list[FusedDepth], *, instant: int = 0, fill=None, fill_stride: int = 3, planes=None):
    """Initial cloud from fused stereo: every camera's static depth (coloured by the median
    image), plus what moves at ``instant`` (the canonical time), plus -- with ``fill`` (a
    function ``FusedDepth -> depth``: its static depth, holes filled) -- every ``fill_stride``-th pixel the stereo left
    empty at an interpolated static depth, or on one of ``planes`` (:mod:`.planes`) where that
    agrees with the interpolation (:func:`~.planes.plane_fill`). Returns (xyz [N,3], rgb [N,3],
    counts dict)."""
    xyz, rgb = [], []
    counts = {"static": 0, "moving": 0, "filled": 0}
    for f in fused:
        med = np.median(f.images, axis=0)
        ok = np.isfinite(f.static_depth)
        pts = backproject(f.view, np.where(ok, f.static_depth, 1.0))
        xyz.append(pts[ok]), rgb.append(med[ok])
        counts["static"] += int(ok.sum())
        mv = f.moving[instant] & np.isfinite(f.depths[instant])
        pts_t = backproject(f.view, np.where(mv, f.depths[instant], 1.0))
        xyz.append(pts_t[mv]), rgb.append(f.images[instant][mv])
        counts["moving"] += int(mv.sum())
        if fill is not None and fill_stride > 0 and ok.any() and not ok.all():
            grid = np.zeros_like(ok)
            grid[fill_stride // 2::fill_stride, fill_stride // 2::fill_stride] = True
            extra = grid & ~ok & ~mv
            dfill = fill(f)
            if planes:
                dfill = plane_fill(f.view, dfill, ok, planes)
            pf = backproject(f.view, dfill)
            xyz.append(pf[extra]), rgb.append(f.images[instant][extra])
            counts["filled"] += int(extra.sum())
    xyz = np.concatenate(xyz).astype(np.float32) if xyz else np.zeros((0, 3), np.float32)
    rgb = np.concatenate(rgb).astype(np.float32) if rgb else np.zeros((0, 3), np.float32)
    good = np.isfinite(xyz).all(1)
    return xyz[good], rgb[good], counts
