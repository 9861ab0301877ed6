"""Geometry sized by what it needs, not by the pixel count (issue 43): stereo and fusion at most
FUSION_MAX_WIDTH wide with the depth priors back at the frames' size, and a backdrop ring that does
not grow with the resolution. Captures no wider than the limits are handled exactly as before."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from engine.cameras import Intrinsics, View
from engine.geometry import resolution
from engine.geometry.depth_priors import fused_depth_priors
from engine.geometry.planesweep import rgb_cameras
from engine.geometry.resolution import at_size, backdrop_stride, resized_to, working_view
from engine.geometry.stereo import capture_fusion
from engine.io.capture import load_capture


def test_working_view_keeps_small_views_and_scales_wide_ones():
    k = Intrinsics(1080, 720, 900.0, 900.0, 540.0, 360.0)
    v = View(k, np.eye(4), 0.25, "rgb0")
    w = working_view(v)
    assert (w.intrinsics.width, w.intrinsics.height) == (resolution.FUSION_MAX_WIDTH, 320)
    s = resolution.FUSION_MAX_WIDTH / 1080
    assert w.intrinsics.fx == pytest.approx(900 * s) and w.intrinsics.cx == pytest.approx(540 * s)
    assert w.time == 0.25 and w.name == "rgb0" and np.array_equal(w.c2w, v.c2w)
    small = View(Intrinsics(320, 240, 300.0, 300.0, 160.0, 120.0), np.eye(4))
    assert working_view(small) is small


def test_resize_and_back():
    img = np.random.default_rng(0).random((720, 1080, 3)).astype(np.float32)
    v = working_view(View(Intrinsics(1080, 720, 900.0, 900.0, 540.0, 360.0), np.eye(4)))
    small = resized_to(img, v)
    assert small.shape == (320, 480, 3) and abs(small.mean() - img.mean()) < 1e-3  # area average
    assert resized_to(img, View(Intrinsics(1080, 720, 9.0, 9.0, 5.0, 5.0), np.eye(4))) is img
    depth = np.arange(6, dtype=np.float32).reshape(2, 3)
    big = at_size(depth, 4, 6)
    assert big.shape == (4, 6) and set(np.unique(big)) == set(depth.ravel())  # nearest: no new depths
    mask = at_size(np.array([[True, False]]), 2, 4)
    assert mask.dtype == bool and mask[:, :2].all() and not mask[:, 2:].any()


def test_backdrop_points_do_not_grow_with_the_resolution():
    assert backdrop_stride(160) == backdrop_stride(320) == 4
    for w in (640, 1080, 1920, 4096):
        # ring points ~ (W / stride)^2: no more than at the reference width
        assert (w / backdrop_stride(w)) ** 2 <= 1.1 * (320 / 4) ** 2


def test_fusion_at_a_working_resolution_gives_priors_at_the_frames_size(demo_capture, monkeypatch):
    cap = load_capture(demo_capture)
    cams = rgb_cameras(cap)
    full_a, _, full_info = capture_fusion(cap, cams)
    assert full_info["size"] == [160, 120]  # no wider than the limit: as before
    monkeypatch.setattr(resolution, "FUSION_MAX_WIDTH", 80)
    fa, fb, info = capture_fusion(cap, cams)
    assert info["size"] == [80, 60] and fa.static_depth.shape == (60, 80)
    # the same surfaces: the half-size static depth agrees with the full-size one, downsampled
    ref = full_a.static_depth[::2, ::2]
    both = np.isfinite(ref) & np.isfinite(fa.static_depth)
    assert both.mean() > 0.3
    assert np.median(np.abs(fa.static_depth[both] - ref[both]) / ref[both]) < 0.03
    priors = fused_depth_priors(cap, cap.frames, cams, fusion=(fa, fb, info))
    assert priors
    for d, ok in priors.values():
        assert d.shape == ok.shape == (120, 160) and ok.dtype == bool and ok.mean() > 0.3


def test_initial_points_at_a_working_resolution(demo_capture, monkeypatch):
    from engine.geometry.init_points import initial_points

    monkeypatch.setattr(resolution, "FUSION_MAX_WIDTH", 80)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = initial_points(load_capture(demo_capture), "stereo", backdrop=0.3, planes=True)
    assert p.info["matcher"] == "sgbm" and "fallback" not in p.info and p.info["size"] == [80, 60]
    assert p.info["backdrop"] > 20 and np.isfinite(p.xyz).all()
