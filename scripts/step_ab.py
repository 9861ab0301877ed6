"""A/B of an exact speed switch inside one training run (issue 13).

    python scripts/step_ab.py CAP MODULE:ATTR [--rgb-only] [--steps 1000] [--from 400]
                              [--fixed on|off] [--set key=value ...]

``MODULE:ATTR`` is a boolean module switch of the engine, e.g. ``engine.scene.trajectory:SINK``
(the curves' gradients summed in place) or ``engine.scene.fused_adam:PARALLEL``. Trains the
fast preset for ``--steps`` steps; from step ``--from`` on, each step draws the switch on or
off at random (seeded) and the wall and CPU time of its ``backward()`` and of the Gaussians'
optimizer step are recorded per side. ``bench-step --variants A,B`` runs its variants one after
the other, and on this shared machine consecutive runs differ by up to ~10 %, more than a
change of a few per cent; drawing per step puts both sides under the same load and model state.

``--fixed on|off`` instead keeps the switch at one side for the whole run and prints a hash of
every Gaussian parameter at the end: two runs with the same hash trained bit for bit alike.
"""
from __future__ import annotations

import argparse
import hashlib
import importlib
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from engine.cli.train import parse_overrides  # noqa: E402
from engine.io.capture import load_capture  # noqa: E402
from engine.scene.fused_adam import FusedAdam  # noqa: E402
from engine.train.budget import warm_up_runtime  # noqa: E402
from engine.train.presets import get_preset  # noqa: E402
from engine.train.trainer import Trainer  # noqa: E402


def _timed(record: dict, key: str, fn):
    def wrapper(*a, **k):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn(*a, **k)
        record.setdefault(key, []).append((time.perf_counter() - w0, time.process_time() - c0))
        return out
    return wrapper


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture")
    ap.add_argument("switch", help="MODULE:ATTR, a boolean module attribute")
    ap.add_argument("--rgb-only", action="store_true")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--from", dest="start", type=int, default=400)
    ap.add_argument("--fixed", choices=("on", "off"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    mod_name, attr = args.switch.split(":")
    mod = importlib.import_module(mod_name)
    if not isinstance(getattr(mod, attr), bool):
        raise SystemExit(f"{args.switch} is not a boolean switch")
    overrides = parse_overrides(args.set)
    warm_up_runtime("cpu")
    tr = Trainer(load_capture(args.capture), get_preset("fast", {"iterations": args.steps, **overrides}),
                 device="cpu", rgb_only=args.rgb_only, seed=args.seed)
    tr.init_model()
    rng = np.random.default_rng(12345)
    sides: dict = {True: {}, False: {}}
    backward, adam_step, original = torch.Tensor.backward, FusedAdam.step, getattr(mod, attr)
    try:
        for s in range(args.steps):
            on = args.fixed == "on" if args.fixed else (bool(rng.integers(2)) if s >= args.start else True)
            setattr(mod, attr, on)
            timing = not args.fixed and s >= args.start
            torch.Tensor.backward = _timed(sides[on], "backward", backward) if timing else backward
            FusedAdam.step = _timed(sides[on], "optimizer", adam_step) if timing else adam_step
            tr.step(s)
    finally:
        torch.Tensor.backward, FusedAdam.step = backward, adam_step
        setattr(mod, attr, original)
    g = tr.model.gaussians
    if args.fixed:
        h = hashlib.sha256()
        for name in sorted(g.param_names):
            h.update(name.encode())
            h.update(getattr(g, name).detach().contiguous().numpy().tobytes())
        print(f"{args.switch} {args.fixed}: {g.num_gaussians} Gaussians, parameters {h.hexdigest()[:16]}")
        return
    print(f"{args.switch}, steps {args.start}..{args.steps - 1} drawn at random; ms, median (mean)")
    for key in ("backward", "optimizer"):
        for on in (False, True):
            a = np.array(sides[on].get(key, [(np.nan, np.nan)])) * 1e3
            side = "on " if on else "off"
            print(f"{key:9s} {side} n {len(a):4d}  wall {np.median(a[:, 0]):7.2f} ({a[:, 0].mean():7.2f})"
                  f"  cpu {np.median(a[:, 1]):7.2f} ({a[:, 1].mean():7.2f})")


if __name__ == "__main__":
    main()
