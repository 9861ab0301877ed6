"""Still frames (issue 11, engine.train.still_hold): the still-pixel mask, its sweep radius,
the frames' records and how the trainer supervises them."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from engine.io.capture import load_capture
from engine.scene.model import TRAJ_MEANS
from engine.train.presets import get_preset
from engine.train.still_hold import StillHold, still_mask, sweep_flow


def _background(h=96, w=128, seed=0):
    rng = np.random.default_rng(seed)
    small = rng.uniform(0.2, 0.8, size=(h // 8, w // 8, 3)).astype(np.float32)
    return np.kron(small, np.ones((8, 8, 1), np.float32))  # 8 px tiles


def _with_disc(img, cx, cy, r, colour=(1.0, 0.0, 0.0)):
    out = img.copy()
    yy, xx = np.mgrid[:img.shape[0], :img.shape[1]]
    out[(xx - cx) ** 2 + (yy - cy) ** 2 <= r * r] = colour
    return out


def test_identical_frames_are_still_everywhere():
    a = _background()
    still, longest = still_mask(a, a.copy())
    assert still.all() and longest == 0.0


def _disc_flows(shape, centres, r, dx):
    """(a -> b, b -> a) flows: the disc's pixels in a move dx, in b they came from -dx."""
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    flows = []
    for (cx, cy), d in zip(centres, (dx, -dx)):
        f = np.zeros(shape + (2,), np.float32)
        f[(xx - cx) ** 2 + (yy - cy) ** 2 <= r * r, 0] = d
        flows.append(f)
    return tuple(flows)


def test_the_sweep_covers_where_a_fast_disc_passed_between_the_frames():
    bg = _background()
    a, b = _with_disc(bg, 30, 48, 6), _with_disc(bg, 70, 48, 6)  # 40 px: over three times its size
    flows = _disc_flows(bg.shape[:2], ((30, 48), (70, 48)), 6, 40.0)
    still, longest = still_mask(a, b, margin_px=2, flows=flows)
    assert longest == 40.0
    assert not still[48, 50] and not still[44, 40]  # half-way: background at both ends, the disc in between
    assert not still[48, 30] and not still[48, 70]  # where it was and where it went
    assert still[30, 50] and still[66, 50]  # beside its path: a band, not a disc around it
    assert still[10, 120] and still[90, 5]
    # without the sweep (zero flows) the half-way pixels would count as still
    zero = tuple(np.zeros_like(f) for f in flows)
    no_sweep, _ = still_mask(a, b, margin_px=0, flows=zero)
    assert no_sweep[48, 50] and not no_sweep[48, 30]
    # a disc that appears only in b sweeps back along the b -> a flow
    b_only = _with_disc(bg, 70, 48, 6)
    still_b, _ = still_mask(bg, b_only, margin_px=0, flows=(np.zeros_like(flows[0]), flows[1]))
    assert not still_b[48, 50] and still_b[48, 20]


def _smooth(h, w, cell, seed):
    small = np.random.default_rng(seed).uniform(0.1, 0.9, size=(h // cell + 1, w // cell + 1, 3)).astype(np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)[:h, :w].clip(0, 1)


def test_the_sweep_flow_finds_the_motion_itself():
    bg, tex = _smooth(120, 160, 8, 1), _smooth(24, 24, 4, 2)
    a, b = bg.copy(), bg.copy()
    a[48:72, 30:54], b[48:72, 40:64] = tex, tex  # a textured square moves 10 px
    flow = sweep_flow(a, b)
    assert abs(float(np.median(flow[50:70, 32:52, 0])) - 10.0) < 1.0  # DIS reads ~-2.7 px here
    still, longest = still_mask(a, b, margin_px=0)
    assert 9.0 <= longest <= 16.0
    assert not still[60, 50] and still[10, 150] and still[100, 45]
    # the same on frames four times larger: the flow runs scaled down, in full-resolution pixels
    big = [cv2.resize(x, (640, 480), interpolation=cv2.INTER_LINEAR) for x in (a, b)]
    flow_big = sweep_flow(*big)
    assert flow_big.shape == (480, 640, 2)
    assert abs(float(np.median(flow_big[200:280, 128:208, 0])) - 40.0) < 4.0


def test_colour_tolerance_is_checked():
    a = _background()
    with pytest.raises(ValueError, match="colour_tol"):
        still_mask(a, a, colour_tol=0.0)


_TINY = {"iterations": 10, "static_fraction": 0.2, "init_max_points": 300, "init_random_points": 100,
         "densify_from": 2.0, "densify_until": 2.0, "time_curriculum": 0.0, "traj_carry": "velocity",
         "birth_error": 0.0}


def _trainer(demo_capture, **over):
    from engine.train.trainer import Trainer
    tr = Trainer(load_capture(demo_capture), get_preset("fast", {**_TINY, **over}), device="cpu", rgb_only=True)
    tr.init_model()
    return tr


def _inner_max(tr):
    p = getattr(tr.model.gaussians, TRAJ_MEANS).detach()
    inner = [p[:, 3 * k + 1:3 * k + 3] for k in range((p.shape[1] - 1) // 3)]
    return float(torch.stack(inner, 1).abs().max())


def test_hold_pairs_are_consecutive_frames_of_one_camera(demo_capture):
    tr = _trainer(demo_capture, still_weight=1.0)
    hold = StillHold(tr.cfg)
    pairs = hold.pairs = hold.build(tr.items)
    per_cam = {}
    for it in tr.items:
        per_cam[it["camera"]] = per_cam.get(it["camera"], 0) + 1
    assert len(pairs) == sum(n - 1 for n in per_cam.values())
    gaps = [float(tr.items[p.b]["time"]) - float(tr.items[p.a]["time"]) for p in pairs]
    assert all(tr.items[p.a]["camera"] == tr.items[p.b]["camera"] for p in pairs)
    assert max(gaps) < 1.01 * min(gaps)
    assert all(p.still is None for p in pairs)  # masks are made when drawn
    assert all(0.3 < float(hold.still_of(p, tr.items).float().mean()) < 1.0 for p in pairs)
    # every still_every-th step only; the instant inside the pair's interval, the target the blend
    assert hold.sample(tr, 1) is None
    vt, t, target, still = hold.sample(tr, 4)
    pair = next(p for p in pairs if p.still.shape == still.shape and torch.equal(p.still, still))
    ta, tb = float(tr.items[pair.a]["time"]), float(tr.items[pair.b]["time"])
    assert ta < t < tb and vt is tr.items[pair.a]
    eps = (t - ta) / (tb - ta)
    blend = tr.items[pair.a]["image"] * (1 - eps) + tr.items[pair.b]["image"] * eps
    assert torch.allclose(target, blend, atol=1e-6)


@pytest.mark.slow
def test_the_hold_bends_the_curves_between_rgb_instants(demo_capture):
    """RGB-only training never moves the curves' inner control points (no loss between the
    RGB instants reaches them); the still hold's render between two frames does, on its
    deformation steps only."""
    bends, seen = {}, {}
    for on in (False, True):
        tr = _trainer(demo_capture, still_weight=1.0 if on else 0.0)
        names = set()
        for step in range(_TINY["iterations"]):
            out = tr.step(step)
            if "still" in out["losses"]:
                names.add((step, out["stage"]))
        bends[on], seen[on] = _inner_max(tr), names
    assert bends[False] == 0.0 and bends[True] > 0.0
    assert seen[False] == set()
    assert seen[True] and all(stage == "deform" and step % 2 == 0 for step, stage in seen[True])


@pytest.mark.slow
def test_the_spike_view_takes_back_what_it_saw_change(demo_capture):
    """Full model: a pixel stays still only where its rendered surface projects onto no spike
    block that changed in the pair's interval (the interval starting at the pair's first frame);
    RGB-only runs have no spike view and keep the frames' mask."""
    from engine.train.trainer import Trainer
    assert StillHold(_trainer(demo_capture).cfg).spike_view(_trainer(demo_capture)) is None  # RGB-only
    tr = Trainer(load_capture(demo_capture), get_preset("fast", {**_TINY, "still_weight": 1.0}), device="cpu")
    tr.init_model()
    for step in range(4):
        tr.step(step)
    hold = StillHold(tr.cfg)
    change, _, _, _, rgb_times = hold.spike_view(tr)
    vt, t, _, still = hold.sample(tr, 4)
    with torch.no_grad():
        _, alpha, meta, _ = tr.model.render(vt, t)
    depth, alpha = meta["depths"][0, ..., 0], alpha[0, ..., 0]
    seen = hold.spike_still(tr, vt, float(vt["time"]), depth, alpha)
    assert seen.shape == still.shape and 0.0 < float((~seen).float().mean()) < 0.5
    assert not bool((~seen[0, ..., 0] & (alpha <= 0.5)).any())  # only over drawn surfaces
    asked = []
    real_gate = change.gate
    for value in (0.0, 1.0):
        change.gate = lambda k, grid, dilate=1, v=value: asked.append((k, dilate)) or torch.full((grid.shape[0],), v)
        out = hold.spike_still(tr, vt, float(vt["time"]), depth, alpha)[0, ..., 0]
        assert bool(out.all()) if value == 0.0 else torch.equal(out, ~(alpha > 0.5))
    change.gate = real_gate
    k = int(np.searchsorted(np.asarray(rgb_times), float(vt["time"]) + 1e-6)) - 1
    assert asked == [(k, tr.cfg.still_spike_dilate)] * 2 and rgb_times[k] <= float(vt["time"]) < rgb_times[k + 1]
