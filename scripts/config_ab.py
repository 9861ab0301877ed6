"""Whole runs of one config field's values, alternated in one process (issue 13).

    python scripts/config_ab.py CAP KEY V1,V2,V1,V2 [--steps 1000] [--rgb-only] [--set key=value ...]

Trains the fast preset for ``--steps`` steps once per listed value of ``KEY`` (same seed),
one after the other in this process (numba's kernels compiled once, the same load for
both sides as far as alternation gives it), and prints per run the wall and CPU ms of a
static and of a deformation step and the run's wall seconds. For a switch whose effect
spans steps (a background worker, a cache), where ``scripts/step_ab.py``'s per-step draw
cannot see it. Example (README "The flows computed ahead of the steps"):
``python scripts/config_ab.py demo_capture spike_flow_prefetch 2,0,0,2,2,0,0,2,2,0``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
# engine's own imports first: engine/__init__ sets OMP_WAIT_POLICY before torch loads libgomp
from engine.cli.train import parse_overrides  # noqa: E402
from engine.io.capture import load_capture  # noqa: E402
from engine.train.budget import warm_up_runtime  # noqa: E402
from engine.train.presets import get_preset  # noqa: E402
from engine.train.spike_flow import close_flow_worker  # noqa: E402
from engine.train.trainer import Trainer  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture")
    ap.add_argument("key")
    ap.add_argument("values", help="comma-separated values of KEY, one run each, in this order")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rgb-only", action="store_true")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    import torch  # after engine (above)

    cap = load_capture(args.capture)
    warm_up_runtime("cpu")
    torch.set_num_threads(1)  # as engine.train.train does on the CPU
    base = parse_overrides(args.set)
    for raw in args.values.split(","):
        over = {**base, **parse_overrides([f"{args.key}={raw}"]), "iterations": args.steps}
        torch.manual_seed(args.seed)
        tr = Trainer(cap, get_preset("fast", over), device="cpu", seed=args.seed, rgb_only=args.rgb_only)
        tr.init_model()
        wall, cpu, n = {}, {}, {}
        t_run = time.perf_counter()
        for i in range(args.steps):
            st = tr.stage_of(i)
            w0, c0 = time.perf_counter(), time.process_time()
            tr.step(i)
            wall[st] = wall.get(st, 0.0) + time.perf_counter() - w0
            cpu[st] = cpu.get(st, 0.0) + time.process_time() - c0
            n[st] = n.get(st, 0) + 1
        close_flow_worker(tr)
        parts = ", ".join(f"{st} {1e3 * wall[st] / n[st]:.1f} ms (cpu {1e3 * cpu[st] / n[st]:.1f})" for st in n)
        print(f"{args.key}={raw}: {parts}, run {time.perf_counter() - t_run:.1f} s", flush=True)


if __name__ == "__main__":
    main()
