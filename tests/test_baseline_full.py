"""Synthetic (baseline) frames in the full model (issue 11): which instants are knots, the
frame-loss weight, and the forward-backward flow mask of flow-interpolated frames."""
from __future__ import annotations

import types

import numpy as np
import pytest
import torch

from engine.io.capture import load_capture
from engine.train.config import get_preset
from engine.train.frames.baselines import baseline_frames, with_baseline
from engine.train.losses.terms import _dssim, _l1, frame_item_fields


@pytest.fixture(scope="module")
def cap(demo_capture):
    return load_capture(demo_capture)


def _textured(h=48, w=64, seed=0):
    rng = np.random.default_rng(seed)
    img = torch.from_numpy(rng.uniform(size=(h // 4, w // 4, 3)).astype(np.float32))
    return torch.nn.functional.interpolate(img.permute(2, 0, 1)[None], size=(h, w), mode="bilinear",
                                           align_corners=False)[0].permute(1, 2, 0).contiguous()


def test_item_fields_say_knot_and_weight(cap):
    real = cap.frames[0]
    syn = baseline_frames(cap, "interp-flow", per_interval=1, cameras=["rgb0"], knots=False)[0]
    cfg = get_preset("fast", {"baseline_weight": 0.25})
    assert frame_item_fields(real, cfg, "cpu") == {"synthetic": False, "knot": True}
    f = frame_item_fields(syn, cfg, "cpu")
    assert f["synthetic"] and not f["knot"] and f["loss_scale"] == 0.25
    assert "trusted" not in f
    syn.knot = True  # "all": the Table 1 baseline as before
    assert frame_item_fields(syn, cfg, "cpu")["knot"]
    with pytest.raises(ValueError, match="instants"):
        with_baseline(cap, "repeat", instants="some")


def test_frame_loss_scales_synthetic_frames():
    gen = torch.Generator().manual_seed(0)
    image = torch.rand(1, 24, 32, 3, generator=gen)
    rgb = torch.rand(1, 24, 32, 3, generator=gen)
    # the weight scales the loss; without the synthetic fields the loss is the plain one
    plain = types.SimpleNamespace(item={"image": image}, rgb=rgb)
    half = types.SimpleNamespace(item={"image": image, "loss_scale": 0.5}, rgb=rgb)
    assert torch.allclose(_l1(half), 0.5 * (rgb - image).abs().mean())
    assert torch.allclose(_dssim(half), 0.5 * _dssim(plain))

def test_real_instants_keep_the_knots_and_stereo_at_the_rgb_frames(cap):
    from engine.geometry.stereo import pair_instants
    from engine.train.loop.trainer import Trainer

    rgb_times = sorted({round(float(f.time), 9) for f in cap.frames if f.role == "train"})
    real_cap = with_baseline(cap, "interp-linear", per_interval=3, instants="real")
    real = Trainer(real_cap, get_preset("fast", {"baseline_instants": "real"}), device="cpu")
    assert real.frame_times == rgb_times
    assert sum(it["synthetic"] for it in real.items) == len(real_cap.frames) - len(cap.frames)
    assert len(pair_instants(real_cap, ["rgb0", "rgb1"])[2]) == len(rgb_times)  # no stereo on synthetic frames
    every_cap = with_baseline(cap, "interp-linear", per_interval=3)
    assert len(pair_instants(every_cap, ["rgb0", "rgb1"])[2]) == 4 * (len(rgb_times) - 1) + 1
    every = Trainer(every_cap, get_preset("fast"), device="cpu")
    assert len(every.frame_times) == 4 * (len(rgb_times) - 1) + 1
