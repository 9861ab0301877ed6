"""``python -m engine render RUN --cameras FILE.json --out DIR``: render camera records."""
from __future__ import annotations

import sys

from ..errors import CaptureError, RunError
from ..export.render_views import read_camera_file, write_renders
from ..scene.model import load_run

HELP = "render a run from the cameras in a JSON file (EXR linear RGBA+Z or PNG sRGB)"


def add_arguments(p) -> None:
    p.add_argument("run", help="run directory")
    p.add_argument("--cameras", required=True, help="camera JSON (capture schema: cameras + frames)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--format", default="exr", choices=["exr", "png"])
    p.add_argument("--time", type=float, default=None, help="render every camera at this capture time (bullet time)")
    p.add_argument("--device", default="cpu")


def main(args) -> int:
    try:
        scene = load_run(args.run, device=args.device)
        views = read_camera_file(args.cameras)
        paths = write_renders(scene, views, args.out, args.format, time=args.time)
    except (CaptureError, RunError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {len(paths)} {args.format.upper()} file(s) to {args.out}")
    return 0
