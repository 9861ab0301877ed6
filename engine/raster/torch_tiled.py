"""Tiled compositing in plain PyTorch (autograd): the fallback when numba is missing, the
path used for tensors on a non-CPU device without gsplat, and the "plain PyTorch"
baseline of ``python -m engine bench-raster``.

Binning is vectorised numpy; tiles are composited in chunks (tiles sorted by list length
so that padding stays small) with the same ``composite_lists`` as the dense reference.
Autograd keeps every chunk's intermediates (~110 bytes per pixel x list entry): the paper's
1080x720 frames with 300k Gaussians are 2e9 such entries, over 24 GiB, so above
``GRAPH_ELEMENTS`` each chunk is checkpointed (its forward recomputed in the backward) and the
graph holds one chunk at a time; below it nothing changes (issue 43).
"""
from __future__ import annotations

import numpy as np
import torch
from torch.utils.checkpoint import checkpoint

from .reference import composite_lists

CHUNK_ELEMENTS = 1 << 22  # pixels x list entries per chunk (bounds autograd memory)
GRAPH_ELEMENTS = 1 << 25  # pixels x list entries of a whole render kept by autograd (~3.7 GB)


def bin_numpy(means2d: np.ndarray, radii_xy: np.ndarray, depths: np.ndarray, width: int,
              height: int, tile_size: int):
    """Vectorised tile binning. means2d [C,N,2], radii_xy [C,N,2], depths [C,N] -> offsets
    [C*T+1] int64, ids [M] int64 (flat c*N+g, front to back per tile), tiles_x, tiles_y."""
    C, N = depths.shape
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n_tiles = tiles_x * tiles_y
    m2d = means2d.reshape(C * N, 2).astype(np.float64)
    rxy = radii_xy.reshape(C * N, 2).astype(np.float64)
    vis = rxy[:, 0] > 0
    cam = np.repeat(np.arange(C), N)
    order = np.lexsort((depths.reshape(-1), cam))  # by camera, then depth
    order = order[vis[order]]
    mx, my = m2d[order, 0], m2d[order, 1]
    rx, ry = rxy[order, 0], rxy[order, 1]
    x0 = np.clip(np.floor((mx - rx - 0.5) / tile_size), 0, tiles_x).astype(np.int64)
    x1 = np.clip(np.floor((mx + rx - 0.5) / tile_size) + 1, 0, tiles_x).astype(np.int64)
    y0 = np.clip(np.floor((my - ry - 0.5) / tile_size), 0, tiles_y).astype(np.int64)
    y1 = np.clip(np.floor((my + ry - 0.5) / tile_size) + 1, 0, tiles_y).astype(np.int64)
    nx = np.maximum(x1 - x0, 0)
    cnt = nx * np.maximum(y1 - y0, 0)
    M = int(cnt.sum())
    rep = np.repeat(np.arange(order.shape[0]), cnt)
    local = np.arange(M) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    nxr = np.maximum(nx[rep], 1)
    tile = (cam[order][rep] * n_tiles + (y0[rep] + local // nxr) * tiles_x + x0[rep] + local % nxr)
    perm = np.argsort(tile, kind="stable")
    ids = order[rep][perm]
    offsets = np.searchsorted(tile[perm], np.arange(C * n_tiles + 1)).astype(np.int64)
    return offsets, ids, tiles_x, tiles_y


def _composite_chunk(pix, m_flat, c_flat, o_flat, f_flat, gidx, valid, alpha_max):
    """One chunk of tiles: gather its lists from the flat tensors and composite them."""
    return composite_lists(pix, m_flat[gidx], c_flat[gidx], o_flat[gidx], f_flat[gidx], valid, alpha_max=alpha_max)


def composite_tiles_torch(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                          feats: torch.Tensor, depths: torch.Tensor, radii_xy: torch.Tensor,
                          width: int, height: int, alpha_max: float = 0.99, tile_size: int = 8
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """Same contract as ``reference.composite_dense`` (radii_xy [C,N,2] per-axis radii)."""
    C, N, D = feats.shape
    dev, dt = feats.device, feats.dtype
    offsets, ids, tiles_x, tiles_y = bin_numpy(
        means2d.detach().cpu().numpy(), radii_xy.cpu().numpy(), depths.detach().cpu().numpy(),
        width, height, tile_size)
    n_tiles = tiles_x * tiles_y
    ts2 = tile_size * tile_size
    m_flat = means2d.reshape(C * N, 2)
    c_flat = conics.reshape(C * N, 3)
    o_flat = opacities.reshape(C * N)
    f_flat = feats.reshape(C * N, D)
    counts = np.diff(offsets)
    recompute = torch.is_grad_enabled() and ts2 * int(ids.shape[0]) > GRAPH_ELEMENTS
    tiles = np.flatnonzero(counts)
    tiles = tiles[np.argsort(counts[tiles], kind="stable")]
    # pixel coordinates of each slot of a tile
    py, px = np.divmod(np.arange(ts2), tile_size)
    out_f = feats.new_zeros(C * height * width, D)
    out_a = feats.new_zeros(C * height * width, 1)
    idx_parts, f_parts, a_parts = [], [], []
    start = 0
    while start < tiles.shape[0]:
        kmax = int(counts[tiles[start]])
        stop = start
        while stop < tiles.shape[0]:
            kmax = int(counts[tiles[stop]])
            if (stop - start + 1) * ts2 * kmax > CHUNK_ELEMENTS and stop > start:
                break
            stop += 1
        chunk = tiles[start:stop]
        kmax = int(counts[chunk].max())
        slot = np.arange(kmax)
        valid = slot[None] < counts[chunk][:, None]                           # [B,K]
        gidx = ids[np.minimum(offsets[chunk][:, None] + slot[None], ids.shape[0] - 1)]
        gidx = torch.from_numpy(np.where(valid, gidx, 0)).to(dev)
        cam, t = np.divmod(chunk, n_tiles)
        ty, tx = np.divmod(t, tiles_x)
        gx = tx[:, None] * tile_size + px[None]                               # [B,P]
        gy = ty[:, None] * tile_size + py[None]
        inside = (gx < width) & (gy < height)
        pix = torch.from_numpy(np.stack([gx + 0.5, gy + 0.5], -1)).to(dev, dt)
        args = (pix, m_flat, c_flat, o_flat, f_flat, gidx, torch.from_numpy(valid).to(dev), alpha_max)
        f, a = checkpoint(_composite_chunk, *args, use_reentrant=False) if recompute else _composite_chunk(*args)
        ins = torch.from_numpy(inside.reshape(-1)).to(dev)
        flat = torch.from_numpy((cam[:, None] * height * width + gy * width + gx).reshape(-1)).to(dev)
        idx_parts.append(flat[ins])
        f_parts.append(f.reshape(-1, D)[ins])
        a_parts.append(a.reshape(-1, 1)[ins])
        start = stop
    if idx_parts:
        idx = torch.cat(idx_parts)
        out_f = out_f.index_copy(0, idx, torch.cat(f_parts))
        out_a = out_a.index_copy(0, idx, torch.cat(a_parts))
    else:  # nothing visible: keep the outputs in the graph (zero gradients)
        z = 0.0 * (m_flat.sum() + c_flat.sum() + o_flat.sum() + f_flat.sum())
        out_f, out_a = out_f + z, out_a + z
    return out_f.reshape(C, height, width, D), out_a.reshape(C, height, width, 1)
