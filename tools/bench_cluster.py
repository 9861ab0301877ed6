"""``python -m tools bench-cluster CAPTURE... --out DIR``: engine batch and sharded rendering on a
local Ray cluster of two nodes (``ray start``: a head and a worker, one CPU each), measured in one run.

1. Ray's own overhead: joining the cluster, an empty task's round trip, the first task on a fresh
   worker (importing torch and the engine), moving 10 MB in and out of a task.
2. Every capture trained alone in this process, then the same captures as one ``engine batch``:
   eval PSNR of each both ways (target: within 0.05 dB), the sum of the alone times against the
   batch's wall time.
3. A worker killed mid-run: the step the progress board last showed, the checkpoint the retry
   resumed from (the work lost), and the checkpoint interval in steps.
4. A camera path of ``--frames`` frames rendered in one process and over two Ray tasks: the same
   bytes, and both times.

Prints a Markdown report (docs/benchmarks.md keeps it) and writes DIR/bench_cluster.json.
"""
from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
import traceback
from pathlib import Path

import numpy as np

HELP = "engine batch and sharded rendering on a local two-node Ray cluster: overhead, equality, a killed worker"
REPO = Path(__file__).resolve().parents[1]


def add_arguments(p) -> None:
    p.add_argument("captures", nargs="+", help="capture folders (4 small ones: the README's figure)")
    p.add_argument("--out", required=True, type=Path, help="working folder (emptied first)")
    p.add_argument("--iterations", type=int, default=500, help="steps per capture (default 500)")
    p.add_argument("--frames", type=int, default=120, help="frames of the sharded camera path (default 120)")
    p.add_argument("--checkpoint-every", type=float, default=5.0, help="seconds between checkpoints in the kill test")


def _ray_cli(*args, env):
    cmd = [str(Path(sys.executable).parent / "ray"), *args]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=180, env=env)
    if r.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{r.stdout[-1500:]}{r.stderr[-1500:]}")


def start_cluster(work: Path) -> tuple[str, dict]:
    """A head and a worker node on this machine (token authentication, the token in ``work``)."""
    token = work / "ray_token"
    token.write_text(secrets.token_hex(32))
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN_PATH=str(token))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    common = ["--num-cpus=1", "--object-store-memory=200000000", "--disable-usage-stats"]
    _ray_cli("start", "--head", f"--port={port}", "--include-dashboard=false", *common, env=env)
    _ray_cli("start", f"--address=127.0.0.1:{port}", *common, env=env)
    return f"127.0.0.1:{port}", env


def ray_overhead(ray) -> dict:
    @ray.remote(num_cpus=1)
    def empty():
        return 0

    @ray.remote(num_cpus=1)
    def first_use():
        t0 = time.perf_counter()
        import engine.cluster.batch  # noqa: F401
        import engine.train  # noqa: F401  (torch, numba, the training code)
        return time.perf_counter() - t0

    @ray.remote(num_cpus=1)
    def echo(a):
        return a

    from engine.cluster.ray_runtime import worker_env

    env = worker_env()
    ray.get(empty.options(runtime_env=env).remote())  # workers up
    times = []
    for _ in range(30):
        t0 = time.perf_counter()
        ray.get(empty.options(runtime_env=env).remote())
        times.append(time.perf_counter() - t0)
    imports = ray.get([first_use.options(runtime_env=env).remote() for _ in range(2)])
    data = np.random.default_rng(0).random(10 * 1024 * 1024 // 8)
    moves = []
    for _ in range(5):
        t0 = time.perf_counter()
        ray.get(echo.options(runtime_env=env).remote(data))
        moves.append(time.perf_counter() - t0)
    return {"empty_task_ms": round(1000 * float(np.median(times)), 2),
            "first_import_s": round(float(max(imports)), 2),
            "move_10mb_in_out_ms": round(1000 * float(np.median(moves)), 1)}


def alone(captures, out: Path, iterations: int) -> dict:
    from engine.cluster.batch import BatchJob, BatchSettings, train_capture

    settings = BatchSettings(overrides={"schedule.iterations": iterations})
    rows = {}
    for c in captures:
        name = Path(c).name
        t0 = time.perf_counter()
        row = train_capture(BatchJob(name=name, capture=str(Path(c).resolve()), run_dir=str(out / name)), settings)
        row["wall_s"] = round(time.perf_counter() - t0, 2)
        rows[name] = row
        print(f"alone {name}: {row['status']}, PSNR {row.get('metrics', {}).get('psnr')}, {row['wall_s']} s",
              file=sys.stderr, flush=True)
    return rows


def engine_cmd(*args, env) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "engine", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, env=env, timeout=3600)


def killed_worker(ray, capture, out: Path, address: str, env: dict, iterations: int, every: float) -> dict:
    from engine.cluster.batch import BOARD_NAMESPACE, board_name, read_attempts

    name = Path(capture).name
    proc = subprocess.Popen([sys.executable, "-m", "engine", "batch", str(capture), "--out", str(out), "--address",
                             address, "--no-eval", "--set", f"schedule.iterations={iterations}",
                             "--set", f"schedule.checkpoint_every_s={every}"],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    run = out / name
    checkpoint_step = 0
    while proc.poll() is None:  # wait for a checkpoint, then half an interval more
        try:
            checkpoint_step = int(json.loads((run / "run.json").read_text()).get("step") or 0)
        except (OSError, ValueError):
            pass
        if checkpoint_step > 0:
            break
        time.sleep(0.2)
    time.sleep(every / 2)
    board = ray.get_actor(board_name(out), namespace=BOARD_NAMESPACE)
    step_at_kill = ray.get(board.snapshot.remote())[name]["step"]
    os.kill(read_attempts(run)[0]["pid"], signal.SIGKILL)
    t_kill = time.perf_counter()
    proc.communicate()
    summary = json.loads((out / "batch.json").read_text())["captures"][0]
    info = json.loads((run / "run.json").read_text())
    step_s = info["train_seconds"] / max(1, info["step"])
    return {"status": summary["status"], "attempts": summary["attempts"], "step_at_kill": step_at_kill,
            "resumed_from": summary["resumed_from"], "steps_lost": step_at_kill - summary["resumed_from"],
            "interval_steps": round(every / step_s, 1), "finish_after_kill_s": round(time.perf_counter() - t_kill, 1)}


def sharded_render(run: Path, work: Path, frames: int, address: str, env: dict) -> dict:
    from engine.cli.render import _first_train_view, orbit_from_result
    from engine.export.cached import load_result
    from engine.export.render_views import write_camera_file

    scene = load_result(run)
    views = orbit_from_result(scene, _first_train_view(scene, run), 60.0, frames, 0.0)
    t0, t1 = scene.time_range
    for i, v in enumerate(views):
        v.time = t0 + (t1 - t0) * i / max(1, frames - 1)
        v.name = f"frame_{i:04d}"
    path = write_camera_file(work / "path.json", views)
    out = {}
    for label, extra in (("one", []), ("two", ["--shards", "2", "--address", address])):
        t = time.perf_counter()
        r = engine_cmd("render", run, "--path", path, "--out", work / label, "--quiet", *extra, env=env)
        if r.returncode:
            raise SystemExit(r.stderr[-2000:])
        out[f"{label}_s"] = round(time.perf_counter() - t, 2)
    names = sorted(p.name for p in (work / "one").iterdir())
    same = names == sorted(p.name for p in (work / "two").iterdir()) and all(
        (work / "one" / n).read_bytes() == (work / "two" / n).read_bytes() for n in names)
    return {"frames": len(names), "identical": bool(same), **out}


def main(args) -> int:
    from engine.cluster.ray_runtime import connect

    work = args.out.resolve()
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    captures = [Path(c).resolve() for c in args.captures]
    address, env = start_cluster(work)
    report = {"captures": [str(c.name) for c in captures], "iterations": args.iterations}
    try:
        os.environ.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN_PATH=env["RAY_AUTH_TOKEN_PATH"])
        ray, join_s = connect(address)
        report["overhead"] = {"join_cluster_s": round(join_s, 2), **ray_overhead(ray)}
        print(f"overhead: {report['overhead']}", file=sys.stderr, flush=True)
        solo = alone(captures, work / "alone", args.iterations)
        t0 = time.perf_counter()
        r = engine_cmd("batch", *captures, "--out", work / "batch", "--address", address,
                       "--set", f"schedule.iterations={args.iterations}", env=env)
        batch_wall = time.perf_counter() - t0
        rows = {row["name"]: row for row in json.loads((work / "batch" / "batch.json").read_text())["captures"]}
        report["batch"] = {"returncode": r.returncode, "wall_s": round(batch_wall, 1),
                           "alone_sum_s": round(sum(x["wall_s"] for x in solo.values()), 1),
                           "captures": {n: {"alone_psnr": solo[n].get("metrics", {}).get("psnr"),
                                            "batch_psnr": rows[n].get("metrics", {}).get("psnr"),
                                            "alone_s": solo[n]["wall_s"], "batch_task_s": rows[n].get("seconds")}
                                        for n in solo}}
        print(f"batch: {report['batch']}", file=sys.stderr, flush=True)
        report["killed_worker"] = killed_worker(ray, captures[0], work / "killed", address, env, args.iterations,
                                                args.checkpoint_every)
        print(f"killed worker: {report['killed_worker']}", file=sys.stderr, flush=True)
        report["sharded_render"] = sharded_render(work / "batch" / captures[0].name, work / "render", args.frames,
                                                  address, env)
    except BaseException:
        traceback.print_exc()  # now: stopping Ray below can end this process before Python prints it
        raise
    finally:
        import ray as _ray

        _ray.shutdown()  # leave the cluster before stopping it
        ray_stop = [str(Path(sys.executable).parent / "ray"), "stop", "--force"]
        subprocess.run(ray_stop, capture_output=True, timeout=180, env=env)
    (work / "bench_cluster.json").write_text(json.dumps(report, indent=2))
    print(format_report(report))
    return 0


def format_report(r: dict) -> str:
    o, b, k, s = r["overhead"], r["batch"], r["killed_worker"], r["sharded_render"]
    lines = [f"Ray overhead: join {o['join_cluster_s']} s, empty task {o['empty_task_ms']} ms, first task on a "
             f"worker {o['first_import_s']} s (imports), 10 MB in and out {o['move_10mb_in_out_ms']} ms", "",
             "| capture | alone: eval PSNR | batch: eval PSNR | difference | alone s | batch task s |",
             "|---|---|---|---|---|---|"]
    for n, c in b["captures"].items():
        d = (c["batch_psnr"] - c["alone_psnr"]) if None not in (c["batch_psnr"], c["alone_psnr"]) else None
        lines.append(f"| {n} | {c['alone_psnr']} | {c['batch_psnr']} | {'' if d is None else f'{d:+.2f}'} | "
                     f"{c['alone_s']} | {c['batch_task_s']} |")
    lines += ["", f"batch wall {b['wall_s']} s on 2 workers; the captures one after another alone: "
              f"{b['alone_sum_s']} s ({b['alone_sum_s'] / b['wall_s']:.2f}x)",
              f"killed worker: {k['status']} after {k['attempts']} attempts; shown at step {k['step_at_kill']}, "
              f"resumed from {k['resumed_from']}: {k['steps_lost']} steps lost (one checkpoint interval is "
              f"{k['interval_steps']} steps)",
              f"sharded render: {s['frames']} frames, identical files: {s['identical']}; one process {s['one_s']} s, "
              f"two Ray tasks {s['two_s']} s"]
    return "\n".join(lines)
