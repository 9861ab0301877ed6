"""``python -m tools bench-kernels``: the step's numba kernels against the torch code they
replace, in one process with the two interleaved (issue 13): the admissions' Lucas-Kanade
flow (``engine.train.frames.interpolation.FUSED_BOX``) on a capture's train pairs, and the curves at
one instant (``engine.scene.trajectory.FUSED_CURVES``) at a knot and between knots, and the
"stepcost" round's paths (:func:`stepcost`): the spike-view flow term's subset positions
(``spike_flow.FUSED_INNER``), the stereo depth term's pixels (``losses.HOIST_STEREO``) and the
flow term's DIS flow pairs on the capture's spike grey images (``scene_flow.REUSE_DIS``,
``spike_flow_pairs.PARALLEL_PAIR``; wall and CPU time). Prints CPU ms (best of ``--repeats``) and
whether the results are identical."""
from __future__ import annotations

import os
import time

import numpy as np
import torch

from engine.io.capture import load_capture
from engine.scene import trajectory
from engine.train.frames import interpolation
from engine.train.loop.scene_setup import train_frames

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
    stepcost(args, knots)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"load average {load:.1f} (cores: {os.cpu_count()})")
    return 0


def _interleaved(module, name, fn, repeats: int) -> tuple[float, float, object, object]:
    """(CPU ms with ``module.name`` False, with it True, the two results): best of ``repeats``
    runs of each, interleaved."""
    best, out = {False: float("inf"), True: float("inf")}, {}
    for flag in (False, True) * repeats:
        dt, res = _switch(module, name, flag, lambda: _best(fn, 1))
        best[flag] = min(best[flag], dt)
        out[flag] = res
    return best[False], best[True], out[False], out[True]


def stepcost(args, knots) -> None:
    """The stepcost round's paths against the code they replace (same process, interleaved)."""
    import types

    from engine.scene.model import TRAJ_MEANS
    from engine.train.config import get_preset
    from engine.train.guidance import spike_flow, spike_flow_pairs
    from engine.train.loop.trainer import Trainer
    from engine.train.losses import terms as losses
    from engine.train.motion import scene_flow

    gen = torch.Generator().manual_seed(1)
    n, m = args.gaussians, min(4096, args.gaussians)
    params = (torch.randn(n, trajectory.num_controls(len(knots)), 3, generator=gen) * 0.01).requires_grad_(True)
    model = types.SimpleNamespace(gaussians=types.SimpleNamespace(means=torch.randn(n, 3, generator=gen),
                                                                  **{TRAJ_MEANS: params}),
                                  trajectory={"knots": knots})
    idx = torch.randperm(n, generator=gen)[:m]
    w = torch.randn(m, 3, generator=gen)
    t = 0.37 * knots[1] + 0.63 * knots[2]

    def inner():
        params.grad = None
        x = spike_flow.inner_only_positions(model, t, idx)
        (x * w).sum().backward()
        return x.detach(), params.grad

    a, b, r0, r1 = _interleaved(spike_flow, "FUSED_INNER", inner, args.repeats * 4)
    print(f"flow term subset positions, {m} of {n} rows, forward + backward: torch {a:.2f} ms, numba {b:.2f} ms "
          f"({a / b:.2f}x), identical: {torch.equal(r0[0], r1[0]) and torch.equal(r0[1], r1[1])}")
    cap = load_capture(args.capture)
    h, wd = np.asarray(train_frames(cap)[0].load_rgb()).shape[:2]
    depth = (1.0 + torch.rand(1, h, wd, 1, generator=gen)).requires_grad_(True)
    ctx = types.SimpleNamespace(run=types.SimpleNamespace(memo={}), meta={"depths": depth},
                                item={"stereo_depth": 1.0 + torch.rand(h, wd, generator=gen),
                                      "stereo_mask": torch.rand(h, wd, generator=gen) < 0.6})

    def stereo():
        depth.grad = None
        val = losses._stereo_depth(ctx)
        val.backward()
        return val.detach(), depth.grad

    a, b, r0, r1 = _interleaved(losses, "HOIST_STEREO", stereo, args.repeats * 4)
    print(f"stereo depth term {wd}x{h}, forward + backward: boolean masks {a:.2f} ms, hoisted indices {b:.2f} ms "
          f"({a / b:.2f}x), identical: {torch.equal(r0[0], r1[0]) and torch.equal(r0[1], r1[1])}")
    tr = Trainer(cap, get_preset("fast", {"iterations": 200}), device="cpu")
    tr.init_model()
    sf = getattr(tr, "spike_flow", None)
    if sf is None:
        print("flow pairs: no spike-view flow term on this capture")
        return
    ts = sf.times
    pairs = [(sf.gray(ts[k]), sf.gray(ts[k] + (ts[k + 1] - ts[k]) * q / 6)) for k in range(len(ts) - 1)
             for q in (1, 3, 5)]
    res, ref, same = {}, None, True
    for _ in range(args.repeats):
        for label, reuse, parallel in (("new DIS per flow, serial", False, False), ("reused DIS", True, False),
                                       ("reused DIS, two threads", True, True)):
            old = scene_flow.REUSE_DIS, spike_flow_pairs.PARALLEL_PAIR
            scene_flow.REUSE_DIS, spike_flow_pairs.PARALLEL_PAIR = reuse, parallel
            try:
                w0, c0 = time.perf_counter(), time.process_time()
                out = [spike_flow.flow_pair(x, y) for x, y in pairs]
                dw, dc = time.perf_counter() - w0, time.process_time() - c0
            finally:
                scene_flow.REUSE_DIS, spike_flow_pairs.PARALLEL_PAIR = old
            ref = out if ref is None else ref
            same &= all(np.array_equal(p[0], q[0]) and np.array_equal(p[1], q[1]) for p, q in zip(out, ref))
            prev = res.get(label, (float("inf"), float("inf")))
            res[label] = (min(prev[0], 1e3 * dw / len(pairs)), min(prev[1], 1e3 * dc / len(pairs)))
    hh, ww = pairs[0][0].shape
    print(f"spike-view flow pairs ({len(pairs)} pairs at {ww}x{hh}), ms per pair: "
          + "; ".join(f"{k}: wall {v[0]:.1f}, CPU {v[1]:.1f}" for k, v in res.items()) + f"; identical: {same}")
