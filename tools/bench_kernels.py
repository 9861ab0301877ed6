"""``python -m tools bench-kernels``: the step's numba kernels against the torch code they
replace, in one process with the two interleaved (issue 13): the admissions' Lucas-Kanade
flow (``engine.train.interpolation.FUSED_BOX``) on a capture's train pairs, and the curves at
one instant (``engine.scene.trajectory.FUSED_CURVES``) at a knot and between knots. Prints CPU
ms (best of ``--repeats``) and whether the results are identical."""
from __future__ import annotations

import os
import time

import numpy as np
import torch

from engine.io.capture import load_capture
from engine.scene import trajectory
from engine.train import interpolation
from engine.train.trainer import train_frames

HELP = "time the Lucas-Kanade flow and curve kernels against their torch code (same process, interleaved)"


def add_arguments(parser) -> None:
    parser.add_argument("capture", help="capture folder (its first train camera's first frame pairs)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--pairs", type=int, default=3, help="consecutive frame pairs of the flow")
    parser.add_argument("--gaussians", type=int, default=26064, help="curve rows (the demo's 200-step count)")


def _best(fn, repeats: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.process_time()
        out = fn()
        best = min(best, time.process_time() - t0)
    return 1e3 * best, out


def _switch(module, name, value, fn):
    old = getattr(module, name)
    setattr(module, name, value)
    try:
        return fn()
    finally:
        setattr(module, name, old)


def main(args) -> int:
    torch.set_num_threads(1)  # as training on the CPU
    interpolation.warmup()
    trajectory.warmup()
    frames = train_frames(load_capture(args.capture))
    cam = [f for f in frames if f.camera == frames[0].camera]
    imgs = [torch.as_tensor(np.asarray(f.load_rgb(), np.float32)[..., :3]).permute(2, 0, 1)[None]
            for f in cam[:args.pairs + 1]]
    torch_ms, fused_ms, same = [], [], True
    for a, b in zip(imgs, imgs[1:]):
        t, ref = _best(lambda: _switch(interpolation, "FUSED_BOX", False, lambda: interpolation.lk_flow(a, b)),
                       args.repeats)
        f, out = _best(lambda: interpolation.lk_flow(a, b), args.repeats)
        torch_ms.append(t)
        fused_ms.append(f)
        same &= torch.equal(ref, out)
    h, w = imgs[0].shape[-2:]
    print(f"lk_flow {w}x{h}, {len(torch_ms)} pairs: torch {np.mean(torch_ms):.1f} ms, numba {np.mean(fused_ms):.1f} ms "
          f"({np.mean(torch_ms) / np.mean(fused_ms):.2f}x), identical: {same}")
    knots = trajectory.default_knots([f.time for f in cam])
    gen = torch.Generator().manual_seed(0)
    for c in (3, 4):
        p0 = torch.randn(args.gaussians, trajectory.num_controls(len(knots)), c, generator=gen)
        w_out = torch.randn(args.gaussians, c, generator=gen)
        for label, t in (("a knot", knots[len(knots) // 2]), ("mid-segment", 0.5 * (knots[1] + knots[2]))):
            def run():
                p = p0.clone().requires_grad_(True)
                t0 = time.process_time()
                out = trajectory.evaluate(p, knots, t)
                (out * w_out).sum().backward()
                return time.process_time() - t0, out.detach(), p.grad

            res = {}
            for fused in (False, True) * args.repeats:
                dt, out, grad = _switch(trajectory, "FUSED_CURVES", fused, run)
                prev = res.get(fused)
                res[fused] = (min(dt, prev[0]) if prev else dt, out, grad)
            (tt, o0, g0), (tf, o1, g1) = res[False], res[True]
            print(f"curve [{args.gaussians}, {p0.shape[1]}, {c}] at {label}, forward + backward (+ loss): "
                  f"torch {1e3 * tt:.2f} ms, numba {1e3 * tf:.2f} ms ({tt / tf:.2f}x), identical: "
                  f"{torch.equal(o0, o1) and torch.equal(g0, g1)}")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"load average {load:.1f} (cores: {os.cpu_count()})")
    return 0
