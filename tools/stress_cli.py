"""``python -m engine stress``: the numerical-stability stress suite (``engine.stress``).

Runs every case (or those named with ``--cases``) for ``--steps`` optimisation steps each
(default 10,000; ``--quick``: 200 steps, a few minutes on a laptop CPU), shows a tqdm
progress bar, prints one table row per case (steps, non-finite parameters / gradients /
other values, max |grad|, final loss) with details, and ends with the line
``non-finite values: <count>``. Exit status 1 when a value was non-finite or a check failed.
"""
from __future__ import annotations

import argparse
import json

HELP = "numerical-stability stress suite: extreme scales, opacities, depths, extents, times, spikes, bad inputs"

QUICK_STEPS = 200


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--steps", type=int, default=None,
                        help="optimisation steps per case (default 10000, or 200 with --quick)")
    parser.add_argument("--quick", action="store_true", help=f"a few-minute version ({QUICK_STEPS} steps per case)")
    parser.add_argument("--cases", default=None, help="comma-separated case names (default: all)")
    parser.add_argument("--list", action="store_true", help="list the cases and exit")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=None, help="also write the results to this JSON file")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def main(args) -> int:
    from .. import stress

    if args.list:
        for name in stress.CASES:
            print(f"{name:<18} {stress.CASE_HELP.get(name, '')}")
        return 0
    steps = args.steps if args.steps is not None else (QUICK_STEPS if args.quick else 10_000)
    if steps < 1:
        print("error: --steps must be at least 1")
        return 2
    cases = [c.strip() for c in args.cases.split(",") if c.strip()] if args.cases else None
    if cases:
        unknown = [c for c in cases if c not in stress.CASES]
        if unknown:
            print(f"error: unknown case(s) {', '.join(unknown)}; cases: {', '.join(stress.CASES)}")
            return 2
    results = stress.run_suite(steps, cases, seed=args.seed, progress=not args.no_progress)
    print(stress.format_table(results))
    total = stress.total_nonfinite(results)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"steps": steps, "cases": [r.to_dict() for r in results], "nonfinite": total}, fh, indent=2)
    print(f"non-finite values: {total}")
    return 0 if total == 0 and all(r.ok for r in results) else 1
