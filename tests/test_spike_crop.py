"""The spike loss's between-frame render cropped to where the spike view changes
(engine.train.spike_crop): crop geometry, box choice and fallback, the loss on the crop."""
from __future__ import annotations

import types

import numpy as np
import pytest
import torch
from train_util import frame_items

from engine.io.capture import load_capture
from engine.raster import rasterization
from engine.spike.change import SpikeChange
from engine.spike.features import bracket
from engine.spike.render import SensorModel, sensor_light
from engine.train.presets import TrainConfig
from engine.train.spike_crop import align_box, crop_box, crop_fraction, crop_view, mask_box, render_ratio
from engine.train.spike_guidance import SpikeGuidance, _spike_term


def _view(width=64, height=48, f=60.0):
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])[None]
    return {"viewmat": torch.eye(4)[None], "K": K, "width": width, "height": height, "campos": torch.zeros(3)}


def _render(vt, g):
    rgb, alpha, _ = rasterization(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
                                  vt["viewmat"], vt["K"], vt["width"], vt["height"],
                                  backgrounds=torch.zeros(1, 3), render_depth=False)
    return rgb[0], alpha[0]


def _gaussians(n=300, seed=0, spread=0.35):
    gen = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=gen) * 2 - 1
    means[:, :2] *= spread  # well inside the view: the projection's FoV clamp never applies
    means[:, 2] = 3.0 + means[:, 2]
    q = torch.randn(n, 4, generator=gen)
    return {"means": means, "quats": q / q.norm(dim=-1, keepdim=True),
            "scales": torch.rand(n, 3, generator=gen) * 0.05 + 0.01,
            "opacities": torch.rand(n, generator=gen) * 0.8 + 0.1, "colors": torch.rand(n, 3, generator=gen)}


@pytest.mark.parametrize("box", [(8, 8, 40, 32), (0, 0, 64, 48), (16, 0, 64, 24), (13, 5, 51, 46)])
def test_cropped_render_equals_the_same_pixels_of_the_full_render(box):
    g = _gaussians()
    vt = _view()
    full_rgb, full_a = _render(vt, g)
    rgb, a = _render(crop_view(vt, box), g)
    x0, y0, x1, y1 = box
    assert rgb.shape == (y1 - y0, x1 - x0, 3)
    assert float(full_a.max()) > 0.5  # the scene is in view
    torch.testing.assert_close(rgb, full_rgb[y0:y1, x0:x1], atol=2e-5, rtol=0)
    torch.testing.assert_close(a, full_a[y0:y1, x0:x1], atol=2e-5, rtol=0)


def test_cropped_render_gradients_are_the_full_renders_on_its_pixels():
    g = _gaussians(spread=0.3)
    vt = _view()
    box = (16, 8, 48, 40)
    w = torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(3))
    x0, y0, x1, y1 = box
    w_out = torch.zeros_like(w)
    w_out[y0:y1, x0:x1] = w[y0:y1, x0:x1]  # a loss on the box's pixels only
    grads = []
    for view, weight in ((vt, w_out), (crop_view(vt, box), w[y0:y1, x0:x1])):
        leaf = {k: v.clone().requires_grad_(True) for k, v in g.items()}
        rgb, _ = _render(view, leaf)
        (rgb * weight).sum().backward()
        grads.append(leaf["means"].grad)
    assert float(grads[0].abs().max()) > 0
    torch.testing.assert_close(grads[1], grads[0], atol=1e-5, rtol=1e-4)


def test_render_without_depth_has_the_same_colours_and_gradients_bit_for_bit():
    """The between-frame render skips the depth channel (spike_guidance.BETWEEN_DEPTH): exact."""
    g = _gaussians(n=1000, spread=0.9)
    vt = _view()
    w = torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(4))
    outs = []
    for depth in (True, False):
        leaf = {k: v.clone().requires_grad_(True) for k, v in g.items()}
        rgb, _, meta = rasterization(leaf["means"], leaf["quats"], leaf["scales"], leaf["opacities"],
                                     leaf["colors"], vt["viewmat"], vt["K"], 64, 48, render_depth=depth)
        (rgb * w).sum().backward()
        assert ("depths" in meta) == depth
        outs.append((rgb.detach(), [leaf[k].grad for k in sorted(leaf)]))
    assert torch.equal(outs[0][0], outs[1][0])
    assert all(torch.equal(a, b) for a, b in zip(outs[0][1], outs[1][1]))


def test_crop_view_shifts_principal_point_and_rejects_boxes_outside():
    vt = _view()
    c = crop_view(vt, (8, 16, 40, 48))
    assert (c["width"], c["height"]) == (32, 32)
    assert float(c["K"][0, 0, 2]) == 32 - 8 and float(c["K"][0, 1, 2]) == 24 - 16
    assert float(vt["K"][0, 0, 2]) == 32  # the full view is untouched
    for bad in ((0, 0, 65, 48), (-1, 0, 10, 10), (10, 10, 10, 20)):
        with pytest.raises(ValueError, match="crop box"):
            crop_view(vt, bad)


def _change(changed_blocks, h=60, w=80, block=4):
    changed = np.zeros((1, -(-h // block), -(-w // block)), bool)
    for by, bx in changed_blocks:
        changed[0, by, bx] = True
    return SpikeChange(np.zeros(changed.shape, np.float32), changed, 0.1, 0.01, block, (h, w))


def test_crop_box_bounds_the_dilated_change_on_whole_tiles():
    ch = _change([(5, 6)])  # spike pixels x 24..27, y 20..23
    # dilate 1: blocks 5..7 x, 4..6 y -> x 20..31, y 16..27 -> 8-px tiles: x 16..32, y 16..32
    assert crop_box(ch, 0, (80, 60), (80, 60), dilate=1) == (16, 16, 32, 32)
    assert crop_box(ch, 0, (80, 60), (80, 60), dilate=0) == (24, 16, 32, 24)
    # render at twice the sensor's size: 8 render px = 4 sensor px
    assert crop_box(ch, 0, (80, 60), (160, 120), dilate=0) == (24, 20, 28, 24)
    assert mask_box(np.zeros((4, 4))) is None
    assert align_box((3, 5, 9, 10), 4, 10, 10) == (0, 4, 10, 10)


def test_crop_box_falls_back_to_the_full_view():
    spread = _change([(1, 1), (13, 18)])  # two corners: the box covers most of the view
    assert crop_box(spread, 0, (80, 60), (80, 60), max_frac=0.8) is None
    assert crop_box(spread, 0, (80, 60), (80, 60), max_frac=1.0) == (0, 0, 80, 60)
    one = _change([(5, 6)])
    assert crop_box(one, 0, (80, 60), (120, 90)) is None  # 1.5 render px per sensor px
    assert crop_box(one, 0, (80, 60), (80, 61)) is None
    assert crop_box(None, 0, (80, 60), (80, 60)) is None
    assert crop_box(one, 3, (80, 60), (80, 60)) is None  # no such interval
    assert crop_box(_change([]), 0, (80, 60), (80, 60)) is None  # nothing changed
    assert render_ratio((160, 120), (80, 60)) == 2 and render_ratio((80, 60), (80, 60)) == 1
    assert crop_fraction(None, (80, 60)) == 1.0 and crop_fraction((0, 0, 40, 30), (80, 60)) == 0.25


def test_sensor_light_of_a_crop_is_the_crop_of_the_full_light():
    gain = (1 + 0.1 * torch.randn(30, 40, generator=torch.Generator().manual_seed(1))).numpy()
    sensor = SensorModel(width=40, height=30, scale=0.4, dark_current=0.01, gain=gain)
    img = torch.rand(60, 80, 3, generator=torch.Generator().manual_seed(2))  # 2 render px per sensor px
    full = sensor_light(img, sensor)
    box = (8, 4, 24, 20)
    part = sensor_light(img[2 * 4:2 * 20, 2 * 8:2 * 24], sensor, box=box)
    torch.testing.assert_close(part, full[4:20, 8:24], atol=1e-6, rtol=1e-6)


# ----------------------------------------------------------------------------- the loss on the crop

class _TextureModel(torch.nn.Module):
    """Renders a learnable texture of the full (half-resolution) view; a view whose principal
    point is shifted (a crop) gets the texture's same pixels."""

    def __init__(self, width=80, height=60, cx=40.0, cy=30.0):
        super().__init__()
        self.tex = torch.nn.Parameter(torch.full((height, width, 3), 0.3))
        self.cx, self.cy = cx, cy
        self.deformation, self.use_deformation = None, False
        self.boxes = []

    def render(self, vt, t=None, render_depth=True, **_):
        self.depth = render_depth
        x0 = int(round(self.cx - float(vt["K"][0, 0, 2])))
        y0 = int(round(self.cy - float(vt["K"][0, 1, 2])))
        self.boxes.append((x0, y0, x0 + vt["width"], y0 + vt["height"]))
        return self.tex[y0:y0 + vt["height"], x0:x0 + vt["width"]][None], None, {}, {}


@pytest.fixture(scope="module")
def cap(demo_capture):
    return load_capture(demo_capture)


def _trainer(cap, **cfg):
    items = frame_items(cap)
    conf = TrainConfig().replace(**{"between_colocated_p": 1.0, **cfg})
    return types.SimpleNamespace(capture=cap, cfg=conf, items=items, seed=0, model=_TextureModel(), deform_opt=None)


def _loss_and_grad(cap, step=10, **cfg):
    tr = _trainer(cap, **cfg)
    g = SpikeGuidance(tr)
    ctx = types.SimpleNamespace(trainer=tr, step=step, stage="deform")
    loss = _spike_term(g)(ctx)
    loss.backward()
    return g, g.between(ctx), tr.model.tex.grad.clone(), tr.model.boxes


def test_spike_loss_uses_the_crop_with_the_full_views_gradient(cap):
    g_full, b_full, grad_full, boxes_full = _loss_and_grad(cap, spike_crop=False)
    g_crop, b_crop, grad_crop, boxes_crop = _loss_and_grad(cap, spike_crop=True)
    assert b_full["instant"].time == b_crop["instant"].time  # same seed: the same instant
    assert b_full["box"] is None and boxes_full == [(0, 0, 80, 60)]
    assert g_crop.trainer.model.depth is False  # no term reads the between render's depth
    box = b_crop["box"]
    assert box is not None and boxes_crop == [box]  # the render was the crop
    x0, y0, x1, y1 = box
    assert b_crop["rgb"].shape == (1, y1 - y0, x1 - x0, 3)
    assert (x1 - x0) * (y1 - y0) <= 0.8 * 80 * 60
    assert all(v % 8 == 0 for v in box[:2])  # whole tiles (sensor = render pixels here)
    inside = torch.zeros(60, 80, dtype=torch.bool)
    inside[y0:y1, x0:x1] = True
    assert float(grad_crop[~inside].abs().max()) == 0.0  # no gradient outside the crop
    assert float(grad_crop[inside].abs().max()) > 0
    # each pixel of the box gets the full-view loss's gradient
    torch.testing.assert_close(grad_crop[inside], grad_full[inside], atol=1e-9, rtol=1e-5)
    # the box bounds where the interval's spike view changed
    cache = g_crop.window_cache()
    k = bracket(cache.rgb_times, b_crop["instant"].time)[0]
    gate = cache.change(4).gate_map(k, 1).numpy() > 0
    assert gate.any() and gate[y0:y1, x0:x1].sum() == gate.sum()


def test_spike_crop_falls_back_to_the_full_view(cap):
    _, b, grad, boxes = _loss_and_grad(cap, spike_crop=True, spike_crop_max_frac=0.05)
    assert b["box"] is None and boxes == [(0, 0, 80, 60)] and float(grad.abs().max()) > 0
    # the block colour loss pools the whole view: no crop while it is on
    _, b, _, boxes = _loss_and_grad(cap, spike_crop=True, block_loss_weight=1.0, block_interp="linear")
    assert b["box"] is None and boxes == [(0, 0, 80, 60)]


def test_spike_crop_with_the_integrate_and_fire_loss(cap):
    _, b, grad, _ = _loss_and_grad(cap, spike_crop=True, spike_loss_mode="if")
    x0, y0, x1, y1 = b["box"]
    outside = torch.ones(60, 80, dtype=torch.bool)
    outside[y0:y1, x0:x1] = False
    assert float(grad[outside].abs().max()) == 0.0 and float(grad.abs().max()) > 0
