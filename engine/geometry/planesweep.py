"""The older hand-written two-view stereo (``init=planesweep``; issue 14 replaced it by
OpenCV semi-global matching in :mod:`engine.geometry.stereo` as the default -- docs/experiments/two-view-geometry.md,
"Two-view geometry", has the comparison). Also the home of ``rgb_cameras`` and
``fill_depth``, which the SGBM path shares.

Plane-sweep stereo: zero-mean NCC over a window on every fronto-parallel depth plane of the
reference camera, winner-take-all with a parabolic sub-plane fit, kept only where the
window is textured, the match is distinctive and the two directions agree (left-right
check).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


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
    ex = torch.from_numpy(e[:, 0].reshape(H, W).astype(np.float32))
    ey = torch.from_numpy(e[:, 1].reshape(H, W).astype(np.float32))
    ge = gx * ex + gy * ey
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
