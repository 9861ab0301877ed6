"""Where a run's rendered depth is wrong, by kind of pixel (issue 14).

    .venv/bin/python scripts/depth_drift.py RUN [CAPTURE] [--cameras rgb0,eval_side20]

For each camera (train or eval) at its first three RGB instants, the relative error
``|d - d_gt| / d_gt`` of the rendered expected depth over the pixels both cover (alpha > 0.5),
split into: *moving* (the GT depth changes by > 2 % to another RGB instant of the same camera),
*unobserved* (no train camera sees the GT point, ``engine.evaluate.novel_view.observed_mask``),
*edge* (within 2 px of a GT depth jump > 5 %), *floor* (GT point within 5 mm of the plane
z = 0 -- the generator's floor) and *other* (wall, static objects). Prints each class's share of
the pixels, median error, share above 5 %, its share of all pixels above 5 %, the signed
median (negative: the render is in front) and the median without that class.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from engine.evaluate.novel_view import backproject, observed_mask  # noqa: E402
from engine.io.capture import load_capture  # noqa: E402
from engine.scene.model import load_run  # noqa: E402


def pixel_classes(frame, others, train_views) -> tuple[np.ndarray, dict]:
    gt = frame.load_depth()
    view = frame.view()
    seen = observed_mask(view, gt, train_views)
    moving = np.zeros_like(seen)
    for o in others:
        g2 = o.load_depth()
        moving |= np.isfinite(gt) & ~(np.abs(g2 - gt) <= 0.02 * gt)
    lg = np.log(np.where(np.isfinite(gt), gt, 100.0))
    jump = ((np.abs(np.diff(lg, axis=1, prepend=lg[:, :1])) > 0.05)
            | (np.abs(np.diff(lg, axis=0, prepend=lg[:1])) > 0.05))
    edge = cv2.dilate(jump.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    floor = backproject(view, np.where(np.isfinite(gt), gt, 1.0))[..., 2] < 0.005
    return gt, {"moving": moving, "unobserved": ~seen & ~moving, "edge": edge & seen & ~moving,
                "floor": floor & seen & ~moving & ~edge, "other": seen & ~moving & ~edge & ~floor}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("capture", nargs="?")
    ap.add_argument("--cameras", default="rgb0,eval0,eval_side20,eval_up30")
    args = ap.parse_args(argv)
    scene = load_run(args.run)
    cap = load_capture(args.capture or json.loads((Path(args.run) / "run.json").read_text())["capture"])
    rgb_times = sorted({float(f.time) for f in cap.frames})
    train_at: dict = {}
    for f in cap.frames:
        train_at.setdefault(round(float(f.time), 6), []).append(f)
    by_cam: dict = {}
    for f in list(cap.eval_frames) + list(cap.frames):
        if f.depth_file_path is not None and any(abs(f.time - t) < 1e-4 for t in rgb_times):
            by_cam.setdefault(f.camera, []).append(f)
    for cam in args.cameras.split(","):
        if cam not in by_cam:
            print(f"{cam}: no frame with GT depth at an RGB instant")
            continue
        fs = sorted(by_cam[cam], key=lambda f: f.time)
        err_by: dict = {}
        sgn_by: dict = {}
        for i, fr in enumerate(fs[:3]):
            t = round(float(fr.time), 6)
            train = [(f.view(), f.load_depth()) for f in train_at[min(train_at, key=lambda s: abs(s - t))]]
            gt, cls = pixel_classes(fr, [fs[j] for j in range(len(fs)) if j != i][:3], train)
            out = scene.render([fr.view()])[0]
            alpha, depth = np.squeeze(out["alpha"]), np.squeeze(out["depth"])
            cov = np.isfinite(gt) & (alpha > 0.5)
            signed = (depth - gt) / gt
            for k, m in cls.items():
                err_by.setdefault(k, []).append(np.abs(signed[cov & m]))
                sgn_by.setdefault(k, []).append(signed[cov & m])
        err = {k: np.concatenate(v) for k, v in err_by.items()}
        tot = np.concatenate(list(err.values()))
        bad = max(1, int((tot > 0.05).sum()))
        print(f"{cam}: median {100 * np.median(tot):.2f} %  p90 {100 * np.percentile(tot, 90):.1f} %  ({len(tot)} px)")
        for k, v in err.items():
            if not len(v):
                continue
            rest = np.concatenate([w for kk, w in err.items() if kk != k])
            print(f"  {k:11s} share {100 * len(v) / len(tot):5.1f} %  median {100 * np.median(v):5.2f} %  "
                  f"signed {100 * np.median(np.concatenate(sgn_by[k])):+6.2f} %  "
                  f">5 %: {100 * (v > 0.05).mean():5.1f} %  "
                  f"of all >5 %: {100 * (v > 0.05).sum() / bad:5.1f} %  median without: {100 * np.median(rest):.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
