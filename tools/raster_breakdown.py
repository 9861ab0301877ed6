"""``python -m tools bench-raster --breakdown``: where one cpu forward+backward goes.

Times each stage of ``rasterization(..., backend="cpu")`` plus ``.backward()`` by wrapping
the numba entry points (and the Python helpers around them) with timers for the duration
of the measurement: wall time and the process's CPU time over all its threads, so
``cpu / wall`` says how well a stage uses the numba threads (2 on this machine: a perfectly
parallel stage on idle cores shows ~2, a serial one 1; under load both shrink). "torch
glue" is what is left of the whole forward+backward: the torch ops around the kernels
(colours, casts, autograd bookkeeping, the loss) and Python overhead.
"""
from __future__ import annotations

import statistics
import time
from contextlib import contextmanager

import torch

from engine.raster import cpu as raster_cpu
from engine.raster import rasterization

# (object, attribute, stage): the kernels module's entry points and cpu.py's helpers.
# A stage listed with a parent is part of it (shown indented, not counted twice).
STAGES = [
    ("kernels", "project_fwd", "projection fwd", None),
    ("cpu", "bin_gaussians", "binning (all)", None),
    ("cpu", "depth_order", "depth sort", "binning (all)"),
    ("kernels", "bin_gaussians", "tile lists", "binning (all)"),
    ("kernels", "pack_split", "pack", None),
    ("kernels", "rasterize_fwd", "composite fwd", None),
    ("kernels", "finish_image", "background + depth fwd", None),
    ("kernels", "finish_grads", "background + depth bwd", None),
    ("kernels", "rasterize_bwd", "composite bwd", None),
    ("kernels", "scatter_grads", "gradient scatter", None),
    ("kernels", "project_bwd", "projection bwd", None),
]


@contextmanager
def _timed(acc: dict):
    """Wrap the stages' functions so that each call adds (wall, cpu) seconds to acc."""
    owners = {"kernels": raster_cpu._load(), "cpu": raster_cpu}
    saved = []

    def wrap(fn, label):
        def timed(*a, **kw):
            c0, t0 = time.process_time(), time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                w, c = acc.get(label, (0.0, 0.0))
                acc[label] = (w + time.perf_counter() - t0, c + time.process_time() - c0)
        return timed

    try:
        for owner, attr, label, _ in STAGES:
            obj = owners[owner]
            if hasattr(obj, attr):
                saved.append((obj, attr, getattr(obj, attr)))
                setattr(obj, attr, wrap(getattr(obj, attr), label))
        yield
    finally:
        for obj, attr, fn in reversed(saved):
            setattr(obj, attr, fn)


def breakdown(scene, width: int, height: int, repeats: int, sh_degree=None) -> list[tuple]:
    """Median (stage, wall ms, cpu ms) over ``repeats`` forward+backward passes."""
    params = [a.clone().requires_grad_(True) for a in scene[:5]]

    def fwd_bwd():
        c, a, m = rasterization(*params, scene[5], scene[6], width, height, sh_degree=sh_degree,
                                backend="cpu")
        m["means2d"].retain_grad()
        (c.sum() + 0.5 * a.sum() + 0.1 * m["depths"].sum()).backward()
        for p in params:
            p.grad = None

    fwd_bwd()  # compile / cache load outside the timing
    runs = []
    for _ in range(max(1, repeats)):
        acc: dict = {}
        with _timed(acc):
            c0, t0 = time.process_time(), time.perf_counter()
            fwd_bwd()
            total = (time.perf_counter() - t0, time.process_time() - c0)
        top = [acc.get(label, (0.0, 0.0)) for _, _, label, parent in STAGES if parent is None]
        acc["torch glue + Python"] = (total[0] - sum(w for w, _ in top),
                                      total[1] - sum(c for _, c in top))
        acc["total"] = total
        runs.append(acc)
    labels = [s[2] for s in STAGES] + ["torch glue + Python", "total"]
    out = []
    for label in labels:
        w = statistics.median(r.get(label, (0.0, 0.0))[0] for r in runs) * 1e3
        c = statistics.median(r.get(label, (0.0, 0.0))[1] for r in runs) * 1e3
        out.append((label, w, c))
    return out


def print_breakdown(rows: list[tuple], width: int, height: int, n: int) -> None:
    parents = {s[2]: s[3] for s in STAGES}
    total_cpu = rows[-1][2]
    print(f"\ncpu forward+backward by stage, {width}x{height}, N={n} (median; cpu = process CPU "
          f"time, all threads; cpu/wall ~ threads kept busy):")
    print("| stage | wall ms | cpu ms | cpu/wall | share of cpu |")
    print("|---|---|---|---|---|")
    for label, w, c in rows:
        name = ("  " + label) if parents.get(label) else label
        ratio = f"{c / w:.2f}" if w > 1e-6 else "-"
        print(f"| {name} | {w:.1f} | {c:.1f} | {ratio} | {100 * c / max(total_cpu, 1e-9):.0f} % |")


def run(make_scene, sizes, counts, repeats: int, sh_degree=None) -> None:
    if not raster_cpu.available():
        print("numba unavailable: no breakdown")
        return
    torch.set_grad_enabled(True)
    for (w, h) in sizes:
        for n in counts:
            rows = breakdown(make_scene(n, w, h, sh_degree=sh_degree), w, h, repeats, sh_degree)
            print_breakdown(rows, w, h, n)
