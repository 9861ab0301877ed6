#!/usr/bin/env python
"""PSNR of trained runs at the SPIKE camera's viewpoint, against the generator's exact light.

The eval camera of a generated capture is a third viewpoint; the spike loss supervises the
in-between instants from the spike camera's viewpoint only. This script scores what the
spike loss sees: each run is rendered at the spike camera (its co-located RGB view at the
spike resolution) at every ``--stride``-th light sample, converted to linear luminance, and
compared with the linear light that ``scripts/make_capture.py --light-cache FILE`` rendered
for the spike simulation (both sRGB-encoded for the metric, as the eval PSNR is)::

    .venv/bin/python tools/spike_view_psnr.py CAPTURE LIGHT.npz RUN [RUN ...]

Prints, per run, the mean PSNR at the RGB instants and between them.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from engine.colour import linear_to_srgb, luminance, srgb_to_linear  # noqa: E402
from engine.io.capture import load_capture  # noqa: E402
from engine.scene.model import load_run, view_tensors  # noqa: E402
from engine.train.guidance.spike_guidance import scaled_view, spike_stream_info  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("light", type=Path, help="the generator's --light-cache npz")
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--stride", type=int, default=7, help="score every N-th light sample")
    args = ap.parse_args(argv)

    cap = load_capture(args.capture)
    with np.load(args.light) as z:
        light = z["light"]
        key = json.loads(str(z["key"]))
    hz = float(key["light_hz"])
    info = spike_stream_info(cap)
    if info is None:
        raise SystemExit(f"{args.capture}: no spike stream co-located with an RGB camera")
    first = min((f for f in cap.frames if f.camera == info.co_located_with), key=lambda f: f.time)
    item = view_tensors(cap.view(first), "cpu")
    scale = info.width / item["width"]
    rgb_times = sorted({float(f.time) for f in cap.frames})
    for run in args.runs:
        model = load_run(run).model
        scores = {"key": [], "between": []}
        for i in range(0, len(light), args.stride):
            t = i / hz
            if t > rgb_times[-1] + 1e-9:
                break
            vt = scaled_view(item, scale)
            vt["time"] = t
            with torch.no_grad():
                rgb = model.render(vt, t)[0][0].clamp(0, 1)
            lum = luminance(srgb_to_linear(rgb)).numpy()
            a, b = linear_to_srgb(np.clip(lum, 0, 1)), linear_to_srgb(np.clip(light[i], 0, 1))
            p = float(-10 * np.log10(max(((a - b) ** 2).mean(), 1e-10)))
            at_rgb = min(abs(t - x) for x in rgb_times) < 1e-6
            scores["key" if at_rgb else "between"].append(p)
        print(f"{run}: spike-view PSNR at RGB instants {np.mean(scores['key']):.2f}, "
              f"between them {np.mean(scores['between']):.2f} ({len(scores['between'])} instants)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
