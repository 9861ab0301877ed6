"""Two-view stereo (engine.geometry.stereo, issue 14): SGBM depth on synthetic pairs with known
depth (parallel, converging, vertical), fusion over instants, and the bad-input fallbacks."""
from __future__ import annotations

import copy

import cv2
import numpy as np
import pytest

from engine.cameras import Intrinsics, View, look_at_c2w
from engine.geometry.stereo import (
    FusedDepth,
    StereoUnavailable,
    capture_fusion,
    fuse_instants,
    pair_depths,
    rectify_pair,
)

W, H = 128, 96
K = Intrinsics(W, H, 110.0, 110.0, W / 2, H / 2)
_TEX = cv2.GaussianBlur(np.random.default_rng(0).random((800, 800)).astype(np.float32), (0, 0), 1.6)
_TEX = (_TEX - _TEX.min()) / (_TEX.max() - _TEX.min())


def _view(eye, target, name):
    return View(K, look_at_c2w(np.asarray(eye, float), np.asarray(target, float)), 0.0, name)


def render_slanted_plane(view):
    """Image and planar depth of the textured plane y = 3 + 0.4 x (texture fixed to the plane)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    d_cv = np.stack([(u + 0.5 - K.cx) / K.fx, (v + 0.5 - K.cy) / K.fy, np.ones_like(u)], -1)
    c2w_cv = np.linalg.inv(view.viewmat)
    d = d_cv @ c2w_cv[:3, :3].T
    o = view.center
    # (o + s d)_y = 3 + 0.4 (o + s d)_x  ->  s = (3 + 0.4 o_x - o_y) / (d_y - 0.4 d_x); z_cv = s
    s = (3.0 + 0.4 * o[0] - o[1]) / (d[..., 1] - 0.4 * d[..., 0])
    p = o + s[..., None] * d
    tu = ((p[..., 0] + 4.0) / 8.0 * 799).astype(np.float32)
    tv = ((p[..., 2] + 4.0) / 8.0 * 799).astype(np.float32)
    img = cv2.remap(_TEX, tu, tv, cv2.INTER_LINEAR)
    return np.repeat(img[..., None], 3, -1), s.astype(np.float32)


def _check(view_a, view_b, max_median=0.01, min_cover=0.6):
    ia, za = render_slanted_plane(view_a)
    ib, zb = render_slanted_plane(view_b)
    (da, ca), (db, cb) = pair_depths(ia, ib, rectify_pair(view_a, view_b))
    for d, c, z in ((da, ca, za), (db, cb, zb)):
        ok = np.isfinite(d)
        assert ok.mean() > min_cover and np.all(c[ok] > 0) and np.all(c[~ok] == 0)
        err = np.abs(d[ok] - z[ok]) / z[ok]
        assert np.median(err) < max_median and np.percentile(err, 90) < 4 * max_median


def test_parallel_pair_depth_matches_ground_truth():
    _check(_view([-0.1, 0, 0], [-0.1, 3, 0], "a"), _view([0.1, 0, 0], [0.1, 3, 0], "b"))


def test_converging_unrectified_pair_and_swapped_order():
    a, b = _view([-0.15, 0, 0], [0, 3, 0.2], "a"), _view([0.15, 0, 0.05], [0, 3, 0], "b")
    _check(a, b)
    _check(b, a)  # camera a on the right: the matcher swaps left and right


def test_vertical_pair_is_matched_along_columns():
    a, b = _view([0, 0, -0.12], [0, 3, 0], "a"), _view([0, 0, 0.12], [0, 3, 0], "b")
    assert rectify_pair(a, b).vertical
    _check(a, b)


def test_wrong_relative_pose_convention_would_fail():
    """Guard the OpenGL->OpenCV handling: swapping the two poses' images must break matching
    (a mirrored pair gives no consistent disparity), so the test above is not trivially true."""
    a, b = _view([-0.1, 0, 0], [-0.1, 3, 0], "a"), _view([0.1, 0, 0], [0.1, 3, 0], "b")
    ia, za = render_slanted_plane(a)
    ib, _ = render_slanted_plane(b)
    (da, _), _ = pair_depths(ib, ia, rectify_pair(a, b))
    ok = np.isfinite(da)
    assert ok.mean() < 0.3 or np.median(np.abs(da[ok] - za[ok]) / za[ok]) > 0.05


def test_fusion_keeps_static_background_and_what_moves():
    T, h, w = 5, 6, 8
    rng = np.random.default_rng(1)
    depths, confs, images = [], [], []
    for t in range(T):
        d = np.full((h, w), 4.0, np.float32) * (1 + rng.normal(0, 0.002, (h, w))).astype(np.float32)
        img = np.full((h, w, 3), 0.3, np.float32)
        d[:, t:t + 2] = 1.5             # a bar moving right one pixel per instant, in front
        img[:, t:t + 2] = 0.9
        d[0, (t * 3) % w] = np.nan      # a missing match somewhere
        depths.append(d), confs.append(np.where(np.isfinite(d), 0.8, 0.0)), images.append(img)
    view = _view([0, 0, 0], [0, 1, 0], "a")
    f = fuse_instants("a", view, list(range(T)), depths, confs, images)
    assert isinstance(f, FusedDepth)
    # every pixel the bar uncovers at some instant gets the background depth
    assert np.all(np.abs(f.static_depth[:, : T + 1] - 4.0) < 0.05)
    assert np.all(f.static_support[:, 0] >= 2)
    for t in range(T):
        assert f.moving[t][1:, t:t + 2].all() and not f.moving[t][:, t + 3:].any()
        d, ok = f.instant_depth(t)
        assert np.allclose(d[1:, t:t + 2], 1.5)               # the moving bar's own depth
        nan_col = (t * 3) % w
        if not (t <= nan_col < t + 2):                          # a hole on static background is filled
            assert ok[0, nan_col] and abs(d[0, nan_col] - 4.0) < 0.05


def test_bad_pairs_raise_a_clear_message():
    a = _view([0, 0, 0], [0, 3, 0], "a")
    with pytest.raises(StereoUnavailable, match="same place"):
        rectify_pair(a, _view([0, 0, 0], [0, 3, 0], "b"))
    with pytest.raises(StereoUnavailable, match="do not see the same"):
        rectify_pair(a, _view([0.2, 0, 0], [0.2, -3, 0], "b"))  # back to back


def _one_camera(cap):
    c = copy.copy(cap)
    c.frames = [f for f in cap.frames if f.camera == "rgb0"]
    return c


def _identical_poses(cap):
    c = copy.copy(cap)
    c.frames = []
    pose = next(f for f in cap.frames if f.camera == "rgb0").c2w
    for f in cap.frames:
        g = copy.copy(f)
        g.c2w = np.array(pose)
        c.frames.append(g)
    return c


def _no_overlap(cap):
    c = copy.copy(cap)
    c.frames = []
    for f in cap.frames:
        g = copy.copy(f)
        if f.camera == "rgb1":
            flip = np.diag([-1.0, 1.0, -1.0, 1.0])  # turn rgb1 around its vertical axis
            g.c2w = np.array(f.c2w) @ flip
        c.frames.append(g)
    return c


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory):
    from engine.io.capture import load_capture
    from tools.synthetic import write_synthetic_capture

    cap = load_capture(write_synthetic_capture(tmp_path_factory.mktemp("st") / "cap", width=64, height=48, n_rgb=3,
                                               eval_fps=30.0))
    cap.points_path = None
    return cap


@pytest.mark.parametrize("make,message", [(_one_camera, "two RGB train cameras"),
                                          (_identical_poses, "identical poses|same place"),
                                          (_no_overlap, "do not see the same")])
def test_not_a_pair_falls_back_to_random_and_says_why(small_capture, make, message):
    from engine.geometry.init_points import initial_points

    cap = make(small_capture)
    with pytest.raises(StereoUnavailable, match=message):
        capture_fusion(cap, sorted({f.camera for f in cap.frames}))
    for method in ("auto", "stereo"):
        with pytest.warns(UserWarning, match="stereo initialisation unavailable"):
            pts = initial_points(cap, method, n_random=300)
        assert pts.method == "random" and len(pts.xyz) == 300
        assert pts.info["fallback"]["to"] == "random"
        import re
        assert re.search(message, pts.info["fallback"]["reason"])


def test_fallback_is_recorded_in_run_json_and_depth_prior_skipped(small_capture, tmp_path):
    from engine.io.checkpoint import read_run_json
    from engine.train import train

    cap = _identical_poses(small_capture)
    with pytest.warns(UserWarning, match="stereo initialisation unavailable"):
        train(cap, tmp_path / "r", overrides={"iterations": 2, "init": "stereo", "lambda_depth": 0.1}, rgb_only=True)
    init = read_run_json(tmp_path / "r")["init"]
    assert init["method"] == "random" and "identical poses" in init["fallback"]["reason"]
    assert "identical poses" in init["depth_prior_unavailable"]


def test_capture_stereo_init_covers_the_scene(small_capture):
    from engine.geometry.init_points import initial_points

    pts = initial_points(small_capture, "stereo", max_points=2000)
    assert pts.method == "stereo" and pts.info["matcher"] == "sgbm" and pts.info["instants"] == 3
    assert pts.info["static"] > 0.4 * 2 * 64 * 48


def test_trainer_fuses_the_pair_once_for_init_and_depth_priors(demo_capture, monkeypatch):
    """Init points (init=stereo) and the lambda_depth priors fuse the same frames: SGBM over
    every instant runs once per run, not once per user."""
    from engine.geometry import depth_priors, init_points, stereo
    from engine.io.capture import load_capture
    from engine.train import get_preset
    from engine.train.loop.trainer import Trainer

    calls = []
    real = stereo.capture_fusion
    counting = lambda *a, **k: calls.append(1) or real(*a, **k)  # noqa: E731
    for module in (stereo, depth_priors, init_points):  # every name it is called by
        monkeypatch.setattr(module, "capture_fusion", counting)
    cfg = get_preset("fast", {"init": "stereo", "lambda_depth": 0.1, "iterations": 2, "init_max_points": 300})
    tr = Trainer(load_capture(demo_capture), cfg, device="cpu", rgb_only=True)
    tr.init_model()
    assert tr.init_info["method"] == "stereo"
    assert any("stereo_depth" in it for it in tr.items)
    assert len(calls) == 1


def test_rectification_passes_opencv5_shaped_arguments(monkeypatch):
    """OpenCV 5 rejects a flat (3,) translation in stereoRectify ('a_size.width == len in
    gemm'; OpenCV 4 accepted it): found on the GPU box, whose image ships OpenCV 5.0.0. The
    pinned OpenCV here is 4.x, so the shapes are checked on the way in."""
    real = cv2.stereoRectify
    seen = {}

    def strict(K1, d1, K2, d2, size, R, T, *args, **kwargs):
        seen["R"], seen["T"] = np.shape(R), np.shape(T)
        return real(K1, d1, K2, d2, size, R, T, *args, **kwargs)

    monkeypatch.setattr(cv2, "stereoRectify", strict)
    rectify_pair(_view([-0.1, 0, 0], [-0.1, 3, 0], "a"), _view([0.1, 0, 0], [0.1, 3, 0], "b"))
    assert seen == {"R": (3, 3), "T": (3, 1)}
