#!/usr/bin/env python
"""PSNR of trained runs at the TRAIN views at the RGB instants: whole image and moving pixels.

Issue 11, build item 0: before anything between frames, a run must reproduce what its own
cameras saw. Each run is rendered at every train RGB frame; the moving-pixel mask of a frame
is :func:`engine.metrics.motion_mask` against the same camera's previous and next frames
(GT change > 0.04, dilated 2 px: where a moving object is now, was or will be)::

    .venv/bin/python scripts/train_view_psnr.py CAPTURE RUN [RUN ...] [--json OUT]

Prints, per run, the mean PSNR over the train frames (``psnr``) and over their moving pixels
(``psnr_moving``, frames without motion skipped), and the step count.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from engine.evaluate.metrics import motion_masks, psnr  # noqa: E402
from engine.io.capture import load_capture  # noqa: E402
from engine.scene.model import load_run  # noqa: E402


def train_view_scores(scene, cap, threshold: float = 0.04, dilate: int = 2) -> dict:
    """{psnr, psnr_moving, n_frames, n_moving, per_frame}: means over the train cameras' RGB
    frames, and per frame ``[camera, time, psnr, psnr_moving or None]`` (where in time a run
    fails, e.g. the instants the time curriculum opens last)."""
    by_cam: dict[str, list] = {}
    for f in cap.frames:
        cam = cap.cameras.get(f.camera)
        if cam is not None and getattr(cam, "role", "train") != "train":
            continue
        by_cam.setdefault(f.camera, []).append(f)
    whole, moving, per_frame = [], [], []
    for fs in by_cam.values():
        fs = sorted(fs, key=lambda fr: fr.time)
        gts = [np.asarray(fr.load_rgb(), np.float32)[..., :3] for fr in fs]
        for fr, gt, mask in zip(fs, gts, motion_masks(gts, threshold, dilate)):
            pred = scene.render([cap.view(fr)])[0]["rgb"]
            whole.append(psnr(pred, gt))
            if mask.any():
                moving.append(psnr(pred, gt, mask))
            per_frame.append([fr.camera, float(fr.time), whole[-1], moving[-1] if mask.any() else None])
    return {"psnr": float(np.mean(whole)), "psnr_moving": float(np.mean(moving)) if moving else float("nan"),
            "n_frames": len(whole), "n_moving": len(moving), "per_frame": per_frame}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--json", type=Path, help="also write the scores here")
    args = ap.parse_args(argv)
    cap = load_capture(args.capture)
    out = {}
    for run in args.runs:
        scene = load_run(run)
        s = train_view_scores(scene, cap)
        s["step"] = scene.info.get("step")
        out[run] = s
        print(f"{run}: train views psnr {s['psnr']:.2f} dB, moving pixels {s['psnr_moving']:.2f} dB "
              f"({s['n_moving']}/{s['n_frames']} frames with motion), step {s['step']}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
