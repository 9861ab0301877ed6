"""``python -m engine demo --out RUN``: train the built-in demo capture, score it, render an orbit."""
from __future__ import annotations

import json
import sys
import threading
from pathlib import Path

from tqdm import tqdm

from ..errors import CaptureError, RunError
from ..evaluate.heldout import evaluate
from ..export.render_views import orbit_views, write_renders
from ..io.capture import load_capture
from ..scene.model import load_run
from ..train import train
from .train import parse_overrides

HELP = "train demo_capture (preset fast), evaluate it, render a 36-view bullet-time sweep at mid capture time"

REPO_ROOT = Path(__file__).resolve().parents[2]


def add_arguments(p) -> None:
    p.add_argument("--out", default=str(REPO_ROOT / "runs" / "demo"), help="run directory")
    p.add_argument("--capture", default=str(REPO_ROOT / "demo_capture"))
    p.add_argument("--preset", default="fast", choices=["fast", "balanced", "quality"])
    p.add_argument("--seconds", type=float, default=None)
    p.add_argument("--views", type=int, default=36, help="orbit views")
    p.add_argument("--degrees", type=float, default=60.0,
                   help="arc swept around the scene, centred on the eval camera (360 = full circle; a stereo "
                        "capture sees the scene from the front only, so wide arcs show its unobserved back)")
    p.add_argument("--restart", action="store_true")
    p.add_argument("--device", default="auto", help="auto (default: CUDA when available), cpu, cuda, cuda:1")
    p.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE")


def orbit_for(scene, capture, n: int, degrees: float):
    """Orbit through the eval (or first train) camera around the scene centre at mid time."""
    import numpy as np


    t_mid = 0.5 * (scene.time_range[0] + scene.time_range[1])
    frames = list(capture.eval_frames) or list(capture.frames)
    ref = capture.view(frames[0])
    g = scene.gaussians_at(t_mid)
    keep = g["opacities"] > 0.3
    pts = g["means"][keep] if keep.sum() >= 10 else g["means"]
    # centre: the median point, pulled onto the reference camera's optical axis
    fwd = -ref.c2w[:3, 2]
    depth = float(np.median((pts - ref.center) @ fwd))
    center = ref.center + fwd * max(depth, 1e-3)
    return orbit_views(center, 0.0, ref.intrinsics, n, time=t_mid, start_eye=ref.center, degrees=degrees), t_mid


def main(args) -> int:
    out = Path(args.out)
    try:
        capture = load_capture(args.capture)
    except CaptureError as exc:
        print(f"error: {exc} (the demo capture ships with the repository: demo_capture/)", file=sys.stderr)
        return 1
    bar = None

    def progress(d):
        nonlocal bar
        if bar is None:
            bar = tqdm(total=d["total_steps"], initial=d["step"] - 1, unit="step", dynamic_ncols=True, file=sys.stderr)
        bar.update(d["step"] - bar.n)
        bar.set_postfix(stage=d["stage"], psnr=f"{d['psnr']:.2f}", gaussians=d["num_gaussians"], refresh=False)

    try:
        summary = train(capture, out, preset=args.preset, seconds=args.seconds, resume=not args.restart,
                        device=args.device, progress=progress, cancel=threading.Event(),
                        overrides=parse_overrides(args.overrides),
                        on_stage=lambda text: print(f"{text}...", file=sys.stderr, flush=True))
        if bar is not None:
            bar.close()
        metrics = evaluate(out, capture)
        scene = load_run(out)
        views, t_mid = orbit_for(scene, capture, args.views, args.degrees)
        paths = write_renders(scene, views, out / "orbit", "png")
    except (CaptureError, RunError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(metrics, indent=2))
    print(f"run:      {out.resolve()}  ({summary['status']}, {summary['step']} steps, "
          f"{summary['train_seconds']:.0f} s, {summary['num_gaussians']} Gaussians)")
    print(f"metrics:  {out.resolve() / 'metrics.json'}  (per frame: {out.resolve() / 'eval_frames.csv'})")
    print(f"orbit:    {len(paths)} PNGs at capture time {t_mid:.4f} s in {out.resolve() / 'orbit'}")
    return 0
