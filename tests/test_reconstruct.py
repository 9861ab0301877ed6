"""bpy.ops.bt4d.reconstruct: background (synchronous) run on the demo capture, the threaded
path with its timer, cancel + resume, and a failing capture that leaves everything as it was."""
from __future__ import annotations

import json
import shutil
import threading
import time
from pathlib import Path

import blender_util
import pytest
import roundtrip_util

bpy = pytest.importorskip("bpy")


from roundtrip_util import reconstructed, run_tmp  # noqa: E402,F401  (fixtures)


@pytest.fixture()
def scene():
    roundtrip_util.enable()
    return blender_util.reset_scene()


def test_job_messages_cancel_and_errors():
    worker = roundtrip_util.addon_module("bt4d_addon.worker")

    def target(progress, cancel, n):
        for i in range(n):
            if cancel.is_set():
                return {"status": "cancelled", "step": i}
            progress({"step": i + 1, "total_steps": n})
            time.sleep(0.01)
        return {"status": "finished", "step": n}

    job = worker.Job(target, n=5).start()
    job.join(5)
    msgs = job.poll()
    assert [m[0] for m in msgs] == ["progress"] * 5 + ["done"]
    assert job.finished and job.result == {"status": "finished", "step": 5}
    assert job.last_progress == {"step": 5, "total_steps": 5}

    gate = threading.Event()

    def slow(progress, cancel):
        gate.set()
        while not cancel.is_set():
            time.sleep(0.005)
        return {"status": "cancelled"}

    job = worker.Job(slow).start()
    gate.wait(5)
    job.cancel()
    job.join(5)
    job.poll()
    assert job.result == {"status": "cancelled"}

    def boom(progress, cancel):
        raise ValueError("bad capture file x.png")

    job = worker.Job(boom).run_sync()
    job.poll()
    assert job.finished and "bad capture file x.png" in job.error and "Traceback" in job.error_traceback


def test_job_run_sync_and_pump():
    """run_sync(progress) hands each progress message over as it is sent and returns a
    finished job; pump drains a threaded job into its watchers and finishes it once."""
    worker = roundtrip_util.addon_module("bt4d_addon.worker")

    def target(progress, cancel, n):
        for i in range(n):
            progress({"step": i + 1, "running": worker.is_running("test")})
        return {"status": "finished"}

    seen = []
    job = worker.Job(target, kind="test", n=3).run_sync(seen.append)
    assert seen == [{"step": i, "running": True} for i in (1, 2, 3)]
    assert job.finished and job.result == {"status": "finished"} and not worker.is_running("test")

    gate = threading.Event()

    def gated(progress, cancel):
        progress({"step": 1})
        gate.wait(5)
        progress({"step": 2})
        return "done"

    progressed, finished = [], []
    job = worker.Job(gated, kind="test").watch(progressed.append, finished.append).start()
    assert worker.active_job("test") is job and worker.is_running("test")
    deadline = time.monotonic() + 5
    while not progressed and time.monotonic() < deadline:
        assert job.pump()
        time.sleep(0.01)
    assert progressed == [{"step": 1}] and not finished
    gate.set()
    job.join(5)
    assert job.pump() is False and job.pump() is False
    assert progressed == [{"step": 1}, {"step": 2}] and finished == [job] and job.result == "done"
    assert worker.active_job("test") is None and not worker.is_running("test")


def test_reconstruct_background_mode(reconstructed):
    info = reconstructed
    assert info["op_result"] == {"FINISHED"}
    assert info["status"] == "FINISHED", info["message"]
    assert info["run_dir"] == info["expected_run_dir"]
    run = Path(info["run_dir"])
    meta = json.loads((run / "run.json").read_text())
    assert meta["status"] == "finished"
    assert (run / "checkpoint.pt").exists()
    assert info["step"] == info["total_steps"] == roundtrip_util.TRAIN_ITERATIONS
    # brought back automatically
    assert len(info["result_objects"]) == 1
    assert info["num_points"] % info["num_gaussians_attr"] == 0 and info["num_points"] >= 2 * info["num_gaussians_attr"]
    # the capture is never written to
    assert roundtrip_util.capture_fingerprint(info["capture"]) == info["fingerprint_before"]


def test_reconstruct_metrics_when_evaluate_exists(reconstructed):
    try:
        import engine.evaluate  # noqa: F401
    except ImportError:
        pytest.skip("engine.evaluate not available yet")
    assert reconstructed["has_metrics"], reconstructed["message"]
    assert reconstructed["metric_psnr"] > 5.0


def test_threaded_reconstruct_cancel_then_resume(scene, demo_capture, tmp_path):
    rec = roundtrip_util.addon_module("operators.reconstruct")
    worker = roundtrip_util.addon_module("bt4d_addon.worker")
    assert bpy.ops.bt4d.import_capture(directory=str(demo_capture)) == {"FINISHED"}
    scene = bpy.context.scene
    scene.bt4d.output_dir = str(tmp_path)
    scene.bt4d.preset = "fast"
    scene.bt4d.use_spikes = False
    n_objects = len(bpy.data.objects)

    def pump(job, until, deadline):
        while not until() and time.monotonic() < deadline:  # the timer's job, pumped by hand
            if not job.pump():
                return
            time.sleep(0.1)

    # run_mode THREAD: the interactive path (worker thread + timer) inside the bpy module,
    # where bpy.app.background is True and no timer fires; the test pumps the job instead
    assert bpy.ops.bt4d.reconstruct(iterations=16, run_mode="THREAD") == {"FINISHED"}  # returns at once
    job = worker.active_job(rec.KIND)
    r = scene.bt4d_run
    assert r.status == "RUNNING" and worker.is_running(rec.KIND) and job is not None
    deadline = time.monotonic() + 180
    pump(job, lambda: r.step >= 2, deadline)
    assert 0 < r.progress < 1 and r.total_steps == 16 and r.loss > 0
    assert bpy.ops.bt4d.cancel_reconstruction() == {"FINISHED"}
    pump(job, lambda: False, deadline)
    assert r.status == "CANCELLED", r.message
    assert not worker.is_running(rec.KIND)
    run = Path(r.run_dir)
    assert json.loads((run / "run.json").read_text())["status"] == "cancelled"
    assert (run / "checkpoint.pt").exists()
    stopped = r.step
    assert len(bpy.data.objects) == n_objects  # nothing brought back
    # Resume (the default) picks the checkpoint up: cancelled again at once, it reports
    # that it resumed from the step where the first run stopped
    assert bpy.ops.bt4d.reconstruct(iterations=16, run_mode="THREAD") == {"FINISHED"}
    job = worker.active_job(rec.KIND)
    bpy.ops.bt4d.cancel_reconstruction()
    pump(job, lambda: False, deadline)
    meta = json.loads((run / "run.json").read_text())
    assert meta["resumed_from"] == stopped and meta["status"] == "cancelled"
    assert r.status == "CANCELLED" and r.step == stopped


def test_failed_reconstruct_leaves_scene_untouched(scene, demo_capture, tmp_path):
    cap = tmp_path / "broken_capture"
    shutil.copytree(demo_capture, cap)
    victim = sorted((cap / "rgb").rglob("*.png"))[0]
    assert bpy.ops.bt4d.import_capture(directory=str(cap)) == {"FINISHED"}
    victim.write_bytes(victim.read_bytes()[:60])  # damaged after import
    scene = bpy.context.scene
    scene.bt4d.output_dir = str(tmp_path / "runs")
    before_objects = sorted(o.name for o in bpy.data.objects)
    fp = roundtrip_util.capture_fingerprint(cap)
    with pytest.raises(RuntimeError, match=victim.name):
        bpy.ops.bt4d.reconstruct(iterations=5)
    r = scene.bt4d_run
    assert r.status == "FAILED" and victim.name in r.message
    assert sorted(o.name for o in bpy.data.objects) == before_objects
    assert roundtrip_util.capture_fingerprint(cap) == fp


def test_sidebar_draws_every_state(scene):
    """The Reconstruction / Result / Bullet Time panel contents draw in every state."""
    pr = roundtrip_util.addon_module("bt4d_addon.panel_run")
    calls = []

    class Layout:
        def __getattr__(self, name):
            def f(*a, **k):
                calls.append(name)
                return Layout()
            return f

    ctx = bpy.context
    r = ctx.scene.bt4d_run
    for status in ("IDLE", "RUNNING", "FINISHED", "CANCELLED", "FAILED"):
        r.status = status
        r.message = "line 1\nline 2"
        pr.draw_reconstruction(Layout(), ctx)
    r.status, r.total_steps, r.step, r.progress = "RUNNING", 10, 3, 0.3
    calls.clear()
    pr.draw_reconstruction(Layout(), ctx)
    assert "progress" in calls and "operator" in calls
    calls.clear()
    pr.draw_advanced(Layout(), ctx)
    assert calls.count("prop") == 5  # motion, freeze, cracks, crack fill, early stop: in the sub-panel
    panel = roundtrip_util.addon_module("bt4d_addon.panel")
    assert panel.BT4D_PT_reconstruction_advanced.bl_parent_id == "BT4D_PT_reconstruction"
    assert "DEFAULT_CLOSED" in panel.BT4D_PT_reconstruction_advanced.bl_options
    r.has_metrics = True
    pr.draw_result(Layout(), ctx)
    pr.draw_bullet_time(Layout(), ctx)


def test_sidebar_warns_when_torch_is_missing(scene, monkeypatch):
    """Issue 45, defect 6: without torch the Reconstruction panel says so and opens the
    preferences (where Install Dependencies is) instead of letting Reconstruct fail."""
    pr = roundtrip_util.addon_module("bt4d_addon.panel_run")
    prefs = roundtrip_util.addon_module("bt4d_addon.preferences")
    drawn = []

    class Layout:
        def __getattr__(self, name):
            def f(*a, **k):
                drawn.append((name, a, k))
                return Layout()
            return f

    pr.draw_reconstruction(Layout(), bpy.context)
    assert not any(n == "operator" and a and a[0] == "preferences.addon_show" for n, a, _ in drawn)
    monkeypatch.setattr(prefs, "torch_location", lambda: None)
    drawn.clear()
    pr.draw_reconstruction(Layout(), bpy.context)
    labels = [k.get("text", "") for n, _, k in drawn if n == "label"]
    assert any("torch is not installed" in t for t in labels)
    assert any(n == "operator" and a and a[0] == "preferences.addon_show" for n, a, _ in drawn)
    assert bpy.ops.preferences.addon_show.poll() in (True, False)  # the operator exists in this Blender


def test_panel_and_command_line_start_from_the_same_defaults():
    """Issue 45: one set of defaults. The panel's preset and budget are the command line's (the
    preset's own step count, no budget), and --device means auto everywhere, as the panel."""
    import argparse

    from engine.cli import evaluate as cli_eval
    from engine.cli import export as cli_export
    from engine.cli import render as cli_render
    from engine.cli import train as cli_train
    from engine.train.config import DEFAULT_PRESET

    props = roundtrip_util.addon_module("bt4d_addon.properties")
    s = bpy.context.scene.bt4d
    defaults = {name: s.bl_rna.properties[name].default for name in ("preset", "seconds", "device")}
    assert defaults == {"preset": DEFAULT_PRESET, "seconds": 0.0, "device": "auto"}
    assert props.PRESET_ITEMS[0][0] == DEFAULT_PRESET
    for mod, argv in ((cli_train, ["cap", "--out", "r"]), (cli_eval, ["run"]), (cli_export, ["run", "--out", "o"]),
                      (cli_render, ["run", "--out", "o", "--orbit", "30"])):
        p = argparse.ArgumentParser()
        mod.add_arguments(p)
        args = p.parse_args(argv)
        assert args.device == "auto", mod.__name__
        if mod is cli_train:
            assert args.preset == DEFAULT_PRESET and args.seconds is None


def test_a_run_never_overwrites_another(tmp_path):
    """Issue 45, defect 7: with Resume on, changed settings used to start over in the same folder
    and overwrite the finished run. Now the same settings resume, others get their own folder."""
    rec = roundtrip_util.addon_module("operators.reconstruct")
    base = tmp_path / "runs" / "cap"
    wanted = {"capture": "/c", "preset": "fast", "overrides": {}, "rgb_only": False, "seed": 0}
    assert rec.choose_run_dir(str(base), wanted, True) == str(base)  # nothing there yet
    base.mkdir(parents=True)
    (base / "run.json").write_text(json.dumps(dict(wanted, status="finished", step=10)))
    assert rec.choose_run_dir(str(base), wanted, True) == str(base)  # same settings: resume it
    other = dict(wanted, rgb_only=True)
    second = rec.choose_run_dir(str(base), other, True)
    assert second == str(base.with_name("cap_2"))
    assert rec.choose_run_dir(str(base), wanted, False) == second  # restart: a new folder too
    Path(second).mkdir()
    (Path(second) / "run.json").write_text(json.dumps(dict(other, status="finished")))
    assert rec.choose_run_dir(str(base), other, True) == second  # and that one resumes in turn
    assert rec.choose_run_dir(str(base), dict(wanted, preset="quality"), True) == str(base.with_name("cap_3"))
    with_override = dict(wanted, overrides={"skip.early_stop": True})
    assert rec.choose_run_dir(str(base), with_override, True) == str(base.with_name("cap_3"))


def test_advanced_switches_reach_the_trainer_as_overrides(scene, demo_capture, tmp_path, monkeypatch):
    """"Freeze Static Gaussians" / "Stop Early" / "Motion" (scene.bt4d) become the training
    overrides freeze_static / early_stop / motion; off (or the default motion), nothing is passed."""
    worker = roundtrip_util.addon_module("bt4d_addon.worker")
    calls = []

    summary = {"status": "finished", "step": 3, "total_steps": 5, "stopped_early": {"step": 3, "total_steps": 5}}

    def fake_job(*, progress, cancel, **kw):
        calls.append(kw)
        return {"summary": dict(summary), "metrics": None, "samples": None, "run_dir": kw["run_dir"]}

    monkeypatch.setattr(worker, "reconstruct_job", fake_job)
    assert bpy.ops.bt4d.import_capture(directory=str(demo_capture)) == {"FINISHED"}
    s = bpy.context.scene.bt4d
    s.output_dir = str(tmp_path)
    assert bpy.ops.bt4d.reconstruct(iterations=5) == {"FINISHED"}
    assert calls[-1]["overrides"] == {"schedule.iterations": 5}
    s.freeze_static = True
    s.early_stop = True
    assert bpy.ops.bt4d.reconstruct(iterations=5) == {"FINISHED"}
    assert calls[-1]["overrides"] == {"schedule.iterations": 5, "skip.freeze_static": True, "skip.early_stop": True}
    s.freeze_static = False
    assert bpy.ops.bt4d.reconstruct() == {"FINISHED"}  # the default: no budget, the preset's steps
    assert calls[-1]["overrides"] == {"skip.early_stop": True} and calls[-1]["seconds"] is None
    s.seconds = 60.0
    assert bpy.ops.bt4d.reconstruct() == {"FINISHED"}
    assert calls[-1]["seconds"] == 60.0
    s.seconds = 0.0
    # its tooltip says what the engine does: held-back train frames, never the eval frames
    assert "never the eval frames" in s.bl_rna.properties["early_stop"].description
    # the time budget's tooltip says what a budget with time to spare does (engine.train.loop.settle)
    budget_tip = s.bl_rna.properties["seconds"].description
    assert "runs the preset's steps, settles, and finishes early once more steps stop paying" in budget_tip
    # "Motion": the engine's default (first item) passes nothing; another choice is passed
    from engine.train.config import TrainConfig
    assert s.motion == TrainConfig().motion.representation
    s.early_stop = False
    s.motion = "hexplane"
    assert bpy.ops.bt4d.reconstruct(iterations=5) == {"FINISHED"}
    assert calls[-1]["overrides"] == {"schedule.iterations": 5, "motion.representation": "hexplane"}
    s.motion = "trajectory"
    # "Close Cracks at New Views": on is the engine's default (nothing passed); off turns the term off
    from engine.train.config import get_preset
    assert s.close_cracks and get_preset("fast").losses.cover > 0
    s.close_cracks = False
    assert bpy.ops.bt4d.reconstruct(iterations=5) == {"FINISHED"}
    assert calls[-1]["overrides"] == {"schedule.iterations": 5, "losses.cover": 0.0}
    s.crack_fill = "opacities+means"  # off wins: no term, nothing else passed
    assert bpy.ops.bt4d.reconstruct(iterations=5) == {"FINISHED"}
    assert calls[-1]["overrides"] == {"schedule.iterations": 5, "losses.cover": 0.0}
    s.close_cracks = True
    # "Fill Cracks By": the engine's default (first item) passes nothing; "Move Only" is passed
    from engine.train.losses.geometry_losses import cover_grad_attrs
    assert TrainConfig().losses.cover_grad == "all" and cover_grad_attrs(s.crack_fill) == ("opacities", "means")
    assert bpy.ops.bt4d.reconstruct(iterations=5) == {"FINISHED"}
    assert calls[-1]["overrides"] == {"schedule.iterations": 5, "losses.cover_grad": "opacities+means"}
    s.crack_fill = "all"
    s.early_stop = True
    r = bpy.context.scene.bt4d_run
    assert r.status == "FINISHED" and "stopped early at step 3/5" in r.message
    # a budget run that settled after its schedule and converged says so, with the share of its time it used
    summary.update(stopped_early=None, step=180, total_steps=900, ended_by="converged", budget_used=0.14,
                   settle={"from_step": 80, "converged_at": 180})
    assert bpy.ops.bt4d.reconstruct(iterations=5) == {"FINISHED"}
    assert "converged after 180 steps, 14% of the time budget (the schedule ended at step 80" in r.message, r.message
    summary.pop("settle")
    # one whose budget went mostly into preparing the capture says that instead
    summary.update(step=3, total_steps=20, ended_by="budget", budget_used=1.3,
                   budget_estimates={"preparation_s": 146.0, "preparation_share": 1.22,
                                                     "preparation_heavy": True})
    assert bpy.ops.bt4d.reconstruct(iterations=5) == {"FINISHED"}
    assert "preparing the capture took 146 s, 122% of the time budget; 3 steps trained" in r.message, r.message
