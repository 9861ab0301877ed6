"""Trained-run API (engine.scene.model), camera files and renders (engine.export.render_views), init points."""
from __future__ import annotations

import json

import numpy as np
import pytest

from engine.cameras import Intrinsics, look_at_c2w
from engine.errors import CaptureError, RunError
from engine.export.npz import export_npz, read_export
from engine.export.render_views import orbit_views, read_camera_file, views_to_records, write_renders
from engine.geometry.init_points import cameras_focus, initial_points, random_points, stereo_points
from engine.io.capture import load_capture
from engine.scene.model import SAMPLE_KEYS, auto_num_samples, load_run
from engine.train import train
from tools.synthetic import synthetic_scene, write_synthetic_capture


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("model")
    cap = write_synthetic_capture(root / "cap", width=32, height=24, n_rgb=3, eval_fps=60.0, with_points=True)
    run = root / "run"
    train(cap, run, overrides={"iterations": 30, "init": "ply", "static_fraction": 0.3})
    return cap, run


def test_load_run_errors(tmp_path):
    with pytest.raises(RunError, match="does not exist"):
        load_run(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RunError, match="no checkpoint"):
        load_run(tmp_path / "empty")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "checkpoint.pt").write_bytes(b"garbage")
    with pytest.raises(RunError, match="unreadable"):
        load_run(tmp_path / "bad")


def test_scene_gaussians_at_and_render(trained):
    cap, run = trained
    scene = load_run(run)
    assert scene.time_range == pytest.approx((0.0, 2 / 30))
    g = scene.gaussians_at(0.05)
    n = scene.num_gaussians
    assert g["means"].shape == (n, 3) and g["quats"].shape == (n, 4) and g["scales"].shape == (n, 3)
    assert g["opacities"].shape == (n,) and g["colors"].shape == (n, 3) and g["sh"].shape[0] == n
    assert all(v.dtype == np.float32 for v in g.values())
    np.testing.assert_allclose(np.linalg.norm(g["quats"], axis=1), 1.0, atol=1e-5)
    assert g["scales"].min() > 0 and 0 <= g["opacities"].min() and g["opacities"].max() <= 1
    assert 0 <= g["colors"].min() and g["colors"].max() <= 1
    c = load_capture(cap)
    views = [c.view(c.eval_frames[0]), c.view(c.frames[0])]
    out = scene.render(views)
    assert len(out) == 2
    assert out[0]["rgb"].shape == (24, 32, 3)
    assert out[0]["alpha"].shape == (24, 32) and out[0]["depth"].shape == (24, 32)
    # the wall sits 3.5 m in front of the cameras: covered pixels have depth near it
    d = out[1]["depth"][out[1]["alpha"] > 0.9]
    assert d.size and 2.0 < np.median(d) < 4.5
    # a background colour shows through where alpha < 1
    white = scene.render(views[:1], background=(1.0, 1.0, 1.0))[0]["rgb"]
    assert np.all(white >= out[0]["rgb"] - 1e-5)


def test_export_round_trip(trained, tmp_path):
    _, run = trained
    scene = load_run(run)
    times = np.linspace(0, 2 / 30, 4)
    path = export_npz(scene, times, tmp_path / "cache.npz")
    data = read_export(path)
    assert data["times"].shape == (4,) and "means_t" in data and str(data["means_mode"]) == "residual_f16"
    assert data["means_t"].dtype == np.float16
    assert "scales_t" not in data  # scale deformation is off: nothing per time
    for i, t in enumerate(times):
        got = read_export(path, i)
        ref = scene.gaussians_at(float(t))
        np.testing.assert_allclose(got["means"], ref["means"], atol=2e-3)
        np.testing.assert_allclose(got["quats"], ref["quats"], atol=3e-3)
        np.testing.assert_allclose(got["scales"], ref["scales"], rtol=1e-6)
    with pytest.raises(RunError):
        read_export(tmp_path / "missing.npz")


def test_camera_files_both_schemas(tmp_path):
    c2w = look_at_c2w([0, -3, 0], [0, 0, 0]).tolist()
    (tmp_path / "a.json").write_text(json.dumps({
        "cameras": {"cam": {"w": 40, "h": 30, "fl_x": 35.0, "fl_y": 35.0, "cx": 20, "cy": 15}},
        "frames": [{"camera": "cam", "transform_matrix": c2w, "time": 0.1, "file_path": "x/000007.png"}]}))
    (tmp_path / "b.json").write_text(json.dumps({
        "frames": [{"w": 16, "h": 12, "fl_x": 10.0, "fl_y": 11.0, "cx": 8, "cy": 6, "transform_matrix": c2w}]}))
    a = read_camera_file(tmp_path / "a.json")
    b = read_camera_file(tmp_path / "b.json")
    assert a[0].intrinsics == Intrinsics(40, 30, 35.0, 35.0, 20.0, 15.0) and a[0].time == 0.1 and a[0].name == "000007"
    assert b[0].intrinsics.fy == 11.0 and b[0].time == 0.0
    again = read_camera_file_from(tmp_path, views_to_records(a + b))
    assert [v.intrinsics for v in again] == [a[0].intrinsics, b[0].intrinsics]
    (tmp_path / "bad.json").write_text(json.dumps({"frames": [{"camera": "nope", "transform_matrix": c2w}]}))
    with pytest.raises(CaptureError, match="unknown camera"):
        read_camera_file(tmp_path / "bad.json")
    bad = {"frames": [{"w": 4, "h": 4, "fl_x": 1, "transform_matrix": [[1]]}]}
    (tmp_path / "bad2.json").write_text(json.dumps(bad))
    with pytest.raises(CaptureError, match="4x4"):
        read_camera_file(tmp_path / "bad2.json")
    with pytest.raises(CaptureError, match="does not exist"):
        read_camera_file(tmp_path / "none.json")


def read_camera_file_from(tmp_path, records):
    p = tmp_path / "rt.json"
    p.write_text(json.dumps(records))
    return read_camera_file(p)


def test_write_renders_png_and_exr(trained, tmp_path):
    from engine.colour import srgb_to_linear
    from engine.io.images import read_exr_channels, read_image_rgba

    cap, run = trained
    scene = load_run(run)
    c = load_capture(cap)
    v = c.view(c.frames[0])
    paths = write_renders(scene, [v], tmp_path / "png", "png")
    rgba = read_image_rgba(paths[0])
    ref = scene.render([v])[0]
    assert rgba.shape == (24, 32, 4)
    np.testing.assert_allclose(rgba[..., 3], ref["alpha"], atol=1 / 255 + 1e-6)
    ok = ref["alpha"] > 0.98
    straight = ref["rgb"][ok] / ref["alpha"][ok][:, None]
    np.testing.assert_allclose(rgba[ok][:, :3], straight.clip(0, 1), atol=2 / 255)
    paths = write_renders(scene, [v], tmp_path / "exr", "exr")
    ch = read_exr_channels(paths[0])
    assert set("RGBAZ") <= set(ch)
    np.testing.assert_allclose(ch["A"], ref["alpha"], atol=1e-6)
    straight = np.clip(ref["rgb"] / np.maximum(ref["alpha"], 1e-6)[..., None], 0, 1)
    lin = srgb_to_linear(straight) * ref["alpha"][..., None]
    np.testing.assert_allclose(ch["R"][ok], lin[..., 0][ok], atol=1e-4)
    np.testing.assert_allclose(ch["Z"][ok], ref["depth"][ok], rtol=1e-5)


def test_scene_sample_stacks_gaussians_at_even_times(trained):
    """Scene4D.sample: K evenly spaced capture times, each slice equal to gaussians_at(t_k)."""
    _, run = trained
    scene = load_run(run)
    n = scene.num_gaussians
    s = scene.sample(4)
    t0, t1 = scene.time_range
    np.testing.assert_allclose(s["times"], np.linspace(t0, t1, 4))
    assert s["means"].shape == (4, n, 3) and s["quats"].shape == (4, n, 4) and s["scales"].shape == (4, n, 3)
    assert s["opacities"].shape == (4, n) and s["colors"].shape == (4, n, 3)
    assert all(s[k].dtype == np.float32 for k in SAMPLE_KEYS)
    g = scene.gaussians_at(float(s["times"][2]))
    for k in SAMPLE_KEYS:
        np.testing.assert_array_equal(s[k][2], g[k])
    assert not np.array_equal(s["means"][0], s["means"][-1])  # the deformation moves something
    sub = scene.sample(3, (0.01, 0.02))
    np.testing.assert_allclose(sub["times"], [0.01, 0.015, 0.02])
    assert len(scene.sample(0)["times"]) == auto_num_samples(t1 - t0, n)


def test_auto_num_samples_bounds():
    assert auto_num_samples(0.0, 100) == 2
    assert auto_num_samples(1.0, 100) == 151
    assert auto_num_samples(10.0, 100) == 300                    # max_samples
    assert auto_num_samples(1.0, 1_000_000) == 4                 # max_points / N
    assert auto_num_samples(1.0, 10_000_000) == 2


def test_write_renders_to_given_paths(trained, tmp_path):
    """Explicit output files (Blender's frame-numbered names), PNG over a background colour,
    and two views that would write one file are refused."""
    from engine.io.images import read_image_rgba

    cap, run = trained
    scene = load_run(run)
    c = load_capture(cap)
    v0, v1 = c.view(c.frames[0]), c.view(c.frames[1])
    out = [tmp_path / "a" / "shot_0001.png", tmp_path / "b" / "shot_0002.png"]
    paths = write_renders(scene, [v0, v1], None, "png", paths=out, png_background=(0.0, 1.0, 0.0))
    assert paths == out and all(p.exists() for p in out)
    ref = scene.render([v0], background=(0.0, 1.0, 0.0))[0]
    np.testing.assert_allclose(read_image_rgba(out[0])[..., :3], ref["rgb"], atol=1 / 255 + 1e-6)
    with pytest.raises(ValueError, match="same output file"):
        write_renders(scene, [v0, v1], None, "exr", paths=[tmp_path / "x.exr"] * 2)
    with pytest.raises(ValueError, match="2 views"):
        write_renders(scene, [v0, v1], None, "exr", paths=[tmp_path / "x.exr"])


def test_orbit_views_circle_the_centre():
    k = Intrinsics(32, 24, 30, 30, 16, 12)
    views = orbit_views([0, 0, 0], 0.0, k, 8, time=0.05, start_eye=[0, -4, 1])
    assert len(views) == 8 and all(v.time == 0.05 for v in views)
    np.testing.assert_allclose(views[0].center, [0, -4, 1], atol=1e-9)
    for v in views:
        assert np.linalg.norm(v.center[:2]) == pytest.approx(4.0) and v.center[2] == pytest.approx(1.0)
        fwd = -v.c2w[:3, 2]
        to_c = -v.center / np.linalg.norm(v.center)
        assert fwd @ to_c == pytest.approx(1.0)
    np.testing.assert_allclose(views[4].center, [0, 4, 1], atol=1e-9)


def test_initial_points_sources(tmp_path):
    cap = load_capture(write_synthetic_capture(tmp_path / "cap", width=128, height=96, n_rgb=2, eval_fps=30.0,
                                               with_points=True, static=True))
    wall, blob, _ = synthetic_scene(0)
    gt = np.concatenate([wall["means"], blob["means"]])
    ply = initial_points(cap, "auto")
    assert ply.method == "ply" and len(ply.xyz) == len(gt)
    st = stereo_points(cap)
    assert st.method == "stereo" and len(st.xyz) > 500
    dist = lambda p: np.linalg.norm(p[:, None] - gt[None], axis=2).min(axis=1)  # noqa: E731
    d = dist(st.xyz)
    # triangulated points lie on the true surfaces (GT centres are ~0.08 apart, blob radius 0.22)
    assert np.median(d) < 0.15 and (d < 0.15).mean() > 0.6
    assert np.all(np.isfinite(st.rgb)) and st.rgb.min() >= 0 and st.rgb.max() <= 1
    rnd = random_points(cap, 500)
    assert np.median(dist(rnd.xyz)) > 2 * np.median(d)
    views = [cap.view(f) for f in cap.frames]
    focus = cameras_focus(views)
    assert focus is not None and np.linalg.norm(focus - [0, 2, 0]) < 0.3
    for v in views[:1]:
        z = (rnd.xyz - v.center) @ (-v.c2w[:3, 2])
        assert z.min() > 0
    auto_no_ply = initial_points(_without_ply(cap), "auto", max_points=800, n_random=200)
    assert auto_no_ply.method == "stereo" and len(auto_no_ply.xyz) == 800 and auto_no_ply.info["filled"] > 0
    random_fill = initial_points(_without_ply(cap), "stereo", max_points=800, n_random=200, fill_stride=0)
    assert len(random_fill.xyz) == 800 + 50 and random_fill.info["random_fill"] == 50
    with pytest.raises(ValueError):
        initial_points(_without_ply(cap), "ply")


def _without_ply(cap):
    import copy

    c = copy.copy(cap)
    c.points_path = None
    return c


def test_train_rejects_a_capture_without_train_frames(tmp_path):
    cap = load_capture(write_synthetic_capture(tmp_path / "cap", width=16, height=12, n_rgb=2, eval_fps=30.0))
    import copy

    c = copy.copy(cap)
    c.frames = []
    with pytest.raises(RunError, match="no train RGB frames"):
        train(c, tmp_path / "run", overrides={"iterations": 2})
