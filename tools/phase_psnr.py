"""PSNR at a capture's eval cameras split by pixel class and by the frame's place in its RGB interval.

    python tools/phase_psnr.py CAP RUN [RUN ...] [--near-px 6]

Issue 11: where a model loses between RGB frames. Each eval frame's pixels are split into
*moving* (the eval motion mask of ``engine.evaluate.metrics.motion_masks``, as ``engine eval``'s
``psnr_dynamic``), *near* (still, within ``--near-px`` of a moving pixel) and *far* (still,
farther); each frame by its phase in its RGB interval, ``min(u, 1 - u)`` with ``u`` the
fraction of the interval: *inst* (an RGB instant), *q1* (< 0.2), *q2* (< 0.35), *half*. A cell is
the PSNR of the squared error pooled over its pixels. Prints one markdown table per run.
(docs/experiments/flow-junctions.md "Where the demo loses to the Interpolate baseline" measured this with a scratch
script of
the same rule.)
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import cv2  # noqa: E402

from engine.evaluate.metrics import motion_masks  # noqa: E402
from engine.io.capture import load_capture  # noqa: E402
from engine.scene.model import load_run  # noqa: E402

CLASSES = ("far", "near", "moving", "all")
PHASES = ("inst", "q1", "q2", "half")


def phase_of(t: float, rgb_times) -> str:
    """The phase bin of time ``t`` in its RGB interval (``rgb_times`` ascending)."""
    ts = list(rgb_times)
    if t <= ts[0] or t >= ts[-1]:
        return "inst"
    i = max(j for j, v in enumerate(ts) if v <= t)
    u = (t - ts[i]) / (ts[i + 1] - ts[i])
    p = min(u, 1.0 - u)
    return "inst" if p < 1e-3 else "q1" if p < 0.2 else "q2" if p < 0.35 else "half"


def split_errors(pred: np.ndarray, gt: np.ndarray, moving: np.ndarray, near_px: int) -> dict:
    """{class: (sum of squared error over the class's pixels and channels' mean, pixel count)}
    for images [H, W, 3] and the bool motion mask [H, W]; far, near and moving partition the
    pixels, "all" is their union."""
    err = ((np.asarray(pred, np.float64)[..., :3] - np.asarray(gt, np.float64)[..., :3]) ** 2).mean(-1)
    k = np.ones((2 * near_px + 1, 2 * near_px + 1), np.uint8)
    around = cv2.dilate(moving.astype(np.uint8), k) > 0
    masks = {"far": ~around, "near": around & ~moving, "moving": moving, "all": np.ones_like(moving)}
    return {c: (float(err[m].sum()), int(m.sum())) for c, m in masks.items()}


def table(run, cap, near_px: int = 6) -> dict:
    """{phase: {class: PSNR dB}} of ``run`` on ``cap``'s eval frames (cells without pixels left out)."""
    scene = load_run(run, device="cpu")
    rgb_times = sorted({float(f.time) for f in cap.frames})
    acc: dict = {}
    by_cam: dict = {}
    for f in cap.eval_frames:
        by_cam.setdefault(f.camera, []).append(f)
    for fs in by_cam.values():
        fs = sorted(fs, key=lambda fr: fr.time)
        gts = [fr.load_rgb() for fr in fs]
        for fr, gt, mask in zip(fs, gts, motion_masks(gts)):
            pred = scene.render([cap.view(fr)])[0]["rgb"]
            ph = phase_of(float(fr.time), rgb_times)
            for c, (sse, n) in split_errors(pred, gt, mask, near_px).items():
                s0, n0 = acc.get((ph, c), (0.0, 0))
                acc[(ph, c)] = (s0 + sse, n0 + n)
    return {ph: {c: -10.0 * np.log10(max(acc[(ph, c)][0] / acc[(ph, c)][1], 1e-12))
                 for c in CLASSES if acc.get((ph, c), (0, 0))[1] > 0}
            for ph in PHASES if (ph, "all") in acc}


def markdown(result: dict) -> str:
    rows = ["| phase | " + " | ".join(CLASSES) + " |", "|---|" + "---|" * len(CLASSES)]
    for ph, cells in result.items():
        rows.append(f"| {ph} | " + " | ".join(f"{cells[c]:.2f}" if c in cells else "" for c in CLASSES) + " |")
    return "\n".join(rows)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture")
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--near-px", type=int, default=6)
    args = ap.parse_args(argv)
    cap = load_capture(args.capture)
    for run in args.runs:
        print(f"{run}\n{markdown(table(run, cap, args.near_px))}\n", flush=True)


if __name__ == "__main__":
    main()
