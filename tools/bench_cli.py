"""``python -m tools bench CAPTURE --out DIR``: eval error against wall time, per preset,
for the method and the RGB-only baseline (and the skip features with ``--variants``), in
one run, plus micro-benchmark ratios (rasterizer, spike decoding). Writes DIR/bench.csv,
DIR/bench.png, DIR/bench.md and DIR/bench.json; see ``tools.bench`` for the design."""
from __future__ import annotations

import argparse

from engine.cli.train import parse_overrides
from engine.errors import CaptureError, RunError

from .bench import VARIANTS, run_bench

HELP = "error against wall time per preset (+ RGB-only baseline, skip features) and micro-benchmarks"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", help="capture folder (transforms.json) with eval frames")
    parser.add_argument("--out", required=True, help="output folder (one run per configuration + reports)")
    parser.add_argument("--seconds", type=float, default=None,
                        help="training budget per run (default 120; 25 with --quick)")
    parser.add_argument("--iterations", type=int, default=None,
                        help="a fixed step count per run instead of a wall-clock budget (same work for every "
                             "variant: compares the time the skip features save)")
    parser.add_argument("--presets", default=None,
                        help="comma-separated presets (default fast,balanced; fast with --quick)")
    parser.add_argument("--variants", default="full,rgb_only",
                        help="comma-separated: full, rgb_only, freeze, early_stop, cull (default full,rgb_only); "
                             "freeze / early_stop / cull are the trainer's switches freeze_static / early_stop / "
                             "cull_frustum (python -m engine train --help)")
    parser.add_argument("--eval-every", type=float, default=None,
                        help="seconds between curve samples (checkpoints; default budget/8)")
    parser.add_argument("--eval-stride", type=int, default=None,
                        help="score every k-th eval frame on the curve (default 1; 4 with --quick)")
    parser.add_argument("--quick", action="store_true", help="a few-minute version")
    parser.add_argument("--no-micro", action="store_true", help="skip the micro-benchmarks")
    parser.add_argument("--no-flicker", action="store_true", help="skip the static-region flicker measurement")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default=None)
    parser.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE", default=[],
                        help="training option override (repeatable), e.g. --set max_gaussians=20000")


def main(args) -> int:
    presets = [p.strip() for p in (args.presets or ("fast" if args.quick else "fast,balanced")).split(",") if p.strip()]
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    bad = [v for v in variants if v not in VARIANTS]
    if bad:
        print(f"error: unknown variant(s) {', '.join(bad)}; choose from {', '.join(VARIANTS)}")
        return 2
    overrides = parse_overrides(args.overrides)
    if args.iterations is not None:
        overrides["iterations"] = int(args.iterations)
        seconds = None
        every = args.eval_every if args.eval_every is not None else 15.0
    else:
        seconds = args.seconds if args.seconds is not None else (25.0 if args.quick else 120.0)
        every = args.eval_every if args.eval_every is not None else max(2.0, seconds / 8)
    stride = args.eval_stride if args.eval_stride is not None else (4 if args.quick else 1)
    try:
        res = run_bench(args.capture, args.out, presets=presets, variants=variants, seconds=seconds,
                        eval_every_s=every, eval_stride=stride, overrides=overrides,
                        seed=args.seed, micro=not args.no_micro, quick=args.quick,
                        flicker=not args.no_flicker, device=args.device)
    except (CaptureError, RunError, KeyError) as exc:
        print(f"error: {exc}")
        return 2
    print(res["markdown"])
    print(f"wrote {args.out}/bench.csv, bench.png, bench.md, bench.json")
    return 0
