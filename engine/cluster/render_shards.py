"""A camera path's frames split into contiguous ranges, each rendered by a Ray task.

The driver decides every view and every file name before anything renders (names from
:func:`engine.export.render_views.output_names` over the whole path, so two shards can never
write the same file), and each task renders its range with the same
:func:`engine.export.render_views.write_renders` as a one-process ``engine render``: the files are
the same bytes. A task loads the result once for its whole range.
"""
from __future__ import annotations

import time
from pathlib import Path

from .ray_runtime import ClusterError, connect, gpus_per_task, worker_env


def shard_ranges(n: int, shards: int) -> list[tuple[int, int]]:
    """``shards`` contiguous ``[start, stop)`` ranges covering ``range(n)``, sizes within one of
    each other (fewer when there are fewer frames than shards)."""
    if shards < 1:
        raise ValueError(f"shards must be at least 1, got {shards}")
    k = min(shards, n)
    bounds = [round(i * n / k) for i in range(k + 1)] if k else [0]
    return [(bounds[i], bounds[i + 1]) for i in range(k)]


def render_range(run: str, views: list, stems: list[str], out_dir: str, fmt: str, device: str = "auto") -> list[str]:
    """Render ``views`` of the result ``run`` to ``out_dir/<stem>.<fmt>`` (the task body; no Ray)."""
    from ..export.cached import load_result
    from ..export.render_views import write_renders

    scene = load_result(run, device=device)
    return [str(p) for p in write_renders(scene, views, out_dir, fmt, names=stems)]


def render_sharded(run, views: list, stems: list[str], out_dir, fmt: str, *, shards: int, address: str | None = None,
                   device: str = "auto", gpus: float | None = None, log=None) -> dict:
    """Render ``views`` (file stems ``stems``) in ``shards`` Ray tasks; returns ``{"paths": [...]
    in view order, "seconds", "ray_start_seconds", "shards"}``."""
    log = log or (lambda text: None)
    if len(stems) != len(views) or len(set(stems)) != len(stems):
        raise ValueError("every view needs its own output name")
    run = str(Path(run).resolve())
    out_dir = str(Path(out_dir).resolve())
    ranges = shard_ranges(len(views), shards)
    ray, start_s = connect(address)
    t0 = time.perf_counter()
    task = ray.remote(render_range).options(num_cpus=1, num_gpus=gpus_per_task(ray, gpus), max_retries=3,
                                            runtime_env=worker_env())
    refs = {task.remote(run, views[a:b], stems[a:b], out_dir, fmt, device): (a, b) for a, b in ranges}
    done: dict[tuple[int, int], list[str]] = {}
    pending = list(refs)
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        for ref in ready:
            a, b = refs[ref]
            try:
                done[(a, b)] = ray.get(ref)
            except Exception as exc:
                raise ClusterError(f"frames {a}-{b - 1} failed: {str(exc).splitlines()[0]}") from exc
            log(f"render: frames {a}-{b - 1} done ({sum(len(p) for p in done.values())}/{len(views)})")
    paths = [p for a, b in ranges for p in done[(a, b)]]
    return {"paths": paths, "seconds": round(time.perf_counter() - t0, 3),
            "ray_start_seconds": round(start_s, 3), "shards": len(ranges)}
