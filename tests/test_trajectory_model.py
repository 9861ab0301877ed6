"""Trajectories inside the model: densification, optimiser state, checkpoints, trainer (issue 11)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from engine.scene.gaussians import GaussianModel
from engine.scene.model import TRAJ_MEANS, TRAJ_QUATS, Model4D
from engine.scene.trajectory import evaluate, junctions, num_controls
from engine.train.config import get_preset

KNOTS = [0.0, 0.1, 0.2, 0.3]


def _model(n=40, seed=0):
    rng = np.random.default_rng(seed)
    g = GaussianModel(rng.normal(size=(n, 3)), rng.uniform(size=(n, 3)))
    g.setup_optimizer(get_preset("fast").gaussians, 1.0)
    m = Model4D(g)
    m.add_trajectories(KNOTS, 1e-3, 1e-3)
    m.use_deformation = True
    with torch.no_grad():
        getattr(g, TRAJ_MEANS).normal_()
        getattr(g, TRAJ_QUATS).normal_(std=0.1)
    return m


def test_attributes_follow_the_trajectory_and_static_rows_stay():
    m = _model()
    g = m.gaussians
    a = m.attributes(0.1)
    assert torch.allclose(a["means"], g.means + getattr(g, TRAJ_MEANS)[:, 3])
    assert torch.allclose(a["quats"], g.quats + getattr(g, TRAJ_QUATS)[:, 3])
    t = 0.137
    assert torch.allclose(m.attributes(t)["means"], g.means + evaluate(getattr(g, TRAJ_MEANS), KNOTS, t))
    m.static_mask = torch.zeros(g.num_gaussians, dtype=torch.bool)
    m.static_mask[:5] = True
    a = m.attributes(t)
    assert torch.equal(a["means"][:5], g.means[:5]) and not torch.equal(a["means"][5:], g.means[5:])


def test_densify_and_prune_carry_trajectory_rows_and_adam_state():
    m = _model()
    g = m.gaussians
    tm = getattr(g, TRAJ_MEANS)
    # one optimiser step so that Adam has moments for the trajectory rows
    (m.attributes(0.15)["means"] ** 2).sum().backward()
    g.optimizer.step()
    before = getattr(g, TRAJ_MEANS).detach().clone()
    with torch.no_grad():
        g.log_scales[:10] = np.log(0.5)  # big: split; the rest clone
        g.log_scales[10:] = np.log(0.01)
        g.opacity_logits[-3:] = -20.0  # pruned
    g.grad_accum[:] = 1.0
    g.grad_count[:] = 1.0
    info = g.densify_and_prune(grad_threshold=0.5, percent_dense=0.1, min_opacity=0.005, max_world_scale=100.0,
                               max_gaussians=1000, generator=torch.Generator().manual_seed(0))
    assert info["split"] == 10 and info["cloned"] == 30
    n = g.num_gaussians
    assert n == 40 - 10 - 3 + 30 + 20
    tm = getattr(g, TRAJ_MEANS)
    assert tm.shape == (n, num_controls(len(KNOTS)), 3) and getattr(g, TRAJ_QUATS).shape[0] == n
    keep = torch.ones(40, dtype=torch.bool)
    keep[:10] = False
    keep[-3:] = False
    kept = before[keep]
    assert torch.equal(tm[: int(keep.sum())], kept)  # survivors, in order
    clones = before[10:40]  # clone candidates (not split), including the 3 later pruned
    assert torch.equal(tm[27:57], clones)
    assert torch.equal(tm[57:67], before[:10]) and torch.equal(tm[67:77], before[:10])  # split halves
    st = g.optimizer.state[tm]
    assert st["exp_avg"].shape == tm.shape and float(st["exp_avg"][57:].abs().sum()) == 0.0
    assert float(st["exp_avg"][:27].abs().sum()) > 0
    g.prune(torch.arange(n) < 7)
    assert getattr(g, TRAJ_MEANS).shape[0] == n - 7 == g.optimizer.state[getattr(g, TRAJ_MEANS)]["exp_avg"].shape[0]


def test_state_round_trip_keeps_trajectories_and_optimiser():
    m = _model()
    g = m.gaussians
    (m.attributes(0.25)["means"] ** 2).sum().backward()
    g.optimizer.step()
    state = m.state()
    m2 = Model4D.from_state(state, get_preset("fast").gaussians)
    assert m2.trajectory == {"knots": KNOTS}
    for t in (0.0, 0.05, 0.3):
        assert torch.equal(m2.attributes(t)["means"], m.attributes(t)["means"])
    g2 = m2.gaussians
    names = [grp["name"] for grp in g2.optimizer.param_groups]
    assert TRAJ_MEANS in names and TRAJ_QUATS in names
    assert torch.equal(g2.optimizer.state[getattr(g2, TRAJ_MEANS)]["exp_avg"],
                       g.optimizer.state[getattr(g, TRAJ_MEANS)]["exp_avg"])


_TINY = {"iterations": 12, "static_fraction": 0.25, "init_max_points": 300, "init_random_points": 100,
         "densify_from": 0.3, "densify_until": 0.9, "densify_every": 3, "densify_grad_threshold": 0.0,
         "time_curriculum": 0.5}


@pytest.mark.slow  # ~1 min each on a loaded 2-core machine (stereo + flow for every instant)
@pytest.mark.parametrize("motion,carry", [("trajectory", "flow"), ("trajectory+hexplane", "velocity")])
def test_trainer_trains_trajectories_end_to_end(demo_capture, tmp_path, motion, carry):
    """Densification during the deformation stage, the time curriculum carrying the motion
    forward (scene flow or constant velocity), checkpoint + load_run + export sampling;
    rgb-only keeps it quick."""
    import json

    from engine.scene.model import load_run
    from engine.train import train

    over = {**_TINY, "motion": motion, "traj_carry": carry}
    summary = train(demo_capture, tmp_path / "run", preset="fast", overrides=over, rgb_only=True, resume=False)
    assert summary["status"] == "finished" and summary["step"] == 12
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    if carry == "flow":  # one record per admitted RGB instant; the demo's moving objects get carried
        rec = info["trajectory_carry"]
        assert len(rec) >= 2 and all(r["total"] > 0 for r in rec) and sum(r["carried"] for r in rec) > 0
        assert sum(r["held"] for r in rec) > 0  # the still background holds its place
    else:
        assert "trajectory_carry" not in info
    scene = load_run(tmp_path / "run")
    m = scene.model
    assert m.trajectory is not None and len(m.trajectory["knots"]) == 7
    assert (m.deformation is not None) == ("hexplane" in motion)
    g = m.gaussians
    n = g.num_gaussians
    assert getattr(g, TRAJ_MEANS).shape == (n, num_controls(7), 3)
    X = junctions(getattr(g, TRAJ_MEANS).detach())
    assert float(X.abs().max()) > 0  # the trajectories moved
    a = scene.gaussians_at(0.05)
    assert a["means"].shape == (n, 3) and np.isfinite(a["means"]).all()
    with torch.no_grad():
        ref = (g.means + evaluate(getattr(g, TRAJ_MEANS), m.trajectory["knots"], 0.05)).numpy()
    if m.deformation is None:
        np.testing.assert_allclose(a["means"], ref, atol=1e-6)
    from engine.export.npz import export_npz, read_export

    path = export_npz(scene, [0.0, 0.05, 0.1], tmp_path / "cache.npz")
    np.testing.assert_allclose(read_export(path, 1)["means"], a["means"], atol=1e-2)


def test_unknown_motion_is_an_error(demo_capture, tmp_path):
    from engine.train import train

    with pytest.raises(ValueError, match="motion"):
        train(demo_capture, tmp_path / "run", preset="fast", rgb_only=True, resume=False,
              overrides={**_TINY, "motion": "splines"})


def test_spike_guided_steps_move_inner_control_points(demo_capture):
    """With spikes (not rgb_only), the between-frame spike / block colour losses reach the
    trajectories' inner control points (E-NeMF's in-between curve), which RGB instants never touch."""
    from engine.io.capture import load_capture
    from engine.scene.trajectory import inner_residuals
    from engine.train.loop.trainer import Trainer

    over = {"iterations": 8, "static_fraction": 0.25, "init_max_points": 300, "init_random_points": 100,
            "densify_from": 2.0, "densify_until": 2.0, "block_interp": "linear", "between_colocated_p": 1.0,
            "time_curriculum": 0.0, "motion": "trajectory", "traj_carry": "velocity", "spike_skip_static": False}
    tr = Trainer(load_capture(demo_capture), get_preset("fast", over), device="cpu")
    tr.init_model()
    seen = set()
    for step in range(8):
        out = tr.step(step)
        seen |= set(out["losses"])
        assert np.isfinite(out["loss"])
    assert {"spike", "traj_reg"} <= seen
    d = inner_residuals(getattr(tr.model.gaussians, TRAJ_MEANS).detach())
    assert float(d.abs().max()) > 0
