"""``python -m tools steps-curve CAPTURE... --out DIR``: new-view quality against the number of
training steps (issue 46: more training must never make the new view worse).

Each capture is trained for 1x, 2x, 4x and 8x the preset's ``schedule.iterations`` steps
(``--multiples``; ``schedule.steps``: the preset's schedule, then the steps past it settle, what a
user with that budget gets, engine.train.loop.schedule), scored on the capture's eval frames
(:func:`engine.evaluate.evaluate`: cameras no train camera stood at) and tabulated: all eval
frames, between RGB frames, moving pixels, static pixels at RGB instants and between them, the
largest static colour drift and LPIPS.
A multiple whose PSNR falls more than ``COLLAPSE_DB`` under the 1x run's, or whose LPIPS rises more
than ``COLLAPSE_LPIPS`` over it, is marked as a collapse. Writes ``DIR/steps_curve.json``,
``DIR/steps_curve.md`` and ``DIR/steps_curve.png`` (the curves); ``--resume`` reuses scored runs.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

from engine.cli.train import parse_overrides
from engine.evaluate import evaluate
from engine.train import get_preset, train

from . import report
from .report import fmt, text_table
from .run_args import add_run_arguments, run_logged

HELP = "new-view PSNR / LPIPS against training steps (1x to 8x the preset's), collapse marked"

# (metrics.json key, column head): the new view as a whole and the parts of it that more steps move
COLUMNS = (("psnr", "all"), ("psnr_interframe", "between"), ("psnr_dynamic", "moving"),
           ("psnr_static_instants", "static@RGB"), ("psnr_static_interframe", "static between"),
           ("static_colour_shift", "drift"), ("lpips", "LPIPS"))
COLLAPSE_DB = 0.1       # a longer run this far under the 1x run's eval PSNR (all or between) has collapsed
COLLAPSE_LPIPS = 0.005  # ... or with its LPIPS this far above


def add_arguments(p) -> None:
    p.add_argument("captures", nargs="+", help="capture folders (transforms.json) with eval frames")
    p.add_argument("--out", required=True, help="output folder: one run per capture and multiple + the report")
    p.add_argument("--multiples", default="1,2,4,8", help="comma-separated multiples of the preset's steps")
    p.add_argument("--rgb-only", action="store_true", help="the RGB-only model (no spike stream)")
    add_run_arguments(p, "run")
    p.add_argument("--resume", action="store_true", help="reuse runs in --out that were scored (curve_point.json)")


def parse_multiples(text: str) -> list[float]:
    try:
        vals = sorted({float(v) for v in text.split(",") if v.strip()})
    except ValueError:
        raise SystemExit(f"--multiples: expected numbers like 1,2,4,8, got {text!r}") from None
    if not vals or vals[0] <= 0:
        raise SystemExit(f"--multiples: expected positive numbers, got {text!r}")
    return vals


def steps_curve(captures, out_dir, multiples, *, preset: str = "fast", rgb_only: bool = False, seed: int = 0,
                device=None, overrides: dict | None = None, resume: bool = False, log=print) -> list[dict]:
    """Train and score every capture at every multiple of the preset's step count; one row each."""
    base = int(get_preset(preset, overrides).schedule.iterations)
    out = Path(out_dir)
    rows = []
    for cap in captures:
        for m in multiples:
            steps = max(1, int(round(m * base)))
            run_dir = out / Path(cap).name / f"x{m:g}"
            metrics_path = run_dir / "curve_point.json"  # metrics.json is the evaluator's
            if resume and metrics_path.exists():
                metrics = json.loads(metrics_path.read_text())
                log(f"[steps-curve] {Path(cap).name} x{m:g}: reusing {metrics_path}")
            else:
                log(f"[steps-curve] {Path(cap).name} x{m:g}: {steps} steps")
                t0 = time.perf_counter()
                summary = train(cap, run_dir, preset=preset, rgb_only=rgb_only, resume=False, device=device,
                                seed=seed, overrides={**(overrides or {}), "schedule.steps": steps})
                wall = time.perf_counter() - t0
                metrics = dict(evaluate(run_dir, cap, device=device or "cpu"))
                metrics.update(steps=summary.get("step"), train_seconds=summary.get("train_seconds"),
                               train_wall_s=round(wall, 2))
                metrics_path.write_text(json.dumps(metrics, indent=2, default=str))
            rows.append({"capture": Path(cap).name, "multiple": m, "steps": metrics.get("steps", steps),
                         "train_seconds": metrics.get("train_seconds"), "num_gaussians": metrics.get("num_gaussians"),
                         **{k: metrics.get(k) for k, _ in COLUMNS}})
    return mark_collapse(rows)


def mark_collapse(rows: list[dict]) -> list[dict]:
    """Each row's change against its capture's smallest multiple (``d_psnr``, ``d_between``,
    ``d_lpips``) and ``collapse``: PSNR (all or between) down by more than COLLAPSE_DB or LPIPS up
    by more than COLLAPSE_LPIPS."""
    first: dict[str, dict] = {}
    for r in sorted(rows, key=lambda r: r["multiple"]):
        first.setdefault(r["capture"], r)
    for r in rows:
        b = first[r["capture"]]
        d = {k: (None if r.get(s) is None or b.get(s) is None else round(r[s] - b[s], 4))
             for k, s in (("d_psnr", "psnr"), ("d_between", "psnr_interframe"), ("d_lpips", "lpips"))}
        r.update(d)
        r["collapse"] = bool((d["d_psnr"] is not None and d["d_psnr"] < -COLLAPSE_DB)
                             or (d["d_between"] is not None and d["d_between"] < -COLLAPSE_DB)
                             or (d["d_lpips"] is not None and d["d_lpips"] > COLLAPSE_LPIPS))
    return rows


def format_table(rows: list[dict]) -> str:
    head = ["capture", "steps", *[h for _, h in COLUMNS], "d all", "d between", "d LPIPS", "collapse"]
    lines = [[r["capture"], f"{r['steps']} (x{r['multiple']:g})",
              *[fmt(r.get(k), 4 if k == "static_colour_shift" else 3 if k == "lpips" else 2) for k, _ in COLUMNS],
              "" if r["d_psnr"] is None else f"{r['d_psnr']:+.2f}",
              "" if r["d_between"] is None else f"{r['d_between']:+.2f}",
              "" if r["d_lpips"] is None else f"{r['d_lpips']:+.3f}", "yes" if r["collapse"] else ""]
             for r in rows]
    return text_table(head, lines)


def plot(rows: list[dict], path, title: str = "") -> Path:
    # (key, title, the least span of the y axis: a flat curve drawn flat, not as noise blown up to the panel)
    panels = [("psnr", "eval PSNR, all frames (dB)", 1.0),
              ("psnr_static_interframe", "static pixels between RGB frames (dB)", 1.0),
              ("lpips", "LPIPS (lower is better)", 0.03)]
    fig, axes = report.plt.subplots(1, len(panels), figsize=(4.3 * len(panels), 3.5), squeeze=False)
    for ax, (key, label, least) in zip(axes[0], panels):
        vals = []
        for cap in dict.fromkeys(r["capture"] for r in rows):
            pts = [(r["multiple"], r[key]) for r in rows if r["capture"] == cap and r.get(key) is not None]
            if pts:
                ax.plot([p[0] for p in pts], [p[1] for p in pts], marker="o", label=cap)
                vals += [p[1] for p in pts]
        if vals and max(vals) - min(vals) < least:
            mid = 0.5 * (max(vals) + min(vals))
            ax.set_ylim(mid - 0.5 * least, mid + 0.5 * least)
        ax.set_xscale("log", base=2)
        ms = sorted({r["multiple"] for r in rows})
        ax.set_xticks(ms, [f"{m:g}x" for m in ms])
        ax.minorticks_off()
        ax.set_xlabel("the preset's steps")
        ax.set_title(label, fontsize=9)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    return report.save_figure(fig, path, title)


def main(args) -> int:
    multiples = parse_multiples(args.multiples)
    overrides = parse_overrides(args.overrides)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = run_logged(steps_curve, args.captures, out, multiples, preset=args.preset, rgb_only=args.rgb_only,
                      seed=args.seed, device=args.device, overrides=overrides, resume=args.resume)
    if rows is None:
        return 1
    table = format_table(rows)
    print(table)
    model = "RGB-only" if args.rgb_only else "full model"
    (out / "steps_curve.json").write_text(json.dumps({"preset": args.preset, "rgb_only": args.rgb_only,
                                                      "seed": args.seed, "overrides": overrides,
                                                      "multiples": multiples, "rows": rows}, indent=2, default=str))
    (out / "steps_curve.md").write_text(f"{args.preset} preset, {model}, seed {args.seed}\n\n```\n{table}\n```\n")
    plot(rows, out / "steps_curve.png", title=f"new view against steps ({args.preset}, {model})")
    bad = [f"{r['capture']} x{r['multiple']:g}" for r in rows if r["collapse"]]
    print(f"collapse: {', '.join(bad)}" if bad else "no collapse: every longer run holds the 1x run's PSNR and LPIPS")
    print(f"wrote {out / 'steps_curve.md'}, {out / 'steps_curve.png'}")
    return 0
