"""Where and when the spike stream shows change: skip spike windows with nothing new.

Between two RGB frames the spike stream only adds information where the light *changes*
inside the window ``S[T1:T2]``; a static window is already described by the RGB frames at
its ends. This module measures that change once per run from the per-sub-window spike
rates the fine branch already computes (TFP images of :class:`engine.spike.features.
SpikeWindowCache`, so no extra decoding):

* per interval ``k`` and block (``block x block`` spike pixels), the change statistic is
  ``d = max_j |r_j - mean_j r_j|`` over the ``K`` sub-window rates ``r_j`` (spikes per
  pixel-frame, block-averaged);
* noise: with integrate-and-fire and a random phase, a static pixel's count over ``L``
  frames takes one of two neighbouring integers, so its variance is at most 1/4 and the
  block-mean rate has standard deviation at most ``0.5 / (L sqrt(B))`` (``B`` pixels);
  shot noise and a real sensor's extra noise are covered by an empirical floor
  (``q x`` the median statistic over all blocks and intervals -- most of a scene is
  static, and for pure noise the median of ``d`` is about 2 sigma);
* a block has *changed* when ``d > max(z sigma, q median(d))``; an interval with no
  changed block is *static*.

Uses (:mod:`engine.train.guidance.spike_guidance`): between-frame instants are drawn only in intervals
that changed (a capture that never changes costs nothing beyond RGB training), and the
fine-scale feature is gated by the (dilated) change map at each Gaussian's projection, so
static regions receive no spike-driven motion (and do not flicker).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["SpikeChange", "block_change_statistic", "detect_change", "change_from_cache"]


def block_change_statistic(rates: np.ndarray, block: int) -> np.ndarray:
    """Sub-window rates [K, h, w] -> change statistic [ceil(h/block), ceil(w/block)]:
    ``max_j |r_j - mean_j r_j|`` of block-averaged rates (edge blocks average what they have)."""
    r = torch.as_tensor(np.asarray(rates, dtype=np.float32))
    if r.ndim != 3 or r.shape[0] < 1:
        raise ValueError(f"rates must be [K, h, w], got shape {tuple(r.shape)}")
    b = max(1, int(block))
    pooled = F.avg_pool2d(r[None], b, stride=b, ceil_mode=True, count_include_pad=False)[0]  # [K, hb, wb]
    return (pooled - pooled.mean(0, keepdim=True)).abs().amax(0).numpy()


@dataclass
class SpikeChange:
    """Change maps of every RGB interval of a spike stream.

    ``statistic`` [I, hb, wb] float32, ``changed`` [I, hb, wb] bool, ``threshold`` (rate
    units), ``sigma`` (theoretical noise of a static block), ``block`` (pixels),
    ``shape`` (h, w) of the spike frames.
    """

    statistic: np.ndarray
    changed: np.ndarray
    threshold: float
    sigma: float
    block: int
    shape: tuple[int, int]
    _unions: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def num_intervals(self) -> int:
        return int(self.changed.shape[0])

    @property
    def changed_fraction(self) -> np.ndarray:
        """[I]: fraction of blocks that changed in each interval."""
        return self.changed.reshape(self.num_intervals, -1).mean(1)

    @property
    def active_intervals(self) -> np.ndarray:
        """Indices of intervals with at least one changed block."""
        return np.nonzero(self.changed.reshape(self.num_intervals, -1).any(1))[0]

    def summary(self) -> dict:
        return {"intervals": self.num_intervals, "active": int(len(self.active_intervals)),
                "mean_changed_fraction": round(float(self.changed_fraction.mean()), 4) if self.num_intervals else 0.0,
                "threshold": float(self.threshold), "sigma": float(self.sigma), "block": int(self.block)}

    def gate_map(self, interval: int, dilate: int = 1) -> torch.Tensor:
        """Float [h, w] in {0, 1} at spike resolution: 1 where a block of ``interval`` (or
        one within ``dilate`` blocks of it: motion blurs across block borders) changed."""
        m = torch.as_tensor(self.changed[int(interval)], dtype=torch.float32)[None, None]
        if dilate > 0:
            m = F.max_pool2d(m, 2 * dilate + 1, stride=1, padding=dilate)
        h, w = self.shape
        up = m.repeat_interleave(self.block, 2).repeat_interleave(self.block, 3)[..., :h, :w]
        return up[0, 0]

    def union_map(self, dilate: int = 1) -> torch.Tensor:
        """Float [h, w]: 1 where any interval changed (dilated as in :meth:`gate_map`); computed
        once per ``dilate`` (it is sampled at every render)."""
        if dilate not in self._unions:
            self._unions[dilate] = torch.stack([self.gate_map(k, dilate) for k in range(self.num_intervals)]).amax(0)
        return self._unions[dilate]

    def gate(self, interval: int | None, grid: torch.Tensor, dilate: int = 1) -> torch.Tensor:
        """Per-point gate [N] in [0, 1]: the (dilated) change map of ``interval`` (None: of
        any interval, :meth:`union_map`) sampled bilinearly at ``grid`` [N, 2]
        (``grid_sample`` coordinates, align_corners False); 0 outside the spike view."""
        m = self.union_map(dilate) if interval is None else self.gate_map(interval, dilate)
        g = m.to(grid.device, grid.dtype)[None, None]
        s = F.grid_sample(g, grid.reshape(1, 1, -1, 2), mode="bilinear", padding_mode="zeros", align_corners=False)
        return s.reshape(-1)


def detect_change(window_rates, frames_per_window, *, block: int = 4, z: float = 6.0, q: float = 3.0) -> SpikeChange:
    """Change maps from per-interval sub-window rates.

    ``window_rates``: list of [K, h, w] arrays (spikes per pixel-frame of each of the ``K``
    sub-windows of an interval); ``frames_per_window``: spike frames per interval (list or
    int). ``z``: theoretical-noise multiplier; ``q``: multiplier of the median statistic.
    """
    rates = [np.asarray(r, dtype=np.float32) for r in window_rates]
    if not rates:
        raise ValueError("no spike windows to analyse")
    h, w = rates[0].shape[-2:]
    n = np.broadcast_to(np.asarray(frames_per_window, dtype=np.float64), (len(rates),))
    stats = np.stack([block_change_statistic(r, block) for r in rates])
    sig = []
    for r, nf in zip(rates, n):
        L = max(1.0, float(nf) / max(1, r.shape[0]))  # frames per sub-window
        sig.append(0.5 / (L * np.sqrt(float(block * block))))
    sigma = float(max(sig))
    finite = stats[np.isfinite(stats)]
    med = float(np.median(finite)) if finite.size else 0.0
    threshold = max(z * sigma, q * med)
    changed = ~(stats <= threshold)  # NaN counts as change (never skip on bad data)
    return SpikeChange(stats.astype(np.float32), changed, float(threshold), sigma, int(block), (int(h), int(w)))


def change_from_cache(cache, *, block: int = 4, z: float = 6.0, q: float = 3.0) -> SpikeChange:
    """:func:`detect_change` over every interval of a :class:`engine.spike.features.
    SpikeWindowCache` (its TFP images / threshold are the sub-window rates)."""
    rates, frames = [], []
    times = cache.rgb_times
    for k in range(len(times) - 1):
        win = cache.window(0.5 * (times[k] + times[k + 1]))
        rates.append(win.tex[:, 0].cpu().numpy() / max(cache.threshold, 1e-12))
        frames.append(max(1, cache.frames_in(k)))
    return detect_change(rates, frames, block=block, z=z, q=q)
