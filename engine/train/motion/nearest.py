"""Exact nearest neighbours of 3D points within a distance, on a uniform grid (issue 13).

:func:`engine.train.motion.scene_flow.propagate_to_hidden` gives each hidden Gaussian the motion
of its nearest decided one within ``max_dist``. A dense ``torch.cdist`` over ~8k x 12k
points cost ~0.2-1.2 s per admitted RGB instant (six per run, up to ~20 % of a 200-step
profile); a grid search in numpy was 18x slower than that (a Python loop over cells). The
numba search here (:mod:`engine.train.motion._nearest_kernels`) bins the points into cells of
width ``max_dist`` (so one ring of cells around a query holds every candidate) and is
exact: it returns what a brute-force ``argmin`` of float64 squared distances returns, ties
to the lower index. (``torch.cdist`` computes ``|x|^2 + |y|^2 - 2 x.y`` in float32, so
between near-equal neighbours it could pick either.) scipy's cKDTree would do the same but
is not a dependency (Blender would need its wheel).
"""
from __future__ import annotations

import math

import numpy as np

from ...numba_cache import LazyKernels

KERNELS = LazyKernels(__package__, "_nearest_kernels")

MAX_CELLS = 1 << 21  # the grid's cell count at most (its start array: 16 MiB)


def _grid(points: np.ndarray, max_dist: float):
    """(lower corner [3], cell width, cells per axis [3]) for ``points`` [S, 3]."""
    lo = points.min(0).astype(np.float64)
    span = points.max(0).astype(np.float64) - lo
    # about as many cells as points; narrower (max_dist) when that bounds the search: then
    # one ring of cells around a query covers every candidate
    cell = max(float(span.max()), 1e-30)
    limit = min(MAX_CELLS, max(len(points), 1))
    while cell > 1e-30 and np.prod(np.floor(span / (cell / 2.0)) + 1) <= limit:
        cell /= 2.0
    if math.isfinite(max_dist) and max_dist > 0:
        cell = max_dist * (1.0 + 1e-6)
        while np.prod(np.floor(span / cell) + 1) > MAX_CELLS:
            cell *= 2.0
    dims = (np.floor(span / cell) + 1).astype(np.int64)
    return lo, cell, dims


def nearest_within(queries, points, max_dist: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
    """For each of ``queries`` [M, 3] the index into ``points`` [S, 3] of its nearest point
    at most ``max_dist`` away (-1 where none) and that distance (inf where none): int64 [M],
    float64 [M]. Exact (module docstring); any finite float positions."""
    q = np.ascontiguousarray(np.asarray(queries, np.float32).reshape(-1, 3))
    p = np.ascontiguousarray(np.asarray(points, np.float32).reshape(-1, 3))
    idx = np.full(len(q), -1, np.int64)
    d2 = np.full(len(q), np.inf)
    if len(q) == 0 or len(p) == 0 or not max_dist >= 0:
        return idx, np.sqrt(d2)
    if not (np.isfinite(q).all() and np.isfinite(p).all()):
        raise ValueError("nearest_within: non-finite positions")
    k = KERNELS.load()
    if k is None:
        raise RuntimeError(f"nearest_within needs numba: {KERNELS.unavailable_reason()}")
    lo, cell, dims = _grid(p, float(max_dist))
    ijk = np.minimum(np.floor((p.astype(np.float64) - lo) / cell).astype(np.int64), dims - 1)
    cells = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    start, order = k.bin_points(cells, int(np.prod(dims)))
    max_d2 = float(max_dist) ** 2 if math.isfinite(max_dist) else math.inf
    k.nearest(q, p, lo, float(cell), dims, start, order, max_d2, idx, d2)
    # ``max_dist`` on the distance itself, as the dense search compared it
    far = np.sqrt(d2) > max_dist
    idx[far], d2[far] = -1, np.inf
    return idx, np.sqrt(d2)


def warmup() -> float:
    """Compile (first run on a machine) or load the kernels now; seconds taken."""
    import time

    t0 = time.perf_counter()
    if KERNELS.load() is not None:
        pts = np.random.default_rng(0).uniform(size=(9, 3)).astype(np.float32)
        nearest_within(pts[:4], pts[4:], 0.5)
    return time.perf_counter() - t0
