"""``python -m engine batch CAPTURE... --out DIR``: train many captures on a Ray cluster (or a local
Ray instance), each as a task of its own; ``DIR/batch.json`` summarises the batch."""
from __future__ import annotations

import json
import sys

from ..cluster.batch import BatchSettings, print_log, run_batch
from ..cluster.ray_runtime import ClusterError
from ..train.config import DEFAULT_PRESET, PRESETS, get_preset
from .train import parse_overrides

HELP = "train many captures as Ray tasks (a cluster with --address, else a local Ray instance)"


def add_arguments(p) -> None:
    p.add_argument("captures", nargs="+", help="capture folders (transforms.json)")
    p.add_argument("--out", required=True, help="batch folder: one run folder per capture and batch.json")
    p.add_argument("--address", default=None,
                   help="HOST:PORT of a running Ray cluster (`ray start --head`); default: a local Ray instance")
    p.add_argument("--preset", default=DEFAULT_PRESET, choices=list(PRESETS))
    p.add_argument("--seconds", type=float, default=None, help="wall-clock budget of each capture")
    p.add_argument("--rgb-only", action="store_true", help="ignore spike streams")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE",
                   help="change a setting for every capture (as engine train --set)")
    p.add_argument("--device", default="auto", help="auto (default: the task's GPU when it has one), cpu, cuda")
    p.add_argument("--cpus-per-task", type=float, default=1.0, help="CPUs Ray reserves for each capture (default 1)")
    p.add_argument("--gpus-per-task", type=float, default=None,
                   help="GPUs Ray reserves for each capture (default: 1 when the cluster has GPUs, else 0)")
    p.add_argument("--retries", type=int, default=3,
                   help="times a capture is retried when its worker dies (each retry resumes its checkpoint)")
    p.add_argument("--no-eval", action="store_true", help="do not score runs on their eval frames")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def main(args) -> int:
    overrides = parse_overrides(args.overrides)
    try:  # a wrong setting is reported before Ray starts
        get_preset(args.preset, overrides)
    except (KeyError, ValueError) as exc:
        print(f"error: {exc.args[0] if exc.args else exc}", file=sys.stderr)
        return 2
    settings = BatchSettings(preset=args.preset, seconds=args.seconds, rgb_only=args.rgb_only, seed=args.seed,
                             overrides=overrides, device=args.device, evaluate=not args.no_eval)
    try:
        summary = run_batch(args.captures, args.out, settings, address=args.address,
                            cpus_per_task=args.cpus_per_task, gpus=args.gpus_per_task,
                            retries=args.retries, log=None if args.quiet else print_log)
    except ClusterError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(summary, indent=2))
    return 0 if all(r["status"] == "finished" for r in summary["captures"]) else 1
