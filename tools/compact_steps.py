"""``python -m tools compact-steps RUN [CAPTURE] [--fps 300] [--scales 1 2 4]``: what the compact
4D cache's quantization steps cost, in one run.

Samples the run's splats at ``--fps`` over its time range (by default 300 = the demo's eval
rate, so every eval frame is a stored instant), encodes them with ``compact.DEFAULT_STEPS``
times each scale, decodes, and renders every eval frame of the capture from the exact
splats and from the decoded ones. Prints per scale: size, ratio to the raw float32 arrays,
encode seconds, eval PSNR (exact, decoded, loss) and the decoded render's PSNR against the
exact render ("fidelity"). The figures of docs/experiments/export-and-lpips.md come from this command.
"""
from __future__ import annotations

import time

import numpy as np

from engine.evaluate.metrics import psnr
from engine.export import compact
from engine.export.splats import render_splats, splats_at
from engine.io.capture import load_capture
from engine.scene.model import load_run, view_tensors

HELP = "size / PSNR of the compact 4D cache at several quantization step scales"


def add_arguments(p) -> None:
    p.add_argument("run", help="run directory")
    p.add_argument("capture", nargs="?", default=None, help="capture (default: the run's)")
    p.add_argument("--fps", type=float, default=300.0, help="instants per capture second")
    p.add_argument("--scales", type=float, nargs="+", default=[1.0, 2.0, 4.0], help="multipliers of DEFAULT_STEPS")


def main(args) -> int:
    scene = load_run(args.run)
    cap = load_capture(args.capture or scene.info["capture"])
    t0, t1 = scene.time_range
    times = t0 + np.arange(int(np.floor((t1 - t0) * args.fps + 1e-6)) + 1) / args.fps
    frames = [splats_at(scene.model, t) for t in times]
    raw = sum(v.nbytes for f in frames for v in f.values())
    evals = sorted(cap.eval_frames, key=lambda f: f.time)
    gts = [f.load_rgb() for f in evals]
    vts = [view_tensors(cap.view(f), "cpu") for f in evals]
    bg, near = scene.background, scene.model.near_plane

    def render(splats_of_time):
        return [render_splats(splats_of_time(f.time), vt, bg, near)["rgb"] for f, vt in zip(evals, vts)]

    exact = render(lambda t: splats_at(scene.model, t))
    p_exact = float(np.mean([psnr(a, g) for a, g in zip(exact, gts)]))
    print(f"{len(times)} instants x {scene.num_gaussians} Gaussians, raw float32 {raw / 1e6:.2f} MB; "
          f"{len(evals)} eval frames, exact eval PSNR {p_exact:.4f} dB")
    print("| step scale | size MB | vs raw | encode s | eval PSNR | loss dB | fidelity dB |")
    print("|---|---|---|---|---|---|---|")
    for scale in args.scales:
        steps = {k: v * scale for k, v in compact.DEFAULT_STEPS.items()}
        s0 = time.perf_counter()
        data = compact.encode(times, frames, steps=steps)
        enc = time.perf_counter() - s0
        cache = compact.decode(data)
        imgs = render(cache.splats_at)
        p = float(np.mean([psnr(a, g) for a, g in zip(imgs, gts)]))
        fid = float(np.mean([psnr(a, b) for a, b in zip(imgs, exact)]))
        print(f"| {scale:g} | {len(data) / 1e6:.3f} | {raw / len(data):.1f}x | {enc:.1f} | {p:.4f} | "
              f"{p_exact - p:+.4f} | {fid:.2f} |")
    return 0
