"""Initial point cloud for the Gaussians.

Three sources, in order of preference for ``method="auto"`` (see README for the measured
comparison):

* ``ply``    -- the capture's ``points.ply`` (e.g. from DUSt3R or the scene generator);
* ``stereo`` -- OpenCV semi-global matching between the two calibrated train RGB cameras,
  fused over every common RGB instant (:func:`sgbm_points`, ``engine.geometry.stereo``);
* ``planesweep`` -- the older plane sweep at the first common instant: zero-mean NCC over a
  window on every fronto-parallel depth plane
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
import torch
import torch.nn.functional as F


@dataclass
class InitPoints:
    xyz: np.ndarray            # [N, 3] float32 world
    rgb: np.ndarray            # [N, 3] float32 sRGB-encoded in [0, 1]
    method: str
    info: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------------- helpers
def rgb_cameras(capture) -> list[str]:
    """Train cameras that have RGB frames, most frames first."""
    counts: dict[str, int] = {}
    for fr in capture.frames:
        cam = capture.cameras.get(fr.camera)
        if cam is not None and getattr(cam, "role", "train") != "train":
            continue
        counts[fr.camera] = counts.get(fr.camera, 0) + 1
    return sorted(counts, key=lambda c: (-counts[c], c))


def _frames_of(capture, camera: str):
    return sorted((f for f in capture.frames if f.camera == camera), key=lambda f: f.time)


def stereo_pair(capture):
    """(frame_a, frame_b) of the two RGB train cameras at their first common time, or None."""
    cams = rgb_cameras(capture)
    for i in range(len(cams)):
        for j in range(i + 1, len(cams)):
            fa, fb = _frames_of(capture, cams[i]), _frames_of(capture, cams[j])
            tb = {round(f.time, 6): f for f in fb}
            for f in fa:
                if round(f.time, 6) in tb:
                    return f, tb[round(f.time, 6)]
            if fa and fb:  # no exactly common instant: nearest pair
                best = min(((abs(a.time - b.time), a, b) for a in fa for b in fb), key=lambda x: x[0])
                return best[1], best[2]
    return None


def _pixel_rays(view) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel OpenCV camera-space directions with z = 1 [H*W, 3] and cam-to-world 4x4."""
    k = view.intrinsics
    v, u = np.mgrid[0:k.height, 0:k.width].astype(np.float64)
    d = np.stack([(u + 0.5 - k.cx) / k.fx, (v + 0.5 - k.cy) / k.fy, np.ones_like(u)], -1).reshape(-1, 3)
    return d, np.linalg.inv(view.viewmat)


def _gray(img: np.ndarray) -> torch.Tensor:
    g = img[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    return torch.from_numpy(g)[None, None]


def _box(x: torch.Tensor, r: int) -> torch.Tensor:
    return F.avg_pool2d(F.pad(x, (r, r, r, r), mode="replicate"), 2 * r + 1, stride=1)


def _depth_range(view_a, view_b, max_disp_frac: float = 0.35) -> tuple[float, float]:
    base = float(np.linalg.norm(view_a.center - view_b.center))
    k = view_a.intrinsics
    f = float(k.fx)
    base = max(base, 1e-6)
    near = f * base / (max_disp_frac * k.width)
    far = min(f * base / 0.5, near * 400.0)
    return near, far


def plane_sweep(img_ref, view_ref, img_src, view_src, depths, radius: int = 3):
    """NCC plane sweep. Returns per reference pixel (best depth, best NCC, margin of the best
    over the best outside +-2 planes, RMS image gradient along the epipolar direction)."""
    H, W = img_ref.shape[:2]
    g_ref, g_src = _gray(img_ref), _gray(img_src)
    rays, c2w_ref = _pixel_rays(view_ref)
    src_w2c = view_src.viewmat
    ks = view_src.intrinsics
    mu_r = _box(g_ref, radius)
    var_r = (_box(g_ref * g_ref, radius) - mu_r ** 2).clamp_min(0)
    std_r = var_r.sqrt()
    # texture along the epipolar direction (aperture problem): the direction in which the
    # match moves between the nearest and farthest plane
    uv_near = _warp_uv(rays, depths[0], c2w_ref, src_w2c, ks)
    uv_far = _warp_uv(rays, depths[-1], c2w_ref, src_w2c, ks)
    e = (uv_near - uv_far)
    e = e / np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-9)
    gx = torch.zeros_like(g_ref)
    gy = torch.zeros_like(g_ref)
    gx[..., 1:-1] = (g_ref[..., 2:] - g_ref[..., :-2]) / 2
    gy[..., 1:-1, :] = (g_ref[..., 2:, :] - g_ref[..., :-2, :]) / 2
    ge = gx * torch.from_numpy(e[:, 0].reshape(H, W).astype(np.float32)) + gy * torch.from_numpy(e[:, 1].reshape(H, W).astype(np.float32))
    epi_texture = _box(ge * ge, radius).sqrt()[0, 0]
    ncc = torch.full((len(depths), H, W), -1.0)
    for i, d in enumerate(depths):
        p_cam = rays * d
        p_world = p_cam @ c2w_ref[:3, :3].T + c2w_ref[:3, 3]
        q = p_world @ src_w2c[:3, :3].T + src_w2c[:3, 3]
        z = q[:, 2]
        u = ks.fx * q[:, 0] / np.maximum(z, 1e-9) + ks.cx
        v = ks.fy * q[:, 1] / np.maximum(z, 1e-9) + ks.cy
        valid = (z > 1e-6) & (u >= 0) & (u <= ks.width) & (v >= 0) & (v <= ks.height)
        grid = torch.from_numpy(np.stack([u / ks.width * 2 - 1, v / ks.height * 2 - 1], -1).astype(np.float32))
        warped = F.grid_sample(g_src, grid.reshape(1, H, W, 2), mode="bilinear", padding_mode="border",
                               align_corners=False)
        mu_s = _box(warped, radius)
        var_s = (_box(warped * warped, radius) - mu_s ** 2).clamp_min(0)
        cov = _box(g_ref * warped, radius) - mu_r * mu_s
        n = cov / (std_r * var_s.sqrt() + 1e-4)
        n = n[0, 0]
        n[~torch.from_numpy(valid.reshape(H, W))] = -1.0
        ncc[i] = n
    best, idx = ncc.max(dim=0)
    # distinctiveness: best vs the best outside +-2 planes
    D = len(depths)
    masked = ncc.clone()
    ar = torch.arange(D)[:, None, None]
    masked[(ar - idx[None]).abs() <= 2] = -1.0
    second = masked.max(dim=0).values
    # parabolic sub-plane refinement in inverse depth
    inv = 1.0 / np.asarray(depths, dtype=np.float64)
    i0 = idx.clamp(1, D - 2)
    c_m, c_0, c_p = (ncc.gather(0, (i0 + o)[None])[0] for o in (-1, 0, 1))
    denom = (c_m - 2 * c_0 + c_p)
    off = torch.where(denom < -1e-6, 0.5 * (c_m - c_p) / denom, torch.zeros_like(denom)).clamp(-0.5, 0.5)
    inv_t = torch.from_numpy(inv)
    step = float(inv[1] - inv[0]) if D > 1 else 0.0
    inv_best = inv_t[i0] + off.double() * step
    inv_best = torch.where((idx == 0) | (idx == D - 1), inv_t[idx], inv_best)
    depth = (1.0 / inv_best.clamp_min(1e-12)).float()
    return depth.numpy(), best.numpy(), (best - second).numpy(), epi_texture.numpy()


def fill_depth(depth: np.ndarray, ok: np.ndarray, max_iters: int = 64) -> np.ndarray:
    """Fill unconfident pixels by normalised convolution of inverse depth from confident ones
    (textureless surfaces between textured edges are usually smooth), widening until done."""
    inv = torch.from_numpy(np.where(ok, 1.0 / np.maximum(depth, 1e-6), 0.0).astype(np.float32))[None, None]
    w = torch.from_numpy(ok.astype(np.float32))[None, None]
    out = inv.clone()
    known = w.clone()
    for _ in range(max_iters):
        if bool(known.min() > 0):
            break
        num = F.avg_pool2d(F.pad(out * known, (2, 2, 2, 2), mode="replicate"), 5, stride=1)
        den = F.avg_pool2d(F.pad(known, (2, 2, 2, 2), mode="replicate"), 5, stride=1)
        new = den > 1e-6
        upd = new & (known == 0)
        out = torch.where(upd, num / den.clamp_min(1e-6), out)
        known = torch.where(upd, torch.ones_like(known), known)
    res = out[0, 0].numpy()
    return np.where(res > 0, 1.0 / np.maximum(res, 1e-9), depth).astype(np.float32)


def _warp_uv(rays, depth, c2w_ref, src_w2c, ks) -> np.ndarray:
    p = rays * depth
    pw = p @ c2w_ref[:3, :3].T + c2w_ref[:3, 3]
    q = pw @ src_w2c[:3, :3].T + src_w2c[:3, 3]
    z = np.where(np.abs(q[:, 2]) < 1e-9, 1e-9, q[:, 2])
    return np.stack([ks.fx * q[:, 0] / z, ks.fy * q[:, 1] / z], -1)


def _backproject(view, depth: np.ndarray) -> np.ndarray:
    rays, c2w = _pixel_rays(view)
    p = rays * depth.reshape(-1, 1)
    return (p @ c2w[:3, :3].T + c2w[:3, 3]).reshape(depth.shape + (3,))


def _project(view, pts: np.ndarray):
    w2c = view.viewmat
    q = pts @ w2c[:3, :3].T + w2c[:3, 3]
    k = view.intrinsics
    z = q[:, 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    return np.stack([k.fx * q[:, 0] / zs + k.cx, k.fy * q[:, 1] / zs + k.cy], -1), z


# ---------------------------------------------------------------------------------- sources
def ply_points(capture) -> InitPoints | None:
    path = getattr(capture, "points_path", None)
    if not path:
        return None
    from .capture import load_points

    xyz, rgb = load_points(path)
    xyz = np.asarray(xyz, np.float32)
    if rgb is None:
        rgb = np.full_like(xyz, 0.5)
    rgb = np.asarray(rgb, np.float32)
    if rgb.max() > 1.0:
        rgb = rgb / 255.0
    return InitPoints(xyz, rgb, "ply", {"path": str(path), "points": len(xyz)})


STEREO_DEFAULTS = dict(num_planes=64, radius=3, min_ncc=0.8, min_margin=0.05, min_texture=0.02, lr_tolerance=0.03)


def stereo_depths(img_a, view_a, img_b, view_b, *, num_planes: int = 64, radius: int = 3, min_ncc: float = 0.8,
                  min_margin: float = 0.05, min_texture: float = 0.02, lr_tolerance: float = 0.03):
    """Depth maps of both views of a calibrated pair and their confidence masks.

    Returns ((depth_a [H,W], ok_a [H,W] bool), (depth_b, ok_b), (near, far)). A pixel is
    confident when the NCC is high, the match is distinctive, the window has texture along
    the epipolar line, and the other direction's depth at its projection agrees.
    """
    near, far = _depth_range(view_a, view_b)
    depths = 1.0 / np.linspace(1.0 / near, 1.0 / far, num_planes)
    da, na, ma, sa = plane_sweep(img_a, view_a, img_b, view_b, depths, radius)
    db, nb, mb, sb = plane_sweep(img_b, view_b, img_a, view_a, depths, radius)
    out = []
    for (d1, n1, m1, s1, v1, d2, v2) in ((da, na, ma, sa, view_a, db, view_b), (db, nb, mb, sb, view_b, da, view_a)):
        pts = _backproject(v1, d1).reshape(-1, 3)
        ok = (n1.reshape(-1) >= min_ncc) & (m1.reshape(-1) >= min_margin) & (s1.reshape(-1) >= min_texture)
        # left-right consistency: the other direction's depth at the projected pixel agrees
        uv, z = _project(v2, pts)
        k2 = v2.intrinsics
        ui = np.clip(np.floor(uv[:, 0]).astype(int), 0, k2.width - 1)
        vi = np.clip(np.floor(uv[:, 1]).astype(int), 0, k2.height - 1)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < k2.width) & (uv[:, 1] >= 0) & (uv[:, 1] < k2.height) & (z > 0)
        other = d2[vi, ui]
        ok &= inside & (np.abs(other - z) <= lr_tolerance * z)
        out.append((d1.astype(np.float32), ok.reshape(d1.shape)))
    return out[0], out[1], (near, far)


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


def stereo_depth_priors(capture, frames, **options) -> dict:
    """Confident stereo depth for every train frame that has a partner camera at its time.

    Returns {id(frame): (depth [H,W] float32, mask [H,W] bool)}.
    """
    cams = rgb_cameras(capture)
    if len(cams) < 2:
        return {}
    a, b = cams[0], cams[1]
    by_time: dict = {}
    for f in frames:
        if f.camera in (a, b):
            by_time.setdefault(round(float(f.time), 6), {})[f.camera] = f
    out = {}
    for pair in by_time.values():
        if a in pair and b in pair:
            fa, fb = pair[a], pair[b]
            (da, oka), (db, okb), _ = stereo_depths(fa.load_rgb(), capture.view(fa), fb.load_rgb(), capture.view(fb),
                                                    **{**STEREO_DEFAULTS, **options})
            out[id(fa)] = (da, oka)
            out[id(fb)] = (db, okb)
    return out


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
        rgb.append(img[np.clip((w * h / k.height).astype(int), 0, h - 1), np.clip((u * wd / k.width).astype(int), 0, wd - 1), :3])
    xyz = np.concatenate(xyz)[:n].astype(np.float32)
    rgb = np.concatenate(rgb)[:n].astype(np.float32)
    return InitPoints(xyz, rgb, "random", {"points": int(len(xyz)), "near": float(near), "far": float(far)})


def _subsample(p: InitPoints, max_points: int, seed: int) -> InitPoints:
    if len(p.xyz) <= max_points:
        return p
    idx = np.sort(np.random.default_rng(seed).choice(len(p.xyz), max_points, replace=False))
    p.info["subsampled_from"] = int(len(p.xyz))
    return InitPoints(p.xyz[idx], p.rgb[idx], p.method, p.info)


def sgbm_points(capture, *, fill_stride: int = 3, instant: int = 0, backdrop: float = 0.0):
    """Issue 14: OpenCV semi-global matching on every common RGB instant of the pair, fused per
    camera (:mod:`engine.geometry.stereo`): static depth + what moves at the first instant +
    interpolated hole fill every ``fill_stride`` px. Returns (InitPoints, backdrop InitPoints
    or None): with ``backdrop`` > 0, points beyond the image borders (a ring that wide, as a
    fraction of the image) at extrapolated depth. Raises ``StereoUnavailable``."""
    from .geometry.stereo import backdrop_points, capture_fusion, fused_points

    fa, fb, info = capture_fusion(capture, rgb_cameras(capture))  # raises StereoUnavailable
    xyz, rgb, counts = fused_points([fa, fb], instant=instant, fill=fill_depth if fill_stride > 0 else None,
                                    fill_stride=fill_stride)
    info = {**info, **counts, "points": int(len(xyz)), "matcher": "sgbm", "filled": counts["filled"]}
    if len(xyz):
        dep = _project(fa.view, xyz)[1]
        info["depth_p5_p95"] = [float(np.percentile(dep, 5)), float(np.percentile(dep, 95))]
    back = None
    if backdrop > 0:
        parts = []
        for f in (fa, fb):
            ok = np.isfinite(f.static_depth)
            if ok.any():
                parts.append(backdrop_points(f, fill_depth(np.where(ok, f.static_depth, 0.0).astype(np.float32), ok),
                                             backdrop))
        if parts:
            back = InitPoints(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]), "backdrop")
    return InitPoints(xyz, rgb, "stereo", info), back


def initial_points(capture, method: str = "auto", *, max_points: int = 6000, n_random: int = 3000,
                   seed: int = 0, min_points: int = 200, fill_stride: int = 3, backdrop: float = 0.0) -> InitPoints:
    """The initial point cloud by ``method`` (auto | ply | stereo | planesweep | random).

    ``stereo`` is OpenCV SGBM fused over every RGB instant (:func:`sgbm_points`); when the
    cameras are not a usable pair (one camera, identical poses, no overlap, nothing matched)
    it falls back to ``random`` with a warning, recorded as ``info["fallback"]`` (run.json).
    ``planesweep`` is the older NCC plane sweep at the first common instant. Stereo leaves
    holes (textureless areas, occlusions): with ``fill_stride`` > 0 they are filled with
    points at interpolated depths (:func:`fill_depth`), else with ``n_random / 4`` random
    points in the stereo depth range.
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
        from .geometry.stereo import StereoUnavailable

        back = None
        try:
            if method == "planesweep":
                result = stereo_points(capture, fill_stride=fill_stride)
            else:
                result, back = sgbm_points(capture, fill_stride=fill_stride, backdrop=backdrop)
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
