"""engine.train.guidance.background.PriorityWorker: the spike-flow prefetch's one background thread."""
from __future__ import annotations

import sys
import threading
import time

import pytest

from engine.train.guidance.background import URGENT, PriorityWorker


def _blocked_worker():
    """A worker whose first job holds its thread until ``gate`` is set."""
    w, gate, started = PriorityWorker("test-worker"), threading.Event(), threading.Event()

    def hold():
        started.set()
        gate.wait(10)

    w.submit("hold", hold, priority=0)
    assert started.wait(10)
    return w, gate


def test_jobs_run_on_one_thread_lowest_priority_first_and_an_urgent_run_jumps_the_queue():
    w, gate = _blocked_worker()
    threads = []
    for key, prio in (("c", 3), ("a", 1), ("b", 2)):
        w.submit(key, lambda: threads.append(threading.current_thread().name), priority=prio)
    waiter = threading.Thread(target=w.run, args=("now", lambda: threads.append("now")))
    waiter.start()
    deadline = time.monotonic() + 10
    while w.pending() < 5 and time.monotonic() < deadline:  # hold, a, b, c, now
        time.sleep(0.001)
    gate.set()
    waiter.join(10)
    w.join(10)
    assert w.ran == ["hold", "now", "a", "b", "c"]
    assert set(threads[1:]) == {"test-worker"} and threads[0] == "now"
    assert w.pending() == 0 and not w.on_worker()


def test_a_key_runs_once_and_a_queued_job_is_promoted():
    w, gate = _blocked_worker()
    n = []
    w.submit("x", lambda: n.append("x"), priority=5)
    w.submit("y", lambda: n.append("y"), priority=1)
    w.submit("x", lambda: n.append("x again"), priority=0)  # promoted, its first fn kept
    gate.set()
    w.join(10)
    w.run("x", lambda: n.append("x third"))  # done: nothing runs
    assert n == ["x", "y"] and w.ran == ["hold", "x", "y"]


def test_run_raises_the_jobs_exception_and_the_worker_goes_on():
    w = PriorityWorker()

    def boom():
        raise ValueError("bad flow")

    with pytest.raises(ValueError, match="bad flow"):
        w.run("boom", boom)
    out = []
    w.run("ok", lambda: out.append(1))
    assert out == [1]


def test_run_on_the_worker_thread_runs_inline():
    w = PriorityWorker()
    seen = []

    def outer():
        w.run("inner", lambda: seen.append(("inner", w.on_worker())))  # would deadlock if queued
        seen.append(("outer", w.on_worker()))

    w.run("outer", outer)
    assert seen == [("inner", True), ("outer", True)]


def test_close_drops_what_has_not_started_and_refuses_new_jobs():
    w, gate = _blocked_worker()
    ran = []
    w.submit("later", lambda: ran.append("later"), priority=1)
    w.close()
    gate.set()
    w.join(10)
    assert ran == [] and w.ran == ["hold"]
    with pytest.raises(RuntimeError, match="closed"):
        w.submit("new", lambda: None)


def test_the_thread_exits_when_idle_and_a_new_job_starts_another():
    w = PriorityWorker()
    w.run("one", lambda: None)
    w.join(10)
    assert w._thread is None
    w.run("two", lambda: None)
    w.join(10)
    assert w.ran == ["one", "two"] and URGENT < 0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")
def test_a_nice_worker_runs_its_jobs_at_a_lower_priority_than_the_caller():
    import os

    seen = []
    w = PriorityWorker("nice-worker", nice=5)
    w.run("p", lambda: seen.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id())))
    mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    assert seen == [min(19, mine + 5)]
    plain = []
    PriorityWorker("plain").run("p", lambda: plain.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id())))
    assert plain == [mine]


def test_interpreter_exit_closes_the_workers_and_waits_for_the_running_job(tmp_path):
    """A process that leaves a worker with queued jobs exits cleanly: at exit the queue is dropped
    and the running job finishes before Python finalizes (a daemon thread killed inside OpenCV
    aborted the test process: "FATAL: exception not rethrown")."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    code = f"""
import sys, time, pathlib
sys.path.insert(0, {str(root)!r})
from engine.train.guidance.background import PriorityWorker
out = pathlib.Path({str(tmp_path)!r})
w = PriorityWorker("exit-test", nice=19)
def job(i):
    time.sleep(0.2)
    (out / f"{{i}}").write_text("done")
for i in range(50):
    w.submit(i, lambda i=i: job(i), priority=i)
time.sleep(0.1)
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    done = sorted(int(p.name) for p in tmp_path.iterdir())
    assert done == [0]  # the running job finished, the 49 queued ones were dropped


def test_join_waits_for_a_thread_that_already_found_the_queue_empty():
    """A thread that found no job left clears ``_thread`` before it has returned; ``join`` must
    still wait for it (a finished run listed its flow worker on a loaded machine)."""

    class SlowToLeave(PriorityWorker):
        def _next(self):
            nxt = super()._next()
            if nxt is None:
                time.sleep(0.3)  # _thread is cleared, the thread is still alive
            return nxt

    w = SlowToLeave("test-leaving")
    w.submit("a", lambda: None)
    w._jobs["a"].done.wait(5)
    time.sleep(0.05)
    assert w._thread is None
    w.join()
    assert not [t for t in threading.enumerate() if t.name == "test-leaving"]
