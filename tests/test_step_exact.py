"""Issue 13's exact step speed-ups change no number: RGB training with per-Gaussian
trajectories runs bit for bit the same with the column-weight curves + FusedAdam as with
the reference slice-by-slice curves + torch.optim.Adam (the grid neighbour search is
exact too but may pick another of two near-equal neighbours than the float32 dense search:
both runs here use the same search)."""
from __future__ import annotations

import pytest
import torch

from engine.io.capture import load_capture
from engine.scene import fused_adam, trajectory
from engine.train.config import get_preset
from engine.train.loop.trainer import Trainer
from tools.synthetic import write_synthetic_capture


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    cap = load_capture(write_synthetic_capture(tmp_path_factory.mktemp("ex") / "cap", width=32, height=24,
                                               n_rgb=4, eval_fps=60.0, with_points=True))
    # the knots are the RGB instants rounded to 1 ns (trajectory.default_knots); frames at
    # times with more decimals (i / 30 here) sit 1e-8 of a segment off their knot, where the
    # two evaluations agree to rounding only. Captures store 9 decimals (demo_capture).
    for f in cap.frames:
        f.time = round(f.time, 9)
    return cap


def _switch(monkeypatch, old: bool):
    monkeypatch.setattr(trajectory, "EVALUATOR", "torch" if old else "fast")
    monkeypatch.setattr(fused_adam, "ENABLED", not old)


@pytest.mark.slow
def test_rgb_training_is_bit_for_bit_the_reference(capture, monkeypatch):
    cfg = {"init": "ply", "iterations": 16, "static_fraction": 0.25, "motion": "trajectory",
           "traj_carry": "velocity", "densify_from": 0.1, "densify_until": 0.8, "densify_every": 4,
           }  # the dense step (LAZY_RGB_ONLY off, below), whose torch reference is bit for bit (lazy: to rounding)
    from engine.scene import gaussians as gaussians_mod

    monkeypatch.setattr(gaussians_mod, "LAZY_RGB_ONLY", False)
    trainers = []
    for old in (True, False):
        _switch(monkeypatch, old)
        tr = Trainer(capture, get_preset("fast", cfg), device="cpu", rgb_only=True)
        tr.init_model()
        trainers.append(tr)
    for step in range(16):
        for old, tr in zip((True, False), trainers):
            _switch(monkeypatch, old)
            tr.step(step)
        a, b = (tr.model.gaussians for tr in trainers)
        assert a.num_gaussians == b.num_gaussians
        for name in a.param_names:
            assert torch.equal(getattr(a, name), getattr(b, name)), (step, name)
    assert trainers[1].model.trajectory is not None


@pytest.mark.slow  # two demo trainers, ~1 min on the loaded 2-core machine
@pytest.mark.parametrize("before,rgb_only", [("step-before", True), ("step-before", False), ("sink-off", False)])
def test_default_training_is_bit_for_bit_before_the_flow_and_curve_kernels(before, rgb_only, demo_capture,
                                                                           monkeypatch):
    """The fast preset's own schedule on the demo (flow carry and births at the admitted
    instants; with the spike branch, curves between knots, every reader of a guided step): the
    engine as it is and bench-step's ``before`` variant keep the same parameters after every
    step. ``step-before``: torch's Lucas-Kanade flow, frames from disk, torch curve column ops;
    ``sink-off``: the curves' gradients summed by autograd, not in place (and the engine as it
    is did add in place)."""
    from engine.scene import trajectory
    from engine.train.loop.budget import warm_up_runtime
    from tools.bench_step import variant

    warm_up_runtime("cpu")
    added = []  # the curves' backward kernels that added into a gradient already there
    k = trajectory.KERNELS.module
    for name, adds in (("curve_at_backward", lambda a: a[-1]), ("residual_sq_backward_add", lambda a: True),
                       ("curve_at_backward_rows", lambda a: a[-1]), ("residual_sq_backward_rows", lambda a: a[-1])):
        kernel = getattr(k, name)
        monkeypatch.setattr(k, name, lambda *a, _k=kernel, _a=adds: (_a(a) and added.append(1), _k(*a))[1])
    cap = load_capture(demo_capture)
    steps = 40
    trainers = {}
    for v in (before, "current"):
        with variant(v):
            tr = Trainer(cap, get_preset("fast", {"iterations": steps}), device="cpu", rgb_only=rgb_only)
            tr.init_model()
        trainers[v] = tr
    for step in range(steps):
        for v, tr in trainers.items():
            n = len(added)
            with variant(v):
                tr.step(step)
            assert v != "sink-off" or len(added) == n  # sink-off: nothing added in place
        a, b = (tr.model.gaussians for tr in trainers.values())
        assert a.num_gaussians == b.num_gaussians
        for name in a.param_names:
            assert torch.equal(getattr(a, name), getattr(b, name)), (step, name)
    assert added  # later readers of a step (between-frame render, residual term, cover render) added in place
    assert trainers["current"].carry_info and trainers["current"].birth_info  # admissions ran the flow
