"""engine batch and sharded renders on a real local Ray cluster: a head and a worker node started
with `ray start` (separate processes, as on two machines), nothing mocked (issue 44)."""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ray = pytest.importorskip("ray")

from engine.cluster.batch import BatchJob, BatchSettings, plan_jobs, read_attempts, train_capture  # noqa: E402
from engine.cluster.ray_runtime import ClusterError, check_reachable, split_address  # noqa: E402
from engine.cluster.render_shards import shard_ranges  # noqa: E402
from tools.bench_cluster import start_cluster  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RAY_CLI = str(Path(sys.executable).parent / "ray")
STEPS = 40  # small runs: what is tested is the batch, not the training
SETTINGS = ["--set", f"schedule.iterations={STEPS}"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# the cluster's environment (token authentication, set the same way on every node and client, as
# Ray's docs ask; the token in the test's folder, not the user's ~/.ray), for every command here
ENV = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}


def _engine(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "engine", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout, env=ENV)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A head node and a worker node (one CPU each) on this machine, started by `ray start` with
    token authentication (tools.bench_cluster.start_cluster); its address."""
    address, env = start_cluster(tmp_path_factory.mktemp("ray"))
    ENV.clear()
    ENV.update(env)
    try:
        yield address
    finally:
        subprocess.run([RAY_CLI, "stop", "--force"], capture_output=True, timeout=120, env=ENV)


@pytest.fixture(scope="module")
def captures(tmp_path_factory, demo_capture):
    """Two copies of the demo capture and one that cannot load."""
    root = tmp_path_factory.mktemp("batch_captures")
    for name in ("alpha", "beta"):
        shutil.copytree(demo_capture, root / name)
    (root / "broken").mkdir()
    (root / "broken" / "transforms.json").write_text("{ not json")
    return root


def test_shard_ranges_cover_every_frame_once():
    assert shard_ranges(120, 2) == [(0, 60), (60, 120)]
    assert shard_ranges(7, 3) == [(0, 2), (2, 5), (5, 7)]
    assert shard_ranges(2, 5) == [(0, 1), (1, 2)]
    for n, k in ((1, 1), (13, 4), (100, 7)):
        r = shard_ranges(n, k)
        assert [i for a, b in r for i in range(a, b)] == list(range(n))
        assert max(b - a for a, b in r) - min(b - a for a, b in r) <= 1
    with pytest.raises(ValueError):
        shard_ranges(5, 0)


def test_plan_jobs_names_never_collide(tmp_path):
    (tmp_path / "a" / "take").mkdir(parents=True)
    (tmp_path / "b" / "take").mkdir(parents=True)
    jobs = plan_jobs([tmp_path / "a" / "take", tmp_path / "b" / "take", tmp_path / "a" / "take"], tmp_path / "out")
    assert [j.name for j in jobs] == ["take", "take_2"]
    assert len({j.run_dir for j in jobs}) == 2


def test_bad_addresses_get_one_line_naming_them():
    with pytest.raises(ClusterError, match="HOST:PORT"):
        split_address("localhost")
    port = _free_port()  # nothing listens there
    with pytest.raises(ClusterError, match=f"127.0.0.1:{port}"):
        check_reachable(f"127.0.0.1:{port}", timeout=2.0)


def test_unreachable_address_on_the_command_line(demo_capture, tmp_path):
    port = _free_port()
    t0 = time.perf_counter()
    r = _engine("batch", demo_capture, "--out", tmp_path / "b", "--address", f"127.0.0.1:{port}", *SETTINGS)
    assert r.returncode == 1
    err = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and f"127.0.0.1:{port}" in err[0], r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    assert time.perf_counter() - t0 < 60


def test_missing_ray_is_named_with_its_install_command(demo_capture, tmp_path):
    block = ("import sys\nclass B:\n    def find_spec(self, name, path=None, target=None):\n"
             "        if name == 'ray' or name.startswith('ray.'):\n            raise ImportError('no ray')\n"
             "sys.meta_path.insert(0, B())\nimport runpy\nsys.argv = ['engine'] + sys.argv[1:]\n"
             "runpy.run_module('engine', run_name='__main__')\n")
    r = subprocess.run([sys.executable, "-c", block, "batch", str(demo_capture), "--out", str(tmp_path / "b"),
                        *SETTINGS], cwd=REPO, capture_output=True, text=True, timeout=300, env=ENV)
    assert r.returncode == 1
    assert "pip install ray==" in r.stderr, r.stderr[-2000:]


@pytest.fixture(scope="module")
def batch(cluster, captures, tmp_path_factory):
    out = tmp_path_factory.mktemp("batch_out")
    r = _engine("batch", captures / "alpha", captures / "beta", captures / "broken", "--out", out,
                "--address", cluster, *SETTINGS)
    return {"out": out, "proc": r, "summary": json.loads((out / "batch.json").read_text())}


def test_batch_trains_each_capture_and_reports_the_broken_one(batch):
    r, s = batch["proc"], batch["summary"]
    assert r.returncode == 1, r.stderr[-3000:]  # one capture failed
    rows = {row["name"]: row for row in s["captures"]}
    assert set(rows) == {"alpha", "beta", "broken"}
    assert rows["broken"]["status"] == "failed" and "transforms.json" in rows["broken"]["error"]
    for name in ("alpha", "beta"):
        row = rows[name]
        assert row["status"] == "finished", row
        assert row["steps"] == STEPS and row["attempts"] == 1
        assert 10.0 < row["metrics"]["psnr"] < 40.0
        assert (batch["out"] / name / "checkpoint.pt").exists()
        assert json.loads((batch["out"] / name / "run.json").read_text())["status"] == "finished"
    assert s["counts"] == {"finished": 2, "failed": 1}
    assert s["cluster_cpus"] == 2.0  # both nodes joined
    assert "batch: 2 done" in r.stderr or "alpha finished" in r.stderr


def test_batch_run_equals_the_capture_trained_alone(batch, captures, tmp_path):
    """Same capture, same seed: the batch's eval PSNR equals a run trained alone (target: 0.05 dB)."""
    row = next(r for r in batch["summary"]["captures"] if r["name"] == "alpha")
    job = BatchJob(name="alone", capture=str(captures / "alpha"), run_dir=str(tmp_path / "alone"))
    alone = train_capture(job, BatchSettings(overrides={"schedule.iterations": STEPS}))
    assert alone["status"] == "finished"
    assert abs(alone["metrics"]["psnr"] - row["metrics"]["psnr"]) <= 0.05
    assert abs(alone["metrics"]["lpips"] - row["metrics"]["lpips"]) <= 0.005


def test_rerun_skips_what_finished(batch, captures, cluster):
    r = _engine("batch", captures / "alpha", captures / "beta", "--out", batch["out"], "--address", cluster,
                *SETTINGS)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "2 finished before" in r.stderr and "0 to train" in r.stderr
    assert all(len(read_attempts(batch["out"] / n)) == 1 for n in ("alpha", "beta"))
    other = _engine("batch", captures / "alpha", "--out", batch["out"], "--set", "schedule.iterations=41")
    assert other.returncode == 1 and "other settings" in other.stderr


def test_a_killed_worker_is_retried_and_resumes_its_checkpoint(cluster, captures, tmp_path):
    """The worker process training a capture is killed mid-run: Ray retries the task, the retry
    resumes from the last checkpoint (saved every second here) and the batch finishes."""
    out = tmp_path / "killed"
    interval = 1.0
    proc = subprocess.Popen([sys.executable, "-m", "engine", "batch", str(captures / "alpha"), "--out", str(out),
                             "--address", cluster, "--no-eval", "--set", "schedule.iterations=300",
                             "--set", f"schedule.checkpoint_every_s={interval}"],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    run = out / "alpha"
    deadline = time.time() + 300
    step_at_kill = 0
    try:
        while time.time() < deadline and proc.poll() is None:
            try:
                step_at_kill = int(json.loads((run / "run.json").read_text()).get("step") or 0)
            except (OSError, ValueError):
                step_at_kill = 0
            if step_at_kill >= 20:
                break
            time.sleep(0.2)
        assert step_at_kill >= 20, "the run never checkpointed"
        pid = read_attempts(run)[0]["pid"]
        checkpoint_age = time.time() - (run / "checkpoint.pt").stat().st_mtime
        os.kill(pid, signal.SIGKILL)
        stdout, stderr = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr[-3000:]
    attempts = read_attempts(run)
    assert len(attempts) == 2 and attempts[0]["pid"] == pid and attempts[1]["pid"] != pid
    row = json.loads((out / "batch.json").read_text())["captures"][0]
    assert row["status"] == "finished" and row["steps"] == row["total_steps"] == 300 and row["attempts"] == 2
    # the retry starts where the last checkpoint was: at most one checkpoint interval of work lost
    assert row["resumed_from"] == attempts[1]["checkpoint_step"] >= step_at_kill
    assert checkpoint_age < interval + 1.0


def test_sharded_render_writes_the_same_files_as_one_process(batch, cluster, tmp_path):
    """A 120-frame camera path over 2 Ray tasks: the same files, byte for byte, as one process."""
    from engine.cli.render import _first_train_view, orbit_from_result
    from engine.export.cached import load_result
    from engine.export.render_views import write_camera_file

    run = batch["out"] / "alpha"
    scene = load_result(run)
    views = orbit_from_result(scene, _first_train_view(scene, run), 60.0, 120, 0.0)
    t0, t1 = scene.time_range
    for i, v in enumerate(views):
        v.time = t0 + (t1 - t0) * i / 119
        v.name = f"frame_{i:04d}"
    path = write_camera_file(tmp_path / "path.json", views)
    one = _engine("render", run, "--path", path, "--out", tmp_path / "one", "--quiet")
    assert one.returncode == 0, one.stderr[-2000:]
    two = _engine("render", run, "--path", path, "--out", tmp_path / "two", "--shards", "2", "--address", cluster)
    assert two.returncode == 0, two.stderr[-2000:]
    assert "in 2 task(s)" in two.stderr
    a = sorted(p.name for p in (tmp_path / "one").iterdir())
    b = sorted(p.name for p in (tmp_path / "two").iterdir())
    assert a == b and len(a) == 120
    for name in a:
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes(), name
