"""The schedule's virtual clock (engine.train.loop.schedule): unchanged without a re-plan,
continuous and monotone through a budget run's re-plans, carried by checkpoints."""
from __future__ import annotations

import math
import threading

import numpy as np
import pytest
import torch

from engine.io.capture import load_capture
from engine.io.checkpoint import load_checkpoint
from engine.train import train
from engine.train.config import get_preset
from engine.train.loop import trainer as trainer_mod
from engine.train.loop.schedule import Schedule
from tools.synthetic import write_synthetic_capture


@pytest.fixture(scope="module")
def tiny_capture(tmp_path_factory):
    return write_synthetic_capture(tmp_path_factory.mktemp("tiny") / "cap", width=32, height=24, n_rgb=3,
                                   eval_fps=60.0, with_points=True)


def _old(cfg, total, step):
    """The schedules as the trainer computed them from ``step / total_steps`` before the clock."""
    s0 = int(round(cfg.schedule.static_fraction * total))
    lo, hi = int(cfg.densify.start * total), int(cfg.densify.stop * total)
    every = max(1, min(cfg.densify.every, max(1, (hi - lo) // 3)))
    deform = max(1, total - s0)
    f_start, f_every = s0 + int(0.3 * deform), max(1, deform // 20)
    return {"stage": "static" if step < s0 else "deform", "s0": s0,
            "curriculum": (step - s0) / max(1, total - s0),
            "lr": step / max(1, total - 1), "deform_lr": (step - s0) / max(1, total - s0 - 1),
            "sh": min(cfg.gaussians.sh_degree, int(step / max(1, cfg.gaussians.sh_step_fraction * total))),
            "stats": step < hi, "densify": lo <= step < hi and step > 0 and (step - lo) % every == 0 and step != lo,
            "freeze_check": step >= f_start and (step - f_start) % f_every == 0}


def _new(cfg, sch, step):
    s0 = sch.static_end(cfg.schedule.static_fraction)
    deform = max(1, sch.nominal - s0)
    return {"stage": "static" if step < sch.static_steps(cfg.schedule.static_fraction) else "deform",
            "s0": sch.static_steps(cfg.schedule.static_fraction),
            "curriculum": sch.deform_progress(step, cfg.schedule.static_fraction),
            "lr": sch.run_progress(step), "deform_lr": sch.deform_progress(step, cfg.schedule.static_fraction, last=1),
            "sh": sch.sh_degree(step, cfg), "stats": sch.in_densify_window(step, cfg),
            "densify": sch.densify_due(step, cfg),
            "freeze_check": sch.mark_at(step, s0 + int(0.3 * deform), max(1, deform // 20)) is not None}


@pytest.mark.parametrize("static_fraction", [0.0, 0.1, 0.3, 0.45])
def test_a_run_that_never_re_plans_keeps_every_schedule_bit_for_bit(static_fraction):
    cfg = get_preset("fast", {"static_fraction": static_fraction, "sh_degree": 2, "densify_every": 37})
    totals = [1, 2, 3, 7, 20, 41, 99, 100, 333, 1000, 1246, 1877]
    for total in totals:
        sch = Schedule.plan(total)
        for step in range(total):
            assert _new(cfg, sch, step) == _old(cfg, total, step), (total, step)


# the totals a 120 s full run on the between scene planned (run.json budget_estimates, main)
BETWEEN_REPLANS = [(71, 1246), (437, 1458), (582, 1941), (776, 1954), (971, 1860), (1157, 1820), (1339, 1842),
                   (1523, 1894), (1712, 1877)]


def _replanned(plan=1409, replans=BETWEEN_REPLANS):
    sch = Schedule.plan(plan)
    trace, i = [], 0
    for step in range(10 ** 5):
        if i < len(replans) and replans[i][0] == step:
            before = sch.virtual(step)
            sch.replan(*replans[i])
            assert sch.virtual(step) == before  # a re-plan keeps the clock where it is
            i += 1
        if step >= sch.total:
            break
        trace.append(sch.virtual(step))
    return sch, np.array(trace)


def test_re_plans_keep_the_clock_continuous_monotone_and_ending_at_the_end():
    sch, v = _replanned()
    assert len(v) == 1877 == sch.total and v[0] == 0.0
    dv = np.diff(v)
    assert (dv > 0).all()                                    # monotone: nothing un-admitted, no lr rebound
    assert dv.max() < 1.2 and dv.min() > 0.5                 # no jump: each step moves the clock < 1.2 steps
    assert v[-1] == pytest.approx(sch.nominal - dv[-1], abs=1e-6)  # the last step is the plan's last step
    # the old clock (step / total, the total clamped to keep the stage) restarted the deformation
    # stage at both clamped re-plans: the curriculum back to its first frame, the lrs back up
    cfg = get_preset("fast")
    for step, (before, after) in ((437, (1246, 1458)), (582, (1458, 1941))):
        old = [_old(cfg, t, step)["curriculum"] for t in (before, after)]
        assert old[0] > 0.07 and old[1] == 0.0


def test_trainer_reads_the_clock_through_a_re_plan(tiny_capture):
    """Every schedule the trainer reads (stage, curriculum window, lrs, SH) is continuous and
    monotone when a budget run re-plans mid-run; a schedule read from ``step / total_steps``
    jumps here (the curriculum window shrinks, the lr rises)."""
    cfg = get_preset("fast", {"init": "ply", "static_fraction": 0.3, "sh_degree": 2})
    tr = trainer_mod.Trainer(load_capture(tiny_capture), cfg, device="cpu", total_steps=100)
    tr.init_model()
    g = tr.model.gaussians
    seen = []
    for step in range(400):
        if step == 20:
            tr.schedule.replan(20, 50)    # static stage: the run got slower
        if step == 35:
            tr.schedule.replan(35, 200)   # deformation stage: faster than planned
        if step == 120:
            tr.schedule.replan(120, 150)
        if step >= tr.total_steps:
            break
        tr._update_lrs(step)
        lr = next(grp["lr"] for grp in g.optimizer.param_groups if grp["name"] == "means")
        seen.append((tr.stage_of(step) == "deform", tr.time_window(step), lr, tr.schedule.sh_degree(step, cfg)))
    deform, window, lr, sh = map(np.array, zip(*seen))
    assert len(seen) == 150
    assert (np.diff(deform.astype(int)) >= 0).all() and deform[-1] and not deform[0]
    assert (np.diff(window) >= -1e-12).all() and window[-1] == pytest.approx(tr.frame_times[-1])
    assert (np.diff(lr) <= 1e-15).all() and (np.diff(sh) >= 0).all()
    # no step moves the curriculum further than its plain per-step pace times the clock's rate
    span = tr.frame_times[-1] - tr.frame_times[0]
    pace = span / (cfg.schedule.time_curriculum * (100 - tr.schedule.static_end(0.3)))
    assert np.diff(window).max() <= pace * max(r for _, _, r in tr.schedule.segments) + 1e-9
    assert tr.static_steps == int(deform.argmax())


def test_schedule_survives_its_checkpoint():
    sch, _ = _replanned()
    back = Schedule.from_state(sch.state_dict(), 0)
    assert back == sch and all(back.virtual(s) == sch.virtual(s) for s in range(0, 1877, 7))
    assert Schedule.from_state(None, 300) == Schedule.plan(300)  # a checkpoint from before the clock


def test_replan_rejects_a_total_before_the_step():
    sch = Schedule.plan(100)
    sch.replan(10, 100)  # the same total: nothing to do
    assert sch.segments == [(0, 0.0, 1.0)]
    with pytest.raises(ValueError, match="step 10"):
        sch.replan(10, 10)


def test_cancel_and_resume_after_a_re_plan_equals_an_uninterrupted_run(tiny_capture, tmp_path, monkeypatch):
    """The checkpoint carries the re-planned clock: a resumed run continues the same schedule
    (a resume that re-planned from the plain total would train differently from step 23 on)."""
    step_fn = trainer_mod.Trainer.step

    def replanning_step(self, step):  # a budget run's re-plan, deterministic
        if step == 12 and self.total_steps == 30:
            self.schedule.replan(12, 45)  # stretched: still within the schedule's span (iterations 50)
        return step_fn(self, step)

    monkeypatch.setattr(trainer_mod.Trainer, "step", replanning_step)
    ov = {"iterations": 50, "schedule.steps": 30, "static_fraction": 0.25, "densify_from": 0.1, "densify_every": 10,
          "init": "ply"}
    full = tmp_path / "full"
    s = train(tiny_capture, full, overrides=ov, seed=3, device="cpu")
    assert s["step"] == s["total_steps"] == 45
    part = tmp_path / "part"
    cancel = threading.Event()
    s1 = train(tiny_capture, part, overrides=ov, seed=3, device="cpu", cancel=cancel,
               progress=lambda d: d["step"] == 23 and cancel.set())
    assert s1["status"] == "cancelled" and s1["step"] == 23
    assert load_checkpoint(part)["schedule"]["segments"][1] == [12, 12.0, 18 / 33]
    s2 = train(tiny_capture, part, overrides=ov, seed=3, device="cpu")
    assert s2["resumed_from"] == 23 and s2["step"] == 45
    a, b = load_checkpoint(full), load_checkpoint(part)
    assert a["schedule"] == b["schedule"]
    for k, v in a["model"]["gaussians"]["params"].items():
        torch.testing.assert_close(v, b["model"]["gaussians"]["params"][k], atol=1e-5, rtol=1e-4)
    assert not math.isnan(float(s2["loss"]))


def test_densify_window_follows_the_clock_and_its_cadence_the_real_steps():
    """The window is a share of the run; the cadence stays ``densify_every`` real steps (the
    gradient statistics gather per step), so a run stretched 2.5x densifies 2.5x as often."""
    cfg = get_preset("fast", {"densify_from": 0.1, "densify_until": 0.7, "densify_every": 10})
    sch = Schedule.plan(100)
    sch.replan(5, 255)                                   # the rest of the plan over 250 steps: 0.38 per step
    events = [s for s in range(sch.total) if sch.densify_due(s, cfg)]
    assert np.all(np.diff(events) == 10)
    assert sch.virtual(events[0] - 10) >= 10 and sch.virtual(events[-1]) < 70 <= sch.virtual(events[-1] + 10)
    assert len(events) == 15                             # 5 in the 100-step plan (20, 30, ..., 60)


def test_settle_monitor_compares_windows_of_whole_epochs():
    """A settling run shows every train frame once per epoch, so windows of whole epochs compare like with like:
    the first starts at the epoch boundary after the schedule; a window that gains under MIN_GAIN ends the run."""
    from engine.train.loop.settle import MIN_GAIN, MIN_WINDOW_STEPS, SettleMonitor

    mon = SettleMonitor(n_frames=20, from_step=1045)
    assert mon.start == 1060 and mon.window == 60 and mon.window >= MIN_WINDOW_STEPS
    mse = iter([0.5] * 15 + [1.0] * 60 + [0.9] * 60 + [0.9 * (1 - MIN_GAIN / 2)] * 60)  # a 10 % gain, then 0.5 %
    done = [s for s in range(1045, 1045 + 195) if mon.update(s, next(mse))]
    assert mon.means == pytest.approx([1.0, 0.9, 0.9 * (1 - MIN_GAIN / 2)])  # the steps before 1060 are not counted
    assert done[0] == 1239 and mon.converged_at == 1240 and mon.summary()["converged_at"] == 1240
    assert mon.update(1240, 5.0)  # once converged it stays so
