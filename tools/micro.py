"""Micro-benchmarks reported by ``python -m tools bench`` (ratios measured in the same run,
so machine load cancels): rasterizer, spike decoding, a frozen deformation step."""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from engine.io.spikes import read_spikes, write_spikes
from engine.raster import rasterization
from engine.scene.model import load_run, view_tensors

from .bench_decode import best_of, community_load_vidar, python_loop_load
from .bench_raster import make_scene, time_cell

__all__ = ["micro_decode", "micro_freeze_step", "micro_raster", "warmup"]


def micro_raster(quick: bool = False, repeats: int | None = None) -> dict:
    """Rasterizer forward+backward: fast cpu vs dense reference (small scene, where the
    reference fits in memory) and vs the plain-PyTorch tiled path (demo resolution)."""
    rep = repeats or (2 if quick else 5)
    out = {}
    w, h, n = (64, 48, 200) if quick else (96, 72, 400)
    scene = make_scene(n, w, h)
    cpu = time_cell(scene, w, h, "cpu", rep, None)
    ref = time_cell(scene, w, h, "reference", max(1, rep - 1), None)
    out["small"] = {"size": f"{w}x{h}", "gaussians": n, "cpu_ms": cpu[1], "reference_ms": ref[1],
                    "speedup_vs_reference": ref[1] / cpu[1]}
    w, h, n = (160, 120, 2000) if quick else (160, 120, 10000)
    scene = make_scene(n, w, h)
    cpu = time_cell(scene, w, h, "cpu", rep, None)
    tor = time_cell(scene, w, h, "torch", max(1, rep - 1), None)
    out["demo"] = {"size": f"{w}x{h}", "gaussians": n, "cpu_ms": cpu[1], "torch_ms": tor[1],
                   "speedup_vs_torch": tor[1] / cpu[1]}
    return out


def micro_decode(quick: bool = False) -> dict:
    """Spike decoding: read_spikes vs the community per-frame loader and the per-byte loop."""
    h, w, n = 250, 400, (200 if quick else 1000)
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory(prefix="bt4d_bench_") as tmp:
        path = Path(tmp) / "s.dat"
        write_spikes(path, (rng.random((n, h, w)) < 0.2).astype(np.uint8))
        t_ours, ours = best_of(lambda: read_spikes(path, h, w), 3)
        t_comm, comm = best_of(lambda: community_load_vidar(path, h, w), 2)
        k = 2
        t_py, py = best_of(lambda: python_loop_load(path, h, w, k), 1)
        ok = bool(np.array_equal(comm, ours) and np.array_equal(py, ours[:k]))
    mb = n * h * w / 8 / 1e6
    return {"frames": n, "size": f"{w}x{h}", "read_spikes_s": t_ours, "community_s": t_comm,
            "python_loop_s_scaled": t_py * n / k, "mb_per_s": mb / t_ours,
            "speedup_vs_community": t_comm / t_ours, "speedup_vs_python_loop": t_py * n / k / t_ours,
            "identical": ok}


def micro_freeze_step(run_dir, capture, repeats: int = 8) -> dict:
    """Forward + backward of one train view (deformation field + rasterizer, what a
    deformation-stage step costs) of a trained run with its frozen mask
    (``Model4D.static_mask``) and without, interleaved A/B so that load drift cancels."""
    scene = load_run(run_dir)
    model = scene.model
    mask = model.static_mask
    if mask is None or model.deformation is None:
        return {"error": "run has no frozen mask or no deformation field"}
    frames = sorted(capture.frames, key=lambda f: f.time)
    vt = view_tensors(capture.view(frames[len(frames) // 2]), "cpu")
    params = [p for p in model.parameters() if p.is_floating_point()]
    for p in params:
        p.requires_grad_(True)

    def once(m):
        model.static_mask = m
        t0 = time.perf_counter()
        rgb, alpha, meta, _ = model.render(vt)
        rgb.mean().backward()
        dt = time.perf_counter() - t0
        for p in params:
            p.grad = None
        return dt

    once(mask)
    once(None)
    on, off = [], []
    for _ in range(max(1, repeats)):
        on.append(once(mask))
        off.append(once(None))
    model.static_mask = mask
    med_on, med_off = float(np.median(on)), float(np.median(off))
    return {"frozen_fraction": float(mask.float().mean()), "gaussians": int(mask.shape[0]),
            "step_ms_frozen": med_on * 1e3, "step_ms_unfrozen": med_off * 1e3, "speedup": med_off / med_on}


def warmup() -> float:
    """Compile / load the rasterizer's JIT kernels (forward + backward) before any timed run,
    so that the first configuration does not pay for it. Returns the seconds it took."""
    t0 = time.perf_counter()
    g = torch.Generator().manual_seed(0)
    n = 16
    means = (torch.rand(n, 3, generator=g) - 0.5).requires_grad_(True)
    quats = torch.randn(n, 4, generator=g)
    scales = torch.full((n, 3), 0.1)
    opac = torch.full((n,), 0.5)
    colors = torch.rand(n, 3, generator=g)
    vm = torch.eye(4)[None].clone()
    vm[0, 2, 3] = 3.0
    K = torch.tensor([[[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]]])
    rgb, alpha, meta = rasterization(means, quats, scales, opac, colors, vm, K, 16, 16,
                                     backgrounds=torch.zeros(1, 3))
    (rgb.sum() + alpha.sum() + meta["depths"].sum()).backward()
    return time.perf_counter() - t0
