"""numba kernels of :mod:`engine.train.motion.nearest`: exact nearest neighbours on a uniform grid.

The points are counting-sorted by cell (``cell_start`` [n_cells + 1], ``order`` [S]); each
query searches Chebyshev rings of cells around its own (clamped into the grid), ring ``k``
after ring ``k - 1``, and stops once nothing unsearched can be nearer or within
``max_dist``: an unsearched point lies beyond a face of the searched box of cells (one
that is not the grid's border), so at least that face's distance from the query. Distances are float64 sums of squared
float64 coordinate differences, ties go to the lower point index: the same answer as a
brute-force ``argmin`` over that formula. Parallel over queries (each query's answer does
not depend on the others or on thread scheduling).
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from ...numba_cache import install_cache_locator

install_cache_locator(__name__)


@njit(cache=True, nogil=True)
def bin_points(cells, n_cells):
    """Counting sort of point cell ids [S] -> (cell_start [n_cells + 1], order [S])."""
    start = np.zeros(n_cells + 1, np.int64)
    for c in cells:
        start[c + 1] += 1
    for i in range(n_cells):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    order = np.empty(cells.size, np.int64)
    for j in range(cells.size):
        c = cells[j]
        order[fill[c]] = j
        fill[c] += 1
    return start, order


@njit(cache=True, nogil=True, inline="always")
def _scan_cell(c, start, order, points, qx, qy, qz, best, best_j):
    for s in range(start[c], start[c + 1]):
        j = order[s]
        dx = np.float64(points[j, 0]) - qx
        dy = np.float64(points[j, 1]) - qy
        dz = np.float64(points[j, 2]) - qz
        d2 = dx * dx + dy * dy + dz * dz
        if d2 < best or (d2 == best and j < best_j):
            best, best_j = d2, j
    return best, best_j


@njit(cache=True, nogil=True, parallel=True)
def nearest(queries, points, lo, cell, dims, start, order, max_d2, out_idx, out_d2):
    """For each query [M, 3] the index of the nearest of ``points`` [S, 3] with squared
    distance <= ``max_d2`` (-1 if none) and that squared distance (inf if none)."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    for q in prange(queries.shape[0]):
        qx, qy, qz = np.float64(queries[q, 0]), np.float64(queries[q, 1]), np.float64(queries[q, 2])
        # the query's cell, clamped into the grid (in floats first: no integer overflow)
        cx = int(min(max(np.floor((qx - lo[0]) / cell), 0.0), nx - 1.0))
        cy = int(min(max(np.floor((qy - lo[1]) / cell), 0.0), ny - 1.0))
        cz = int(min(max(np.floor((qz - lo[2]) / cell), 0.0), nz - 1.0))
        best, best_j = np.inf, -1
        k = 0
        while True:
            x0, x1 = max(cx - k, 0), min(cx + k, nx - 1)
            y0, y1 = max(cy - k, 0), min(cy + k, ny - 1)
            z0, z1 = max(cz - k, 0), min(cz + k, nz - 1)
            # the shell of ring k (cells at Chebyshev distance k), clipped to the grid
            for ix in range(x0, x1 + 1):
                on_x = ix == cx - k or ix == cx + k
                for iy in range(y0, y1 + 1):
                    if on_x or iy == cy - k or iy == cy + k:
                        for iz in range(z0, z1 + 1):
                            best, best_j = _scan_cell((ix * ny + iy) * nz + iz, start, order, points,
                                                      qx, qy, qz, best, best_j)
                    else:
                        if cz - k >= 0:
                            best, best_j = _scan_cell((ix * ny + iy) * nz + cz - k, start, order, points,
                                                      qx, qy, qz, best, best_j)
                        if k > 0 and cz + k <= nz - 1:
                            best, best_j = _scan_cell((ix * ny + iy) * nz + cz + k, start, order, points,
                                                      qx, qy, qz, best, best_j)
            # every point not searched yet lies beyond one of the searched box's faces that
            # are not the grid's border: at least that face's distance away (less a rounding
            # margin: a coordinate on a cell border may bin either way)
            reach = np.inf
            if x0 > 0:
                reach = min(reach, qx - (lo[0] + x0 * cell))
            if x1 < nx - 1:
                reach = min(reach, lo[0] + (x1 + 1) * cell - qx)
            if y0 > 0:
                reach = min(reach, qy - (lo[1] + y0 * cell))
            if y1 < ny - 1:
                reach = min(reach, lo[1] + (y1 + 1) * cell - qy)
            if z0 > 0:
                reach = min(reach, qz - (lo[2] + z0 * cell))
            if z1 < nz - 1:
                reach = min(reach, lo[2] + (z1 + 1) * cell - qz)
            if reach == np.inf:
                break  # the whole grid searched
            reach = max(reach, 0.0) - cell * 1e-9
            if reach > 0 and (best <= reach * reach or reach * reach > max_d2):
                break
            k += 1
        if best_j >= 0 and best <= max_d2:
            out_idx[q] = best_j
            out_d2[q] = best
        else:
            out_idx[q] = -1
            out_d2[q] = np.inf
