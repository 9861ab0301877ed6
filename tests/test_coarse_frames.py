"""Coarse-to-fine for large frames (issue 43): the static warm-up trains a frame wider than
COARSE_MAX_WIDTH at that width (camera scaled, image area-averaged, depth prior nearest); frames no
wider are used as they are."""
from __future__ import annotations

import numpy as np
import torch

from engine.train.frames import coarse
from engine.train.frames.coarse import CoarseItems, coarse_item


def _item(w=160, h=120):
    K = torch.tensor([[[100.0, 0.0, w / 2], [0.0, 100.0, h / 2], [0.0, 0.0, 1.0]]])
    img = torch.rand(1, h, w, 3, generator=torch.Generator().manual_seed(0))
    depth = torch.full((h, w), 2.0)
    depth[:, : w // 2] = 1.0
    return {"viewmat": torch.eye(4)[None], "K": K, "width": w, "height": h, "campos": torch.zeros(3), "time": 0.1,
            "image": img, "index": 3, "camera": "rgb0", "stereo_depth": depth, "stereo_mask": depth > 0}


def test_coarse_item_scales_camera_image_and_depth():
    it = _item()
    c = coarse_item(it, 80)
    assert (c["width"], c["height"]) == (80, 60) and c["image"].shape == (1, 60, 80, 3)
    assert torch.allclose(c["K"][0, 0, 0], torch.tensor(50.0)) and torch.allclose(c["K"][0, 0, 2], torch.tensor(40.0))
    assert abs(float(c["image"].mean()) - float(it["image"].mean())) < 1e-5  # area average keeps the mean
    assert set(np.unique(c["stereo_depth"].numpy())) == {1.0, 2.0} and c["stereo_mask"].dtype == torch.bool
    assert c["time"] == 0.1 and c["index"] == 3 and c["camera"] == "rgb0"
    assert it["image"].shape == (1, 120, 160, 3)  # the full frame is untouched
    assert coarse_item(it, 160) is it


def test_coarse_item_carries_the_stereo_planes_at_its_size():
    from engine.train.losses.geometry_losses import attach_stereo, lie_flat

    it, partner = _item(), _item()
    partner.update(camera="rgb1", campos=torch.tensor([0.3, 0.0, 0.0]))
    d = it.pop("stereo_depth").numpy()
    it.pop("stereo_mask")
    attach_stereo([it, partner], [(d, d > 0), None], planes=True)  # two fronto-parallel walls at 1 m and 2 m
    c = coarse_item(it, 80)
    assert c["stereo_normal"].shape == (60, 80, 3) and c["stereo_offset"].shape == (60, 80)
    assert torch.allclose(c["stereo_normal"][30, 60], torch.tensor([0.0, 0.0, -1.0]))
    assert torch.allclose(c["stereo_offset"][30, 60], torch.tensor(-2.0))
    assert torch.allclose(c["stereo_offset"][30, 10], torch.tensor(-1.0))
    means = torch.tensor([[0.5, 0.0, 2.0], [-0.5, 0.0, 1.0]])   # one disc on each wall
    disc, scales = torch.tensor([[1.0, 0, 0, 0]] * 2), torch.tensor([[0.02, 0.02, 0.001]] * 2)
    assert float(lie_flat(means, disc, scales, c)) < 1e-2 and float(lie_flat(means, disc, scales, it)) < 1e-2
    assert float(lie_flat(means + torch.tensor([0.0, 0.0, 0.02]), disc, scales, c)) > 0.3  # 2 cm off each wall


def test_coarse_items_are_made_once_and_only_for_wide_frames():
    items = CoarseItems(80)
    it = _item()
    assert items(it) is items(it) and items(it)["width"] == 80
    assert CoarseItems(160)(it) is it
    assert CoarseItems()(it) is it  # the demo's frames are far below the default limit
    assert coarse.COARSE_MAX_WIDTH >= 320


def test_static_stage_trains_wide_frames_coarse(demo_capture, tmp_path, monkeypatch):
    """A run whose frames are 'wide' (limit lowered to 80 px): the warm-up renders 80x60, the
    deformation stage the full 160x120 frames, and the run finishes with a finite loss."""
    from engine.scene.model import Model4D
    from engine.train import train

    sizes = []
    real = Model4D.render

    def spy(self, item, *a, **kw):
        sizes.append((int(item["width"]), int(item["height"])))
        return real(self, item, *a, **kw)

    monkeypatch.setattr(coarse, "COARSE_MAX_WIDTH", 80)
    monkeypatch.setattr(Model4D, "render", spy)
    s = train(demo_capture, tmp_path / "run", overrides={"schedule.iterations": 20}, rgb_only=True)
    assert s["status"] == "finished" and np.isfinite(s["loss"])
    assert (80, 60) in sizes and (160, 120) in sizes


def test_stereo_planes_only_where_the_pair_resolves_depth():
    from engine.train.losses.geometry_losses import PLANE_MIN_DISPARITY, attach_stereo

    it, partner = _item(), _item()                                 # fx = 100 px, walls at 1 m and 2 m
    d = it.pop("stereo_depth").numpy()
    it.pop("stereo_mask")
    partner.update(camera="rgb1", campos=torch.tensor([1.5 * PLANE_MIN_DISPARITY / 100.0, 0.0, 0.0]))
    attach_stereo([it, partner], [(d, d > 0), None], planes=True)  # disparity 12 px at 1 m, 6 px at 2 m
    has = it["stereo_normal"].abs().sum(-1) > 0
    assert has[:, 10:70].all() and not has[:, 90:].any()
    alone = _item()
    alone.pop("stereo_depth"), alone.pop("stereo_mask")
    attach_stereo([alone], [(d, d > 0)], planes=True)              # no partner camera: no planes
    assert not (alone["stereo_normal"].abs().sum(-1) > 0).any() and "stereo_depth" in alone
