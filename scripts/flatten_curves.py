#!/usr/bin/env python
"""Copy a trained run with its curves' in-between bends removed (issue 11 diagnosis).

Per-Gaussian trajectories (engine.scene.trajectory) pass through their junctions at the RGB
instants; the inner control points (residuals from the Catmull-Rom spline) are what the spike
branch's between-frame terms move. Scoring a copy without them (``engine eval OUT``) against the
run itself separates what the bends do between RGB frames from everything else (appearance,
junctions, which the copy keeps)::

    .venv/bin/python scripts/flatten_curves.py RUN OUT                     # every bend
    .venv/bin/python scripts/flatten_curves.py RUN OUT --quiet CAP [--dilate 1]
    .venv/bin/python -m engine eval OUT

``--quiet CAP``: only the bends the ``quiet_curves`` switch would hold (engine.train.quiet_curves:
segment ``k`` of Gaussians that project at both of its RGB instants where the capture's spike view
did not change in interval ``k``, change map dilated by ``--dilate`` blocks).
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from engine.io.capture import load_capture  # noqa: E402
from engine.scene.model import TRAJ_MEANS, TRAJ_QUATS  # noqa: E402
from engine.spike.features import SpikeWindowCache  # noqa: E402
from engine.train.quiet_curves import quiet_segments, segment_intervals, zero_inner  # noqa: E402
from engine.train.spike_guidance import spike_stream_info  # noqa: E402


def quiet_mask(capture, params: dict, knots, dilate: int, block: int = 4, k_sub: int = 8) -> torch.Tensor:
    """bool [N, F-1]: the segments ``quiet_curves`` holds, from the run's final junctions."""
    info = spike_stream_info(capture)
    if info is None:
        raise SystemExit(f"{capture.root}: no spike stream co-located with a train camera")
    stream = info.open()
    if stream.c2w is None or stream.intrinsics is None:
        raise SystemExit(f"{capture.root}: the spike stream has no calibration")
    rgb_times = sorted({float(f.time) for f in capture.frames if f.camera == info.co_located_with})
    cache = SpikeWindowCache(stream, rgb_times, k_sub=k_sub)
    change = cache.change(block)
    intervals = segment_intervals(knots, rgb_times, change.num_intervals)  # as the hook picks them
    view = stream.view(0.0)
    curves = params[TRAJ_MEANS]
    return quiet_segments(params["means"].float(), curves[:, 0::3].float(), change, intervals,
                          torch.as_tensor(view.viewmat, dtype=torch.float32),
                          torch.as_tensor(stream.intrinsics.K, dtype=torch.float32),
                          int(stream.width), int(stream.height), dilate=dilate)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--quiet", metavar="CAPTURE", help="only the segments quiet_curves would hold")
    ap.add_argument("--dilate", type=int, default=1, help="change-map dilation in blocks (with --quiet)")
    args = ap.parse_args(argv)
    ckpt = args.run / "checkpoint.pt"
    if not ckpt.exists():
        raise SystemExit(f"{ckpt}: no checkpoint")
    state = torch.load(ckpt, map_location="cpu", weights_only=False)
    params = state["model"]["gaussians"]["params"]
    if TRAJ_MEANS not in params:
        raise SystemExit(f"{ckpt}: the run has no per-Gaussian trajectories")
    knots = [float(t) for t in state["model"]["trajectory"]["knots"]]
    n, segs = params[TRAJ_MEANS].shape[0], len(knots) - 1
    quiet = (quiet_mask(load_capture(args.quiet), params, knots, args.dilate) if args.quiet
             else torch.ones(n, segs, dtype=torch.bool))
    for name in (TRAJ_MEANS, TRAJ_QUATS):
        if name in params:
            zero_inner(params[name], quiet)
    if args.out.resolve() == args.run.resolve():
        raise SystemExit("OUT must differ from RUN")
    shutil.rmtree(args.out, ignore_errors=True)
    shutil.copytree(args.run, args.out)
    torch.save(state, args.out / "checkpoint.pt")
    print(f"{args.out}: {int(quiet.sum())} of {quiet.numel()} segments flattened ({n} Gaussians)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
