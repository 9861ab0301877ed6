"""``python -m tools ablate CAPTURE (--seconds N | --steps N) --out DIR``: equal-time or
equal-step ablation (paper Tables 1, 3).

Trains every variant for the same wall-clock budget (``--seconds``: each variant's schedule
is sized to fit, so a guided variant runs fewer steps) or the same number of steps
(``--steps``: ``iterations`` = N, no time budget; under ``--seconds`` a variant whose schedule
ends before its time settles and may end early, converged: run.json ``ended_by``), records each one's steps and seconds
(wall time under shared load is noisy: read the two together), scores each on the capture's eval
frames (:func:`engine.evaluate.evaluate`), prints one table (PSNR / SSIM over all eval
frames, over inter-frame instants, PSNR over dynamic pixels, PSNR at the RGB instants) and writes
``DIR/ablation.csv``, ``DIR/ablation.json`` and ``DIR/ablation.png`` (bar chart).

Variants (``--variants`` picks a comma-separated subset, in this order):

============== ===================================================================
rgb-only       coarse DSR + L_frame (the RGB-only 4D Gaussians; Table 3 row 1)
+fine          + fine-scale spike deformation feature (Table 3 row 2)
+spike         + spike rendering and L_spike (Table 3 row 3)
full           + block colour loss: the BulletTime4D objective (Table 3 row 4)
full-pg        full with per-Gaussian fine features (sampled at each projection)
rgb+repeat     RGB-only trained on repeated frames (Table 1 "Repeat")
rgb+interp     RGB-only trained on flow-interpolated frames (Table 1 "Interpolate")
rgb+spike2img  RGB-only trained on spike TFP images + Reinhard colour (Table 1)
============== ===================================================================
"""
from __future__ import annotations

import csv
import json
import time
from pathlib import Path

from engine.cli.train import parse_overrides
from engine.evaluate import evaluate
from engine.train import train

from . import report
from .report import fmt, text_table
from .run_args import add_run_arguments, run_logged

HELP = "train each ablation variant for the same wall time, evaluate, tabulate and plot"

# name -> (rgb_only, overrides, description)
VARIANTS: dict[str, tuple[bool, dict, str]] = {
    "rgb-only": (True, {}, "coarse + L_frame (RGB only)"),
    "+fine": (False, {"fine_deformation": True, "spike_loss_weight": 0.0, "block_loss_weight": 0.0},
              "+ fine spike feature"),
    "+spike": (False, {"fine_deformation": True, "block_loss_weight": 0.0}, "+ spike render & L_spike"),
    "full": (False, {"fine_deformation": True}, "full BulletTime4D"),
    "full-pg": (False, {"fine_deformation": True, "fine_per_gaussian": True},
                "full, per-Gaussian fine features"),
    "full+block": (False, {"fine_deformation": True, "block_loss_weight": 1.0},
                   "full + the block colour loss (Eq. 20, off by default)"),
    "full-hexplane": (False, {"fine_deformation": True, "motion": "hexplane", "block_loss_weight": 1.0},
                      "full with the HexPlane field and fine branch (the paper's model)"),
    "rgb-hexplane": (True, {"motion": "hexplane"}, "RGB only, HexPlane field"),
    "rgb+repeat": (True, {"baseline": "repeat"}, "RGB-only + Repeat"),
    "rgb+interp": (True, {"baseline": "interp-flow"}, "RGB-only + Interpolate (flow)"),
    # issue 11: the interpolated frames supervise only between the RGB instants (no knots, carries,
    # births or stereo at their instants: baseline_instants="real";
    # docs/experiments/interpolated-frames-in-full-model.md)
    "rgb+interp-real": (True, {"baseline": "interp-flow", "baseline_instants": "real"},
                        "RGB-only + Interpolate (flow), knots at the RGB instants only"),
    "full+interp": (False, {"fine_deformation": True, "baseline": "interp-flow", "baseline_instants": "real"},
                    "full + flow-interpolated frames between the RGB instants"),
    "rgb+spike2img": (True, {"baseline": "spike2img"}, "RGB-only + Spike2img + colour"),
}

COLUMNS = ("psnr", "ssim", "lpips", "psnr_interframe", "ssim_interframe", "psnr_dynamic", "psnr_keyframe")


def keyframe_psnr(run_dir) -> float | None:
    """Mean PSNR of the eval frames AT the RGB instants (from RUN/eval_frames.csv): with
    ``psnr_interframe`` it shows how much quality is lost between the RGB frames."""
    path = Path(run_dir) / "eval_frames.csv"
    if not path.exists():
        return None
    vals = [float(r["psnr"]) for r in csv.DictReader(open(path)) if r.get("interframe") == "0" and r.get("psnr")]
    return round(sum(vals) / len(vals), 4) if vals else None


def add_arguments(p) -> None:
    p.add_argument("capture", help="capture folder (transforms.json)")
    budget = p.add_mutually_exclusive_group(required=True)
    budget.add_argument("--seconds", type=float, help="training wall-clock budget per variant (equal time)")
    budget.add_argument("--steps", type=int, help="training steps per variant, no time budget (equal steps)")
    p.add_argument("--out", required=True, help="output folder: one run per variant + ablation.csv/png/json")
    p.add_argument("--variants", default=",".join(VARIANTS),
                   help=f"comma-separated subset of: {', '.join(VARIANTS)}")
    add_run_arguments(p, "variant")
    p.add_argument("--resume", action="store_true", help="reuse finished variants' metrics.json in --out")


def parse_variants(text: str) -> list[str]:
    names = [v.strip() for v in text.split(",") if v.strip()]
    bad = [v for v in names if v not in VARIANTS]
    if bad:
        raise SystemExit(f"unknown variant(s) {', '.join(bad)}; choose from {', '.join(VARIANTS)}")
    return names


def run_ablation(capture, out_dir, seconds: float | None, variants: list[str], *, preset: str = "fast", seed: int = 0,
                 device=None, overrides: dict | None = None, resume: bool = False, train_fn=None, eval_fn=None,
                 log=print, steps: int | None = None) -> list[dict]:
    """Train + evaluate each variant; returns one row per variant (metrics + settings).
    Exactly one of ``seconds`` (equal wall time) and ``steps`` (equal steps: ``iterations``
    set for every variant, no time budget) is given."""
    if (seconds is None) == (steps is None):
        raise ValueError("give exactly one of seconds (equal time) and steps (equal steps)")
    if steps is not None and int(steps) < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    train_fn = train_fn or train
    eval_fn = eval_fn or evaluate
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in variants:
        rgb_only, ov, desc = VARIANTS[name]
        run_dir = out / name.replace("+", "plus_")
        metrics_path = run_dir / "metrics.json"
        if resume and metrics_path.exists():
            metrics = json.loads(metrics_path.read_text())
            log(f"[ablate] {name}: reusing {metrics_path}")
        else:
            merged = {**(overrides or {}), **ov}
            if steps is not None:
                merged["iterations"] = int(steps)
            budget = f"{seconds:g} s" if steps is None else f"{int(steps)} steps"
            log(f"[ablate] {name}: training {budget} (rgb_only={rgb_only}, {merged or 'defaults'})")
            t0 = time.perf_counter()
            summary = train_fn(capture, run_dir, preset=preset, seconds=seconds, rgb_only=rgb_only, resume=False,
                               device=device, seed=seed, overrides=merged or None)
            wall = time.perf_counter() - t0
            metrics = dict(eval_fn(run_dir, capture, device=device or "cpu"))
            metrics.setdefault("train_seconds", summary.get("train_seconds"))
            metrics["steps"] = summary.get("step")
            metrics["train_wall_s"] = round(wall, 2)
        if metrics.get("psnr_keyframe") is None:
            metrics["psnr_keyframe"] = keyframe_psnr(run_dir)
        rows.append({"variant": name, "description": desc, **{k: metrics.get(k) for k in COLUMNS},
                     "train_seconds": metrics.get("train_seconds"), "steps": metrics.get("steps", metrics.get("step")),
                     "train_wall_s": metrics.get("train_wall_s"), "num_gaussians": metrics.get("num_gaussians")})
        log(f"[ablate] {name}: " + ", ".join(f"{k}={fmt(metrics.get(k))}" for k in COLUMNS))
    return rows


def format_table(rows: list[dict]) -> str:
    head = ["variant", "PSNR", "SSIM", "LPIPS", "PSNR inter", "SSIM inter", "PSNR dyn", "PSNR key", "steps", "train s"]
    lines = [[r["variant"], fmt(r["psnr"]), fmt(r["ssim"], 3), fmt(r.get("lpips"), 3), fmt(r["psnr_interframe"]),
              fmt(r["ssim_interframe"], 3), fmt(r["psnr_dynamic"]), fmt(r.get("psnr_keyframe")), fmt(r.get("steps")),
              fmt(r.get("train_seconds"), 1)] for r in rows]
    base = next((r for r in rows if r["variant"] == "rgb-only"), None)
    if base is not None and base.get("psnr_interframe") is not None:
        head.append("d inter vs rgb-only")
        for line, r in zip(lines, rows):
            v = r.get("psnr_interframe")
            line.append("-" if v is None else f"{v - base['psnr_interframe']:+.2f}")
    return text_table(head, lines)


def write_csv(rows: list[dict], path) -> Path:
    return report.write_csv(rows, path, ["variant", "description", *COLUMNS, "steps", "train_seconds", "train_wall_s",
                                         "num_gaussians"])


def plot(rows: list[dict], path, title: str = "") -> Path:
    metrics = [("psnr", "PSNR (all eval)"), ("psnr_interframe", "PSNR (inter-frame)"),
               ("psnr_dynamic", "PSNR (dynamic px)")]
    fig, axes = report.plt.subplots(1, len(metrics), figsize=(4.2 * len(metrics), 3.6), squeeze=False)
    names = [r["variant"] for r in rows]
    colours = ["#888888" if n.startswith("rgb") else "#d62728" if n == "full" else "#1f77b4" for n in names]
    for ax, (key, label) in zip(axes[0], metrics):
        vals = [r.get(key) if r.get(key) is not None else float("nan") for r in rows]
        ax.bar(range(len(vals)), vals, color=colours)
        finite = [v for v in vals if v == v]
        if finite:
            lo, hi = min(finite), max(finite)
            ax.set_ylim(max(0.0, lo - 1.5), hi + 0.8)
        for i, v in enumerate(vals):
            if v == v:
                ax.text(i, v + 0.05, f"{v:.2f}", ha="center", va="bottom", fontsize=7)
        ax.set_xticks(range(len(vals)))
        ax.set_xticklabels(names, rotation=35, ha="right", fontsize=8)
        ax.set_title(label, fontsize=10)
        ax.set_ylabel("dB")
    return report.save_figure(fig, path, title)


def main(args) -> int:
    variants = parse_variants(args.variants)
    overrides = parse_overrides(args.overrides)
    out = Path(args.out)
    rows = run_logged(run_ablation, args.capture, out, args.seconds, variants, preset=args.preset, seed=args.seed,
                      device=args.device, overrides=overrides, resume=args.resume, steps=args.steps)
    if rows is None:
        return 1
    table = format_table(rows)
    print(table)
    write_csv(rows, out / "ablation.csv")
    (out / "ablation.json").write_text(json.dumps({"capture": str(args.capture), "seconds": args.seconds,
                                                   "steps": args.steps,
                                                   "preset": args.preset, "seed": args.seed, "rows": rows},
                                                  indent=2, default=str))
    (out / "ablation.txt").write_text(table + "\n")
    budget = f"{args.seconds:g} s" if args.steps is None else f"{args.steps} steps"
    plot(rows, out / "ablation.png", title=f"{Path(args.capture).name}: {budget} per variant ({args.preset})")
    print(f"wrote {out / 'ablation.csv'}, {out / 'ablation.png'}")
    return 0
