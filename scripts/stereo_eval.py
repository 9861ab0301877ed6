"""Depth accuracy of the stereo initialisations against ground truth (issue 14).

    .venv/bin/python scripts/stereo_eval.py CAPTURE

Ground truth: the capture's GT depth EXRs of the train cameras (COMMON.md), else its
``points.ply`` when that is the generator's exact stereo pointmap at t = 0 (pixels of rgb0
on the stride-2 grid). Prints, for the first train camera: the share of GT pixels with a
stereo depth (coverage) and the median / 90th percentile relative depth error, for the
OpenCV SGBM depth of one instant, the SGBM depth fused over every instant
(``FusedDepth.instant_depth``), and the older NCC plane sweep (its confident pixels).
``--no-outlier-removal`` runs SGBM as before the half-occlusion / margin / depth-range
filters (README, Two-view geometry) for comparison.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from geometry_eval import depth_files, gt_depth  # noqa: E402

from engine.geometry.planesweep import rgb_cameras, stereo_depths  # noqa: E402
from engine.geometry.stereo import capture_fusion  # noqa: E402
from engine.io.capture import load_capture  # noqa: E402


def pointmap_depth(cap, frame) -> np.ndarray | None:
    pts = cap.load_points()
    if pts is None:
        return None
    xyz = np.asarray(pts[0], np.float64)
    view = cap.view(frame)
    k = view.intrinsics
    q = xyz @ view.viewmat[:3, :3].T + view.viewmat[:3, 3]
    u = k.fx * q[:, 0] / q[:, 2] + k.cx - 0.5
    v = k.fy * q[:, 1] / q[:, 2] + k.cy - 0.5
    own = (np.abs(u - np.round(u)) < 1e-2) & (np.abs(v - np.round(v)) < 1e-2) & (q[:, 2] > 0)
    own &= (np.round(u) % 2 == 1) & (np.round(v) % 2 == 1)
    gt = np.full((k.height, k.width), np.nan)
    gt[np.round(v[own]).astype(int), np.round(u[own]).astype(int)] = q[own, 2]
    return gt


def score(name, depth, gt):
    m = np.isfinite(gt)
    have = m & np.isfinite(depth) & (depth > 0)
    e = np.abs(depth[have] - gt[have]) / gt[have]
    print(f"{name:34s} coverage {have.sum() / max(1, m.sum()):6.3f}  median {np.median(e):.4f}  "
          f"p90 {np.percentile(e, 90):.4f}")


# the SGBM options of the pipeline before outlier removal (README: "before" rows)
NO_OUTLIER_REMOVAL = dict(replicate_border=False, occlusion_margin=-1, clip_far=False)


def main(capture, options=None):
    options = options or {}
    cap = load_capture(capture)
    cams = rgb_cameras(cap)
    files = depth_files(cap)
    fa = sorted((f for f in cap.frames if f.camera == cams[0]), key=lambda f: f.time)
    fb = sorted((f for f in cap.frames if f.camera == cams[1]), key=lambda f: f.time)
    gts = [gt_depth(f, files) for f in fa]
    if gts[0] is None:
        gts = [pointmap_depth(cap, fa[0])] + [None] * (len(fa) - 1)
        print("ground truth: points.ply pointmap at t = 0 (stride 2)")
    t0 = time.perf_counter()
    fused_a, _fb, info = capture_fusion(cap, cams, **options)
    print(f"SGBM + fusion over {info['instants']} instants: {time.perf_counter() - t0:.1f} s")
    for i, gt in enumerate(gts):
        if gt is None:
            continue
        score(f"{cams[0]} t{i} SGBM one instant", fused_a.depths[i], gt)
        score(f"{cams[0]} t{i} SGBM fused", fused_a.instant_depth(i)[0], gt)
        if i == 0:
            t0 = time.perf_counter()
            (d, ok), _, _ = stereo_depths(fa[0].load_rgb(), cap.view(fa[0]), fb[0].load_rgb(), cap.view(fb[0]))
            score(f"{cams[0]} t0 plane sweep ({time.perf_counter() - t0:.1f} s)", np.where(ok, d, np.nan), gt)
    all_gt = [g for g in gts if g is not None]
    if len(all_gt) > 1:
        cat = lambda xs: np.concatenate([x.ravel() for x in xs])  # noqa: E731
        score(f"{cams[0]} all instants SGBM one instant", cat(fused_a.depths[: len(all_gt)]), cat(all_gt))
        score(f"{cams[0]} all instants SGBM fused", cat([fused_a.instant_depth(i)[0] for i in range(len(all_gt))]),
              cat(all_gt))


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    if len(args) != 1:
        sys.exit("usage: stereo_eval.py CAPTURE [--no-outlier-removal]")
    main(args[0], NO_OUTLIER_REMOVAL if "--no-outlier-removal" in sys.argv else None)
