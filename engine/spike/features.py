"""Spike windows around an instant and their texture images (paper Eq. 6-7 inputs).

For a target time ``t`` the window is ``S[T1:T2]`` with ``T1 <= t < T2`` the neighbouring
RGB frame times (Eq. 6). It is split into ``K`` equal sub-windows; each sub-window gives
two texture images (Zhu et al. 2019):

* TFP (texture from playback): mean spike count over the sub-window (x threshold), and
* TFI (texture from interval): threshold / inter-spike interval at the sub-window centre,
  searched inside the whole window.

Both are light estimates in the simulator's units (charge per spike frame). They are
stacked into a float32 tensor ``[K, 2, h, w]`` with the sub-window centre times ``[K]``.
:class:`SpikeWindowCache` computes each RGB interval once and keeps it (a few hundred KB
per interval at the demo's 80x60) so training never re-reads the ``.dat`` file.
"""
from __future__ import annotations

import numpy as np
import torch

from .change import change_from_cache
from .simulate import tfi, tfp

__all__ = ["bracket", "window_textures", "SpikeWindow", "SpikeWindowCache"]


def bracket(times: np.ndarray, t: float) -> tuple[int, float, float]:
    """Index ``k`` and (T1, T2) = (times[k], times[k+1]) with T1 <= t < T2 (clamped to the
    first/last interval). ``times`` sorted ascending, at least two entries."""
    times = np.asarray(times, dtype=np.float64)
    if len(times) < 2:
        raise ValueError("need at least two RGB frame times to bracket an instant")
    k = int(np.searchsorted(times, t, side="right")) - 1
    k = min(max(k, 0), len(times) - 2)
    return k, float(times[k]), float(times[k + 1])


def window_textures(spikes: np.ndarray, k_sub: int, *, threshold: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Spikes [n, h, w] -> textures float32 [K, 2, h, w] (TFP, TFI) and sub-window centre
    positions in [0, 1] (fraction of the window) [K]."""
    s = np.asarray(spikes)
    n = s.shape[0]
    if n == 0:
        raise ValueError("empty spike window")
    k_sub = max(1, min(int(k_sub), n))
    edges = np.linspace(0, n, k_sub + 1).round().astype(int)
    out = np.empty((k_sub, 2, s.shape[1], s.shape[2]), dtype=np.float32)
    centres = np.empty(k_sub, dtype=np.float32)
    for i in range(k_sub):
        a, b = edges[i], max(edges[i + 1], edges[i] + 1)
        out[i, 0] = tfp(s[a:b], None, threshold=threshold)
        mid = (a + b - 1) // 2
        out[i, 1] = tfi(s, mid, threshold=threshold)
        centres[i] = (a + b) / 2.0 / n
    return out, centres


class SpikeWindow:
    """Cached textures of one RGB interval: ``tex`` [K, 2, h, w], ``times`` [K] (seconds),
    ``t1``, ``t2`` (the bracketing RGB times)."""

    __slots__ = ("tex", "times", "t1", "t2", "index")

    def __init__(self, tex: torch.Tensor, times: torch.Tensor, t1: float, t2: float, index: int):
        self.tex, self.times, self.t1, self.t2, self.index = tex, times, t1, t2, index

    def to(self, device) -> "SpikeWindow":
        return SpikeWindow(self.tex.to(device), self.times.to(device), self.t1, self.t2, self.index)


class SpikeWindowCache:
    """Per-RGB-interval spike textures of a stream, computed once.

    ``rgb_times``: the RGB frame instants (any camera; sorted, deduplicated here).
    ``k_sub``: sub-windows per interval (tokens for the attention).
    ``window(t)`` -> :class:`SpikeWindow` of the interval holding ``t``.
    """

    def __init__(self, stream, rgb_times, *, k_sub: int = 8, threshold: float = 1.0, device="cpu"):
        self.stream = stream
        times = np.unique(np.asarray(rgb_times, dtype=np.float64))
        if len(times) < 2:
            raise ValueError("SpikeWindowCache needs at least two RGB frame times")
        self.rgb_times = times
        self.k_sub = int(k_sub)
        self.threshold = float(threshold)
        self.device = device
        self._cache: dict[int, SpikeWindow] = {}

    def __len__(self) -> int:
        return len(self._cache)

    @property
    def height(self) -> int:
        return int(self.stream.height) if self.stream is not None else self._size[0]

    @property
    def width(self) -> int:
        return int(self.stream.width) if self.stream is not None else self._size[1]

    def interval(self, t: float) -> int:
        return bracket(self.rgb_times, t)[0]

    def window(self, t: float) -> SpikeWindow:
        k, t1, t2 = bracket(self.rgb_times, t)
        w = self._cache.get(k)
        if w is None:
            spikes, _ = self.stream.frames_between(t1, t2)
            if spikes.shape[0] == 0:  # interval outside the stream: an empty (zero) window
                tex = np.zeros((self.k_sub, 2, self.height, self.width), np.float32)
                frac = (np.arange(self.k_sub, dtype=np.float32) + 0.5) / self.k_sub
            else:
                tex, frac = window_textures(spikes, self.k_sub, threshold=self.threshold)
            times = t1 + frac.astype(np.float64) * (t2 - t1)
            w = SpikeWindow(torch.from_numpy(tex).to(self.device),
                            torch.as_tensor(times, dtype=torch.float32, device=self.device), t1, t2, k)
            self._cache[k] = w
        return w

    def change(self, block: int = 4):
        """:class:`engine.spike.change.SpikeChange` of every interval (computed once)."""
        ch = getattr(self, "_change", None)
        if ch is None or ch.block != int(block):
            ch = self._change = change_from_cache(self, block=int(block))
        return ch

    def frames_in(self, k: int) -> int:
        """Spike frames in RGB interval ``k`` (from the stream, or as stored)."""
        if self.stream is None:
            return int(self._frames[k])
        a, b = self.stream.index_range(self.rgb_times[k], self.rgb_times[k + 1])
        return int(b - a)

    # --- stored with a run (issue 11): a run renders without its capture ------------------
    def state(self) -> dict:
        """Every interval's textures, as tensors (computed first where missing): what the
        fine branch reads at render time, so a checkpoint needs no spike stream."""
        self.precompute()
        n = len(self.rgb_times) - 1
        wins = [self._cache[k] for k in range(n)]
        return {"rgb_times": torch.as_tensor(self.rgb_times, dtype=torch.float64),
                "k_sub": self.k_sub, "threshold": self.threshold,
                "height": self.height, "width": self.width,
                "frames": torch.as_tensor([self.frames_in(k) for k in range(n)], dtype=torch.int64),
                "tex": torch.stack([w.tex.cpu() for w in wins]),
                "times": torch.stack([w.times.cpu() for w in wins])}

    @classmethod
    def from_state(cls, state: dict, device="cpu") -> "SpikeWindowCache":
        """A cache of stored windows (:meth:`state`); ``stream`` is None."""
        c = cls.__new__(cls)
        c.stream = None
        c.rgb_times = np.asarray(state["rgb_times"], dtype=np.float64)
        c.k_sub = int(state["k_sub"])
        c.threshold = float(state["threshold"])
        c.device = device
        c._size = (int(state["height"]), int(state["width"]))
        c._frames = [int(x) for x in state["frames"]]
        tex, times = state["tex"], state["times"]
        c._cache = {k: SpikeWindow(tex[k].to(device), times[k].to(device), float(c.rgb_times[k]),
                                   float(c.rgb_times[k + 1]), k) for k in range(len(c.rgb_times) - 1)}
        return c

    def precompute(self) -> "SpikeWindowCache":
        for k in range(len(self.rgb_times) - 1):
            self.window(0.5 * (self.rgb_times[k] + self.rgb_times[k + 1]))
        return self
