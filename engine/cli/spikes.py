"""``python -m engine spikes CAPTURE``: describe a capture's spike streams, write a TFP image.

Prints every spike stream (or the one of ``--camera``): camera, file, size, frame count,
rate, time span, co-located RGB camera and the mean firing rate in the window. With
``--out`` it writes the TFP reconstruction (mean spike count per frame x threshold, i.e.
light in threshold units per frame) over ``[--t0, --t1)``: an ``.exr`` gets the linear
value, a ``.png`` is normalised (``--scale``; default: the 99.5th percentile maps to 1)
and sRGB-encoded.
"""
from __future__ import annotations

import argparse

import numpy as np

from ..colour import linear_to_srgb
from ..errors import CaptureError
from ..io.capture import load_capture
from ..io.images import write_exr, write_png

HELP = "print a capture's spike stream info and write a TFP (spike count) image"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", help="capture folder (or its transforms.json)")
    parser.add_argument("--camera", help="spike camera name (default: every stream; the first for --out)")
    parser.add_argument("--t0", type=float, default=None, help="window start, seconds (default: stream start)")
    parser.add_argument("--t1", type=float, default=None, help="window end, seconds (default: stream end)")
    parser.add_argument("--out", help="write the TFP image here (.png or .exr)")
    parser.add_argument("--scale", type=float, default=None,
                        help="PNG only: TFP value shown as white (default: 99.5th percentile)")
    parser.add_argument("--threshold", type=float, default=1.0, help="sensor threshold (TFP units)")


def main(args) -> int:
    try:
        cap = load_capture(args.capture)
        infos = cap.spike_streams
        if args.camera:
            infos = [s for s in infos if s.camera == args.camera]
            if not infos:
                raise CaptureError(cap.transforms_path or cap.root,
                                   f"no spike stream for camera {args.camera!r}; streams: "
                                   f"{[s.camera for s in cap.spike_streams]}")
        if not infos:
            print(f"{cap.root}: no spike streams")
            return 1 if args.out else 0
        tfp_img = None
        for info in infos:
            st = info.open()
            t0 = st.t0 if args.t0 is None else args.t0
            t1 = st.t_end if args.t1 is None else args.t1
            a, b = st.index_range(t0, t1)
            counts = st.window_counts(t0, t1)
            n = b - a
            rate = float(counts.mean()) / n if n else 0.0
            print(f"spike stream {info.camera!r}: {info.path}")
            print(f"  {st.width}x{st.height}, {st.num_frames} frames @ {st.rate_hz:g} Hz, "
                  f"t = {st.t0:.6f} .. {st.t_end:.6f} s, co-located with {info.co_located_with!r}")
            print(f"  window [{t0:.6f}, {t1:.6f}) s = frames {a}..{b - 1} ({n} frames): "
                  f"mean firing rate {rate:.4f} spikes/pixel/frame, max count {int(counts.max()) if n else 0}")
            if tfp_img is None and n:
                tfp_img = counts * (args.threshold / n)
        if args.out:
            if tfp_img is None:
                print("error: the window holds no spike frames; nothing written")
                return 1
            out = str(args.out)
            if out.lower().endswith(".exr"):
                write_exr(out, {"R": tfp_img, "G": tfp_img, "B": tfp_img})
            else:
                scale = args.scale if args.scale else float(np.percentile(tfp_img, 99.5)) or 1.0
                write_png(out, np.clip(linear_to_srgb(np.clip(tfp_img / scale, 0.0, 1.0)), 0.0, 1.0))
            print(f"wrote TFP image {out}")
    except CaptureError as exc:
        print(f"error: {exc}")
        return 2
    return 0
