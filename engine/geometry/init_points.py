"""Initial point cloud for the Gaussians.

Three sources, in order of preference for ``method="auto"`` (docs/experiments/two-view-geometry.md has the measured
comparison):

* ``ply``    -- the capture's ``points.ply`` (e.g. from DUSt3R or the scene generator);
* ``stereo`` -- OpenCV semi-global matching between the two calibrated train RGB cameras,
  fused over every common RGB instant (:func:`sgbm_points`, :mod:`engine.geometry.stereo`);
* ``planesweep`` -- the older plane-sweep stereo between the two train RGB cameras at their
  first common instant: zero-mean NCC over a window on every fronto-parallel depth plane
  of the reference camera, winner-take-all with a parabolic sub-plane fit, kept only where
  the window is textured, the match is distinctive and the two directions agree
  (left-right check); points are coloured from the reference image;
* ``random`` -- points spread uniformly (in inverse depth) over the cameras' frustum,
  coloured from the image they project into.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from ..io.points import load_points
from .depth_priors import FusionCache
from .planes import plane_backdrop_points, static_planes
from .planesweep import (
    STEREO_DEFAULTS,
    _backproject,
    _depth_range,
    _frames_of,
    _project,
    fill_depth,
    rgb_cameras,
    stereo_depths,
    stereo_pair,
)
from .resolution import backdrop_points, backdrop_stride, continued_depth
from .stereo import StereoUnavailable, capture_fusion, fused_points


@dataclass
class InitPoints:
    xyz: np.ndarray            # [N, 3] float32 world
    rgb: np.ndarray            # [N, 3] float32 sRGB-encoded in [0, 1]
    method: str
    info: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------------- helpers
# ---------------------------------------------------------------------------------- sources
def ply_points(capture) -> InitPoints | None:
    path = getattr(capture, "points_path", None)
    if not path:
        return None
    xyz, rgb = load_points(path)
    xyz = np.asarray(xyz, np.float32)
    if rgb is None:
        rgb = np.full_like(xyz, 0.5)
    rgb = np.asarray(rgb, np.float32)
    if rgb.max() > 1.0:
        rgb = rgb / 255.0
    return InitPoints(xyz, rgb, "ply", {"path": str(path), "points": len(xyz)})


def stereo_points(capture, *, fill_stride: int = 0, **options) -> InitPoints | None:
    """Plane-sweep stereo between the two train RGB cameras at their first common time.

    With ``fill_stride`` > 0, unconfident pixels (every ``fill_stride``-th in x and y) are
    added too, at depths interpolated from their confident neighbours (:func:`fill_depth`).
    """
    pair = stereo_pair(capture)
    if pair is None:
        return None
    fa, fb = pair
    va, vb = capture.view(fa), capture.view(fb)
    ia, ib = fa.load_rgb(), fb.load_rgb()
    (da, oka), (db, okb), (near, far) = stereo_depths(ia, va, ib, vb, **{**STEREO_DEFAULTS, **options})
    out_xyz, out_rgb = [], []
    n_fill = 0
    for d, ok, v, img in ((da, oka, va, ia), (db, okb, vb, ib)):
        sel = ok.copy()
        if fill_stride > 0 and ok.any():
            grid = np.zeros_like(ok)
            grid[fill_stride // 2::fill_stride, fill_stride // 2::fill_stride] = True
            extra = grid & ~ok
            d = np.where(ok, d, fill_depth(d, ok))
            sel |= extra
            n_fill += int(extra.sum())
        out_xyz.append(_backproject(v, d).reshape(-1, 3)[sel.reshape(-1)])
        out_rgb.append(img[..., :3].reshape(-1, 3)[sel.reshape(-1)])
    xyz = np.concatenate(out_xyz).astype(np.float32)
    rgb = np.concatenate(out_rgb).astype(np.float32)
    info = {"cameras": [fa.camera, fb.camera], "time": float(fa.time), "near": near, "far": far,
            "points": int(len(xyz)), "filled": n_fill, "pixels": int(ia.shape[0] * ia.shape[1] * 2)}
    if len(xyz):
        dep = _project(va, xyz)[1]
        info["depth_p5_p95"] = [float(np.percentile(dep, 5)), float(np.percentile(dep, 95))]
    return InitPoints(xyz, rgb, "stereo", info)


def cameras_focus(views, min_angle_deg: float = 2.0):
    """The point closest (least squares) to all cameras' optical axes, or None when the axes
    are (nearly) parallel or the point is not in front of every camera."""
    if len(views) < 2:
        return None
    A = np.zeros((3, 3))
    b = np.zeros(3)
    dirs = []
    for v in views:
        d = -np.asarray(v.c2w, dtype=np.float64)[:3, 2]
        d /= np.linalg.norm(d)
        dirs.append(d)
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ v.center
    angles = [np.degrees(np.arccos(np.clip(dirs[i] @ dirs[j], -1, 1)))
              for i in range(len(dirs)) for j in range(i + 1, len(dirs))]
    if max(angles) < min_angle_deg:
        return None
    p = np.linalg.solve(A, b)
    if any((p - v.center) @ d <= 0 for v, d in zip(views, dirs)):
        return None
    return p


def random_points(capture, n: int, *, depth_range=None, seed: int = 0) -> InitPoints:
    """``n`` points over the train RGB cameras' frustums, uniform in inverse depth between
    ``depth_range`` (default: 0.5x to 1.5x the distance to where the optical axes meet)."""
    rng = np.random.default_rng(seed)
    cams = rgb_cameras(capture)
    frames = [_frames_of(capture, c)[0] for c in cams] or list(capture.frames[:1])
    views = [capture.view(f) for f in frames]
    images = [f.load_rgb() for f in frames]
    if depth_range is None:
        focus = cameras_focus(views)
        if focus is not None:
            d = float(np.linalg.norm(focus - views[0].center))
            near, far = 0.5 * d, 1.5 * d
        elif len(views) >= 2:
            near, far = _depth_range(views[0], views[1])
            far = min(far, near * 10)
        else:
            near, far = 0.5, 10.0
    else:
        near, far = depth_range
    xyz, rgb = [], []
    per = int(np.ceil(n / max(1, len(views))))
    for v, img in zip(views, images):
        k = v.intrinsics
        u = rng.uniform(0, k.width, per)
        w = rng.uniform(0, k.height, per)
        inv = rng.uniform(1.0 / far, 1.0 / near, per)
        d = 1.0 / inv
        cam = np.stack([(u - k.cx) / k.fx * d, (w - k.cy) / k.fy * d, d], -1)
        c2w = np.linalg.inv(v.viewmat)
        xyz.append(cam @ c2w[:3, :3].T + c2w[:3, 3])
        h, wd = img.shape[:2]
        rows = np.clip((w * h / k.height).astype(int), 0, h - 1)
        cols = np.clip((u * wd / k.width).astype(int), 0, wd - 1)
        rgb.append(img[rows, cols, :3])
    xyz = np.concatenate(xyz)[:n].astype(np.float32)
    rgb = np.concatenate(rgb)[:n].astype(np.float32)
    return InitPoints(xyz, rgb, "random", {"points": int(len(xyz)), "near": float(near), "far": float(far)})


def _subsample(p: InitPoints, max_points: int, seed: int) -> InitPoints:
    if len(p.xyz) <= max_points:
        return p
    idx = np.sort(np.random.default_rng(seed).choice(len(p.xyz), max_points, replace=False))
    p.info["subsampled_from"] = int(len(p.xyz))
    return InitPoints(p.xyz[idx], p.rgb[idx], p.method, p.info)


def sgbm_points(capture, *, fill_stride: int = 3, instant: int = 0, backdrop: float = 0.0,
                fusion_cache: FusionCache | None = None, planes: bool = False):
    """Issue 14: OpenCV semi-global matching on every common RGB instant of the pair, fused per
    camera (:mod:`engine.geometry.stereo`): static depth + what moves at the first instant +
    interpolated hole fill every ``fill_stride`` px. Returns (InitPoints, backdrop InitPoints
    or None): with ``backdrop`` > 0, points beyond the image borders (a ring that wide, as a
    fraction of the image) on the static cloud's dominant planes (:mod:`engine.geometry.planes`;
    where a ray meets none, or no plane was found, the depth continued linearly from the border).
    ``planes``: the hole fill too takes the plane depth where it agrees with the interpolation.
    ``fusion_cache``: share the fusion with the depth priors. Raises ``StereoUnavailable``."""
    fuse = fusion_cache if fusion_cache is not None else (lambda cams: capture_fusion(capture, cams))
    fa, fb, info = fuse(rgb_cameras(capture))  # raises StereoUnavailable
    found = static_planes([fa, fb]) if planes or backdrop > 0 else []
    filled: dict[str, np.ndarray] = {}

    def static_filled(f) -> np.ndarray:  # one hole fill per camera, for the cloud and its backdrop
        if f.camera not in filled:
            ok = np.isfinite(f.static_depth)
            filled[f.camera] = fill_depth(np.where(ok, f.static_depth, 0.0).astype(np.float32), ok)
        return filled[f.camera]

    xyz, rgb, counts = fused_points([fa, fb], instant=instant, fill=static_filled if fill_stride > 0 else None,
                                    fill_stride=fill_stride, planes=found if planes else None)
    info = {**info, **counts, "points": int(len(xyz)), "matcher": "sgbm", "filled": counts["filled"]}
    if found:
        info["planes"] = [{"normal": [round(float(x), 4) for x in p.normal], "offset": round(p.offset, 4),
                           "inliers": p.inliers} for p in found]
    if len(xyz):
        dep = _project(fa.view, xyz)[1]
        info["depth_p5_p95"] = [float(np.percentile(dep, 5)), float(np.percentile(dep, 95))]
    back = None
    if backdrop > 0:
        parts = []
        far = 3.0 * float(info["depth_p5_p95"][1]) if "depth_p5_p95" in info else np.inf
        for f in (fa, fb):
            depth = static_filled(f) if np.isfinite(f.static_depth).any() else None
            stride = backdrop_stride(f.view.intrinsics.width)
            if found:  # on the planes; beyond their extent, the depth continued from the image
                cont = continued_depth(f.view, depth, backdrop) if depth is not None else None
                parts.append(plane_backdrop_points(f.view, np.median(f.images, axis=0), found, backdrop, max_depth=far,
                                                   stride=stride, continued=cont))
            elif depth is not None:
                parts.append(backdrop_points(f, depth, backdrop, stride=stride))
        if parts:
            back = InitPoints(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]), "backdrop")
    return InitPoints(xyz, rgb, "stereo", info), back


def initial_points(capture, method: str = "auto", *, max_points: int = 6000, n_random: int = 3000,
                   seed: int = 0, min_points: int = 200, fill_stride: int = 3, backdrop: float = 0.0,
                   fusion_cache: FusionCache | None = None, planes: bool = False) -> InitPoints:
    """The initial point cloud by ``method`` (auto | ply | stereo | planesweep | random).

    ``stereo`` is OpenCV SGBM fused over every RGB instant (:func:`sgbm_points`); when the
    cameras are not a usable pair (one camera, identical poses, no overlap, nothing matched)
    it falls back to ``random`` with a warning, recorded as ``info["fallback"]`` (run.json).
    ``planesweep`` is the older NCC plane sweep at the first common instant. Stereo leaves
    holes (textureless areas, occlusions): with ``fill_stride`` > 0 they are filled with
    points at interpolated depths (:func:`fill_depth`), else with ``n_random / 4`` random
    points in the stereo depth range. ``fusion_cache`` (:class:`~engine.geometry.depth_priors.FusionCache`)
    shares the SGBM fusion with the trainer's depth priors.
    """
    if method not in ("auto", "ply", "stereo", "planesweep", "random"):
        raise ValueError(f"unknown init method {method!r} (auto, ply, stereo, planesweep, random)")
    result = None
    fallback = None
    if method in ("auto", "ply"):
        result = ply_points(capture)
        if result is None and method == "ply":
            raise ValueError("the capture has no points.ply; use init='stereo' or 'random'")
    if result is None and method in ("auto", "stereo", "planesweep"):
        # ---- issue 14: SGBM stereo with a recorded fallback (engine.geometry.stereo) ----
        back = None
        try:
            if method == "planesweep":
                result = stereo_points(capture, fill_stride=fill_stride)
            else:
                result, back = sgbm_points(capture, fill_stride=fill_stride, backdrop=backdrop,
                                           fusion_cache=fusion_cache, planes=planes)
            if result is not None and len(result.xyz) - result.info.get("filled", 0) < min_points:
                raise StereoUnavailable(f"stereo found only {len(result.xyz) - result.info.get('filled', 0)} "
                                        f"confident points (< {min_points})")
        except StereoUnavailable as err:
            fallback = {"from": "stereo", "to": "random", "reason": str(err)}
            warnings.warn(f"stereo initialisation unavailable: {err}; using random points", stacklevel=2)
            result = None
        # ---- end issue 14 ----
        if result is not None:
            result = _subsample(result, max_points, seed)
            if fill_stride <= 0 and n_random > 0:
                dep = result.info.get("depth_p5_p95")
                fill = random_points(capture, max(1, n_random // 4), depth_range=dep, seed=seed + 1)
                result = InitPoints(np.concatenate([result.xyz, fill.xyz]), np.concatenate([result.rgb, fill.rgb]),
                                    "stereo", {**result.info, "random_fill": int(len(fill.xyz))})
            if back is not None and len(back.xyz):
                result = InitPoints(np.concatenate([result.xyz, back.xyz]), np.concatenate([result.rgb, back.rgb]),
                                    "stereo", {**result.info, "backdrop": int(len(back.xyz))})
            return result
    if result is None:
        result = random_points(capture, n_random, seed=seed)
        if fallback is not None:
            result.info["fallback"] = fallback
    return _subsample(result, max_points, seed)
