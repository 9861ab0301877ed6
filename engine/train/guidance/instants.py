"""Training instants across the whole capture (paper Eq. 21-23).

* RGB instants ``t in {T1, T2, ...}`` carry the frame loss (beta = 1, Eq. 23);
* between-frame instants ``t in (T_k, T_k+1)`` carry the spike loss (co-located view) and
  the block colour loss (every training view, Eq. 18-20) — only where the spike stream
  covers the interval when the spike loss is wanted.

:class:`InstantSampler` draws them: with probability ``p_between`` a between-frame instant
(intervals visited in shuffled rounds so every interval is seen equally often; ``eps``
uniform in ``[margin, 1 - margin]``, optionally snapped to a spike frame time), otherwise
an RGB instant (also in shuffled rounds).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Instant", "InstantSampler"]


@dataclass(frozen=True)
class Instant:
    """One training instant. ``kind`` 'rgb' (``frame`` = index into ``rgb_times``) or
    'between' (``interval`` k with ``t1 = rgb_times[k] < time < t2 = rgb_times[k+1]``,
    ``eps = (time - t1) / (t2 - t1)``, Eq. 19)."""

    kind: str
    time: float
    frame: int | None = None
    interval: int | None = None
    t1: float | None = None
    t2: float | None = None
    eps: float | None = None

    @property
    def is_rgb(self) -> bool:
        return self.kind == "rgb"


class InstantSampler:
    def __init__(self, rgb_times, *, p_between: float = 0.5, coverage: tuple[float, float] | None = None,
                 margin: float = 0.05, snap_hz: float | None = None, snap_t0: float = 0.0, seed: int = 0):
        """``rgb_times``: RGB frame instants (sorted, deduplicated here). ``coverage``:
        (t_start, t_end) of the spike stream; intervals not fully inside get no
        between-frame instants (None: all intervals). ``snap_hz``: round between-frame
        instants to the spike frame grid ``snap_t0 + i / snap_hz``."""
        self.rgb_times = np.unique(np.asarray(rgb_times, dtype=np.float64))
        if len(self.rgb_times) == 0:
            raise ValueError("InstantSampler needs at least one RGB frame time")
        self.p_between = float(p_between)
        self.margin = float(margin)
        if not 0.0 <= self.margin < 0.5:
            raise ValueError("margin must be in [0, 0.5)")
        self.snap_hz = snap_hz
        self.snap_t0 = float(snap_t0)
        self.rng = np.random.default_rng(seed)
        ivs = []
        for k in range(len(self.rgb_times) - 1):
            a, b = self.rgb_times[k], self.rgb_times[k + 1]
            if coverage is None or (a >= coverage[0] - 1e-9 and b <= coverage[1] + 1e-9):
                ivs.append(k)
        self.intervals = np.asarray(ivs, dtype=np.int64)
        self._rgb_queue: list[int] = []
        self._iv_queue: list[int] = []

    def restrict(self, keep) -> int:
        """Keep only the between-frame intervals ``k`` in ``keep`` (e.g. the spike windows
        that show change, :mod:`engine.spike.change`). Returns how many were dropped."""
        keep = {int(k) for k in keep}
        before = len(self.intervals)
        self.intervals = np.asarray([k for k in self.intervals.tolist() if k in keep], dtype=np.int64)
        self._iv_queue = []
        return before - len(self.intervals)

    @property
    def has_between(self) -> bool:
        return len(self.intervals) > 0

    def _next(self, queue: list[int], pool: np.ndarray) -> int:
        if not queue:
            queue.extend(self.rng.permutation(pool).tolist())
        return int(queue.pop())

    def rgb_instant(self) -> Instant:
        i = self._next(self._rgb_queue, np.arange(len(self.rgb_times)))
        return Instant("rgb", float(self.rgb_times[i]), frame=i)

    def between_instant(self, interval: int | None = None, eps: float | None = None,
                        max_time: float | None = None) -> Instant | None:
        """A between-frame instant (interval from the shuffled rounds unless given).

        ``max_time``: only instants up to this time (the run's time curriculum: the
        window of admitted capture time grows continuously, so in-between instants are
        admitted before the next RGB frame and lead the motion towards it); returns None
        when no covered interval starts before it."""
        if not self.has_between:
            raise ValueError("no between-frame interval is covered")
        hi_eps = 1.0 - self.margin
        if max_time is not None and interval is None:
            lead = 1.0 / self.snap_hz if self.snap_hz else 0.0
            allowed = self.intervals[self.rgb_times[self.intervals] + lead < max_time]
            if len(allowed) == 0:
                return None
            if len(allowed) < len(self.intervals):  # the curriculum's front: uniform over what is open
                k = int(allowed[self.rng.integers(len(allowed))])
            else:
                k = self._next(self._iv_queue, self.intervals)
            t1, t2 = float(self.rgb_times[k]), float(self.rgb_times[k + 1])
            hi_eps = min(hi_eps, (max_time - t1) / (t2 - t1))
        else:
            k = self._next(self._iv_queue, self.intervals) if interval is None else int(interval)
        t1, t2 = float(self.rgb_times[k]), float(self.rgb_times[k + 1])
        if eps is None:
            lo_eps = min(self.margin, hi_eps)
            eps = float(self.rng.uniform(lo_eps, max(lo_eps, hi_eps)))
        t = t1 + eps * (t2 - t1)
        if self.snap_hz:
            t = self.snap_t0 + round((t - self.snap_t0) * self.snap_hz) / self.snap_hz
            t = min(max(t, t1 + 1.0 / self.snap_hz), t2 - 1.0 / self.snap_hz)
            eps = (t - t1) / (t2 - t1)
        return Instant("between", float(t), interval=k, t1=t1, t2=t2, eps=float(eps))

    def sample(self) -> Instant:
        if self.has_between and self.rng.random() < self.p_between:
            return self.between_instant()
        return self.rgb_instant()

    def between_grid(self, per_interval: int) -> list[Instant]:
        """Evenly spaced between-frame instants (``per_interval`` per covered interval),
        e.g. 9 for 30 -> 300 FPS."""
        out = []
        for k in self.intervals:
            for j in range(1, per_interval + 1):
                out.append(self.between_instant(int(k), j / (per_interval + 1)))
        return out
