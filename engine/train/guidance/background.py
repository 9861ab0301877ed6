"""One background thread that runs keyed jobs, most urgent first (issue 13: work a step will
need, done while the steps before it run).

The spike-view flow term (engine.train.guidance.spike_flow) needs DIS optical flows that depend on
the spike stream only, never on the model: a data loader's work. Computed inside the step
that first asks for them, they stalled that step (~150 ms for a chain of 15 pairs on the
demo, 2 ms a guided step on average); on this worker they are computed while earlier steps
run, on what the training step leaves idle (docs/experiments/benchmark-history.md "The flows computed ahead of the
steps").

Rules, so that what the worker computes is what the step would have computed:

* every job runs on the one worker thread, in priority order (lower first; ties in
  submission order); a job's own state (caches, warm starts) is touched by that thread only,
  so callers never race with it;
* :meth:`PriorityWorker.run` is the caller's way to get a result now: it submits (or
  promotes) the job at :data:`URGENT` and waits; an exception of the job is raised there;
* a job is identified by its key and runs once (a second submit of a done key is a no-op);
* :meth:`PriorityWorker.close` drops what has not started (a cancelled run stops
  computing), lets the running job finish, and makes later submits raise.

The thread starts with the first job and exits when the queue is empty, so an idle run
holds no thread. With ``nice`` > 0 it lowers its own scheduling priority (Linux: a thread has
its own nice value) so that it runs on what the training threads leave idle instead of taking
turns with them: numba's parallel regions wait for their slowest thread, and a flow sharing a
core with one of them stalled the whole region (docs/experiments/benchmark-history.md "The flows computed ahead of
the steps":
the demo's 1000 steps +1.7 % wall at normal priority over 6 alternated pairs, -5.4 % at nice 19
over 16, on a 2-core machine).
"""
from __future__ import annotations

import atexit
import heapq
import itertools
import os
import sys
import threading
import weakref
from typing import Callable, Hashable

__all__ = ["URGENT", "PriorityWorker"]

URGENT = -1  # priority of a job a caller waits for (run)
_LIVE: "weakref.WeakSet[PriorityWorker]" = weakref.WeakSet()


@atexit.register
def _close_all() -> None:
    """At interpreter exit, close every worker and wait for its running job. A daemon thread still
    inside OpenCV when Python finalizes is unwound by force and the process aborts ("FATAL:
    exception not rethrown"): a Trainer made without ``train()`` (tests, scripts) leaves its flow
    worker running, and at nice 19 behind a busy process it is still running at exit."""
    for w in list(_LIVE):
        w.close()
        w.join(60.0)


class _Job:
    __slots__ = ("fn", "priority", "started", "done", "error")

    def __init__(self, fn: Callable[[], object], priority: float):
        self.fn, self.priority = fn, priority
        self.started = False
        self.done = threading.Event()
        self.error: BaseException | None = None


class PriorityWorker:
    """Keyed jobs on one lazily started thread named ``name``, lowest priority first."""

    def __init__(self, name: str = "bt4d-worker", nice: int = 0):
        self.name, self.nice = name, int(nice)
        self._cv = threading.Condition()
        self._heap: list = []  # (priority, seq, key); stale entries (promoted, started) are skipped
        self._jobs: dict[Hashable, _Job] = {}
        self._seq = itertools.count()
        self._thread: threading.Thread | None = None
        self._started: list[threading.Thread] = []  # every thread started (join waits for all)
        self._closed = False
        self.ran: list = []  # keys in the order they ran (tests, diagnostics)
        _LIVE.add(self)

    def on_worker(self) -> bool:
        """True on the worker's own thread (a job that needs another result computes it itself)."""
        return self._thread is not None and threading.current_thread() is self._thread

    def pending(self) -> int:
        """Jobs submitted and not finished."""
        with self._cv:
            return sum(not j.done.is_set() for j in self._jobs.values())

    def submit(self, key: Hashable, fn: Callable[[], object], priority: float = 0.0) -> None:
        """Queue ``fn`` under ``key`` at ``priority`` (a queued job submitted again at a lower
        number is promoted; a started or done one is left as it is)."""
        with self._cv:
            if self._closed:
                raise RuntimeError(f"{self.name}: closed, no new jobs")
            job = self._jobs.get(key)
            if job is None:
                job = self._jobs[key] = _Job(fn, priority)
            elif job.started or priority >= job.priority:
                return
            job.priority = priority
            heapq.heappush(self._heap, (priority, next(self._seq), key))
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name=self.name, daemon=True)
                self._started = [t for t in self._started if t.is_alive()] + [self._thread]
                self._thread.start()
            self._cv.notify()

    def run(self, key: Hashable, fn: Callable[[], object]) -> None:
        """Run ``key``'s job ahead of everything queued (``fn`` unless it was submitted before)
        and wait for it; raises what the job raised. On the worker's own thread: runs ``fn`` now."""
        if self.on_worker():
            fn()
            return
        self.submit(key, fn, URGENT)
        with self._cv:
            job = self._jobs[key]
        job.done.wait()
        if job.error is not None:
            raise job.error

    def close(self) -> None:
        """Drop the jobs not started; the running one finishes. Later submits raise."""
        with self._cv:
            self._closed = True
            self._heap.clear()
            for key, job in list(self._jobs.items()):
                if not job.started:
                    job.error = RuntimeError(f"{self.name}: closed before job {key!r} ran")
                    job.done.set()

    def join(self, timeout: float | None = None) -> None:
        """Wait until the thread has nothing left and has exited: a thread that found the queue
        empty has already cleared ``_thread`` while it is still returning (a loaded machine
        widened that window until a finished run still listed its worker)."""
        with self._cv:
            threads = list(self._started)
        for t in threads:
            if t is not threading.current_thread():
                t.join(timeout)

    def _next(self):
        with self._cv:
            while self._heap:
                priority, _, key = heapq.heappop(self._heap)
                job = self._jobs[key]
                if not job.started and priority == job.priority:
                    job.started = True
                    return key, job
            self._thread = None  # a submit after this starts a new thread
            return None

    def _lower_priority(self) -> None:
        """Raise this thread's nice value by :attr:`nice` (Linux only; no privilege is needed to
        lower a priority; where it fails the thread runs at the process's priority)."""
        if self.nice <= 0 or not sys.platform.startswith("linux"):
            return
        try:
            tid = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + self.nice))
        except OSError:
            pass

    def _loop(self) -> None:
        self._lower_priority()
        while True:
            nxt = self._next()
            if nxt is None:
                return
            key, job = nxt
            try:
                job.fn()
            except BaseException as e:  # handed to whoever waits (run), not lost in the thread
                job.error = e
            self.ran.append(key)
            job.done.set()
