#!/usr/bin/env python
"""How well the spike view's flow follows each moving object (diagnostic, issue 11).

For every RGB interval and both of its ends ``T``, the flows from ``T`` to the
``spike_flow_steps`` grid instants of the interval are computed as the flow term does, from
zero (``flow_pair``) and warm-started along the grid (``warm_flow_pair``), and compared with the
true motion of each object's visible surface samples (the capture's ``ground_truth.objects``,
:func:`engine.io.ground_truth.points_at`; visible = nearest sample in its spike pixel, 2 cm slack). Printed per
object, method and half of the interval (near / far from ``T``): the share of the points that
pass the forward-backward check, their mean end-point error, their mean true motion, and the
share of them whose flow is worse than no flow at all::

    .venv/bin/python scripts/spike_flow_objects.py CAPTURE [--objects ball,cube] [--steps 15]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from engine.cameras import project_points  # noqa: E402
from engine.io.capture import load_capture  # noqa: E402
from engine.io.ground_truth import points_at  # noqa: E402
from engine.spike.render import estimate_sensor  # noqa: E402
from engine.train.baselines import spike_to_gray  # noqa: E402
from engine.train.spike_flow_pairs import flow_pair, warm_flow_pair  # noqa: E402
from engine.train.spike_guidance import spike_stream_info  # noqa: E402


def visible_motion(truth, name: str, view, w: int, h: int, t_ref: float, t: float):
    """(spike pixels [M, 2] at ``t_ref`` of the object's visible samples, their true motion [M, 2])."""
    uva, za = project_points(view, points_at(truth, name, t_ref))
    uvt, _ = project_points(view, points_at(truth, name, t))
    inside = (uva[:, 0] >= 0) & (uva[:, 0] < w) & (uva[:, 1] >= 0) & (uva[:, 1] < h) & (za > 0)
    pix = np.clip(np.floor(uva[:, 1]).astype(int) * w + np.floor(uva[:, 0]).astype(int), 0, w * h - 1)
    zmin = np.full(w * h, np.inf)
    np.minimum.at(zmin, pix[inside], za[inside])
    vis = inside & (za <= zmin[pix] + 0.02)
    return uva[vis], (uvt - uva)[vis]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("--objects", default="", help="comma-separated names (default: all in the ground truth)")
    ap.add_argument("--steps", type=int, default=15, help="grid instants per interval (spike_flow_steps)")
    ap.add_argument("--window", type=int, default=128, help="TFP window (spike_flow_window)")
    ap.add_argument("--upsample", type=int, default=2, help="DIS on the grey images upsampled this many times "
                    "(spike_flow_upsample)")
    args = ap.parse_args(argv)
    cap = load_capture(args.capture)
    if cap.ground_truth is None or cap.ground_truth.objects is None:
        raise SystemExit(f"{args.capture}: no ground_truth.objects block in transforms.json")
    truth = cap.ground_truth.objects.load()
    names = [n for n in args.objects.split(",") if n] or list(cap.ground_truth.objects.names)
    stream = spike_stream_info(cap).open()
    view, w, h = stream.view(0.0), int(stream.width), int(stream.height)
    sensor = estimate_sensor(cap, stream)
    grays: dict[int, np.ndarray] = {}

    def gray(t: float) -> np.ndarray:
        k = int(round((t - stream.t0) * stream.rate_hz))
        if k not in grays:
            grays[k] = spike_to_gray(stream, stream.t0 + k / stream.rate_hz, sensor, window=args.window)
        return grays[k]

    def at(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
        return img[np.clip(np.floor(uv[:, 1]).astype(int), 0, h - 1), np.clip(np.floor(uv[:, 0]).astype(int), 0, w - 1)]

    n1 = args.steps + 1
    times = sorted({round(float(f.time), 9) for f in cap.frames})
    stats: dict = {}
    for a, b in zip(times, times[1:]):
        for ref, sign in ((a, 1.0), (b, -1.0)):
            init = None
            for q in range(1, n1):
                t = ref + sign * (b - a) * q / n1
                fw, bw, ok = warm_flow_pair(gray(ref), gray(t), init, upsample=args.upsample)
                init = (fw, bw)
                flows = {"from zero": flow_pair(gray(ref), gray(t), upsample=args.upsample), "warm": (fw, ok)}
                for name in names:
                    uv, true = visible_motion(truth, name, view, w, h, ref, t)
                    mag = np.linalg.norm(true, axis=1)
                    for method, (flow, valid) in flows.items():
                        keep = at(valid, uv)
                        err = np.linalg.norm(at(flow, uv) - true, axis=1)[keep]
                        s = stats.setdefault((name, method, "near" if 2 * q < n1 else "far"), np.zeros(5))
                        s += (len(uv), keep.sum(), err.sum(), mag[keep].sum(), (err > mag[keep]).sum())
    print("object, flow, half: kept, end-point error (px), |motion| (px), worse than no flow")
    for (name, method, half), s in sorted(stats.items()):
        k = max(s[1], 1)
        print(f"{name:12s} {method:9s} {half:4s}: kept {s[1] / max(s[0], 1):.2f}, EPE {s[2] / k:.2f}, "
              f"|motion| {s[3] / k:.2f}, worse {s[4] / k:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
