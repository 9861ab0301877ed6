"""The spike-view flow term's flows (issue 11), cached per (reference instant, between instant)
pair and computed on a background worker ahead of the steps that need them (issue 13).

A flow depends on the spike stream only (grey images reconstructed from the spikes, OpenCV's
DIS both ways, the forward-backward check: engine.train.guidance.spike_flow_pairs), never on the
model, so it is a data loader's work. The term asks for pairs at the grid instants of the RGB
intervals the time curriculum has admitted, and its interval fit asks for every pair of an
interval at once (both chains: from the left end to the last grid instant and from the right
end to the first). :meth:`FlowCache.prefetch` queues those chains' pairs (one job each, in
chain order) for the intervals admitted and ``spike_flow_prefetch`` intervals beyond, on one
:class:`engine.train.guidance.background.PriorityWorker`; a pair a step needs before the worker got to it
jumps the queue, and the step waits for the pair being computed at most, then for its own.

Every flow is computed on that one thread, by the same code in the same order along its chain
(each grid instant's flow warm-started from the one a step closer to its RGB instant), so the
cache holds the very arrays an inline computation gives (``tests/test_spike_flow.py``: equal
flows and a bit-identical run). ``spike_flow_prefetch = 0`` computes inline, in the step, as
before. Measured (docs/experiments/benchmark-history.md "The flows computed ahead of the steps"): inline, the flows
were ~2 ms
of a demo guided step (~6 %), each chain a ~150 ms stall of the step that first needed it. Ahead,
on a worker at normal priority, 1000 demo steps took +1.7 % wall time on this 2-core machine (six
alternated pairs: the static stage paid what the guided stage saved); on the worker at nice
:data:`WORKER_NICE`, both flows of a pair on its thread, -5.4 % (16 pairs, 13 faster).

Shapes: cached flow float16 [h, w, 2] (spike px), valid uint8 [h, w, 1]; ``sample_map`` reads
both as float32.
"""
from __future__ import annotations

import numpy as np
import torch

from ..frames.baselines import spike_to_gray
from .background import PriorityWorker
from .spike_flow_pairs import RecentGreys, warm_flow_pair

__all__ = ["GRAY_CACHE", "FLOW_DTYPE", "WORKER_NICE", "FlowCache"]

# the spike view's grey images: TFP over GRAY_WINDOW spike frames; FLOW_STEPS between instants per RGB
# interval with a cached flow; DIS on the grey images upsampled UPSAMPLE times (1 loses on all six runs);
# forward-backward tolerance FB_TOL (spike px, + 10 % of |flow|); PREFETCH RGB intervals beyond the
# admitted time computed ahead by the worker thread (0: each in the step that first needs it; same flows).
# docs/experiments/spike-flow.md
GRAY_WINDOW = 128
FLOW_STEPS = 15
UPSAMPLE = 2
FB_TOL = 0.5
PREFETCH = 2
GRAY_CACHE = 64  # grey images the flow term keeps (spike_flow_pairs.RecentGreys); a miss recomputes one
# cached flows (every pair is kept for the run; docs/experiments/benchmark-history.md "The guided step's
# per-run work")
FLOW_DTYPE = torch.float16
# the prefetch worker's nice increment: it computes on what the step leaves idle (background.PriorityWorker)
WORKER_NICE = 19


class FlowCache:
    """The flow half of :class:`engine.train.guidance.spike_flow.SpikeFlowSupervision`: needs ``cfg``,
    ``stream``, ``guidance.sensor``, ``times`` (the RGB instants) and ``run.device``
    (set by :meth:`init_flows`, called from the term's constructor)."""

    def init_flows(self) -> None:
        self._gray = RecentGreys(self._make_gray, GRAY_CACHE)
        self._flows: dict[tuple[int, int], tuple[torch.Tensor, torch.Tensor]] = {}
        self._warm: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}  # chain ends (spike_flow_warm)
        ahead = int(PREFETCH)
        self._ahead = ahead
        self._worker = PriorityWorker("bt4d-flow-prefetch", nice=WORKER_NICE) if ahead > 0 else None
        self._stopping = False  # close_flows: the worker's chain stops before its next pair
        self._queued = -1  # intervals [0, _queued] have their chains queued

    def frame_of(self, t: float) -> int:
        """Spike frame index nearest to ``t`` (the cache's key for an instant)."""
        return int(round((float(t) - self.stream.t0) * self.stream.rate_hz))

    def gray(self, t: float) -> np.ndarray:
        """Linear grey image [h, w] reconstructed from the spikes around ``t`` (LRU-cached)."""
        return self._gray(self.frame_of(t))

    def _make_gray(self, k: int) -> np.ndarray:
        return spike_to_gray(self.stream, self.stream.t0 + k / self.stream.rate_hz, self.guidance.sensor,
                             method="tfp", window=int(GRAY_WINDOW))

    def flow(self, t_ref: float, t: float) -> tuple[torch.Tensor, torch.Tensor]:
        """(flow ref -> t float16 [h, w, 2], valid uint8 [h, w, 1]; sample_map reads both as float32)
        on the run's device (cached). With ``spike_flow_warm`` the flow to a grid instant starts
        from the flow to the grid instant one step closer to ``t_ref`` (spike_flow_pairs). With a
        prefetch worker, computed on its thread (first in its queue) while this one waits."""
        key = (self.frame_of(t_ref), self.frame_of(t))
        hit = self._flows.get(key)
        if hit is None:
            if self._worker is not None and not self._worker.on_worker():
                self._worker.run(key, lambda: self.flow(t_ref, t))
                return self._flows[key]
            prev, more = self.warm_from(t_ref, t)
            init = None
            if prev is not None:
                self.flow(t_ref, prev)
                init = self._warm.pop((key[0], self.frame_of(prev)), None)
            if self._stopping:  # on the worker, closing: what is cached stays valid (the chain resumes from it)
                if init is not None:
                    self._warm[(key[0], self.frame_of(prev))] = init
                raise RuntimeError("spike-flow prefetch closed")
            fl, ok, back = self.estimate(t_ref, t, init)
            if more:  # only the latest pair of a chain is kept, for the next one
                self._warm[key] = (fl, back)
            dev = self.run.device
            hit = (torch.as_tensor(fl, dtype=FLOW_DTYPE, device=dev),
                   torch.as_tensor(np.asarray(ok) > 0, dtype=torch.uint8, device=dev)[..., None])
            self._flows[key] = hit
        return hit

    def prefetch(self, admitted: float) -> int:
        """Queue the pairs of both chains of every RGB interval that starts at or before ``admitted`` and of
        the ``spike_flow_prefetch`` intervals after it, earlier intervals first (nothing
        without a worker). Returns the last interval queued (-1: none)."""
        if self._worker is None or len(self.times) < 2:
            return self._queued
        n1 = max(1, int(FLOW_STEPS)) + 1
        k_adm = max((i for i, v in enumerate(self.times[:-1]) if v <= admitted + 1e-9), default=0)
        last = min(len(self.times) - 2, k_adm + self._ahead)
        for k in range(self._queued + 1, last + 1):
            a, b = self.times[k], self.times[k + 1]
            # one job per pair, in chain order (each starts from the pair before it): a step that
            # needs a pair now waits for the pair being computed at most, not for a whole chain
            for e, (ref, qs) in enumerate(((a, range(1, n1)), (b, range(n1 - 1, 0, -1)))):
                for i, q in enumerate(qs):
                    t = a + (b - a) * q / n1
                    self._worker.submit((self.frame_of(ref), self.frame_of(t)),
                                        lambda r=ref, tt=t: self.flow(r, tt), priority=(2 * k + e) * n1 + i)
            self._queued = k
        return self._queued

    def close_flows(self) -> None:
        """Stop the worker: the chains not started are dropped, the running one stops before
        its next pair and is waited for (one thread touches the cache at a time: a cancel waits
        one DIS pair at most); later flows are computed inline, a cut chain from where it stopped."""
        if self._worker is not None:
            self._stopping = True
            self._worker.close()
            self._worker.join()
            self._worker, self._stopping = None, False

    def grid_step(self, t: float) -> tuple[float, float, int, int]:
        """(a, b, q, n + 1): ``t``'s RGB interval [a, b] and its nearest grid index q, not clamped."""
        k = max(i for i, v in enumerate(self.times) if v <= t)  # ts[0] < t < ts[-1]
        a, b, n1 = self.times[k], self.times[k + 1], max(1, int(FLOW_STEPS)) + 1
        return a, b, int(round((t - a) / (b - a) * n1)), n1

    def warm_from(self, t_ref: float, t: float) -> tuple[float | None, bool]:
        """(the grid instant one step from ``t`` towards ``t_ref`` (an end of ``t``'s RGB
        interval) whose flow warm-starts ``t``'s, or None at the first step, off the grid or
        with ``spike_flow_warm`` off; whether a later step will start from ``t``'s flow)."""
        if not self.cfg.spike_flow.warm or not self.times or not self.times[0] < t < self.times[-1]:
            return None, False
        a, b, q, n1 = self.grid_step(t)
        if self.frame_of(a + (b - a) * q / n1) != self.frame_of(t) or t_ref not in (a, b):
            return None, False
        step = -1 if t_ref == a else 1
        prev, nxt = q + step, q - step
        return (None if prev in (0, n1) else a + (b - a) * prev / n1), nxt not in (0, n1)

    def estimate(self, t_ref: float, t: float, init: tuple | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(flow [h, w, 2], valid bool [h, w], backward flow [h, w, 2]) from the spike stream,
        warm-started from ``init`` (forward, backward) when given (the oracle script
        a one-off study replaced this with the ground-truth motion). On the
        prefetch worker both flows run on its own low-priority thread, not the pair thread."""
        on_worker = self._worker is not None and self._worker.on_worker()
        fw, bw, ok = warm_flow_pair(self.gray(t_ref), self.gray(t), init, upsample=int(UPSAMPLE),
                                    tol_px=float(FB_TOL), parallel=False if on_worker else None)
        return fw, ok, bw
