"""``python -m engine export RESULT --out PATH [--format npz|ply|compact] [--fps F | --times T0 T1 N]``.

* ``npz`` (default): the raw sampled arrays (``engine.export.npz.export_npz``);
* ``ply``: ``PATH/frame_000000.ply ...`` in the 3DGS layout plus ``PATH/index.json``;
* ``compact``: one DynTCG-style compact 4D cache file (``.bt4c``), which ``eval``, ``render``,
  ``export`` and Blender's Load Result open like a run.

RESULT is a run directory, or (for ``ply`` and ``compact``) a compact cache.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..errors import RunError
from ..export import compact, ply
from ..export.cached import CachedScene, load_result, run_meta, sample_splats
from ..export.npz import export_npz

HELP = "export the Gaussians over time: raw .npz arrays, a 3DGS PLY sequence, or a compact 4D cache"
FORMATS = ("npz", "ply", "compact")


def add_arguments(p) -> None:
    p.add_argument("run", help="run directory (or a compact cache for --format ply/compact)")
    p.add_argument("--format", choices=FORMATS, default=None,
                   help="npz (raw sampled arrays), ply (3DGS PLY per instant + index.json), compact (.bt4c); "
                        "default: compact for an --out ending in .bt4c, else npz")
    when = p.add_mutually_exclusive_group()
    when.add_argument("--fps", type=float, default=None,
                      help="instants per capture second over the whole time range (e.g. 300 = the eval cameras' rate)")
    when.add_argument("--times", nargs=3, metavar=("T0", "T1", "N"), default=None,
                      help="N instants from T0 to T1 seconds (default: the capture's range, 31 instants)")
    p.add_argument("--out", required=True, help="output file (npz, compact) or folder (ply)")
    p.add_argument("--device", default="auto", help="auto (default: CUDA when available), cpu, cuda, cuda:1")


def export_times(time_range, fps=None, times=None):
    """The export instants: ``fps`` over ``time_range`` (both ends included), or ``times``
    = (T0, T1, N), or 31 instants over the range."""
    t0, t1 = float(time_range[0]), float(time_range[1])
    if fps is not None:
        if not fps > 0:
            raise ValueError(f"--fps must be positive, got {fps}")
        n = int(np.floor((t1 - t0) * fps + 1e-6)) + 1
        return t0 + np.arange(n) / float(fps)
    if times is not None:
        t0, t1, n = float(times[0]), float(times[1]), int(times[2])
    else:
        n = 31
    if n < 1:
        raise ValueError("N must be at least 1")
    return np.linspace(t0, t1, n)


def main(args) -> int:
    fmt = args.format or ("compact" if str(args.out).endswith(".bt4c") else "npz")
    out = Path(args.out)
    try:
        scene = load_result(args.run, device=args.device)
        try:
            times = export_times(scene.time_range, args.fps, args.times)
        except ValueError as exc:
            raise RunError(args.out, str(exc)) from exc
        if fmt == "npz":
            if isinstance(scene, CachedScene):
                raise RunError(args.run, "npz export needs a run directory (a compact cache holds no model)")
            path = export_npz(scene, times, out)
        else:
            bar = tqdm(total=len(times), desc=f"export {fmt}", unit="instant", leave=False)

            def progress(done, total):
                bar.update(done - bar.n)

            meta = run_meta(scene)
            if fmt == "ply":
                path = ply.write_sequence(out, times, sample_splats(scene), fps=args.fps, source=meta["source"],
                                          background=meta["background"], progress=progress)
            else:
                path = compact.write_compact(out, times, sample_splats(scene), meta=meta, progress=progress)
            bar.close()
    except RunError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    size = (sum(p.stat().st_size for p in out.glob("frame_*.ply")) + path.stat().st_size if fmt == "ply"
            else path.stat().st_size)
    print(f"wrote {out if fmt == 'ply' else path} ({fmt}, {len(times)} instants, {scene.num_gaussians} Gaussians, "
          f"{size / 1e6:.3f} MB)")
    return 0
