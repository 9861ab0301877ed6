"""``python -m tools bench-adam``: the Gaussians' optimizer step per parameter (issue 13).

Trains ``--steps`` of the preset's schedule (RGB only, then with the spike branch), and on the
final real state (the parameters, their last gradients, Adam's moments) times one Adam update
of each parameter by three code paths, interleaved in one process, CPU ms best of
``--repeats``, each on its own copy of the state:

* ``torch``: ``torch.optim.Adam`` (``foreach=False``, the seven-pass single-tensor step);
* ``two-pass``: FusedAdam's moments pass, torch's ``sqrt``, update pass (``ONE_PASS=False``);
* ``one-pass``: FusedAdam's default where ``vmsSqrt`` is exported: the three stages a block at
  a time in one numba call (:mod:`engine.numba_vml`).

Also per parameter: its element count and the share of elements whose gradient and both
moments are exactly zero (curve columns no render has read: Adam leaves them as they are).
Prints whether the three paths' results are identical after the timed repeats.
"""
from __future__ import annotations

import os
import time

import torch

from engine.cli.train import parse_overrides
from engine.io.capture import load_capture
from engine.scene import fused_adam
from engine.train.config import get_preset
from engine.train.loop.budget import warm_up_runtime
from engine.train.loop.trainer import Trainer

HELP = "time the Gaussians' Adam step per parameter: torch, FusedAdam's two passes, its one pass"

PATHS = ("torch", "two-pass", "one-pass")


def add_arguments(parser) -> None:
    parser.add_argument("capture", help="capture folder")
    parser.add_argument("--steps", type=int, default=200, help="training steps before the state is timed")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    parser.add_argument("--rgb-only", action="store_true", help="skip the guided (spike) run")


def _copy_state(p: torch.Tensor, st: dict) -> tuple:
    q = p.detach().clone()
    return q, p.grad.detach().clone(), st["exp_avg"].clone(), st["exp_avg_sq"].clone(), st["step"].clone()


def _time(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return 1e3 * best


def time_parameters(opt: torch.optim.Optimizer, repeats: int) -> list[dict]:
    """Per parameter with a gradient in ``opt`` (a FusedAdam after a step): name, elements,
    zero share, CPU ms of each of :data:`PATHS` and whether their results agree."""
    rows = []
    for grp in opt.param_groups:
        beta1, beta2 = grp["betas"]
        lr, eps = float(grp["lr"]), float(grp["eps"])
        for p in grp["params"]:
            st = opt.state.get(p)
            if p.grad is None or not st:
                continue
            step = float(st["step"].item())
            copies = {k: _copy_state(p, st) for k in PATHS}
            q, g, m, v, s = copies["torch"]
            q = torch.nn.Parameter(q)
            q.grad = g
            ref = torch.optim.Adam([q], lr=lr, betas=(beta1, beta2), eps=eps, foreach=False)
            ref.state[q] = {"step": s, "exp_avg": m, "exp_avg_sq": v}

            def torch_step():
                ref.state[q]["step"].fill_(step - 1)  # every repeat the same bias correction
                ref.step()

            scratch = torch.empty(p.numel(), dtype=torch.float32)

            def fused(key, one_pass):
                qq, gg, mm, vv, _ = copies[key]
                return lambda: fused_adam._fused_update(qq, gg, mm, vv, step, lr, float(beta1), float(beta2), eps,
                                                        scratch, one_pass)

            fns = {"torch": torch_step, "two-pass": fused("two-pass", False), "one-pass": fused("one-pass", True)}
            ms = {k: float("inf") for k in PATHS}
            for _ in range(repeats):  # interleaved: the machine's load moves all three alike
                for k in PATHS:
                    if k == "one-pass" and not fused_adam.one_pass_exact():
                        continue
                    ms[k] = min(ms[k], _time(fns[k], 1))
            same = torch.equal(q.detach(), copies["two-pass"][0])
            if fused_adam.one_pass_exact():
                same = same and torch.equal(copies["two-pass"][0], copies["one-pass"][0])
            zero = ((p.grad == 0) & (st["exp_avg"] == 0) & (st["exp_avg_sq"] == 0)).float().mean().item()
            rows.append({"name": grp.get("name", "?"), "shape": tuple(p.shape), "numel": p.numel(),
                         "zero": zero, "ms": ms, "same": same})
    return rows


def _table(rows: list[dict]) -> str:
    lines = ["| parameter | shape | floats | g = m = v = 0 | torch ms | two-pass ms | one-pass ms | identical |",
             "|---|---|---|---|---|---|---|---|"]
    tot = {k: 0.0 for k in PATHS}
    for r in sorted(rows, key=lambda r: -r["numel"]):
        lines.append(f"| {r['name']} | {'x'.join(map(str, r['shape']))} | {r['numel']} | {100 * r['zero']:.0f}% | "
                     + " | ".join(f"{r['ms'][k]:.2f}" for k in PATHS) + f" | {r['same']} |")
        for k in PATHS:
            tot[k] += r["ms"][k]
    n = sum(r["numel"] for r in rows)
    lines.append(f"| **all** | | {n} | | " + " | ".join(f"**{tot[k]:.2f}**" for k in PATHS) + " | |")
    return "\n".join(lines)


def main(args) -> int:
    cap = load_capture(args.capture)
    warm_up_runtime("cpu")
    torch.set_num_threads(1)  # as engine.train.train does on the CPU
    load0 = os.getloadavg()[0]
    for rgb_only in ((True,) if args.rgb_only else (True, False)):
        cfg = get_preset(args.preset, {**parse_overrides(args.set), "iterations": int(args.steps)})
        tr = Trainer(cap, cfg, device="cpu", rgb_only=rgb_only)
        tr.init_model()
        for i in range(int(args.steps)):
            tr.step(i)
        g = tr.model.gaussians
        print(f"### {'RGB only' if rgb_only else 'guided'}: state after {args.steps} steps, "
              f"{g.num_gaussians} Gaussians, {type(g.optimizer).__name__} (CPU ms, best of {args.repeats})\n")
        print(_table(time_parameters(g.optimizer, args.repeats)))
        print()
    print(f"load average start/end {load0:.1f} / {os.getloadavg()[0]:.1f} (cores: {os.cpu_count()}); "
          f"one pass exact here: {fused_adam.one_pass_exact()}")
    return 0
