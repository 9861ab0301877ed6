"""``python -m engine export RUN --times T0 T1 N --out FILE.npz``: Gaussians over time."""
from __future__ import annotations

import sys

from ..errors import RunError
from ..export.npz import export_npz
from ..scene.model import load_run

HELP = "export the Gaussians at N instants in [T0, T1] to a compact .npz cache"


def add_arguments(p) -> None:
    p.add_argument("run", help="run directory")
    p.add_argument("--times", nargs=3, metavar=("T0", "T1", "N"), default=None,
                   help="N instants from T0 to T1 seconds (default: the capture's range, 31 instants)")
    p.add_argument("--out", required=True, help="output .npz")
    p.add_argument("--device", default="cpu")


def main(args) -> int:
    import numpy as np


    try:
        scene = load_run(args.run, device=args.device)
        if args.times is None:
            t0, t1, n = scene.time_range[0], scene.time_range[1], 31
        else:
            t0, t1, n = float(args.times[0]), float(args.times[1]), int(args.times[2])
        if n < 1:
            raise RunError(args.out, "N must be at least 1")
        times = np.linspace(t0, t1, n)
        path = export_npz(scene, times, args.out)
    except RunError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    size = path.stat().st_size
    print(f"wrote {path} ({n} instants, {scene.num_gaussians} Gaussians, {size / 1e6:.2f} MB)")
    return 0
