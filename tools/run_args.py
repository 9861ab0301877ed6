"""What the training benchmarks' commands share (``tools ablate``, ``tools steps-curve``): the preset, seed,
device and ``--set`` arguments, and running the benchmark with its log on stderr and a clean error."""
from __future__ import annotations

import sys

from engine.errors import CaptureError, RunError
from engine.train.config import PRESETS

__all__ = ["add_run_arguments", "run_logged"]


def add_run_arguments(p, each: str = "run") -> None:
    """``--preset``, ``--seed``, ``--device`` and repeatable ``--set KEY=VALUE`` (``args.overrides``;
    ``engine.cli.train.parse_overrides`` reads them); ``each`` names what one training is in the help."""
    p.add_argument("--preset", default="fast", choices=list(PRESETS))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default=None, help="cpu, cuda (default: cuda when available)")
    p.add_argument("--set", dest="overrides", action="append", metavar="KEY=VALUE",
                   help=f"override a preset field for every {each} (repeatable)")


def run_logged(fn, *args, **kw):
    """``fn(*args, log=<a line on stderr>, **kw)``; None after printing a capture or run error (the
    command then returns 1)."""
    try:
        return fn(*args, log=lambda s: print(s, file=sys.stderr, flush=True), **kw)
    except (CaptureError, RunError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None
