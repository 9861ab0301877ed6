"""``engine batch``: train many captures, one Ray task each, and keep a summary of the batch.

Each capture trains into ``OUT/<capture folder name>`` with the same :func:`engine.train.train`
as ``engine train`` (so a batch run equals a run trained alone with the same seed), then is scored
on its eval frames when it has any. A task whose worker dies is retried by Ray
(``max_retries``), and the retry resumes from the run's last checkpoint: ``train(resume=True)``
continues a checkpoint of the same settings. Re-running the batch skips what finished and
resumes the rest. Every attempt appends a line to ``RUN/batch_attempts.jsonl`` (host, process,
the step it resumed from), so a retry can be seen and what it lost measured.

The task body, :func:`train_capture`, knows nothing of Ray; :func:`run_batch` does the Ray part:
resources per task, a progress board every task reports to, and ``OUT/batch.json`` written
after each capture ends.
"""
from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ..errors import CaptureError, RunError
from ..io.capture import load_capture
from ..io.checkpoint import read_run_json, write_json
from .ray_runtime import ClusterError, cluster_gpus, connect, gpus_per_task, worker_env

SUMMARY = "batch.json"
ATTEMPTS = "batch_attempts.jsonl"
REPORT_EVERY_S = 1.0  # a task tells the progress board at most this often
PROGRESS_EVERY_S = 10.0  # the batch's progress line, at most this often (and when a capture ends)


@dataclass
class BatchSettings:
    """What every capture of a batch is trained with (``engine train``'s options)."""
    preset: str = "fast"
    seconds: float | None = None
    rgb_only: bool = False
    seed: int = 0
    overrides: dict = field(default_factory=dict)
    device: str = "auto"
    evaluate: bool = True


@dataclass
class BatchJob:
    name: str     # the run folder's name under OUT, unique in the batch
    capture: str  # absolute path
    run_dir: str  # absolute path


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def plan_jobs(captures, out_dir) -> list[BatchJob]:
    """One job per capture, its run folder named after the capture folder (``_2``, ``_3`` for
    captures of the same name from different places; the same folder twice is one job)."""
    out = Path(out_dir).resolve()
    jobs, seen, names = [], set(), set()
    for c in captures:
        path = Path(c).resolve()
        root = path.parent if path.is_file() else path
        if root in seen:
            continue
        seen.add(root)
        base = root.name or "capture"
        name, k = base, 1
        while name in names:
            k += 1
            name = f"{base}_{k}"
        names.add(name)
        jobs.append(BatchJob(name=name, capture=str(path), run_dir=str(out / name)))
    return jobs


def _append_attempt(run_dir: Path, record: dict) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / ATTEMPTS, "a", encoding="utf-8") as fh:  # one short line: appends do not interleave
        fh.write(json.dumps(record) + "\n")
        fh.flush()
        os.fsync(fh.fileno())


def read_attempts(run_dir) -> list[dict]:
    path = Path(run_dir) / ATTEMPTS
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def _row(job: BatchJob, **fields) -> dict:
    """A summary row for ``job`` (its name, capture and run folder) with ``fields``."""
    return {"name": job.name, "capture": job.capture, "run_dir": job.run_dir, **fields}


def train_capture(job: BatchJob, settings: BatchSettings, report=None) -> dict:
    """Train (resuming what a previous attempt checkpointed) and score one capture; the summary
    row. ``report(name, dict)`` is told the step, total and stage now and then. A capture or run
    that cannot be used is a ``failed`` row with its error, never an exception."""
    from ..evaluate.heldout import evaluate
    from ..train import train

    run_dir = Path(job.run_dir)
    t0 = time.perf_counter()
    row = _row(job)
    try:
        resumed_from = int(read_run_json(run_dir).get("step") or 0)
    except RunError:
        resumed_from = 0
    _append_attempt(run_dir, {"started": _now(), "host": platform.node(), "pid": os.getpid(),
                              "checkpoint_step": resumed_from})
    last = [0.0]

    def progress(d):
        now = time.perf_counter()
        if report is not None and (now - last[0] >= REPORT_EVERY_S or d["step"] == d["total_steps"]):
            last[0] = now
            report(job.name, {"step": d["step"], "total_steps": d["total_steps"], "stage": d["stage"]})

    try:
        cap = load_capture(job.capture)
        if report is not None:
            report(job.name, {"step": 0, "total_steps": None, "stage": "preparing"})
        summary = train(cap, run_dir, preset=settings.preset, seconds=settings.seconds, rgb_only=settings.rgb_only,
                        resume=True, device=settings.device, seed=settings.seed, overrides=dict(settings.overrides),
                        progress=progress)
        row.update(status=summary["status"], steps=summary["step"], total_steps=summary["total_steps"],
                   train_seconds=summary["train_seconds"], resumed_from=summary["resumed_from"],
                   num_gaussians=summary["num_gaussians"], device=summary["device"])
        if settings.evaluate and summary["status"] == "finished" and cap.eval_frames:
            if report is not None:
                report(job.name, {"step": summary["step"], "total_steps": summary["total_steps"], "stage": "eval"})
            m = evaluate(run_dir, cap, device=settings.device)
            row["metrics"] = {k: m[k] for k in ("psnr", "ssim", "lpips", "psnr_interframe", "psnr_dynamic")}
    except (CaptureError, RunError, ValueError, KeyError) as exc:
        row.update(status="failed", error=str(exc))
    row["seconds"] = round(time.perf_counter() - t0, 2)
    row["host"] = platform.node()
    return row


def _finished_before(job: BatchJob, previous: dict) -> dict | None:
    """The previous summary's row for ``job`` when it finished and its run still says so."""
    row = previous.get(job.name)
    if not row or row.get("status") != "finished":
        return None
    try:
        info = read_run_json(job.run_dir)
    except RunError:
        return None
    return row if info.get("status") == "finished" and info.get("step") == row.get("steps") else None


def _load_summary(out: Path, settings: BatchSettings) -> dict:
    """Rows of the batch already in ``out`` (by name); ClusterError if it used other settings."""
    path = out / SUMMARY
    if not path.exists():
        return {}
    data = json.loads(path.read_text(encoding="utf-8"))
    if data.get("settings") != asdict(settings):
        raise ClusterError(f"{path}: this folder holds a batch trained with other settings "
                           f"({data.get('settings')}); choose another --out")
    return {r["name"]: r for r in data.get("captures", [])}


def write_summary(out: Path, settings: BatchSettings, rows: dict, jobs: list[BatchJob], extra: dict) -> Path:
    order = [j.name for j in jobs]
    listed = [rows.get(n, {"name": n, "status": "pending"}) for n in order]
    counts = dict(Counter(r["status"] for r in listed))
    data = {"settings": asdict(settings), "updated": _now(), "counts": counts, **extra, "captures": listed}
    write_json(out / SUMMARY, data)
    return out / SUMMARY


BOARD_NAMESPACE = "bullettime4d"


def board_name(out_dir) -> str:
    """The progress board's actor name for the batch in ``out_dir``: another driver on the
    cluster can read it (``ray.get_actor(board_name(out), namespace=BOARD_NAMESPACE)``)."""
    return f"batch:{Path(out_dir).resolve()}"


def _progress_board(ray, name: str):
    @ray.remote(num_cpus=0)
    class ProgressBoard:  # where tasks say how far they are; the driver reads it
        def __init__(self):
            self.rows = {}

        def report(self, name, d):
            self.rows[name] = d

        def snapshot(self):
            return dict(self.rows)

    return ProgressBoard.options(name=name, namespace=BOARD_NAMESPACE, get_if_exists=True).remote()


def _task(ray, cpus: float, gpus: float, retries: int):
    """The Ray task that trains one capture; a dead worker's task is retried ``retries`` times."""
    @ray.remote
    def train_task(job, settings, board):
        return train_capture(job, settings, report=lambda n, d: board.report.remote(n, d))

    return train_task.options(num_cpus=cpus, num_gpus=gpus, max_retries=retries, retry_exceptions=False,
                              runtime_env=worker_env())


def run_batch(captures, out_dir, settings: BatchSettings, *, address: str | None = None, cpus_per_task: float = 1.0,
              gpus: float | None = None, retries: int = 3, log=None) -> dict:
    """Train every capture as a Ray task; returns the summary (also in ``OUT/batch.json``).

    ``address``: a running cluster (``ray start --head``), else a local Ray instance.
    ``gpus``: GPUs per task; None = one where the cluster has GPUs, else none.
    ``log(text)``: progress lines for the whole batch."""
    log = log or (lambda text: None)
    out = Path(out_dir).resolve()
    jobs = plan_jobs(captures, out)
    if not jobs:
        raise ClusterError("no capture folders given")
    out.mkdir(parents=True, exist_ok=True)
    previous = _load_summary(out, settings)
    rows, todo, n_before, n_bad = {}, [], 0, 0
    for job in jobs:  # what cannot load is reported now, before anything starts
        done = _finished_before(job, previous)
        if done is not None:
            rows[job.name], n_before = done, n_before + 1
            continue
        try:
            load_capture(job.capture)
        except CaptureError as exc:
            rows[job.name] = _row(job, status="failed", error=str(exc))
            n_bad += 1
            log(f"batch: {job.name} cannot load: {exc}")
            continue
        todo.append(job)
    log(f"batch: {len(jobs)} capture(s): {n_before} finished before, {n_bad} cannot load, {len(todo)} to train")
    t0 = time.perf_counter()
    extra = {"address": address or "local"}
    write_summary(out, settings, rows, jobs, extra)
    if todo:
        ray, start_s = connect(address)
        extra.update(ray_start_seconds=round(start_s, 2), cluster_cpus=ray.cluster_resources().get("CPU", 0.0),
                     cluster_gpus=cluster_gpus(ray))
        board = _progress_board(ray, board_name(out))
        task = _task(ray, cpus_per_task, gpus_per_task(ray, gpus), retries)
        pending = {task.remote(job, settings, board): job for job in todo}
        last_line, last_t = "", 0.0
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=2.0)
            for ref in ready:
                job = pending.pop(ref)
                try:
                    row = ray.get(ref)
                except Exception as exc:  # the worker died more than `retries` times, or Ray failed it
                    row = _row(job, status="failed",
                               error=f"{exc.__class__.__name__}: {str(exc).splitlines()[0] if str(exc) else ''}")
                row["attempts"] = len(read_attempts(job.run_dir))
                rows[job.name] = row
                write_summary(out, settings, rows, jobs, extra)
                log(f"batch: {job.name} {row['status']}" + (f" ({row.get('error')})" if row.get("error") else "")
                    + (f", eval PSNR {row['metrics']['psnr']:.2f} dB" if row.get("metrics") else ""))
            line = _progress_line(ray.get(board.snapshot.remote()), pending.values(), len(jobs) - len(pending))
            if pending and line != last_line and (ready or time.perf_counter() - last_t >= PROGRESS_EVERY_S):
                log(line)
                last_line, last_t = line, time.perf_counter()
    extra["seconds"] = round(time.perf_counter() - t0, 2)
    path = write_summary(out, settings, rows, jobs, extra)
    return json.loads(path.read_text(encoding="utf-8"))


def _progress_line(board: dict, running, n_done: int) -> str:
    parts = []
    for job in running:
        d = board.get(job.name)
        if not d:
            parts.append(f"{job.name} waiting")
        elif d.get("total_steps"):
            parts.append(f"{job.name} {d['step']}/{d['total_steps']} {d['stage']}")
        else:
            parts.append(f"{job.name} {d['stage']}")
    return f"batch: {n_done} done; " + ", ".join(parts)


def print_log(text: str) -> None:
    print(text, file=sys.stderr, flush=True)
