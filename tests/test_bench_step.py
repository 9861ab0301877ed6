"""bench-step's profiler: every part of a step is charged, the parts add up to the step,
and the patched entry points are restored afterwards."""
from __future__ import annotations

import numpy as np
import pytest

from engine.raster import cpu as raster_cpu
from engine.scene import model as scene_model
from engine.scene.deformation import DeformationField
from tools import bench_step
from tools.synthetic import write_synthetic_capture


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return write_synthetic_capture(tmp_path_factory.mktemp("bs") / "cap", width=32, height=24, n_rgb=3,
                                   eval_fps=60.0, with_points=True)


def test_step_profile_charges_every_part_and_restores_the_patches(capture):
    before = (scene_model.rasterization, raster_cpu._RasterizeFused.backward, DeformationField.forward)
    prof, counts = bench_step.profile_runs(capture, 12, overrides={"init": "ply", "static_fraction": 0.25,
                                                                           "motion": "hexplane"},
                                           spike=False)
    assert (scene_model.rasterization, raster_cpu._RasterizeFused.backward, DeformationField.forward) == before
    static, deform = prof.table("static"), prof.table("rgb_deform")
    assert static["steps"] == 2 and deform["steps"] == 8  # 12 steps less the two set-up steps
    for tab in (static, deform):
        ms = tab["ms"]
        assert ms["raster_fwd"] > 0 and ms["raster_bwd"] > 0 and ms["losses"] > 0 and ms["optimizer"] > 0
        # exclusive times: the parts add up to the step (other is the remainder, never negative)
        assert sum(ms.values()) == pytest.approx(tab["step_ms"], rel=1e-6)
        assert ms["other"] >= 0
    assert static["ms"]["field_fwd"] == 0 and static["ms"]["field_bwd"] == 0  # no field in the static stage
    assert deform["ms"]["field_fwd"] > 0 and deform["ms"]["field_bwd"] > 0
    r = bench_step.ratios(prof)
    assert np.isfinite(r["rgb_step_over_raster"]) and r["rgb_step_over_raster"] > 1.0
    md = bench_step.markdown(prof)
    assert "| field_bwd |" in md and "guided_deform" not in md


def test_trajectory_curves_are_charged_to_the_field_rows(capture):
    """The default motion model (per-Gaussian curves): its evaluations and their backward are
    the field rows, not "other" (they read 0 there before)."""
    from engine.scene import trajectory

    before = (trajectory._CurveAt.forward, trajectory._CurveAt.backward)
    prof, _ = bench_step.profile_runs(capture, 12, overrides={"init": "ply", "static_fraction": 0.25,
                                                              "motion": "trajectory"}, spike=False)
    assert (trajectory._CurveAt.forward, trajectory._CurveAt.backward) == before
    static, deform = prof.table("static"), prof.table("rgb_deform")
    assert static["ms"]["field_fwd"] == 0 and static["ms"]["field_bwd"] == 0
    assert deform["ms"]["field_fwd"] > 0 and deform["ms"]["field_bwd"] > 0
    assert sum(deform["ms"].values()) == pytest.approx(deform["step_ms"], rel=1e-6)
    assert deform["ms"]["other"] >= 0


def test_variants_profile_both_code_paths_in_one_process(capture, monkeypatch):
    from engine.scene.deformation import HexPlane

    seen = []
    real = HexPlane.forward

    def spy(self, xyzt):
        seen.append(HexPlane.sampler)
        return real(self, xyzt)

    monkeypatch.setattr(HexPlane, "forward", spy)
    profs, counts = bench_step.compare_runs(capture, 8, overrides={"init": "ply", "static_fraction": 0.25,
                                                                   "motion": "hexplane"},
                                            spike=False, variants=("reference", "current"))
    assert set(profs) == {"reference", "current"} and HexPlane.sampler == "auto"  # restored
    assert {"torch", "auto"} <= set(seen)
    for prof in profs.values():
        for clock in bench_step.CLOCKS:
            tab = prof.table("rgb_deform", clock)
            assert tab["steps"] == 5 and tab["ms"]["field_bwd"] > 0
            assert sum(tab["ms"].values()) == pytest.approx(tab["step_ms"], rel=1e-6)


def test_guided_before_variant_patches_the_old_code_paths_and_restores_them():
    import torch

    from engine.train.frames import interpolation
    from engine.train.guidance import spike_guidance

    fl, cons = interpolation._flow_length, spike_guidance.flow_consistency
    with bench_step.variant("guided-before"):
        assert spike_guidance.FINE_ENCODER_EVERY == 0
        assert interpolation._flow_length is bench_step._norm_flow_length
        assert spike_guidance.flow_consistency(None, None) is None  # occlusion maps recomputed every time
        f = torch.randn(1, 2, 5, 6)
        old = interpolation._flow_length(f)
    assert (interpolation._flow_length, spike_guidance.flow_consistency) == (fl, cons)
    assert spike_guidance.FINE_ENCODER_EVERY == 1
    assert torch.allclose(interpolation._flow_length(f), old, atol=1e-6)  # same values, other code path


def test_trajectory_step_variants_switch_the_old_paths_and_restore_them():
    from engine.scene import fused_adam, trajectory
    from engine.train.motion import scene_flow

    now = (trajectory.EVALUATOR, fused_adam.ENABLED, scene_flow.DENSE_SEARCH)
    assert now == ("fast", True, False)
    with bench_step.variant("traj-before"):
        assert (trajectory.EVALUATOR, fused_adam.ENABLED, scene_flow.DENSE_SEARCH) == ("torch", False, True)
    for name, attr in (("traj-reference", (trajectory, "EVALUATOR")), ("adam-torch", (fused_adam, "ENABLED")),
                       ("nn-dense", (scene_flow, "DENSE_SEARCH"))):
        with bench_step.variant(name):
            assert getattr(*attr) != now[("traj-reference", "adam-torch", "nn-dense").index(name)]
    assert (trajectory.EVALUATOR, fused_adam.ENABLED, scene_flow.DENSE_SEARCH) == now


def test_guided_main_variants_switch_the_old_paths_and_restore_them():
    from engine.train.guidance import spike_flow, spike_guidance

    now = (spike_guidance.BETWEEN_DEPTH, spike_flow.inner_only_positions)
    assert now[0] is False
    with bench_step.variant("guided-main"):
        assert spike_guidance.BETWEEN_DEPTH is True
        assert spike_flow.inner_only_positions is bench_step._inner_only_positions_gather
    with bench_step.variant("flow-gather"):
        assert spike_flow.inner_only_positions is bench_step._inner_only_positions_gather
        assert spike_guidance.BETWEEN_DEPTH is False
    assert (spike_guidance.BETWEEN_DEPTH, spike_flow.inner_only_positions) == now


def test_refresh_before_variant_is_the_old_refresh_periods():
    """``refresh-before`` trains with the guided step's caches refreshed as before (every 10
    steps); the defaults are the new periods (docs/experiments/benchmark-history.md "The guided step's per-run
    work")."""
    from engine.train.guidance import quiet_curves, spike_flow, spike_flow_cache

    assert (spike_flow.SURFACE_EVERY, quiet_curves.REFRESH, spike_flow_cache.UPSAMPLE) == (30, 50, 2)
    with bench_step.variant("refresh-before"):
        assert (spike_flow.SURFACE_EVERY, quiet_curves.REFRESH) == (10, 10)
    assert (spike_flow.SURFACE_EVERY, quiet_curves.REFRESH) == (30, 50)


def test_flow_inline_variant_computes_the_flows_in_the_step():
    """``flow-inline`` is the flow term without its prefetch worker (the default has one, two
    intervals ahead: docs/experiments/benchmark-history.md "The guided step's per-run work")."""
    from engine.train.guidance import spike_flow_cache

    assert spike_flow_cache.PREFETCH == 2
    with bench_step.variant("flow-inline"):
        assert spike_flow_cache.PREFETCH == 0
    assert spike_flow_cache.PREFETCH == 2


def test_step_before_variant_switches_the_old_paths_and_restores_them():
    from engine.scene import trajectory
    from engine.train.frames import interpolation
    from engine.train.motion import scene_flow

    def state():
        return interpolation.FUSED_BOX, scene_flow.ITEM_IMAGES, trajectory.FUSED_FINITE, trajectory.FUSED_CURVES

    now = state()
    assert now == (True, True, True, True)
    with bench_step.variant("step-before"):
        assert state() == (False, False, False, False)
    assert state() == now


def test_rounds_alternate_the_runs_and_report_each_rounds_ratios(capture, monkeypatch):
    """``--rounds 2``: RGB, guided, RGB, guided; the tables cover every round's steps and each
    round's ratios are printed with their median."""
    order = []
    real = bench_step._profile_run

    def spy(cap, steps, preset, overrides, rgb_only, prof, device="cpu"):
        order.append(rgb_only)
        return real(cap, steps, preset, overrides, rgb_only, prof, device)

    monkeypatch.setattr(bench_step, "_profile_run", spy)
    over = {"init": "ply", "static_fraction": 0.25}
    profs, _ = bench_step.compare_runs(capture, 8, overrides=over, spike=True, rounds=2)
    assert order == [True, False, True, False]
    prof = profs["current"]
    assert len(prof.rounds) == 2
    for label in ("rgb_deform", "guided_deform"):
        parts = [p.table(label)["steps"] for p in prof.rounds]
        assert parts[0] > 0 and prof.table(label)["steps"] == sum(parts)
        # the merged step time is the step-weighted mean of the rounds'
        mean = sum(p.table(label)["step_ms"] * p.table(label)["steps"] for p in prof.rounds) / sum(parts)
        assert prof.table(label)["step_ms"] == pytest.approx(mean, rel=1e-9)
    text = bench_step.round_ratios(prof)
    per = [bench_step.ratios(p)["guided_step_over_rgb_step"] for p in prof.rounds]
    assert f"guided / RGB step by round: {per[0]:.2f}x, {per[1]:.2f}x; median {np.median(per):.2f}x" in text
    with pytest.raises(ValueError, match="rounds"):
        bench_step.compare_runs(capture, 8, overrides=over, spike=False, rounds=0)
