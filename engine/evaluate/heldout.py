"""Score a run on the capture's held-out (role: eval) frames.

``evaluate(run_dir)`` renders every eval frame at its own capture time and viewpoint and
returns one JSON-able dict:

* ``psnr``, ``ssim``: mean over all eval frames;
* ``psnr_interframe``, ``ssim_interframe``: over eval instants strictly between the train
  cameras' RGB frame times (what the 30 FPS frames never show);
* ``psnr_dynamic``: PSNR over motion-mask pixels (GT changes across neighbouring eval frames),
  averaged over frames that have any;
* ``lpips``: LPIPS-Alex (``lpips.py``; lower is better), mean over all eval frames;
* ``psnr_static``, ``psnr_static_instants``, ``psnr_static_interframe``: PSNR over the pixels
  whose ground truth never changes over the capture (per eval camera, ``static_mask``), over
  all frames, the frames at RGB instants and those between them; ``static_colour_shift``: the
  largest change of those pixels' mean colour error between RGB instants (0: what does not
  move renders the same at every instant); ``static_fraction``: their share of the pixels;
* ``n_frames``, ``n_interframe``, ``train_seconds``, ``num_gaussians``, ``render_seconds``;
* ``fill_holes``: with ``fill_holes=True`` frames are scored as a viewer of an opaque render
  sees them, uncovered pixels filled from their covered neighbourhood
  (``Scene4D.render(fill_holes=True)``, issue 14) rather than showing the black training
  background. Off by default: a capture whose background really is black (the synthetic
  test captures) would be scored against invented colour.

With ``images_dir`` it also writes one PNG per scored frame, ground truth | render side by side
(``engine eval`` puts them in RUN/eval_images). It writes RUN/eval_frames.csv (index, time, camera,
interframe, psnr, ssim, psnr_dynamic, lpips, psnr_static) and RUN/metrics.json. ``scene=`` scores an
already opened result instead (e.g. a compact cache, ``engine.export.cached``), whose path is then only
a label.
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
from ..io.images import write_png
from ..scene.model import default_device, load_run
from .lpips import MIN_SIZE as LPIPS_MIN_SIZE
from .lpips import lpips
from .metrics import is_interframe, motion_masks, psnr, ssim, static_colour_bias, static_colour_shift, static_mask

LPIPS_BATCH = 16  # eval frames per LPIPS forward pass: batching is ~15x faster than one by one on 2 cores
# ...but no more pixels a pass than 16 frames of 320x240: 16 frames of 1080x720 took 5.9 GB (issue 43)
LPIPS_BATCH_PIXELS = 16 * 320 * 240


def _mean(values) -> float | None:
    v = [x for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return float(np.mean(v)) if v else None


def _round(x, nd=4):
    return None if x is None else round(float(x), nd)


def evaluate(run_dir, capture=None, *, device="cpu", write: bool = True, mask_threshold: float = 0.04,
             mask_dilate: int = 2, scene=None, fill_holes: bool = False, static_tol: float = 0.03,
             images_dir=None) -> dict:

    run_dir = Path(run_dir)
    device = default_device(device)  # "auto" means the same here as for training
    scene = load_run(run_dir, device=device) if scene is None else scene
    info = scene.info
    if capture is None:
        cap_path = info.get("capture")
        if not cap_path:
            where = run_dir if run_dir.is_file() else run_dir / "run.json"
            raise RunError(where, "no capture recorded for this result; pass the capture path")
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
    pairs = []  # (row, pred, gt) for LPIPS, scored in batches after the timed renders
    for cam, fs in by_cam.items():
        fs = sorted(fs, key=lambda fr: fr.time)
        gts = [fr.load_rgb() for fr in fs]
        masks = motion_masks(gts, mask_threshold, mask_dilate)
        still = static_mask(gts, static_tol) if len(gts) > 1 else np.zeros(np.shape(gts[0])[:2], bool)
        for fr, gt, mask in zip(fs, gts, masks):
            pred = scene.render([cap.view(fr)], fill_holes=fill_holes)[0]["rgb"]
            p_dyn = psnr(pred, gt, mask) if mask.any() else float("nan")
            rows.append({"time": float(fr.time), "camera": cam, "interframe": is_interframe(fr.time, rgb_times),
                         "psnr": psnr(pred, gt), "ssim": ssim(pred, gt), "psnr_dynamic": p_dyn,
                         "mask_fraction": float(mask.mean()), "lpips": float("nan"),
                         "psnr_static": psnr(pred, gt, still) if still.any() else float("nan"),
                         "static_bias": static_colour_bias(pred, gt, still), "static_fraction": float(still.mean())})
            pairs.append((rows[-1], pred, gt))
    render_s = time.perf_counter() - t0
    if images_dir is not None:  # what was scored, to look at: ground truth | render, one PNG per frame
        for i, (row, pred, gt) in enumerate(pairs):
            side = np.concatenate([np.asarray(gt, np.float32)[..., :3], np.asarray(pred, np.float32)[..., :3]], axis=1)
            write_png(Path(images_dir) / f"{row['camera']}_{i:04d}_t{row['time']:.4f}.png", np.clip(side, 0, 1))
    _score_lpips(pairs, device)
    rows.sort(key=lambda r: (r["time"], r["camera"]))
    inter = [r for r in rows if r["interframe"]]
    shifts = [static_colour_shift([r["static_bias"] for r in rows if r["camera"] == cam],
                                  [r["interframe"] for r in rows if r["camera"] == cam]) for cam in by_cam]
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
        "lpips": _round(_mean(r["lpips"] for r in rows)),
        "psnr_static": _round(_mean(r["psnr_static"] for r in rows)),
        "psnr_static_instants": _round(_mean(r["psnr_static"] for r in rows if not r["interframe"])),
        "psnr_static_interframe": _round(_mean(r["psnr_static"] for r in inter)),
        "static_colour_shift": _round(max((x for x in shifts if x is not None), default=None), 5),
        "static_fraction": _round(_mean(r["static_fraction"] for r in rows)),
        "n_frames": len(rows),
        "n_interframe": len(inter),
        "train_seconds": _round(run_info.get("train_seconds"), 2),
        "num_gaussians": scene.num_gaussians,
        "render_seconds": round(render_s, 3),
        "fill_holes": bool(fill_holes),
        "preset": run_info.get("preset", info.get("preset")),
        "step": info.get("step"),
        "run_dir": str(run_dir.resolve()),
        "capture": str(getattr(cap, "root", capture)),
    }
    if info.get("pruned_unobserved"):  # scored after engine.scene.observed.prune_unobserved
        result["pruned_unobserved"] = info["pruned_unobserved"]
    if write:
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["index", "time", "camera", "interframe", "psnr", "ssim", "psnr_dynamic", "lpips", "psnr_static"])
        for i, r in enumerate(rows):
            w.writerow([i, f"{r['time']:.6f}", r["camera"], int(r["interframe"]), f"{r['psnr']:.4f}",
                        f"{r['ssim']:.5f}", "" if math.isnan(r["psnr_dynamic"]) else f"{r['psnr_dynamic']:.4f}",
                        "" if math.isnan(r["lpips"]) else f"{r['lpips']:.5f}",
                        "" if math.isnan(r["psnr_static"]) else f"{r['psnr_static']:.4f}"])
        atomic_write(run_dir / "eval_frames.csv", lambda fh: fh.write(buf.getvalue().encode()))
        write_json(run_dir / "metrics.json", result)
    return result


def _score_lpips(pairs: list, device) -> None:
    """Fill each row's ``lpips`` (nan where the image is under LPIPS's 31 px minimum)."""
    by_shape: dict[tuple, list] = {}
    for pair in pairs:
        by_shape.setdefault(np.shape(pair[1]), []).append(pair)
    for shape, group in by_shape.items():
        if min(shape[:2]) < LPIPS_MIN_SIZE:
            continue
        batch = max(1, min(LPIPS_BATCH, LPIPS_BATCH_PIXELS // (shape[0] * shape[1])))
        for s in range(0, len(group), batch):
            chunk = group[s:s + batch]
            values = lpips(np.stack([p for _, p, _ in chunk]), np.stack([np.asarray(g)[..., :3] for _, _, g in chunk]),
                           device=device)
            for (row, _, _), v in zip(chunk, values):
                row["lpips"] = float(v)
