"""Score a run on the capture's held-out (role: eval) frames.

``evaluate(run_dir)`` renders every eval frame at its own capture time and viewpoint and
returns one JSON-able dict:

* ``psnr``, ``ssim``: mean over all eval frames;
* ``psnr_interframe``, ``ssim_interframe``: over eval instants strictly between the train
  cameras' RGB frame times (what the 30 FPS frames never show);
* ``psnr_dynamic``: PSNR over motion-mask pixels (GT changes across neighbouring eval frames),
  averaged over frames that have any;
* ``n_frames``, ``n_interframe``, ``train_seconds``, ``num_gaussians``, ``render_seconds``.

It writes RUN/eval_frames.csv (index, time, camera, interframe, psnr, ssim, psnr_dynamic)
and RUN/metrics.json.
"""
from __future__ import annotations

import csv
import io
import math
import time
from pathlib import Path

import numpy as np

from ..errors import RunError
from ..io.capture import load_capture
from ..io.checkpoint import read_run_json, write_json
from ..io.fileio import atomic_write
from ..scene.model import load_run
from .metrics import is_interframe, motion_masks, psnr, ssim


def _mean(values) -> float | None:
    v = [x for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return float(np.mean(v)) if v else None


def _round(x, nd=4):
    return None if x is None else round(float(x), nd)


def evaluate(run_dir, capture=None, *, device="cpu", write: bool = True, mask_threshold: float = 0.04,
             mask_dilate: int = 2) -> dict:

    run_dir = Path(run_dir)
    scene = load_run(run_dir, device=device)
    info = scene.info
    if capture is None:
        cap_path = info.get("capture")
        if not cap_path:
            raise RunError(run_dir / "run.json", "no capture recorded in run.json; pass the capture path")
        capture = cap_path
    cap = load_capture(capture) if not hasattr(capture, "eval_frames") else capture
    frames = list(cap.eval_frames)
    if not frames:
        raise RunError(Path(getattr(cap, "root", capture)), "the capture has no eval frames (role: eval) to score")
    rgb_times = sorted({float(f.time) for f in cap.frames})

    rows = []
    t0 = time.perf_counter()
    by_cam: dict[str, list] = {}
    for f in frames:
        by_cam.setdefault(f.camera, []).append(f)
    for cam, fs in by_cam.items():
        fs = sorted(fs, key=lambda fr: fr.time)
        gts = [fr.load_rgb() for fr in fs]
        masks = motion_masks(gts, mask_threshold, mask_dilate)
        for fr, gt, mask in zip(fs, gts, masks):
            pred = scene.render([cap.view(fr)])[0]["rgb"]
            p_dyn = psnr(pred, gt, mask) if mask.any() else float("nan")
            rows.append({"time": float(fr.time), "camera": cam, "interframe": is_interframe(fr.time, rgb_times),
                         "psnr": psnr(pred, gt), "ssim": ssim(pred, gt), "psnr_dynamic": p_dyn,
                         "mask_fraction": float(mask.mean())})
    render_s = time.perf_counter() - t0
    rows.sort(key=lambda r: (r["time"], r["camera"]))
    inter = [r for r in rows if r["interframe"]]
    try:
        run_info = read_run_json(run_dir)
    except RunError:
        run_info = {}
    result = {
        "psnr": _round(_mean(r["psnr"] for r in rows)),
        "ssim": _round(_mean(r["ssim"] for r in rows)),
        "psnr_interframe": _round(_mean(r["psnr"] for r in inter)),
        "ssim_interframe": _round(_mean(r["ssim"] for r in inter)),
        "psnr_dynamic": _round(_mean(r["psnr_dynamic"] for r in rows)),
        "n_frames": len(rows),
        "n_interframe": len(inter),
        "train_seconds": _round(run_info.get("train_seconds"), 2),
        "num_gaussians": scene.num_gaussians,
        "render_seconds": round(render_s, 3),
        "preset": run_info.get("preset"),
        "step": info.get("step"),
        "run_dir": str(run_dir.resolve()),
        "capture": str(getattr(cap, "root", capture)),
    }
    if write:
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["index", "time", "camera", "interframe", "psnr", "ssim", "psnr_dynamic"])
        for i, r in enumerate(rows):
            w.writerow([i, f"{r['time']:.6f}", r["camera"], int(r["interframe"]), f"{r['psnr']:.4f}",
                        f"{r['ssim']:.5f}", "" if math.isnan(r["psnr_dynamic"]) else f"{r['psnr_dynamic']:.4f}"])
        atomic_write(run_dir / "eval_frames.csv", lambda fh: fh.write(buf.getvalue().encode()))
        write_json(run_dir / "metrics.json", result)
    return result
