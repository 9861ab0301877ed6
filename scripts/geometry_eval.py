"""Per-eval-camera geometry figures of a run (issue 14), at the RGB instants.

    .venv/bin/python scripts/geometry_eval.py RUN [CAPTURE] [--all-times] [--json OUT]

Per eval camera: PSNR over the whole image; coverage (share of the pixels the ground truth
covers -- finite GT depth, every pixel without GT depth -- that the render covers with
alpha > 0.5); with GT depth: median / 90th percentile relative error of the rendered
expected depth where both cover, and PSNR over the pixels some train camera saw at that
instant (GT point projected into a train camera lands inside it and agrees with that
camera's GT depth within 2 %), so what is unobservable is separated from what is wrong.
The branch ``novel`` has the engine's own per-camera evaluation; this script only reads the
capture format (COMMON.md) and renders the run.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from engine.evaluate.metrics import psnr  # noqa: E402
from engine.io.capture import load_capture  # noqa: E402
from engine.io.images import read_exr_channels  # noqa: E402
from engine.scene.model import load_run  # noqa: E402


def depth_files(cap) -> dict:
    """{absolute image path: absolute GT depth path} from transforms.json (COMMON.md format)."""
    root = Path(cap.root)
    data = json.loads((Path(cap.transforms_path or root / "transforms.json")).read_text())
    out = {}
    for rec in data.get("frames", []) + data.get("eval_frames", []):
        if rec.get("depth_file_path"):
            out[str((root / rec["file_path"]).resolve())] = root / rec["depth_file_path"]
    return out


def gt_depth(frame, files: dict) -> np.ndarray | None:
    path = files.get(str(Path(frame.path).resolve()))
    if path is None:
        return None
    ch = read_exr_channels(path)
    z = ch.get("Z", next(iter(ch.values()))).astype(np.float32)
    return np.where(np.isfinite(z) & (z < 1e9) & (z > 0), z, np.nan)


def _backproject(view, depth):
    k = view.intrinsics
    v, u = np.mgrid[0:k.height, 0:k.width].astype(np.float64)
    cam = np.stack([(u + 0.5 - k.cx) / k.fx * depth, (v + 0.5 - k.cy) / k.fy * depth, depth], -1)
    c2w = np.linalg.inv(view.viewmat)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def observed_mask(view, depth, train):
    """bool [H,W]: pixels of ``view`` whose GT surface point some train (view, depth) sees."""
    pts = _backproject(view, np.nan_to_num(depth, nan=1.0)).reshape(-1, 3)
    seen = np.zeros(len(pts), bool)
    for tv, td in train:
        q = pts @ tv.viewmat[:3, :3].T + tv.viewmat[:3, 3]
        k = tv.intrinsics
        z = q[:, 2]
        zs = np.where(z > 1e-9, z, 1e-9)
        u = np.floor(k.fx * q[:, 0] / zs + k.cx).astype(int)
        v = np.floor(k.fy * q[:, 1] / zs + k.cy).astype(int)
        inside = (z > 1e-9) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
        ok = np.zeros_like(inside)
        if td is None:
            ok = inside
        else:
            zt = td[np.clip(v, 0, k.height - 1), np.clip(u, 0, k.width - 1)]
            ok = inside & (np.abs(zt - z) <= 0.02 * z)
        seen |= ok
    return seen.reshape(depth.shape) & np.isfinite(depth)


def evaluate_geometry(run, capture=None, all_times: bool = False, save_dir=None, fill_holes: bool = False) -> dict:
    scene = load_run(run)
    cap = load_capture(capture or scene.info["capture"])
    files = depth_files(cap)
    rgb_times = sorted({round(float(f.time), 6) for f in cap.frames})
    train_at = {}
    for f in cap.frames:
        train_at.setdefault(round(float(f.time), 6), []).append(f)
    out = {}
    for f in sorted(cap.eval_frames, key=lambda fr: (fr.camera, fr.time)):
        t = round(float(f.time), 6)
        if not all_times and t not in rgb_times:
            continue
        view = cap.view(f)
        r = scene.render([view], fill_holes=fill_holes)[0]
        gt = f.load_rgb()
        dgt = gt_depth(f, files)
        cover_px = np.isfinite(dgt) if dgt is not None else np.ones(gt.shape[:2], bool)
        row = {"psnr": psnr(r["rgb"], gt), "coverage": float((r["alpha"][cover_px] > 0.5).mean())}
        if dgt is not None:
            both = cover_px & (r["alpha"] > 0.5) & (r["depth"] > 0)
            e = np.abs(r["depth"][both] - dgt[both]) / dgt[both]
            row["depth_med"] = float(np.median(e)) if e.size else float("nan")
            row["depth_p90"] = float(np.percentile(e, 90)) if e.size else float("nan")
            train = [(cap.view(tf), gt_depth(tf, files)) for tf in train_at.get(t, [])]
            if train:
                obs = observed_mask(view, dgt, train)
                row["observed"] = float(obs.mean())
                row["psnr_observed"] = psnr(r["rgb"], gt, obs) if obs.any() else float("nan")
        if save_dir is not None and f.camera not in out:  # first RGB instant: GT | render | alpha
            from engine.io.images import write_png

            a = np.repeat(r["alpha"][..., None], 3, -1)
            write_png(Path(save_dir) / f"{f.camera}_t{t:.3f}.png", np.concatenate([gt, np.clip(r["rgb"], 0, 1), a], 1))
        out.setdefault(f.camera, []).append(row)
    table = {}
    for cam, rows in out.items():
        table[cam] = {k: round(float(np.nanmean([r[k] for r in rows if k in r])), 4)
                      for k in rows[0]} | {"frames": len(rows)}
    return table


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("capture", nargs="?")
    ap.add_argument("--all-times", action="store_true", help="every eval frame, not only the RGB instants")
    ap.add_argument("--json")
    ap.add_argument("--fill-holes", action="store_true", help="render with Scene4D.render(fill_holes=True)")
    ap.add_argument("--save-png", help="folder for GT | render | alpha strips at the first RGB instant")
    a = ap.parse_args(argv)
    table = evaluate_geometry(a.run, a.capture, a.all_times, a.save_png, a.fill_holes)
    keys = ["frames", "psnr", "psnr_observed", "observed", "coverage", "depth_med", "depth_p90"]
    print("camera        " + " ".join(f"{k:>13}" for k in keys))
    for cam, row in table.items():
        print(f"{cam:13s} " + " ".join(f"{row.get(k, float('nan')):13.4f}" for k in keys))
    if a.json:
        Path(a.json).write_text(json.dumps(table, indent=1))


if __name__ == "__main__":
    main()
