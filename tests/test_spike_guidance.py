"""Spike guidance glue: between-frame instants, spike + block colour terms, fine encoder hook."""
from __future__ import annotations

import types

import numpy as np
import pytest
import torch
from train_util import fake_run, frame_items

from engine.io.capture import load_capture
from engine.scene.fine_deformation import SpikeFineEncoder
from engine.scene.model import view_tensors
from engine.train.config import TrainConfig
from engine.train.guidance.spike_guidance import (
    SpikeGuidance,
    _block_term,
    _spike_term,
    make_fine_encoder,
    scaled_view,
    spike_stream_info,
)


class _FakeModel(torch.nn.Module):
    """Renders a learnable constant-grey image whatever the view and time."""

    def __init__(self, level=0.2):
        super().__init__()
        self.level = torch.nn.Parameter(torch.tensor(float(level)))
        self.deformation = None
        self.use_deformation = False

    def render(self, vt, t=None, **_):
        img = self.level.clamp(0, 1).expand(1, vt["height"], vt["width"], 3)
        return img, None, {}, {}


def _fake_trainer(cap, **cfg):
    items = frame_items(cap)
    conf = TrainConfig().replace(**{"block_interp": "linear", "motion": "hexplane", **cfg})  # block loss on
    return fake_run(conf, capture=cap, items=items, model=_FakeModel())


def _ctx(tr, step=10, stage="deform"):
    return types.SimpleNamespace(run=tr, step=step, stage=stage)


@pytest.fixture(scope="module")
def cap(demo_capture):
    return load_capture(demo_capture)


def test_spike_stream_info_and_sensor(cap):
    info = spike_stream_info(cap)
    assert info is not None and info.co_located_with == "rgb0"
    g = SpikeGuidance(_fake_trainer(cap))
    assert g.renderer is not None and 0.2 < g.sensor.scale < 0.5  # demo simulates light_scale 1/3
    counts, frames, n = g.observed(0.05, 32)
    assert n == 32 and frames.shape == (32, 60, 80) and counts.sum() == frames.sum()


def test_between_render_once_per_step_and_only_in_deform(cap):
    tr = _fake_trainer(cap, between_colocated_p=1.0)
    g = SpikeGuidance(tr)
    ctx = _ctx(tr)
    b = g.between(ctx)
    assert b["camera"] == "rgb0" and not b["instant"].is_rgb
    t1, t2 = b["instant"].t1, b["instant"].t2
    assert t1 < b["instant"].time < t2
    assert g.between(ctx) is b  # cached for the step: spike and block terms share one render
    assert b["rgb"].shape == (1, 60, 80, 3) and b["scale"] == 0.5  # half-resolution between renders
    assert g.between(_ctx(tr, stage="static")) is None
    tr.cfg.spike.between_every = 3
    assert g.between(_ctx(tr, step=11)) is None


def test_spike_term_gradient_brightens_a_too_dark_render(cap):
    tr = _fake_trainer(cap, between_colocated_p=1.0)
    tr.model.level.data.fill_(0.05)  # far darker than the scene
    g = SpikeGuidance(tr)
    loss = _spike_term(g)(_ctx(tr))
    assert torch.isfinite(loss) and float(loss.detach()) > 0
    loss.backward()
    assert float(tr.model.level.grad) < 0  # gradient descent raises the level
    tr.cfg.spike.loss_mode = "if"
    tr.model.level.grad = None
    loss_if = _spike_term(g)(_ctx(tr, step=12))
    loss_if.backward()
    assert torch.isfinite(loss_if) and float(tr.model.level.grad) < 0


def test_block_term_against_interpolated_frame(cap):
    for interp in ("linear", "flow"):
        tr = _fake_trainer(cap, between_colocated_p=0.0, block_interp=interp)
        g = SpikeGuidance(tr)
        ctx = _ctx(tr)
        b = g.between(ctx)
        assert b["camera"] == "rgb1"  # the non-co-located view gets only the block colour loss
        assert _spike_term(g)(ctx) is None
        loss = _block_term(g)(ctx)
        assert torch.isfinite(loss) and float(loss.detach()) > 0
        target = g.interpolated("rgb1", b["instant"].time)
        assert target.shape == (1, 120, 160, 3)
    assert len(g._flows) == 12  # 6 intervals x 2 cameras, computed once


def test_no_spike_stream_skips_spike_branch(cap):
    import dataclasses
    plain = dataclasses.replace(cap, spike_streams=[])
    tr = _fake_trainer(plain, between_colocated_p=1.0)
    g = SpikeGuidance(tr)
    assert g.renderer is None and spike_stream_info(plain) is None
    b = g.between(_ctx(tr))
    assert b is not None and _spike_term(g)(_ctx(tr)) is None  # block colour loss only


def test_fine_encoder_hook_and_spec_rebuild(cap):
    from engine.scene.deformation import DeformationField

    field = DeformationField([-3, -3, -1], [3, 3, 3], (0.0, 0.2), features=4, resolution=4, multires=(1,),
                             time_resolution=4, width=16)
    tr = _fake_trainer(cap, fine_d_model=16, fine_channels=8, fine_k_sub=4)
    enc = make_fine_encoder(tr, field)
    assert enc is not None and enc.spec["stream_camera"] == "spike0"
    xyz = torch.rand(5, 3) * 2 - 1
    f = enc(xyz, 0.05)
    assert f.shape == (5, 16) and torch.count_nonzero(f) == 0  # zero-initialised output
    enc.net.out.weight.data.normal_()
    a, b = enc(xyz, 0.04), enc(xyz, 0.06)
    assert not torch.allclose(a, b)  # depends on the spike window / query time
    assert torch.count_nonzero(enc(xyz, 0.5)) == 0  # outside the stream: no fine feature
    # a checkpoint rebuilds it from the JSON-able spec and re-reads the windows lazily
    again = SpikeFineEncoder(16, enc.spec)
    again.load_state_dict(enc.state_dict())
    assert torch.allclose(again(xyz, 0.04), a, atol=1e-5)
    # per-Gaussian variant: different Gaussians get different features
    tr2 = _fake_trainer(cap, fine_d_model=16, fine_channels=8, fine_k_sub=4, fine_per_gaussian=True)
    enc2 = make_fine_encoder(tr2, field)
    enc2.net.out.weight.data.normal_()
    pts = torch.tensor([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.2]])
    out = enc2(pts, 0.05)
    assert out.shape == (2, 16)
    assert np.isfinite(out.detach().numpy()).all()


def test_scaled_view_keeps_field_of_view(cap):
    from engine.cameras import project_points
    f = cap.frames[0]
    vt = view_tensors(cap.view(f), "cpu")
    vt["image"] = torch.zeros(1, 120, 160, 3)
    half = scaled_view(vt, 0.5)
    assert (half["width"], half["height"]) == (80, 60) and "image" not in half
    pts = np.array([[0.0, 0.3, 0.9], [1.0, 0.5, 1.2]])
    uv, _ = project_points(cap.view(f), pts)
    K = half["K"][0].numpy()
    cam = (half["viewmat"][0].numpy() @ np.c_[pts, np.ones(2)].T).T
    uv_half = np.stack([K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]], 1)
    assert np.allclose(uv_half * 2, uv, atol=1e-3)
    assert torch.equal(scaled_view(vt, 1.0)["K"], vt["K"])


# ----------------------------------------------------------------------------- with the real trainer

_TINY = {"iterations": 6, "static_fraction": 0.34, "init_max_points": 300, "init_random_points": 100,
         "densify_from": 2.0, "densify_until": 2.0, "fine_d_model": 16, "fine_channels": 8, "fine_k_sub": 4,
         "block_interp": "linear", "between_colocated_p": 1.0,
         "motion": "hexplane"}  # the fine branch (Eq. 10) belongs to the HexPlane field


def test_trainer_runs_spike_losses_and_checkpoint_restores_fine_branch(cap, tmp_path):
    from engine.scene.model import load_run
    from engine.train import train
    from engine.train.config import get_preset
    from engine.train.loop.trainer import Trainer

    tr = Trainer(cap, get_preset("fast", _TINY), device="cpu")
    assert {t.name for t in tr.loss_terms} >= {"spike", "block_colour"}
    assert len(tr.deformation_hooks) == 1  # attaches the fine branch when the field exists
    tr.init_model()
    seen = set()
    for step in range(6):
        out = tr.step(step)
        seen |= set(out["losses"])
        assert np.isfinite(out["loss"])
    assert {"spike", "block_colour"} <= seen
    field = tr.model.deformation
    assert isinstance(field.fine_encoder, SpikeFineEncoder)
    assert any(g["name"] == "fine" for g in tr.deform_opt.param_groups)
    # between-frame supervision raises the HexPlane's time resolution
    assert field.grid.resolutions[0][3] == int(np.ceil(7 * 6.0)) + 1
    # the checkpoint rebuilds the fine encoder (spec in the field config) and re-reads the windows
    summary = train(cap, tmp_path / "run", preset="fast", overrides=_TINY, resume=False)
    assert summary["status"] == "finished"
    scene = load_run(tmp_path / "run")
    assert scene.model.deformation.fine_spec["stream_camera"] == "spike0"
    img = scene.render([cap.view(cap.eval_frames[5])])[0]["rgb"]  # restores the encoder lazily
    assert img.shape == (120, 160, 3) and np.isfinite(img).all()
    enc = scene.model.deformation.fine_encoder
    assert isinstance(enc, SpikeFineEncoder) and enc.source() is not None
    import torch as _t
    saved = _t.load(tmp_path / "run" / "checkpoint.pt", map_location="cpu",
                    weights_only=False)["model"]["deformation"]["state_dict"]
    assert _t.equal(enc.net.out.weight.cpu(), saved["fine_encoder.net.out.weight"])  # trained weights, not a fresh init


def test_rgb_only_and_spikeless_captures_skip_the_spike_branch(cap):
    import dataclasses

    from engine.train.config import get_preset
    from engine.train.loop.trainer import Trainer

    rgb = Trainer(cap, get_preset("fast", _TINY), device="cpu", rgb_only=True)
    assert not {"spike", "block_colour"} & {t.name for t in rgb.loss_terms} and not rgb.deformation_hooks
    assert not rgb.between_supervised()
    plain = dataclasses.replace(cap, spike_streams=[])
    tr = Trainer(plain, get_preset("fast", _TINY), device="cpu")
    names = {t.name for t in tr.loss_terms}
    assert not {"spike", "block_colour"} & names  # no flag needed: no stream, plain RGB training
    assert not tr.between_supervised() and not tr.deformation_hooks
    tr.init_model()
    for step in range(4):
        tr.step(step)
    assert tr.model.deformation.fine_encoder is None


def test_baseline_training_data_variant(cap, tmp_path, monkeypatch):
    from engine.train import train
    from engine.train.frames import baselines

    monkeypatch.setattr(baselines, "PER_INTERVAL", 2)
    summary = train(cap, tmp_path / "rep", preset="fast", rgb_only=True, resume=False,
                    overrides={**_TINY, "iterations": 2, "baseline": "repeat"})
    assert summary["status"] == "finished"
    import json
    info = json.loads((tmp_path / "rep" / "run.json").read_text())
    assert info["config"]["baseline"]["kind"] == "repeat"


def test_between_instants_follow_the_trainers_time_curriculum(cap):
    tr = _fake_trainer(cap, between_colocated_p=0.5)
    g = SpikeGuidance(tr)
    tr.time_window = lambda step: 0.0  # only the first RGB instant admitted
    assert all(g.between(_ctx(tr, step=s)) is None for s in range(10, 30))
    tr.time_window = lambda step: 0.05
    times = [g.between(_ctx(tr, step=s))["instant"].time for s in range(30, 60)]
    assert max(times) <= 0.05 + 1e-4 and min(times) > 0.0
    tr.cfg.spike.between_curriculum = False  # switched off: the whole stream from the first step
    assert max(g.between(_ctx(tr, step=s))["instant"].time for s in range(60, 120)) > 0.1


@pytest.mark.slow
def test_block_targets_are_pooled_cached_and_close_to_the_exact_instant(cap, monkeypatch):
    from engine.train.frames.interpolation import avg_pool_blocks
    from engine.train.guidance import spike_guidance as sg

    tr = _fake_trainer(cap, block_interp="flow")
    g = SpikeGuidance(tr)
    t = 0.05 + 0.3 / 30.0 * 0.5  # inside the second interval
    first = g.pooled_target("rgb1", t, 4)
    exact = avg_pool_blocks(g.interpolated("rgb1", t), 4)
    assert first.shape == (1, 30, 40, 3) and (first - exact).abs().max() < 0.02  # 1/64-interval rounding
    calls = []
    monkeypatch.setattr(sg, "flow_interpolate", lambda *a, **k: calls.append(1))
    assert g.pooled_target("rgb1", t + 1e-5, 4) is first and not calls  # same 1/64 step: no new warp
    monkeypatch.undo()
    g.TARGET_CACHE_BYTES = 2 * first.numel() * first.element_size()
    g.pooled_target("rgb1", 0.01, 4)
    g.pooled_target("rgb1", 0.012, 4)
    assert len(g._targets) <= 2  # bounded: least recently used out


def test_run_renders_its_fine_branch_without_the_capture(demo_capture, tmp_path):
    """Issue 11: the fine branch was rebuilt from the capture path recorded in the run and
    returned zeros when that path was gone. The checkpoint now stores the spike windows:
    the same pixels with the capture deleted; a checkpoint without them (older runs) fails
    with a RunError naming the missing path."""
    import shutil

    import torch as _t

    from engine.errors import RunError
    from engine.scene.model import load_run
    from engine.train import train

    copy = tmp_path / "capture"
    shutil.copytree(demo_capture, copy)
    cap_copy = load_capture(copy)
    view = cap_copy.view(cap_copy.eval_frames[4])
    t = float(cap_copy.eval_frames[4].time)
    summary = train(cap_copy, tmp_path / "run", preset="fast", overrides=_TINY, resume=False)
    assert summary["status"] == "finished"
    before = load_run(tmp_path / "run").render([view])[0]["rgb"]
    shutil.rmtree(copy)
    scene = load_run(tmp_path / "run")
    after = scene.render([view])[0]["rgb"]
    assert np.array_equal(before, after)
    field = scene.model.deformation
    xyz = field.normalize_xyz(scene.model.gaussians.means.detach())
    f = field.fine_encoder(xyz, t)
    assert float(f.detach().abs().sum()) > 0  # the branch is live, not the zero fallback
    # an older checkpoint (no stored windows) with its capture gone: a clear error
    ck = tmp_path / "run" / "checkpoint.pt"
    state = _t.load(ck, weights_only=False)
    state["model"]["deformation"].pop("fine_windows")
    _t.save(state, ck)
    with pytest.raises(RunError, match="capture"):
        load_run(tmp_path / "run").render([view])


@pytest.mark.slow
@pytest.mark.parametrize("frozen", [False, True])
def test_fine_encoder_every_reaches_the_encoder_and_each_step_ticks_it(cap, frozen, monkeypatch):
    """``FINE_ENCODER_EVERY`` goes through the spec to the encoder's kept windows, every
    training step advances their clock; with k > 1 later steps reuse kept tokens (stale), and
    a frozen encoder (the default) encodes each window once for the run (shared)."""
    from engine.scene.fine_deformation import EncodedWindows
    from engine.train.config import get_preset
    from engine.train.loop.trainer import Trainer

    assert get_preset("fast").spike.fine_frozen_encoder  # the default (docs/experiments/spike-guidance.md)
    from engine.train.guidance import spike_guidance

    monkeypatch.setattr(spike_guidance, "FINE_ENCODER_EVERY", 50)
    tr = Trainer(cap, get_preset("fast", {**_TINY, "iterations": 10, "static_fraction": 0.2,
                                          "fine_frozen_encoder": frozen}), device="cpu")
    tr.init_model()
    for step in range(10):
        tr.step(step)
    enc = tr.model.deformation.fine_encoder
    assert enc.spec["encoder_every"] == 50 and isinstance(enc.encoded, EncodedWindows)
    assert enc.encoded.refresh_every == 50 and enc.encoded.clock == 8  # the 8 deformation steps
    # one encoder pass per window visited (at most the 6 windows), whatever the renders (>= 1 a step)
    e = enc.encoded
    assert e.computed <= 6 and e.computed + e.shared + e.stale >= 8
    assert (e.stale == 0 and e.shared > 0) if frozen else e.stale > 0
    assert all(p.grad is None for p in enc.net.encoder.parameters()) == frozen
    assert SpikeFineEncoder(16, {**enc.spec, "encoder_every": 0}).encoded.refresh_every == 0
    old_spec = {k: v for k, v in enc.spec.items() if k != "encoder_every"}  # runs saved before it
    assert SpikeFineEncoder(16, old_spec).encoded.refresh_every == 1
