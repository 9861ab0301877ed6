"""Optical flow between two grey images reconstructed from spikes (issue 11): the pairs the
spike-view flow term (engine.train.guidance.spike_flow) supervises the curves with.

A pair is OpenCV's DIS flow both ways on the 8-bit images (one shared scale and a gamma) and
the forward-backward check that keeps the pixels where they agree. A **warm start** (``init``)
starts both flows from a pair computed one step closer in time, so a large displacement is
found as a chain of small refinements while each flow still compares the two images
themselves (no error accumulates as in chaining flows end to end). Measured on the fast
scene's ball (~27 spike px per RGB interval, its grey texture faint; measured per object,
the 15 grid instants of every interval against the ground-truth motion of its visible surface
points): at the far half of an interval the end-point error on pixels that pass the check is
5.8 px with the warm start against 14.6 px from zero (|motion| 16-17 px), 80 % of them pass
against 60 %, and 7 % are worse than no flow against 42 %; on ``between`` (cube, ball,
turntable: a few px) the two are equal within 0.1 px. DIS's patch mean normalisation is off
when warm: the ball's centre error 0.15 of its motion against 0.21 with it (16 steps).

Shapes: grey images [h, w] float (linear luminance), flows [h, w, 2] (x, y spike px) with
``a(p) ~ b(p + flow(p))``, validity bool [h, w].
"""
from __future__ import annotations

import cv2
import numpy as np

from ..motion.scene_flow import dense_flow

__all__ = ["gray_to_u8", "forward_backward_valid", "flow_pair", "warm_flow_pair", "PARALLEL_PAIR", "RecentGreys"]


class RecentGreys:
    """The ``capacity`` most recently used grey images by spike frame, least recently used
    first out; ``make(k)`` builds frame ``k``'s on a miss (deterministic: an evicted one asked
    for again is the same array). A grey image is needed while its flows are computed (each
    grid instant by the chains from both ends of its interval), never after; the flow term kept
    all of them: ~0.4 MB each at 400 x 250, 1.1 GB over a 3 s capture's 2,790 instants."""

    def __init__(self, make, capacity: int = 64):
        self.make, self.capacity = make, max(1, int(capacity))
        self._items: dict[int, np.ndarray] = {}  # insertion order = least recently used first

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, k: int) -> bool:
        return k in self._items

    def __call__(self, k: int) -> np.ndarray:
        hit = self._items.pop(k, None)
        if hit is None:
            hit = self.make(k)
            while len(self._items) >= self.capacity:
                self._items.pop(next(iter(self._items)))
        self._items[k] = hit
        return hit


def gray_to_u8(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two linear-luminance images [h, w] -> uint8 with one shared scale (the 99.5th
    percentile of both) and a 1/2.2 gamma, so dark texture keeps contrast for the flow."""
    hi = float(np.percentile(np.concatenate([a.ravel(), b.ravel()]), 99.5)) or 1.0
    enc = lambda x: (np.clip(x / hi, 0.0, 1.0) ** (1.0 / 2.2) * 255.0 + 0.5).astype(np.uint8)  # noqa: E731
    return enc(a), enc(b)


def forward_backward_valid(fw: np.ndarray, bw: np.ndarray, tol_px: float = 0.5, tol_rel: float = 0.1) -> np.ndarray:
    """bool [h, w]: pixels whose forward flow lands inside the image and comes back with the
    backward flow: ``|fw(p) + bw(p + fw(p))| <= tol_px + tol_rel (|fw| + |bw(p + fw)|)``."""
    h, w = fw.shape[:2]
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    mx, my = gx + fw[..., 0], gy + fw[..., 1]
    back = cv2.remap(bw, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    err = np.linalg.norm(fw + back, axis=-1)
    mag = np.linalg.norm(fw, axis=-1) + np.linalg.norm(back, axis=-1)
    inside = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
    return inside & (err <= tol_px + tol_rel * mag)


# True: flow_pair runs the backward flow on a second thread while this one runs the forward flow
# (OpenCV releases the GIL; each thread has its own DIS object, scene_flow.REUSE_DIS): the same
# flows, in about half the wall time of a pair when a core is free, the same CPU time. The flows are
# most of what the spike-view flow term costs (~15 % of a guided step in a 200-step fast run, measured).
# False: one after the other (bench-step's "stepcost-before" variant)
PARALLEL_PAIR = True
_PAIR_POOL: list = []  # one lazily started worker thread, shared by the process's runs


def _pair_pool():
    if not _PAIR_POOL:
        from concurrent.futures import ThreadPoolExecutor

        _PAIR_POOL.append(ThreadPoolExecutor(max_workers=1, thread_name_prefix="bt4d-flow"))
    return _PAIR_POOL[0]


def warm_flow_pair(gray_a: np.ndarray, gray_b: np.ndarray, init: tuple | None = None, *, upsample: int = 2,
                   tol_px: float = 0.5, parallel: bool | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(flow a -> b, flow b -> a, valid bool [h, w]) between two linear grey images [h, w].
    ``init``: (forward, backward) flows to start from (a warm start, mean normalisation off),
    e.g. this function's flows to the instant one step closer to ``a``; None: from zero.
    ``parallel``: the backward flow on the pair thread (None: :data:`PARALLEL_PAIR`)."""
    a8, b8 = gray_to_u8(gray_a, gray_b)
    f0, b0 = (None, None) if init is None else init
    kw = {} if init is None else {"mean_normalization": False}
    if PARALLEL_PAIR if parallel is None else parallel:
        back = _pair_pool().submit(dense_flow, b8, a8, upsample, 0, b0, **kw)
        fw = dense_flow(a8, b8, upsample, 0, f0, **kw)
        bw = back.result()
    else:
        fw = dense_flow(a8, b8, upsample, 0, f0, **kw)
        bw = dense_flow(b8, a8, upsample, 0, b0, **kw)
    return fw, bw, forward_backward_valid(fw, bw, tol_px)


def flow_pair(gray_a: np.ndarray, gray_b: np.ndarray, *, upsample: int = 2, tol_px: float = 0.5
              ) -> tuple[np.ndarray, np.ndarray]:
    """(flow a -> b [h, w, 2], valid bool [h, w]) between two linear grey images [h, w]."""
    fw, _, valid = warm_flow_pair(gray_a, gray_b, None, upsample=upsample, tol_px=tol_px)
    return fw, valid
