"""``python -m tools time-to-result CAPTURE --out DIR``: how long a capture takes from ``train`` to a
finished, scored and exported run, stage by stage, and how the new view improves on the way.

One training run (``engine.train.train`` with ``--seconds`` or the preset's steps), measured as
``tools bench`` measures a run (:func:`tools.bench.run_one`: periodic checkpoints scored afterwards,
so the measurement does not slow the run), then the run's full evaluation and a compact export.
Reported:

* every stage's wall time and the process's peak memory after it: the preparation stages that
  ``train`` announces (kernels, loading, stereo and fusion, initial Gaussians, the budget's timing;
  run.json ``preparation``), the static and the deformation stage, evaluation, export;
* eval PSNR / SSIM (every ``--eval-stride``-th eval frame) against wall time since ``train`` was
  called, LPIPS at the end, and where the curve comes within 1 dB of its last point.

Writes DIR/time_to_result.json and DIR/time_to_result.md.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

HELP = "stage-by-stage time and peak memory from train to a scored, exported run; PSNR against wall time"


def add_arguments(p) -> None:
    p.add_argument("capture", help="capture folder with eval frames (e.g. make_capture.py --preset real)")
    p.add_argument("--out", required=True, type=Path, help="working folder (the run goes to DIR/fast-full)")
    p.add_argument("--preset", default="fast")
    p.add_argument("--seconds", type=float, default=None, help="training budget (default: the preset's steps)")
    p.add_argument("--eval-every", type=float, default=120.0, help="seconds between curve samples (default 120)")
    p.add_argument("--eval-stride", type=int, default=4, help="score every k-th eval frame on the curve (default 4)")
    p.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE", default=[])
    p.add_argument("--rgb-only", action="store_true")


def main(args) -> int:
    from engine.__main__ import main as engine_main
    from engine.cli.train import parse_overrides
    from engine.evaluate import evaluate
    from engine.io.capture import load_capture
    from engine.train import train

    from .bench import peak_rss_mb, run_one

    capture = load_capture(args.capture)
    stages: list[dict] = []
    marks = {"first_deform": None}

    def train_fn(cap, run_dir, *, progress, **kw):
        def on_progress(p):
            if p["stage"] != "static" and marks["first_deform"] is None:
                marks["first_deform"] = (time.perf_counter(), int(p["step"]))
            if marks.get("first_step") is None:
                marks["first_step"] = (time.perf_counter(), int(p["step"]))
            progress(p)

        summary = train(cap, run_dir, progress=on_progress, **kw)
        marks["end"] = (time.perf_counter(), int(summary["step"]))
        marks["peak_after_train"] = peak_rss_mb()[0]
        return summary

    def evaluate_fn(run_dir, cap):
        t0 = time.perf_counter()
        out = evaluate(run_dir, cap)
        stages.append({"stage": "evaluation (every eval frame, LPIPS)", "seconds": round(time.perf_counter() - t0, 1),
                       "peak_rss_mb": round(peak_rss_mb()[0], 1)})
        return out

    overrides = parse_overrides(args.overrides)
    variant = "rgb_only" if args.rgb_only else "full"
    res = run_one(capture, args.out, args.preset, variant, seconds=args.seconds, eval_every_s=args.eval_every,
                  eval_stride=args.eval_stride, overrides=overrides, train_fn=train_fn, evaluate_fn=evaluate_fn,
                  flicker=False)
    run_dir = Path(res.run_dir)
    info = json.loads((run_dir / "run.json").read_text())
    rows = [{"stage": r["stage"], "seconds": r["seconds"], "peak_rss_mb": r.get("peak_rss_mb")}
            for r in info.get("preparation", [])]
    t_first, s_first = marks["first_step"]
    t_def, s_def = marks["first_deform"] or marks["end"]
    t_end, s_end = marks["end"]
    rows.append({"stage": f"static stage ({s_def - s_first + 1} steps)", "seconds": round(t_def - t_first, 1),
                 "peak_rss_mb": None})
    rows.append({"stage": f"deformation stage ({s_end - s_def} steps)", "seconds": round(t_end - t_def, 1),
                 "peak_rss_mb": round(marks["peak_after_train"], 1)})
    rows += stages
    t0 = time.perf_counter()
    code = engine_main(["export", str(run_dir), "--format", "compact", "--out", str(args.out / "result.bt4c")])
    rows.append({"stage": "export (compact .bt4c)" + ("" if code == 0 else " FAILED"),
                 "seconds": round(time.perf_counter() - t0, 1), "peak_rss_mb": round(peak_rss_mb()[0], 1)})
    final = res.final
    curve = res.curve
    last = curve[-1]["psnr"] if curve else None
    within = next((c for c in curve if last is not None and c["psnr"] >= last - 1.0), None)
    report = {"capture": str(Path(args.capture).name), "preset": args.preset, "variant": variant,
              "seconds_budget": args.seconds, "steps": res.summary["step"], "wall_s": round(res.wall_s, 1),
              "train_to_scored_s": round(res.wall_s + sum(r["seconds"] for r in stages), 1),
              "peak_rss_mb": res.peak_rss_mb, "num_gaussians": res.summary["num_gaussians"],
              "init": res.summary.get("init"), "stages": rows, "curve": curve,
              "final": {k: final.get(k) for k in ("psnr", "ssim", "lpips", "psnr_interframe", "psnr_dynamic")},
              "within_1db_of_last": within}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "time_to_result.json").write_text(json.dumps(report, indent=2, default=str))
    md = format_report(report)
    (args.out / "time_to_result.md").write_text(md + "\n")
    print(md)
    return 0


def format_report(r: dict) -> str:
    lines = [f"{r['capture']}: preset {r['preset']} ({r['variant']}), {r['steps']} steps, "
             f"{r['num_gaussians']} Gaussians at the end; train {r['wall_s']} s, train to scored "
             f"{r['train_to_scored_s']} s; peak memory {r['peak_rss_mb']} MB", "",
             "| stage | seconds | peak memory MB |", "|---|---|---|"]
    lines += [f"| {s['stage']} | {s['seconds']} | {s['peak_rss_mb'] if s['peak_rss_mb'] is not None else ''} |"
              for s in r["stages"]]
    f = r["final"]
    lines += ["", f"final: PSNR {f['psnr']} dB, SSIM {f['ssim']}, LPIPS {f['lpips']}, between RGB frames "
                  f"{f['psnr_interframe']} dB, moving pixels {f['psnr_dynamic']} dB", "",
              "| wall s | step | eval PSNR (curve frames) | SSIM | Gaussians |", "|---|---|---|---|---|"]
    for c in r["curve"]:
        lines.append(f"| {c['wall_s']:.0f} | {c['step']} | {c['psnr']:.2f} | {c['ssim']:.4f} | {c['num_gaussians']} |"
                     if c["wall_s"] is not None else f"| | {c['step']} | {c['psnr']:.2f} | {c['ssim']:.4f} | |")
    w = r["within_1db_of_last"]
    if w:
        lines += ["", f"within 1 dB of the last curve point at step {w['step']}, {w['wall_s']:.0f} s after train began"]
    return "\n".join(lines)
