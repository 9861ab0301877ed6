"""``python -m engine eval RUN [CAPTURE]``: score a run on the capture's eval frames (JSON)."""
from __future__ import annotations

import json
import sys

from ..errors import CaptureError, RunError
from ..evaluate.heldout import evaluate

HELP = "render every role:eval frame of the capture and print PSNR / SSIM as JSON"


def add_arguments(p) -> None:
    p.add_argument("run", help="run directory")
    p.add_argument("capture", nargs="?", default=None, help="capture folder (default: the one recorded in run.json)")
    p.add_argument("--device", default="cpu")


def main(args) -> int:
    try:
        result = evaluate(args.run, args.capture, device=args.device)
    except (CaptureError, RunError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(result, indent=2))
    return 0
