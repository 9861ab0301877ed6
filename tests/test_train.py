"""Training end to end on tiny synthetic captures: recovery, motion, checkpoints, resume, presets."""
from __future__ import annotations

import json
import math
import threading

import numpy as np
import pytest
import torch
from train_util import fake_run

from engine.evaluate.heldout import evaluate
from engine.io.capture import load_capture
from engine.io.checkpoint import load_checkpoint, read_run_json
from engine.train import train
from engine.train.config import PRESETS, TrainConfig, get_preset
from engine.train.loop import budget as budget_mod
from engine.train.loop import run as run_mod
from engine.train.loop import trainer as trainer_mod
from engine.train.loop.budget import steps_for_budget
from engine.train.losses.terms import LossTerm
from tools.synthetic import write_synthetic_capture

TINY = dict(width=32, height=24, n_rgb=3, eval_fps=60.0)


@pytest.fixture(scope="module")
def static_capture(tmp_path_factory):
    return write_synthetic_capture(tmp_path_factory.mktemp("static") / "cap", width=40, height=30, n_rgb=2,
                                   eval_fps=30.0, static=True, train_cameras=4)


@pytest.fixture(scope="module")
def moving_capture(tmp_path_factory):
    return write_synthetic_capture(tmp_path_factory.mktemp("moving") / "cap", width=32, height=24, n_rgb=4,
                                   eval_fps=90.0, with_points=True, speed=(3.0, 0.0, 0.0))


@pytest.fixture(scope="module")
def tiny_capture(tmp_path_factory):
    return write_synthetic_capture(tmp_path_factory.mktemp("tiny") / "cap", with_points=True, **TINY)


def _params(run_dir):
    st = load_checkpoint(run_dir)
    return st["model"]["gaussians"]["params"], st["model"]["deformation"]


# ------------------------------------------------------------------------------- quality
def test_static_scene_is_recovered_from_random_init(static_capture, tmp_path):
    run = tmp_path / "run"
    s = train(static_capture, run, overrides={"iterations": 120, "init": "random", "static_fraction": 1.0,
                                              "init_random_points": 1500})
    assert s["status"] == "finished" and s["init"]["method"] == "random"
    assert s["ended_by"] == "steps" and s["budget_used"] is None  # no budget: it ran its steps
    m = evaluate(run)
    # an untrained model (random colours, opacity 0.1) scores ~10 dB on this scene
    assert m["psnr"] > 19.0, m
    assert m["ssim"] > 0.6, m
    # a static scene: every pixel is static, and a model without motion renders them alike at every instant
    assert m["static_fraction"] > 0.99 and abs(m["psnr_static"] - m["psnr"]) < 0.05, m
    assert m["static_colour_shift"] is None or m["static_colour_shift"] < 1e-4, m


@pytest.mark.slow
def test_deforming_scene_improves_with_training_and_beats_the_static_model(moving_capture, tmp_path):
    ov = {"iterations": 120, "init": "ply", "static_fraction": 0.25, "densify_until": 0.5}
    run = tmp_path / "dyn"
    cancel = threading.Event()

    def stop_at(d):
        if d["step"] == 50:
            cancel.set()

    s1 = train(moving_capture, run, overrides=ov, progress=stop_at, cancel=cancel)
    assert s1["status"] == "cancelled" and s1["step"] == 50
    mid = evaluate(run)
    s2 = train(moving_capture, run, overrides=ov)
    assert s2["status"] == "finished" and s2["resumed_from"] == 50 and s2["step"] == 120
    end = evaluate(run)
    assert end["psnr"] > mid["psnr"] + 0.3, (mid, end)
    assert end["psnr_dynamic"] > mid["psnr_dynamic"], (mid, end)

    static = tmp_path / "static"
    train(moving_capture, static, overrides={**ov, "static_fraction": 1.0})
    st = evaluate(static)
    assert end["psnr_dynamic"] > st["psnr_dynamic"] + 1.0, (st, end)
    assert end["psnr"] > st["psnr"], (st, end)
    assert end["n_interframe"] > 0 and end["psnr_interframe"] is not None
    # the moving blob actually moves in the trained model
    from engine.scene.model import load_run

    scene = load_run(run)
    a, b = scene.gaussians_at(0.0), scene.gaussians_at(0.1)
    moved = np.linalg.norm(b["means"] - a["means"], axis=1)
    assert moved.max() > 0.05


# ------------------------------------------------------------------------------- checkpoints and resume
@pytest.mark.parametrize("motion", ["trajectory", "hexplane"])
def test_cancel_then_resume_equals_an_uninterrupted_run(tiny_capture, tmp_path, motion):
    # on the CPU: there the step is deterministic. On a GPU gsplat's backward sums with atomics,
    # so two uninterrupted runs already differ in the last bits (and densify differently).
    ov = {"iterations": 40, "static_fraction": 0.4, "densify_from": 0.1, "densify_every": 10, "init": "ply",
          "motion": motion}
    full = tmp_path / "full"
    train(tiny_capture, full, overrides=ov, seed=3, device="cpu")

    part = tmp_path / "part"
    cancel = threading.Event()
    seen = []

    def progress(d):
        seen.append(d)
        if d["step"] == 23:
            cancel.set()

    s = train(tiny_capture, part, overrides=ov, seed=3, device="cpu", progress=progress, cancel=cancel)
    assert s["status"] == "cancelled" and s["step"] == 23
    info = read_run_json(part)
    assert info["status"] == "cancelled" and info["step"] == 23
    assert load_checkpoint(part)["step"] == 23
    keys = {"step", "total_steps", "stage", "loss", "psnr", "elapsed_s", "eta_s", "num_gaussians"}
    assert keys <= set(seen[0]) and seen[0]["stage"] == "static" and seen[-1]["stage"] == "deform"

    s2 = train(tiny_capture, part, overrides=ov, seed=3, device="cpu")
    assert s2["resumed_from"] == 23 and s2["step"] == 40 and s2["status"] == "finished"
    pa, da = _params(full)
    pb, db = _params(part)
    assert ("traj_means" in pa) == (motion == "trajectory") and (da is None) == (motion == "trajectory")
    for k in pa:
        torch.testing.assert_close(pa[k], pb[k], atol=1e-5, rtol=1e-4)
    for k, v in (da or {"state_dict": {}})["state_dict"].items():
        torch.testing.assert_close(v, db["state_dict"][k], atol=1e-5, rtol=1e-4)
    assert read_run_json(part)["status"] == "finished"

    # a finished run resumed again does nothing
    s3 = train(tiny_capture, part, overrides=ov, seed=3, device="cpu")
    assert s3["step"] == 40 and s3["resumed_from"] == 40


def test_config_change_or_restart_starts_over_but_keeps_the_old_checkpoint_until_replaced(tiny_capture, tmp_path):
    run = tmp_path / "run"
    train(tiny_capture, run, overrides={"iterations": 12, "init": "ply"})
    assert load_checkpoint(run)["step"] == 12
    during = []

    def progress(d):
        if d["step"] == 1:
            during.append(load_checkpoint(run)["step"])

    s = train(tiny_capture, run, overrides={"iterations": 12, "init": "ply"}, resume=False, progress=progress)
    assert s["resumed_from"] is None and during == [12]  # old checkpoint intact while restarting
    s = train(tiny_capture, run, overrides={"iterations": 14, "init": "ply"})  # different config
    assert s["resumed_from"] is None and s["step"] == 14


def test_checkpoint_writes_are_atomic(tiny_capture, tmp_path, monkeypatch):
    from engine.io import checkpoint as ck

    run = tmp_path / "run"
    train(tiny_capture, run, overrides={"iterations": 6, "init": "ply"})
    before = (run / ck.CHECKPOINT).read_bytes()

    def torn_save(obj, fh):
        fh.write(b"partial garbage")
        raise OSError("disk full")

    monkeypatch.setattr(ck.torch, "save", torn_save)
    with pytest.raises(OSError):
        ck.save_checkpoint(run, {"gaussians": 1})
    monkeypatch.undo()
    assert (run / ck.CHECKPOINT).read_bytes() == before
    assert not [p for p in run.iterdir() if p.name.endswith(".tmp")]
    assert load_checkpoint(run)["step"] == 6

    # a newer checkpoint that got corrupted falls back to the previous good one
    ck.save_checkpoint(run, load_checkpoint(run))
    (run / ck.CHECKPOINT).write_bytes(b"not a checkpoint")
    assert load_checkpoint(run)["step"] == 6


def test_failed_run_is_recorded(tiny_capture, tmp_path):
    def boom(d):
        if d["step"] == 2:
            raise RuntimeError("stop")

    with pytest.raises(RuntimeError):
        train(tiny_capture, tmp_path / "r", overrides={"iterations": 5, "init": "ply"}, progress=boom)
    info = read_run_json(tmp_path / "r")
    assert info["status"] == "failed" and "stop" in info["error"]


# ------------------------------------------------------------------------------- extension points
def test_loss_factories_extend_the_objective_unless_rgb_only(tiny_capture, tmp_path, monkeypatch):
    calls = []

    def factory(trainer):
        return [LossTerm("extra", 0.5, lambda ctx: calls.append(ctx.stage) or ctx.rgb.mean(), stages=("deform",))]

    train(tiny_capture, tmp_path / "a", overrides={"iterations": 6, "static_fraction": 0.5, "init": "ply"},
          loss_factories=[factory])
    assert calls == ["deform"] * 3
    calls.clear()
    train(tiny_capture, tmp_path / "b", overrides={"iterations": 6, "static_fraction": 0.5, "init": "ply"},
          rgb_only=True, loss_factories=[factory])
    assert calls == []


def test_run_json_layout(tiny_capture, tmp_path):
    run = tmp_path / "run"
    s = train(tiny_capture, run, preset="fast", overrides={"iterations": 4, "init": "ply"}, seed=1)
    info = json.loads((run / "run.json").read_text())
    for k in ("capture", "preset", "config", "status", "step", "train_seconds", "device", "created"):
        assert k in info
    assert info["capture"] == str(tiny_capture.resolve()) and info["status"] == "finished" and info["step"] == 4
    device = "cuda" if torch.cuda.is_available() else "cpu"  # train()'s default device
    assert info["config"]["schedule"]["iterations"] == 4 and info["device"] == device == s["device"]


# ------------------------------------------------------------------------------- presets and budget
def test_presets_exist_and_are_sized():
    assert set(PRESETS) == {"fast", "balanced", "quality"}
    f, b, q = (get_preset(n) for n in ("fast", "balanced", "quality"))
    assert f.schedule.iterations < b.schedule.iterations < q.schedule.iterations
    assert f.densify.max_gaussians < b.densify.max_gaussians < q.densify.max_gaussians
    assert not f.hexplane.deform_scale and f.gaussians.sh_degree == 0
    c = get_preset("fast", {"iterations": 7, "losses.background": [0.5, 0.5, 0.5]})
    assert c.schedule.iterations == 7 and c.losses.background == (0.5, 0.5, 0.5)
    assert get_preset("fast", {"schedule.iterations": 7}) == get_preset("fast", {"iterations": 7})
    with pytest.raises(KeyError):
        get_preset("fast", {"no_such_field": 1})
    with pytest.raises(KeyError):
        get_preset("ultra")
    assert TrainConfig.from_dict(c.to_dict()) == c


def test_motion_defaults_and_the_block_weight_by_motion():
    """Per-Gaussian trajectories carried by flow are the default motion; the block colour loss
    (Eq. 20) is on with the HexPlane field alone and off with trajectories unless asked for."""
    from engine.train.config import block_weight

    f = get_preset("fast")
    assert f.motion.representation == "trajectory" and f.motion.carry == "flow" and f.spike.block_loss_weight is None
    assert block_weight(f) == 0.0
    assert block_weight(get_preset("fast", {"motion": "hexplane"})) == 1.0
    assert block_weight(get_preset("fast", {"motion": "trajectory+hexplane"})) == 0.0
    c = get_preset("fast", {"block_loss_weight": 2})  # as `--set block_loss_weight=2` parses it
    assert c.spike.block_loss_weight == 2.0 and isinstance(c.spike.block_loss_weight, float) and block_weight(c) == 2.0
    assert block_weight(get_preset("fast", {"motion": "hexplane", "block_loss_weight": 0})) == 0.0
    assert TrainConfig.from_dict(f.to_dict()) == f


def test_steps_for_budget_scales_with_time():
    cfg = get_preset("fast")
    a = steps_for_budget(60, 0.05, 0.1, cfg)
    b = steps_for_budget(120, 0.05, 0.1, cfg)
    assert b == pytest.approx(2 * a, rel=0.02)
    per = (0.3 * 0.05 + 0.7 * 0.1) * 1.5
    assert a == int(60 / per)
    assert steps_for_budget(0.001, 1.0, 1.0, cfg) == 20  # never fewer than 20 steps


def test_seconds_budget_sizes_the_schedule(tiny_capture, tmp_path):
    run = tmp_path / "run"
    s = train(tiny_capture, run, seconds=4.0, overrides={"init": "ply"})
    info = read_run_json(run)
    assert s["status"] == "finished" and info["seconds_budget"] == 4.0
    assert s["total_steps"] == info["total_steps"] >= 20 and s["total_steps"] != get_preset("fast").schedule.iterations
    assert isinstance(s["stopped_by_budget"], bool)
    assert s["step"] == s["total_steps"] or s["stopped_by_budget"]
    # resuming keeps the step count chosen for the budget (no re-measurement)
    s2 = train(tiny_capture, run, seconds=4.0, overrides={"init": "ply"})
    assert s2["total_steps"] == s["total_steps"]


def test_the_budget_probe_leaves_the_run_as_it_was(tiny_capture):
    """The budget's throw-away steps run on a copy with a context of its own: the run's settings,
    model, clock and report are untouched (the probe changes its stage fractions and densification)."""
    import copy

    from engine.train.loop.budget import measure_step_seconds

    tr = trainer_mod.Trainer(load_capture(tiny_capture), get_preset("fast", {"init": "ply"}), device="cpu")
    tr.init_model()
    before = (copy.deepcopy(tr.cfg), tr.model, tr.schedule, tr.total_steps, copy.deepcopy(tr.run.info))
    t_s, t_d = measure_step_seconds(tr, n_static=2, n_deform=2)
    assert t_s > 0 and t_d > 0
    assert (tr.cfg, tr.model, tr.schedule, tr.total_steps, tr.run.info) == before
    assert tr.run.stage_of.__self__ is tr and tr.model.use_deformation is False


def test_fine_encoder_hook_trains_and_is_checkpointed(tiny_capture, tmp_path, monkeypatch):
    from torch import nn

    from engine.scene.model import load_run

    class Fine(nn.Module):
        def __init__(self, width):
            super().__init__()
            self.bias = nn.Parameter(torch.zeros(width))

        def forward(self, xyz, t):
            return self.bias.expand(xyz.shape[0], -1) * t

    def attach(trainer):
        d = trainer.model.deformation
        d.fine_encoder = Fine(d.feature_dim).to(trainer.device)
        if d.pending_fine_state:
            d.fine_encoder.load_state_dict(d.pending_fine_state)
        trainer.add_deformation_parameters(d.fine_encoder.parameters(), lr=1e-2, name="fine")

    def factory(trainer):
        trainer.deformation_hooks.append(attach)
        return []

    run = tmp_path / "run"
    train(tiny_capture, run, overrides={"iterations": 8, "static_fraction": 0.25, "init": "ply", "motion": "hexplane"},
          loss_factories=[factory])
    sd = load_checkpoint(run)["model"]["deformation"]["state_dict"]
    assert "fine_encoder.bias" in sd and float(sd["fine_encoder.bias"].abs().sum()) > 0  # it was optimised
    scene = load_run(run)  # inference without the extension still loads; the weights wait for it
    assert set(scene.model.deformation.pending_fine_state) == {"bias"}


def test_time_curriculum_admits_frames_in_order_and_carries_motion_forward(tiny_capture):
    from engine.io.capture import load_capture
    from engine.train.loop.trainer import Trainer

    cap = load_capture(tiny_capture)
    tr = Trainer(cap, get_preset("fast", {"init": "ply", "static_fraction": 0.2, "time_curriculum": 0.5,
                                          "motion": "hexplane"}),
                 device="cpu", total_steps=100)
    times = tr.frame_times
    assert len(times) == 3
    first = {i for i, it in enumerate(tr.items) if it["time"] == times[0]}
    assert set(tr.frame_pool(0)) == first and set(tr.frame_pool(19)) == first     # static: t0 only
    assert tr.time_window(20) == times[0] and tr.time_window(60) == pytest.approx(times[-1])
    assert set(tr.frame_pool(99)) == set(range(len(tr.items)))
    assert tr.time_window(40) == pytest.approx(times[0] + (times[-1] - times[0]) * 0.5)

    tr.init_model()
    tr.start_deformation()
    d = tr.model.deformation
    tr._carry_forward(times[0])           # first admitted instant: nothing to copy yet
    with torch.no_grad():
        for p in d.grid.temporal:
            p[:, :, 0, :] = 2.0           # pretend t0's time cell learned something
    tr._carry_forward(times[1])           # admitting t1 starts it from t0's motion
    for p in d.grid.temporal:
        assert torch.all(p == 2.0)
    xyz = tr.model.gaussians.means.detach()
    f0 = d.grid(torch.cat([d.normalize_xyz(xyz), torch.full((len(xyz), 1), -1.0)], 1))
    f1 = d.grid(torch.cat([d.normalize_xyz(xyz), torch.full((len(xyz), 1), d.normalize_time(times[1]))], 1))
    torch.testing.assert_close(f0, f1)


def test_loss_terms_block_and_stereo_depth():

    from engine.train.losses.terms import StepContext, _block_l1, _l1, _stereo_depth, default_loss_terms

    img = torch.zeros(1, 16, 16, 3)
    img[:, ::2, ::2] = 1.0                      # fine checker, mean 0.25 per 4x4 block
    flat = torch.full((1, 16, 16, 3), 0.25)
    trainer = fake_run()
    depth = torch.full((1, 16, 16, 1), 2.0)
    mask = torch.zeros(16, 16, dtype=torch.bool)
    mask[4:8] = True
    item = {"image": img, "stereo_depth": torch.full((16, 16), 2.5), "stereo_mask": mask}
    ctx = StepContext(trainer, 0, "static", item, flat, torch.ones(1, 16, 16, 1), {"depths": depth}, {})
    assert float(_l1(ctx)) > 0.3 and float(_block_l1(ctx)) == pytest.approx(0.0, abs=1e-6)
    assert float(_stereo_depth(ctx)) == pytest.approx(0.2)
    names = [t.name for t in default_loss_terms(get_preset("fast", {"lambda_depth": 0.0}))]
    assert names[:3] == ["l1", "dssim", "block_l1"] and "stereo_depth" not in names
    assert "stereo_depth" in [t.name for t in default_loss_terms(get_preset("fast"))]  # on by default (issue 14)


# ------------------------------------------------------------------------------- skipping
# freezing skips the HexPlane field (it turns itself off with trajectories)
FREEZE = {"motion": "hexplane", "freeze_static": True, "freeze_k_checks": 2}


def _freeze_early(monkeypatch, *, proxy_frames=2, **early):
    """The freezer's checks from the start of the deformation stage, ten per stage; the early
    stop's proxy of ``proxy_frames`` frames and its other constants as given (tiny runs)."""
    from engine.train.skipping import early_stop, freezing

    monkeypatch.setattr(freezing, "START_FRACTION", 0.0)
    monkeypatch.setattr(freezing, "CHECKS_PER_STAGE", 10)
    monkeypatch.setattr(early_stop, "PROXY_FRAMES", proxy_frames)
    for name, value in early.items():
        monkeypatch.setattr(early_stop, name, value)
# learning rates ~0 and no densification: nothing changes, the proxy PSNR is a plateau
FROZEN_LRS = {k: 1e-12 for k in ("lr_means", "lr_means_final", "lr_scales", "lr_quats", "lr_opacities", "lr_sh_dc",
                                 "lr_grid", "lr_mlp", "lr_traj", "lr_traj_final", "lr_traj_quats")}


def _frozen_field_lrs(monkeypatch):
    """The HexPlane's final learning rates (module constants) at ~0 too, for FROZEN_LRS."""
    monkeypatch.setattr(trainer_mod, "LR_GRID_FINAL", 1e-12)
    monkeypatch.setattr(trainer_mod, "LR_MLP_FINAL", 1e-12)


def test_freeze_static_freezes_the_static_background_rgb_only(tiny_capture, tmp_path, monkeypatch):
    _freeze_early(monkeypatch)
    ov = {"iterations": 40, "static_fraction": 0.25, "init": "ply", "densify_from": 2.0}
    off = train(tiny_capture, tmp_path / "off", overrides=ov, rgb_only=True)
    assert off["skips"] == {} and off["stopped_early"] is None
    assert load_checkpoint(tmp_path / "off")["model"]["static_mask"] is None

    run = tmp_path / "on"
    s = train(tiny_capture, run, overrides={**ov, **FREEZE}, rgb_only=True)
    fz = s["skips"]["freeze"]
    assert s["status"] == "finished" and s["step"] == 40
    assert fz["checks"] >= 5 and fz["fraction_frozen"] > 0.2, fz   # the wall does not move
    assert fz["num_gaussians"] == s["num_gaussians"]
    mask = load_checkpoint(run)["model"]["static_mask"]
    assert mask is not None and int(mask.sum()) == fz["frozen"] > 0
    assert read_run_json(run)["skips"]["freeze"] == fz
    # the frozen model is still a 4D model whose moving part moves
    from engine.scene.model import load_run

    scene = load_run(run)
    a, b = scene.gaussians_at(0.0), scene.gaussians_at(0.06)
    moved = np.linalg.norm(b["means"] - a["means"], axis=1)
    assert moved[mask.numpy()].max() == 0.0 and moved.max() > 0


def test_early_stop_stops_on_a_plateau_with_held_back_train_proxy(tiny_capture, tmp_path, monkeypatch):
    _freeze_early(monkeypatch)
    _frozen_field_lrs(monkeypatch)
    # births off: Gaussians born at admitted instants would end the plateau this test builds
    ov = {"iterations": 40, "static_fraction": 0.25, "init": "ply", "densify_from": 2.0, "early_stop": True,
          "birth_error": 0.0, **FROZEN_LRS}
    run = tmp_path / "es"
    s = train(tiny_capture, run, overrides=ov, rgb_only=True)
    st = s["stopped_early"]
    assert s["status"] == "finished" and st is not None and st["proxy"] == "held_back_train"
    assert s["step"] == st["step"] < s["total_steps"] == 40
    # evaluations every 2 steps (1, 3, 5, ...); the deformation stage (from step 10) must run
    # 25% of its 30 steps before 3 evaluations without a gain (19, 21, 23) stop it
    assert st["step"] == 23, st
    info = read_run_json(run)
    assert info["status"] == "finished" and info["stopped_early"] == st and info["step"] == st["step"]
    assert info["ended_by"] == s["ended_by"] == "converged"
    proxy = info["early_stop_proxy"]
    # the proxy is train frames (one camera each at the 2nd and 3rd instant), never eval frames
    assert proxy["source"] == "held_back_train" and len(proxy["frames"]) == 2
    assert proxy["frames"] == ["train:rgb0@0.033333", "train:rgb1@0.066667"], proxy
    cap = load_capture(tiny_capture)
    assert not {str(f.path) for f in cap.eval_frames} & set(proxy["frames"])
    # resuming a run that stopped early does not train on
    s2 = train(tiny_capture, run, overrides=ov, rgb_only=True)
    assert s2["resumed_from"] == st["step"] == s2["step"] and s2["stopped_early"] == st
    # without the switch the same plateau runs to the end (and nothing is held back)
    s3 = train(tiny_capture, tmp_path / "off", overrides={**ov, "early_stop": False})
    assert s3["step"] == 40 and s3["stopped_early"] is None
    assert "early_stop_proxy" not in read_run_json(tmp_path / "off")


def test_early_stop_holds_back_train_frames_and_never_scores_eval_frames(tiny_capture, monkeypatch):
    """The held-back frames leave the training set, and the proxy scores them (not eval)."""
    _freeze_early(monkeypatch)
    ov = {"iterations": 10, "init": "ply", "early_stop": True}
    cap = load_capture(tiny_capture)
    tr = trainer_mod.Trainer(cap, get_preset("fast", ov), device="cpu", rgb_only=True)
    held = {(f.camera, round(f.time, 6)) for f in tr.held_back}
    assert held == {("rgb0", round(1 / 30, 6)), ("rgb1", round(2 / 30, 6))}
    trained = {(it["camera"], round(it["time"], 6)) for it in tr.items}
    assert len(trained) == 4 and not held & trained
    # every instant is still trained by one camera
    assert {t for _, t in trained} == {0.0, round(1 / 30, 6), round(2 / 30, 6)}
    eval_times = {round(f.time, 6) for f in cap.eval_frames}
    es = tr.early_stop
    assert [round(vt["time"], 6) for vt in es.frames] == sorted(t for _, t in held)
    # the proxy images are the held-back train images, not eval images at those times
    for vt, f in zip(es.frames, tr.held_back):
        np.testing.assert_array_equal(vt["image"][0].numpy(), np.asarray(f.load_rgb(), np.float32)[..., :3])
    assert eval_times  # the capture has eval frames: they were available and not used
    tr.init_model()
    monkeypatch.setattr(cap.eval_frames[0].__class__, "load_rgb",
                        lambda self: (_ for _ in ()).throw(AssertionError("eval frame read")), raising=True)
    assert np.isfinite(es.score(tr.model))
    # and the CLI's help says so (it promised "held-out eval frames" while the code held back train frames)
    from engine.cli.train import SKIP_HELP
    early = SKIP_HELP[SKIP_HELP.index("early_stop=true"):SKIP_HELP.index("cull_frustum=true")]
    assert "held back from training" in early and "never the eval frames" in early


def test_early_stop_is_off_without_a_multi_camera_instant(tiny_capture, tmp_path, monkeypatch):
    _freeze_early(monkeypatch)
    import shutil

    cap = tmp_path / "mono"
    shutil.copytree(tiny_capture, cap)
    tj = json.loads((cap / "transforms.json").read_text())
    tj["frames"] = [f for f in tj["frames"] if f["camera"] != "rgb1"]
    tj["cameras"].pop("rgb1")
    (cap / "transforms.json").write_text(json.dumps(tj))
    ov = {"iterations": 12, "init": "ply", "early_stop": True}
    s = train(cap, tmp_path / "run", overrides=ov, rgb_only=True)
    assert s["step"] == 12 and s["stopped_early"] is None
    note = read_run_json(tmp_path / "run")["early_stop_proxy"]
    assert note["source"] is None and "no train frame can be held back" in note["note"]


def test_cull_frustum_prunes_gaussians_behind_every_camera(tiny_capture, tmp_path, monkeypatch):
    # the cameras sit at y=-1.5 facing +y
    behind = np.array([[0.0, -10.0, 0.0], [0.5, -12.0, 0.3], [-0.4, -9.0, -0.2]], np.float32)
    orig = trainer_mod.initial_points

    def with_behind(*a, **k):
        pts = orig(*a, **k)
        pts.xyz = np.concatenate([pts.xyz, behind])
        pts.rgb = np.concatenate([pts.rgb, np.full((len(behind), 3), 0.5, np.float32)])
        return pts

    monkeypatch.setattr(trainer_mod, "initial_points", with_behind)
    ov = {"iterations": 8, "static_fraction": 0.5, "init": "ply", "densify_from": 2.0}
    off = train(tiny_capture, tmp_path / "off", overrides=ov, rgb_only=True)
    s = train(tiny_capture, tmp_path / "on", overrides={**ov, "cull_frustum": True}, rgb_only=True)
    cull = s["skips"]["cull"]
    assert cull["pruned"] >= len(behind) and cull["events"][0]["step"] == 0, cull
    assert s["num_gaussians"] == off["num_gaussians"] - cull["pruned"]
    means = load_checkpoint(tmp_path / "on")["model"]["gaussians"]["params"]["means"]
    assert float(means[:, 1].min()) > -5.0          # the ones behind the cameras are gone
    assert float(load_checkpoint(tmp_path / "off")["model"]["gaussians"]["params"]["means"][:, 1].min()) < -5.0


def test_skip_state_survives_cancel_and_resume(tiny_capture, tmp_path, monkeypatch):
    _freeze_early(monkeypatch, MIN_DEFORM_FRACTION=0.9, EVERY_FRACTION=0.1)
    ov = {"iterations": 40, "static_fraction": 0.4, "densify_from": 0.1, "densify_every": 10, "init": "ply",
          **FREEZE, "early_stop": True, "cull_frustum": True}
    full = tmp_path / "full"
    s_full = train(tiny_capture, full, overrides=ov, seed=3, device="cpu", rgb_only=True)
    assert s_full["skips"]["freeze"]["frozen"] > 0  # the freezer had something to carry over

    part = tmp_path / "part"
    cancel = threading.Event()

    def progress(d):
        if d["step"] == 19:  # after the checks at steps 16 and 18, before the densification at 20
            cancel.set()

    s = train(tiny_capture, part, overrides=ov, seed=3, device="cpu", progress=progress, cancel=cancel, rgb_only=True)
    assert s["status"] == "cancelled" and s["step"] == 19 and s["skips"]["freeze"]["frozen"] > 0
    s2 = train(tiny_capture, part, overrides=ov, seed=3, device="cpu", rgb_only=True)
    assert s2["resumed_from"] == 19 and s2["step"] == s_full["step"]
    a, b = load_checkpoint(full), load_checkpoint(part)
    for k, v in a["model"]["gaussians"]["params"].items():
        torch.testing.assert_close(v, b["model"]["gaussians"]["params"][k], atol=1e-5, rtol=1e-4)
    assert torch.equal(a["model"]["static_mask"], b["model"]["static_mask"])
    fa, fb = a["skips"]["freeze"], b["skips"]["freeze"]
    assert torch.equal(fa["freezer"]["frozen"], fb["freezer"]["frozen"])
    assert torch.equal(fa["freezer"]["streak"], fb["freezer"]["streak"])
    assert fa["num_checks"] == fb["num_checks"] and fa["woken"] == fb["woken"]
    ea, eb = a["skips"]["early_stop"], b["skips"]["early_stop"]
    assert [h["step"] for h in ea["history"]] == [h["step"] for h in eb["history"]]
    np.testing.assert_allclose([h["proxy_psnr"] for h in ea["history"]], [h["proxy_psnr"] for h in eb["history"]],
                               atol=1e-3)
    assert a["skips"]["cull"]["pruned"] == b["skips"]["cull"]["pruned"]
    assert s2["skips"]["freeze"] == s_full["skips"]["freeze"]


def test_seconds_budget_is_re_estimated_from_the_real_steps(tiny_capture, tmp_path, monkeypatch):
    """The probe sees an idle machine (5 ms/step); the real steps take 50 ms (a loaded one):
    the re-estimate after ~5% of the run shrinks the schedule so that it fits the budget."""
    import time as _time

    monkeypatch.setattr(run_mod, "measure_step_seconds", lambda trainer: (0.005, 0.005))

    def slow_step(self, step):
        _time.sleep(0.05)
        return {"loss": 0.0, "psnr": 0.0, "stage": self.stage_of(step), "losses": {}, "densify": {}}

    monkeypatch.setattr(trainer_mod.Trainer, "step", slow_step)
    run = tmp_path / "run"
    s = train(tiny_capture, run, seconds=5.0, overrides={"init": "ply", "static_fraction": 0.9})
    est = read_run_json(run)["budget_estimates"]
    probe, measured = est["probe"], est["measured"]
    assert probe["total_steps"] > 150                         # ~4 s at 7.5 ms a step
    assert measured["at_step"] == budget_mod.reestimate_at(probe["total_steps"])
    assert measured["static_step_s"] == pytest.approx(0.05, rel=0.5)
    assert measured["total_steps"] < probe["total_steps"] / 4
    # the deformation stage (the last 10%) re-plans from its own rate, then fills time left at the end
    assert s["total_steps"] == read_run_json(run)["total_steps"] >= measured["total_steps"]
    assert s["total_steps"] == measured["total_steps"] or est["deform"][-1]["total_steps"] == s["total_steps"]
    # a fill aims at the budget's end (less the final checkpoint's reserve): the hard stop may cut its last step
    assert s["status"] == "finished" and (s["step"] == s["total_steps"] or s["stopped_by_budget"])
    assert s["budget_estimates"] == est


@pytest.mark.parametrize("profile", ["cheaper", "growing", "faster_at_the_end"])
def test_seconds_budget_run_ends_within_5_percent_of_its_budget(tiny_capture, tmp_path, monkeypatch, profile):
    """The deformation stage's cost is unknown up front: cheaper than probed (a run sized
    by the probe alone ends far too early, issue 13), growing step by step (densification),
    or dropping after the last re-estimate (a loaded machine freed: the plan runs out with
    time left, which the run fills with more steps). It ends within 5% of its budget."""
    import time as _time

    monkeypatch.setattr(run_mod, "measure_step_seconds", lambda trainer: (0.01, 0.02))

    def step(self, i):
        if self.stage_of(i) == "static":
            cost = 0.01
        elif profile == "cheaper":
            cost = 0.006
        elif profile == "faster_at_the_end":
            cost = 0.003 if self.schedule.run_progress(i) > 0.92 else 0.03
        else:
            cost = 0.01 + 0.02 * min(1.0, i / max(1, self.total_steps))
        _time.sleep(cost)  # still improving: a fill past the schedule's end settles but does not converge
        return {"loss": 0.0, "psnr": 0.01 * i, "stage": self.stage_of(i), "losses": {}, "densify": {}}

    monkeypatch.setattr(trainer_mod.Trainer, "step", step)
    budget = 6.0
    s = train(tiny_capture, tmp_path / "run", seconds=budget, overrides={"init": "ply", "static_fraction": 0.2})
    est = s["budget_estimates"]
    assert len(est["deform"]) >= 3, est
    assert 0.95 * budget <= s["train_seconds"] <= budget + 0.3, s
    assert s["ended_by"] == "budget" and s["budget_used"] >= 0.95  # run.json says so
    assert s["step"] >= 0.97 * s["total_steps"]  # the schedule ran (nearly) to its end
    assert read_run_json(tmp_path / "run")["budget_estimates"]["deform"] == est["deform"]


def test_deformation_re_estimate_keeps_the_stage(tiny_capture):
    from engine.train.loop.budget import reestimate_deform_steps
    from engine.train.loop.trainer import Trainer

    cfg = get_preset("fast", {"init": "ply", "static_fraction": 0.3})
    tr = Trainer(load_capture(tiny_capture), cfg, device="cpu", total_steps=1000)
    rec = reestimate_deform_steps(tr, 400, 0.01, remaining_s=5.0)    # 500 more steps fit
    assert rec["total_steps"] == 900 and rec["previous_total_steps"] == 1000
    rec = reestimate_deform_steps(tr, 400, 0.001, remaining_s=100.0)  # 1e5 more: step / total would be static again
    assert rec["total_steps"] == 100400 and int(round(0.3 * rec["total_steps"])) > 400
    tr.schedule.replan(400, rec["total_steps"])                        # the schedule's clock keeps the stage
    assert tr.stage_of(400) == "deform" and tr.static_steps == 300
    rec = reestimate_deform_steps(tr, 400, 0.5, remaining_s=-1.0)     # over budget: the next step still runs
    assert rec["total_steps"] == 401


def test_a_run_longer_than_its_schedule_settles_after_it(tiny_capture):
    """A budget or ``schedule.steps`` that buys more steps than ``iterations`` runs the schedule at its own
    length and then settles: the clock holds its end value (stretching the schedule to the budget overfit the
    two train views: docs/experiments/settle-after-the-schedule.md). No step cap: the budget plans what fits."""
    from engine.train.loop.budget import reestimate_deform_steps
    from engine.train.loop.trainer import Trainer

    assert steps_for_budget(1e6, 0.01, 0.01, get_preset("fast")) > 10 ** 7
    tr = Trainer(load_capture(tiny_capture), get_preset("fast", {"init": "ply", "iterations": 300}), device="cpu",
                 total_steps=500)
    sch = tr.schedule
    assert (sch.nominal, sch.total, sch.settle_from()) == (300, 500, 300)
    assert sch.virtual(299) == sch.virtual(450) == 299 and sch.run_progress(450) == 1.0
    assert not sch.settling(299) and sch.settling(300) and sch.settling(499)
    assert not sch.in_densify_window(450, tr.cfg) and sch.static_steps(0.3) == 90
    rec = reestimate_deform_steps(tr, 200, 0.001, remaining_s=100.0)  # 1e5 more fit: all of them planned
    assert rec["total_steps"] == 100200
    sch.replan(200, rec["total_steps"])  # the schedule still ends at step 300
    assert sch.settle_from() == 300 and sch.virtual(299) == 299 and sch.total == 100200
    short = Trainer(load_capture(tiny_capture), get_preset("fast", {"init": "ply", "iterations": 300}),
                    device="cpu", total_steps=200).schedule  # a budget that buys less compresses it
    assert (short.nominal, short.settle_from()) == (200, 200)
    short.replan(100, 400)  # a re-plan that buys more stretches it at most to iterations, then settles
    assert 298 <= short.settle_from() <= 300 and short.virtual(350) == 199
    plain = Trainer(load_capture(tiny_capture), get_preset("fast", {"init": "ply"}), device="cpu").schedule
    assert plain.settle_from() == plain.total == 1000  # a plain run never settles
    longer = Trainer(load_capture(tiny_capture), get_preset("fast", {"init": "ply", "schedule.steps": 4000}),
                     device="cpu").schedule
    assert (longer.nominal, longer.total, longer.settle_from()) == (1000, 4000, 1000)


def test_settling_lowers_every_lr_but_the_positions(tiny_capture, tmp_path):
    """Past its schedule a run trains scales, rotations, opacities, colours and rotation curves at
    SETTLE_LR x their lr, SETTLE_DECAY-fold less every schedule's length (at their full lr two fixed views
    collapsed the new view: 154, 1000 + 3000 steps, 22.04 -> 16.89 dB); the positions' and curves' lrs stay at
    their decayed final values."""
    from engine.train.loop.settle import SETTLE_DECAY, SETTLE_LR

    base = {"init": "ply", "iterations": 20, "static_fraction": 0.3}
    s = train(tiny_capture, tmp_path / "a", overrides={**base, "schedule.steps": 26})
    assert s["step"] == 26 and s["ended_by"] == "steps"
    t = train(tiny_capture, tmp_path / "b", overrides=base)
    assert t["step"] == 20
    cfg, means = get_preset("fast"), []
    # the checkpoint holds the last step's lrs: step 25, the 6th settling step, 5 steps after the first
    for run, f in ((tmp_path / "a", SETTLE_LR * SETTLE_DECAY ** (5 / 20)), (tmp_path / "b", 1.0)):
        groups = {g["name"]: g["lr"] for g in load_checkpoint(run)["model"]["gaussians"]["optimizer"]["param_groups"]}
        assert groups["opacity_logits"] == pytest.approx(cfg.gaussians.lr_opacities * f)
        assert groups["log_scales"] == pytest.approx(cfg.gaussians.lr_scales * f)
        assert groups["traj_quats"] == pytest.approx(cfg.motion.lr_traj_quats * f)
        means.append(groups["means"])
    assert means[0] == pytest.approx(means[1])  # the positions: at their final lr either way


@pytest.mark.parametrize("gain", [0.0, 0.002])
def test_a_budget_run_past_its_schedule_ends_when_it_converges(tiny_capture, tmp_path, monkeypatch, gain):
    """Cheap steps and a long budget: the run takes its schedule's steps, settles, and ends as soon as a window
    of whole epochs of train frames gains less than 1 % on the one before (run.json ``settle``, ``ended_by``
    converged, said in one line); a run that keeps gaining uses its budget."""
    import time as _time

    from engine.train.loop.settle import MIN_WINDOW_STEPS

    monkeypatch.setattr(run_mod, "measure_step_seconds", lambda trainer: (0.002, 0.002))

    def step(self, i):
        _time.sleep(0.002)  # gain: the train frames' PSNR rises this many dB a step (MSE -4.5 % per 50 steps)
        return {"loss": 0.0, "psnr": 20.0 + gain * i, "stage": self.stage_of(i), "losses": {}, "densify": {}}

    monkeypatch.setattr(trainer_mod.Trainer, "step", step)
    budget = 4.0
    s = train(tiny_capture, tmp_path / "run", seconds=budget,
              overrides={"init": "ply", "iterations": 40, "static_fraction": 0.2})
    info = read_run_json(tmp_path / "run")
    assert s["status"] == "finished" and info["budget_estimates"]["schedule_steps"] == 40
    assert info["settle"] == s["settle"] and s["settle"]["from_step"] == 40
    from engine.cli.train import ended_note
    if gain == 0.0:
        window = s["settle"]["window_steps"]
        assert window >= MIN_WINDOW_STEPS and len(s["settle"]["train_mse"]) == 2
        assert s["step"] == s["settle"]["converged_at"] <= 40 + 3 * window and not s["stopped_by_budget"]
        assert info["ended_by"] == s["ended_by"] == "converged" and 0 < info["budget_used"] == s["budget_used"] < 0.5
        assert "converged after" in ended_note(s) and "the schedule ended at step 40" in ended_note(s)
    else:
        assert s["ended_by"] == "budget" and s["budget_used"] >= 0.9 and s["settle"]["converged_at"] is None
        assert s["step"] > 200 and ended_note(s) is None


def test_a_budget_run_that_spends_its_time_preparing_says_so(tiny_capture, tmp_path, monkeypatch):
    """The budget counts the preparation (stereo, the initial Gaussians): where that takes most of it, the run
    trains what is left and run.json, the command line's note and the summary say how much went into preparing
    (the Interpolate baseline on a 0.3 s 320x240 capture: 146 s of stereo at 91 instants in a 120 s budget)."""
    import time as _time

    def slow_probe(trainer):
        _time.sleep(1.5)
        return 0.002, 0.002

    monkeypatch.setattr(run_mod, "measure_step_seconds", slow_probe)

    def step(self, i):
        _time.sleep(0.002)
        return {"loss": 0.0, "psnr": 0.0, "stage": self.stage_of(i), "losses": {}, "densify": {}}

    monkeypatch.setattr(trainer_mod.Trainer, "step", step)
    s = train(tiny_capture, tmp_path / "run", seconds=2.0, overrides={"init": "ply", "iterations": 400})
    est = read_run_json(tmp_path / "run")["budget_estimates"]
    assert s["status"] == "finished" and s["ended_by"] == "budget"
    assert est["preparation_s"] >= 1.5 and est["preparation_share"] >= 0.75 and est["preparation_heavy"] is True
    from engine.cli.train import ended_note
    note = ended_note(s)
    assert note.startswith("warning: preparing the capture took") and f"{est['preparation_share']:.0%}" in note
    # a budget mostly trained: no note
    assert ended_note({**s, "budget_estimates": {**est, "preparation_share": 0.2, "preparation_heavy": False}}) is None


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_warm_up_compiles_the_host_kernels_on_any_device(monkeypatch, device):
    """On a GPU the admissions' flow and neighbour search still run numba kernels on host
    copies: their first compile was charged to the first admissions (H100 box: RGB admission
    56.7 ms/step cold, 6.7 after this warm-up). The CPU-only kernels are not compiled there."""
    from engine.train.loop import budget

    called = []
    for name in ("nearest_warmup", "flow_warmup", "raster_warmup", "hexplane_warmup", "adam_warmup",
                 "trajectory_warmup", "selective_warmup", "ssim_warmup"):
        monkeypatch.setattr(budget, name, lambda *a, _n=name: called.append(_n))
    budget.warm_up_runtime(device)  # only compares the device type: no GPU needed
    assert {"nearest_warmup", "flow_warmup"} <= set(called)
    assert ("raster_warmup" in called) == (device == "cpu") == ("adam_warmup" in called)


def test_warm_up_runs_before_the_budget_clock(tiny_capture, tmp_path, monkeypatch):
    """Kernel compilation / first imports are not charged to --seconds: run.json has them apart."""
    import time as _time

    monkeypatch.setattr(run_mod, "warm_up_runtime", lambda device: (_time.sleep(1.5), 1.5)[1])
    t0 = _time.perf_counter()
    s = train(tiny_capture, tmp_path / "run", seconds=3.0, overrides={"init": "ply"}, rgb_only=True)
    wall = _time.perf_counter() - t0
    info = read_run_json(tmp_path / "run")
    assert info["warmup_seconds"] == 1.5 and s["train_seconds"] <= 3.3
    assert wall - s["train_seconds"] >= 1.5  # the warm-up ran, outside the budget's clock


def test_budget_re_estimate_keeps_the_schedule_consistent(tiny_capture):
    from engine.io.capture import load_capture
    from engine.train.loop.budget import reestimate_steps
    from engine.train.loop.trainer import Trainer

    cfg = get_preset("fast", {"init": "ply", "static_fraction": 0.3})
    tr = Trainer(load_capture(tiny_capture), cfg, device="cpu", total_steps=1000)
    probe = {"static_step_s": 0.01, "deform_step_s": 0.02}
    rec = reestimate_steps(tr, 50, 0.1, probe, loop_seconds=30.0)     # 10x slower than probed
    assert rec["total_steps"] == 117 and rec["deform_step_s"] == pytest.approx(0.2)
    tr.schedule.replan(50, rec["total_steps"])  # the rest of the static stage shrinks with the rest of the run
    assert tr.stage_of(50) == "static" and tr.static_steps == 50 + math.ceil(250 / (950 / 67))
    tr.total_steps = 1000
    rec = reestimate_steps(tr, 50, 0.001, probe, loop_seconds=100.0)  # faster: more steps
    assert rec["total_steps"] > 1000
    tr.total_steps = 100
    rec = reestimate_steps(tr, 40, 0.001, probe, loop_seconds=100.0)  # already deforming: no change
    assert rec["total_steps"] == 100 and "skipped" in rec


def test_cli_train_takes_the_skip_switches(tiny_capture, tmp_path, capsys):
    from engine.__main__ import main
    from engine.cli.train import parse_overrides

    assert parse_overrides(["early_stop=False", "freeze_static=on", "cull_frustum=true", "iterations=5"]) == \
        {"early_stop": False, "freeze_static": True, "cull_frustum": True, "iterations": 5}
    rc = main(["train", str(tiny_capture), "--out", str(tmp_path / "r"), "--quiet", "--rgb-only",
               "--set", "iterations=6", "--set", "init=ply", "--set", "cull_frustum=true",
               "--set", "freeze_static=true"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    cfg = read_run_json(tmp_path / "r")["config"]
    assert cfg["skip"]["cull_frustum"] and cfg["skip"]["freeze_static"] and not cfg["skip"]["early_stop"]
    assert set(summary["skips"]) == {"freeze", "cull"}


def test_budget_probe_prices_the_spike_branchs_in_between_render(demo_capture, monkeypatch):
    """The deformation probe must admit the whole capture time: at the curriculum's start
    the spike branch has no in-between instant open, and a probe that never pays for that
    render sizes a --seconds run far too long (it then ends mid-curriculum)."""
    from engine.io.capture import load_capture
    from engine.scene.model import Model4D
    from engine.train.loop.budget import measure_step_seconds
    from engine.train.loop.trainer import Trainer

    cap = load_capture(demo_capture)
    tr = Trainer(cap, get_preset("fast", {"init_max_points": 400, "init_random_points": 100,
                                          "between_colocated_p": 1.0}), device="cpu")
    tr.init_model()
    widths = []
    render = Model4D.render

    def counting(self, vt, t=None, **kw):
        widths.append(int(vt["width"]))
        return render(self, vt, t, **kw)

    monkeypatch.setattr(Model4D, "render", counting)
    measure_step_seconds(tr, n_static=1, n_deform=3)
    assert widths.count(80) >= 3  # a half-resolution in-between render in every deformation probe step


def test_spike_guided_runs_use_their_own_time_smoothness():
    """Between RGB frames a guided field's finer time cells are watched by one view only:
    its time smoothness is ``spike_time_smooth_weight`` (measured: 0.1 beats 0.001 and 1.0)."""
    import types

    from engine.train.losses.terms import _deform_reg

    seen = []
    field = types.SimpleNamespace(regularization=lambda tv, smooth, l1: seen.append(smooth) or torch.tensor(0.0))
    cfg = get_preset("fast")
    for guided in (False, True):
        tr = fake_run(cfg, model=types.SimpleNamespace(deformation=field, use_deformation=True), guided=guided)
        _deform_reg(types.SimpleNamespace(run=tr))
    assert seen == [cfg.hexplane.time_smooth_weight, cfg.spike.time_smooth_weight] and seen[0] != seen[1]


def test_preparation_stages_are_announced_before_the_first_step(tiny_capture, tmp_path):
    """Issue 45 / 43: minutes can pass before the first step (kernels, stereo, the initial cloud);
    each stage is said as it starts, all before the first step's progress."""
    events = []
    train(tiny_capture, tmp_path / "run", overrides={"iterations": 3, "init": "ply"}, seconds=30.0,
          on_stage=lambda text: events.append(("stage", text)), progress=lambda d: events.append(("step", d["step"])))
    stages = [text for kind, text in events if kind == "stage"]
    assert stages[0].startswith("compiling kernels (first run only")
    assert stages[1:] == ["loading the capture", "reading frames and stereo depth", "initial Gaussians from stereo",
                          "timing a few steps for the budget"]
    first_step = next(i for i, (kind, _) in enumerate(events) if kind == "step")
    assert all(kind == "stage" for kind, _ in events[:first_step]) and first_step == len(stages)
    # run.json keeps each stage's time and the peak memory so far (issue 43: time to a usable result)
    prep = json.loads((tmp_path / "run" / "run.json").read_text())["preparation"]
    assert [p["stage"] for p in prep] == stages
    assert all(p["seconds"] >= 0 for p in prep) and all(p["peak_rss_mb"] > 50 for p in prep)
    assert [p["peak_rss_mb"] for p in prep] == sorted(p["peak_rss_mb"] for p in prep)  # a peak only grows


def test_densification_cap_grows_with_the_frames_and_reaches_densify(tiny_capture, tmp_path, monkeypatch):
    """densify.max_gaussians is the count at 160x120; larger frames get sqrt(pixel ratio) times it (at most
    DENSIFY_MAX_SCALE), smaller ones keep it. At 320x240 the fixed 20k left no room once the backdrop ring's
    15k points were in (docs/experiments/more-steps-random-scenes.md). The run records the cap it used."""
    from engine.scene.gaussians import GaussianModel
    from engine.train.loop import scene_setup

    cap = scene_setup.densify_cap
    assert cap(20000, [{"width": 160, "height": 120}]) == (20000, 1.0)
    assert cap(20000, [{"width": 320, "height": 240}] * 2) == (40000, 2.0)
    assert cap(20000, [{"width": 1080, "height": 720}]) == (80000, scene_setup.DENSIFY_MAX_SCALE)
    assert cap(20000, [{"width": 80, "height": 60}]) == (20000, 1.0) and cap(5, []) == (5, 1.0)
    # a run: the scaled cap is recorded with the initial cloud and is what densification gets
    monkeypatch.setattr(scene_setup, "DENSIFY_REFERENCE_PIXELS", 32 * 24 / 4)  # these frames count as 2x
    seen = []
    real = GaussianModel.densify_and_prune

    def spy(self, **kw):
        seen.append(kw["max_gaussians"])
        return real(self, **kw)

    monkeypatch.setattr(GaussianModel, "densify_and_prune", spy)
    s = train(tiny_capture, tmp_path / "run", overrides={"init": "ply", "iterations": 30, "densify.every": 5,
                                                          "densify.max_gaussians": 700})
    assert s["init"]["max_gaussians"] == 1400 and read_run_json(tmp_path / "run")["init"]["max_gaussians"] == 1400
    assert seen and set(seen) == {1400}
