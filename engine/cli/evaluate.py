"""``python -m engine eval RUN [CAPTURE]``: score a run on the capture's eval frames (JSON).

``--per-camera`` instead prints the novel-view table (engine.evaluate.novel_view): per eval camera
PSNR/SSIM at and between RGB instants, coverage, relative depth error against the capture's
ground-truth depth, PSNR over the whole image and over what a train camera saw; it writes
ground truth | render | depth-error strips, novel_view.json and the table (novel_view.md) to ``--images`` (default
RUN/novel_view)."""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from ..errors import CaptureError, RunError
from ..evaluate.heldout import evaluate
from ..evaluate.novel_view import evaluate_novel_views, format_table
from ..export.cached import CachedScene, load_result
from ..io.capture import load_capture
from ..io.fileio import atomic_write
from ..scene.model import load_run
from ..scene.observed import DEFAULT_INSET_PX, prune_unobserved

HELP = ("render every role:eval frame of the capture and print PSNR / SSIM / LPIPS as JSON "
        "(--per-camera: the novel-view table)")


def add_arguments(p) -> None:
    p.add_argument("run", help="run directory, or a compact cache (.bt4c; scored without writing files)")
    p.add_argument("capture", nargs="?", default=None, help="capture folder (default: the one recorded in run.json)")
    p.add_argument("--device", default="auto", help="auto (default: CUDA when available), cpu, cuda, cuda:1")
    p.add_argument("--fill-holes", action="store_true",
                   help="score what a viewer of an opaque render sees: uncovered pixels filled from their "
                        "neighbourhood instead of the black background (issue 14)")
    p.add_argument("--prune-unobserved", type=float, nargs="?", const=DEFAULT_INSET_PX, default=None, metavar="PX",
                   help="drop the Gaussians whose centre no train camera saw at least PX pixels inside its image "
                        f"(default {DEFAULT_INSET_PX:g}) before scoring: floaters at new viewpoints (issue 14; "
                        "engine.scene.observed); run folders only")
    p.add_argument("--per-camera", action="store_true",
                   help="novel-view table per eval camera (needs ground-truth depth in the capture)")
    p.add_argument("--images", type=Path, default=None,
                   help="folder for the ground truth | render PNG of every scored frame (default RUN/eval_images); "
                        "with --per-camera: for the eval strips and novel_view.json (default RUN/novel_view)")
    p.add_argument("--no-images", action="store_true", help="write no images")


def _angle_labels(cap) -> dict:
    """eval camera -> '19.5° off': the angle between its viewing axis and the mean viewing
    axis of the train cameras (for cameras looking at one target: the angle they subtend)."""
    def forward(f):
        return -np.asarray(f.c2w, dtype=np.float64)[:3, 2]

    firsts = {}
    for f in cap.frames + cap.eval_frames:
        firsts.setdefault(f.camera, f)
    train = [forward(f) for n, f in firsts.items() if cap.cameras[n].role == "train"]
    if not train:
        return {}
    mid = np.sum(train, axis=0)
    mid /= np.linalg.norm(mid)
    out = {}
    for n, f in firsts.items():
        if cap.cameras[n].role == "eval":
            c = float(np.clip(forward(f) @ mid, -1.0, 1.0))
            out[n] = f"{math.degrees(math.acos(c)):.1f}° off"
    return out


def maybe_prune(scene, capture, args) -> None:
    """``--prune-unobserved``: drop what no train camera constrained (prints how many)."""
    if args.prune_unobserved is None:
        return
    if isinstance(scene, CachedScene):
        raise RunError(Path(args.run), "--prune-unobserved needs a run folder, not a compact cache")
    n = prune_unobserved(scene, capture, inset_px=args.prune_unobserved)
    print(f"pruned {n} unobserved Gaussians ({scene.num_gaussians} left)", file=sys.stderr)


def per_camera(args) -> int:
    scene = load_run(args.run, device=args.device)
    cap_path = args.capture or scene.info.get("capture")
    if not cap_path:
        print(f"error: {Path(args.run) / 'run.json'}: no capture recorded; pass the capture path", file=sys.stderr)
        return 1
    cap = load_capture(cap_path)
    maybe_prune(scene, cap, args)
    out = args.images or Path(args.run) / "novel_view"
    out.mkdir(parents=True, exist_ok=True)
    result = evaluate_novel_views(scene, cap, out, log=lambda m: print(m, file=sys.stderr, flush=True))
    table = format_table(result["cameras"], _angle_labels(cap))
    atomic_write(out / "novel_view.md", lambda fh: fh.write((table + "\n").encode()))
    print(table)
    print(f"\nstrips, novel_view.json and novel_view.md in {out}")
    return 0


def main(args) -> int:
    try:
        if args.per_camera:
            return per_camera(args)
        scene = load_result(args.run, device=args.device)
        maybe_prune(scene, args.capture, args)
        # a cache is a single file: its scores are printed, nothing is written beside it
        writes = not isinstance(scene, CachedScene)
        images = None if args.no_images else (args.images or (Path(args.run) / "eval_images" if writes else None))
        result = evaluate(args.run, args.capture, device=args.device, scene=scene, write=writes,
                          fill_holes=args.fill_holes, images_dir=images)
    except (CaptureError, RunError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(result, indent=2))
    return 0
