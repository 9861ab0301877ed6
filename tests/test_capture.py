"""Capture loading: our format, D-NeRF and nerfstudio; laziness; every bad-input case."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import engine
from engine.cameras import View
from engine.errors import CaptureError
from engine.io import images
from engine.io.capture import Capture, load_capture
from engine.io.images import write_exr, write_png
from engine.io.points import load_points, write_points
from engine.io.spikes import SpikeStream, write_spikes

W, H = 8, 6
SW, SH = 8, 4


def _pose(x=0.0):
    m = np.eye(4)
    m[0, 3] = x
    return m.tolist()


def _img(seed, w=W, h=H):
    return np.random.default_rng(seed).random((h, w, 3)).astype(np.float32)


def make_ours(root: Path, *, n_rgb=3, n_spike=40) -> dict:
    """Tiny capture in our format: 2 stereo RGB cameras, 1 eval camera, 1 spike stream."""
    root.mkdir(parents=True, exist_ok=True)
    cams = {
        "rgb0": {"w": W, "h": H, "fl_x": 10.0, "fl_y": 11.0, "cx": 4.0, "cy": 3.0, "role": "train"},
        "rgb1": {"w": W, "h": H, "fl_x": 10.0, "fl_y": 11.0, "cx": 4.0, "cy": 3.0, "role": "train"},
        "spike0": {"w": SW, "h": SH, "fl_x": 5.0, "fl_y": 5.0, "cx": 4.0, "cy": 2.0, "role": "train"},
        "eval0": {"w": W, "h": H, "fl_x": 10.0, "fl_y": 10.0, "cx": 4.0, "cy": 3.0, "role": "eval"},
    }
    frames = []
    for ci, cam in enumerate(("rgb0", "rgb1")):
        for i in range(n_rgb):
            rel = f"rgb/{cam}/{i:06d}.png"
            write_png(root / rel, _img(10 * ci + i), bits=16 if ci else 8)
            frames.append({"file_path": rel, "camera": cam, "time": i / 30, "transform_matrix": _pose(0.1 * ci)})
    rel = "eval/eval0/000000.exr"
    write_exr(root / rel, _img(99))
    evals = [{"file_path": rel, "camera": "eval0", "time": 0.01, "transform_matrix": _pose(0.5)}]
    spikes = (np.random.default_rng(0).random((n_spike, SH, SW)) < 0.3).astype(np.uint8)
    write_spikes(root / "spike" / "spike0.dat", spikes)
    streams = [{"file_path": "spike/spike0.dat", "camera": "spike0", "rate_hz": 400, "t0": 0.0,
                "num_frames": n_spike, "w": SW, "h": SH, "co_located_with": "rgb0", "transform_matrix": _pose()}]
    data = {"version": 1, "cameras": cams, "frames": frames, "eval_frames": evals, "spike_streams": streams}
    (root / "transforms.json").write_text(json.dumps(data, indent=1))
    return data


def _rewrite(root: Path, data: dict):
    (root / "transforms.json").write_text(json.dumps(data, indent=1))


# ----------------------------------------------------------------------------- our format

def test_load_ours(tmp_path):
    make_ours(tmp_path)
    cap = load_capture(tmp_path)
    assert isinstance(cap, Capture) and engine.load_capture is load_capture
    assert cap.format == "bt4d"
    assert set(cap.cameras) == {"rgb0", "rgb1", "spike0", "eval0"}
    assert cap.cameras["eval0"].role == "eval" and cap.cameras_with_role("eval") == ["eval0"]
    k = cap.cameras["rgb0"].intrinsics
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy) == (W, H, 10.0, 11.0, 4.0, 3.0)
    assert len(cap.frames) == 6 and len(cap.eval_frames) == 1
    f = cap.frames[1]
    assert f.path.is_absolute() and f.path.name == "000001.png" and f.camera == "rgb0"
    assert f.time == pytest.approx(1 / 30) and f.c2w.shape == (4, 4) and f.c2w.dtype == np.float64
    assert [fr.camera for fr in cap.train_frames("rgb1")] == ["rgb1"] * 3
    assert len(cap.train_frames()) == 6
    assert set(cap.frames_by_camera()) == {"rgb0", "rgb1", "eval0"}
    assert np.allclose(cap.rgb_times("rgb1"), np.arange(3) / 30)
    assert cap.time_range == (0.0, pytest.approx(0.1))  # 40 spike frames at 400 Hz
    v = cap.view(f)
    assert isinstance(v, View) and v.time == f.time and v.intrinsics == k
    # pixels
    rgb8 = f.load_rgb()
    assert rgb8.dtype == np.float32 and rgb8.shape == (H, W, 3)
    assert np.abs(rgb8 - _img(1)).max() <= 0.5 / 255 + 1e-6
    rgb16 = cap.frames[4].load_rgb()
    assert np.abs(rgb16 - _img(11)).max() <= 0.5 / 65535 + 1e-6
    ev = cap.eval_frames[0].load_rgb()  # EXR: linear -> sRGB-encoded, clipped
    assert np.allclose(ev, np.clip(engine.colour.linear_to_srgb(_img(99)), 0, 1), atol=1e-6)
    # spikes
    info = cap.spike_streams[0]
    assert info.camera == "spike0" and info.co_located_with == "rgb0" and info.num_frames == 40
    st = cap.spike_stream("spike0")
    assert isinstance(st, SpikeStream) and len(st) == 40 and st.rate_hz == 400
    assert st.intrinsics == cap.cameras["spike0"].intrinsics
    assert st.frames_between(0.0, 0.05)[0].shape == (20, SH, SW)
    assert st.view(0.02).time == 0.02
    assert cap.points_path is None and cap.load_points() is None


def test_load_ours_points_and_json_file_path(tmp_path):
    make_ours(tmp_path)
    xyz = np.random.default_rng(0).random((20, 3)).astype(np.float32)
    rgb = np.random.default_rng(1).random((20, 3)).astype(np.float32)
    write_points(tmp_path / "points.ply", xyz, rgb)
    cap = load_capture(tmp_path / "transforms.json")
    assert cap.points_path == (tmp_path / "points.ply").resolve()
    pxyz, prgb = cap.load_points()
    assert np.allclose(pxyz, xyz) and np.abs(prgb - rgb).max() <= 0.5 / 255 + 1e-6
    write_points(tmp_path / "plain.ply", xyz)
    assert load_points(tmp_path / "plain.ply")[1] is None


def test_eval_role_camera_frames_go_to_eval(tmp_path):
    data = make_ours(tmp_path)
    data["frames"].append(dict(data["eval_frames"][0], time=0.02))  # another instant of that camera
    _rewrite(tmp_path, data)
    cap = load_capture(tmp_path)
    assert len(cap.frames) == 6 and len(cap.eval_frames) == 2
    assert all(f.camera != "eval0" for f in cap.train_frames())


def test_loading_reads_no_pixels(tmp_path, monkeypatch):
    make_ours(tmp_path)

    def boom(*a, **k):
        raise AssertionError("pixels read during load_capture")

    for name in ("read_image", "read_image_rgba", "read_image_srgb", "read_exr_channels", "_read_png",
                 "_read_pillow"):
        monkeypatch.setattr(images, name, boom)
    cap = load_capture(tmp_path)
    assert len(cap.frames) == 6
    with pytest.raises(AssertionError):
        cap.frames[0].load_rgb()  # the loader really goes through engine.io.images


def test_many_frames_load_without_reading(tmp_path, monkeypatch):
    data = make_ours(tmp_path)
    one = data["frames"][0]
    data["frames"] = [dict(one, time=i / 30) for i in range(3000)]
    _rewrite(tmp_path, data)
    monkeypatch.setattr(images, "read_image_rgba", lambda *a: (_ for _ in ()).throw(AssertionError))
    cap = load_capture(tmp_path)
    assert len(cap.frames) == 3000


def test_wrong_image_size_on_load_rgb(tmp_path):
    data = make_ours(tmp_path)
    write_png(tmp_path / data["frames"][0]["file_path"], _img(0, w=5, h=4))
    cap = load_capture(tmp_path)  # not detected at load time (no pixels read)
    with pytest.raises(CaptureError) as e:
        cap.frames[0].load_rgb()
    assert "000000.png" in str(e.value) and "5x4" in str(e.value) and f"{W}x{H}" in str(e.value)


def test_background_composite(tmp_path):
    rgba = np.zeros((H, W, 4), np.float32)
    rgba[..., 0] = 1.0
    rgba[:, : W // 2, 3] = 1.0  # left half opaque red, right half transparent
    data = make_ours(tmp_path)
    write_png(tmp_path / data["frames"][0]["file_path"], rgba)
    f = load_capture(tmp_path).frames[0]
    out = f.load_rgb(background=(1, 1, 1))
    assert np.allclose(out[0, 0], [1, 0, 0]) and np.allclose(out[0, -1], [1, 1, 1])
    assert np.allclose(f.load_alpha()[0], [1] * (W // 2) + [0] * (W // 2))


# ----------------------------------------------------------------------------- D-NeRF

def make_dnerf(root: Path, *, with_time=True):
    root.mkdir(parents=True, exist_ok=True)
    angle = 0.6911112070083618
    for split, n in (("train", 4), ("val", 2), ("test", 3)):
        frames = []
        for i in range(n):
            rel = f"./{split}/r_{i:03d}"
            rgba = np.concatenate([_img(i), np.ones((H, W, 1), np.float32)], axis=-1)
            write_png(root / f"{split}/r_{i:03d}.png", rgba)
            fr = {"file_path": rel, "rotation": 0.1, "transform_matrix": _pose(i)}
            if with_time:
                fr["time"] = i / max(n - 1, 1)
            frames.append(fr)
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    return angle


def test_load_dnerf(tmp_path):
    angle = make_dnerf(tmp_path)
    cap = load_capture(tmp_path)
    assert cap.format == "dnerf"
    assert len(cap.frames) == 4 and len(cap.eval_frames) == 3 and len(cap.val_frames) == 2
    assert cap.cameras["train"].role == "train" and cap.cameras["test"].role == "eval"
    k = cap.cameras["train"].intrinsics
    assert (k.width, k.height) == (W, H)
    assert k.fx == pytest.approx(0.5 * W / math.tan(0.5 * angle)) and k.fy == k.fx
    assert (k.cx, k.cy) == (W / 2, H / 2)
    assert [f.time for f in cap.frames] == pytest.approx([0, 1 / 3, 2 / 3, 1])  # kept as-is
    assert cap.time_range == (0.0, 1.0)
    assert cap.frames[2].path.name == "r_002.png"
    assert all(f.role == "eval" for f in cap.eval_frames)
    assert cap.frames[1].load_rgb().shape == (H, W, 3)
    assert load_capture(tmp_path / "transforms_train.json").format == "dnerf"


def test_dnerf_without_time_and_missing_image(tmp_path):
    make_dnerf(tmp_path, with_time=False)
    cap = load_capture(tmp_path)
    assert all(f.time == 0.0 for f in cap.frames)
    (tmp_path / "test" / "r_001.png").unlink()
    with pytest.raises(CaptureError) as e:
        load_capture(tmp_path)
    assert "transforms_test.json" in str(e.value) and "frames[1]" in str(e.value) and "r_001" in str(e.value)


def test_dnerf_style_single_transforms_json(tmp_path):
    # no cameras block, only camera_angle_x, times in [0, 1]
    write_png(tmp_path / "a.png", _img(0))
    data = {"camera_angle_x": 0.8, "frames": [{"file_path": "./a", "time": 0.5, "transform_matrix": _pose()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    cap = load_capture(tmp_path)
    assert cap.frames[0].time == 0.5 and cap.cameras["cam0"].intrinsics.width == W


# ----------------------------------------------------------------------------- nerfstudio

def test_load_nerfstudio(tmp_path):
    for i in range(3):
        write_png(tmp_path / "images" / f"frame_{i:05d}.png", _img(i))
    write_png(tmp_path / "images" / "big.png", _img(7, w=10, h=6))
    frames = [{"file_path": f"images/frame_{i:05d}.png", "transform_matrix": _pose(i)} for i in range(3)]
    frames.append({"file_path": "images/big.png", "transform_matrix": _pose(), "w": 10, "fl_x": 20.0, "cx": 5.0})
    data = {"camera_model": "OPENCV", "fl_x": 9.0, "fl_y": 9.5, "cx": 4.1, "cy": 3.2, "w": W, "h": H,
            "k1": 0.01, "frames": frames, "ply_file_path": "sparse.ply"}
    write_points(tmp_path / "sparse.ply", np.zeros((4, 3)))
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    cap = load_capture(tmp_path)
    assert cap.format == "nerfstudio"
    assert set(cap.cameras) == {"cam0", "cam1"}
    k0, k1 = cap.cameras["cam0"].intrinsics, cap.cameras["cam1"].intrinsics
    assert (k0.width, k0.height, k0.fx, k0.fy, k0.cx, k0.cy) == (W, H, 9.0, 9.5, 4.1, 3.2)
    assert (k1.width, k1.fx, k1.fy, k1.cx) == (10, 20.0, 9.5, 5.0)  # per-frame overrides
    assert cap.cameras["cam0"].extra["k1"] == 0.01
    assert all(f.time == 0.0 for f in cap.frames) and cap.eval_frames == []
    assert cap.points_path.name == "sparse.ply"
    assert cap.frames[3].load_rgb().shape == (H, 10, 3)


def test_nerfstudio_size_from_image_header(tmp_path):
    write_png(tmp_path / "x.png", _img(0))
    data = {"fl_x": 9.0, "frames": [{"file_path": "x.png", "transform_matrix": _pose(), "time": 0.25}]}
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    cap = load_capture(tmp_path)
    k = cap.cameras["cam0"].intrinsics
    assert (k.width, k.height, k.cx) == (W, H, W / 2) and cap.frames[0].time == 0.25


# ----------------------------------------------------------------------------- bad input

def _expect(tmp_path, match_file: str, *fragments: str):
    with pytest.raises(CaptureError) as e:
        load_capture(tmp_path)
    msg = str(e.value)
    assert match_file in msg, msg
    for frag in fragments:
        assert frag in msg, msg
    return msg


def test_missing_transforms(tmp_path):
    _expect(tmp_path, "transforms.json", "missing")
    _expect(tmp_path / "nowhere", "nowhere", "does not exist")


def test_malformed_json_reports_line_and_column(tmp_path):
    (tmp_path / "transforms.json").write_text('{\n  "cameras": {\n    "a": 1,,\n  }\n}')
    _expect(tmp_path, "transforms.json", "line 3", "column")


@pytest.mark.parametrize(
    "mutate, fragments",
    [
        (lambda d: d.pop("frames"), ["'frames'"]),
        (lambda d: d["frames"][2].pop("transform_matrix"), ["frames[2]", "transform_matrix"]),
        (lambda d: d["frames"][1].pop("time"), ["frames[1]", "'time'"]),
        (lambda d: d["cameras"]["rgb0"].pop("w"), ["rgb0", "'w'"]),
        (lambda d: d["frames"][0].update(camera="nope"), ["frames[0].camera", "unknown camera 'nope'"]),
        (lambda d: d["eval_frames"][0].update(camera="ghost"), ["eval_frames[0]", "ghost"]),
        (lambda d: d["spike_streams"][0].update(camera="nope"), ["spike_streams[0].camera", "nope"]),
        (lambda d: d["spike_streams"][0].update(co_located_with="rgbX"), ["co_located_with", "rgbX"]),
        (lambda d: d["frames"][3].update(file_path="rgb/rgb1/999999.png"), ["frames[3]", "999999.png",
                                                                             "does not exist"]),
        (lambda d: d["spike_streams"][0].update(file_path="spike/none.dat"), ["spike_streams[0]", "none.dat"]),
        (lambda d: d["spike_streams"][0].update(num_frames=41), ["num_frames", "40"]),
        (lambda d: d["frames"][0]["transform_matrix"][1].__setitem__(2, float("nan")),
         ["frames[0].transform_matrix", "non-finite"]),
        (lambda d: d["frames"][0].update(time=float("inf")), ["frames[0].time", "finite"]),
        (lambda d: d["cameras"]["rgb1"].update(fl_x=float("nan")), ["rgb1", "fl_x", "finite"]),
        (lambda d: d["frames"][4].update(transform_matrix=np.eye(4)[:3].tolist()), ["frames[4]", "4x4",
                                                                                    "(3, 4)"]),
        (lambda d: d["frames"][0].update(transform_matrix=[[1, 2], [3]]), ["frames[0].transform_matrix", "4x4"]),
        (lambda d: d["cameras"]["rgb0"].update(role="test"), ["rgb0", "role"]),
        (lambda d: d["spike_streams"][0].update(rate_hz=0), ["rate_hz", "positive"]),
        (lambda d: d["spike_streams"][0].update(w=16), ["spike_streams[0]", "16x4"]),
    ],
)
def test_bad_transforms_raise(tmp_path, mutate, fragments):
    data = make_ours(tmp_path)
    mutate(data)
    _rewrite(tmp_path, data)
    _expect(tmp_path, "transforms.json", *fragments)


def test_spike_file_not_whole_frames(tmp_path):
    make_ours(tmp_path)
    with open(tmp_path / "spike" / "spike0.dat", "ab") as fh:
        fh.write(b"\x00")
    _expect(tmp_path, "spike0.dat", "not a whole number of frames")


def test_bad_points_file(tmp_path):
    make_ours(tmp_path)
    (tmp_path / "points.ply").write_bytes(b"garbage")
    cap = load_capture(tmp_path)
    with pytest.raises(CaptureError, match="points.ply"):
        cap.load_points()


def test_two_frames_of_one_camera_at_one_time_are_refused(tmp_path):
    """Issue 45, defect 2: which image trains that instant was a silent choice."""
    data = make_ours(tmp_path)
    write_png(tmp_path / "rgb" / "other.png", _img(50))
    data["frames"].append({"file_path": "rgb/other.png", "camera": "rgb1", "time": 1 / 30,
                           "transform_matrix": _pose(0.1)})
    _rewrite(tmp_path, data)
    msg = _expect(tmp_path, "transforms.json", "frames[6]", "frames[4]", "'rgb1'", "conflict")
    assert "listed twice" not in msg
    data["frames"][-1]["file_path"] = data["frames"][4]["file_path"]
    _rewrite(tmp_path, data)
    _expect(tmp_path, "transforms.json", "frames[6]", "listed twice")
    data["frames"][-1]["time"] = 0.5  # another instant: fine
    _rewrite(tmp_path, data)
    assert len(load_capture(tmp_path).frames) == 7


def test_nerfstudio_static_views_are_not_conflicts_but_repeated_poses_are(tmp_path):
    for i in range(2):
        write_png(tmp_path / f"f{i}.png", _img(i))
    frames = [{"file_path": f"f{i}.png", "transform_matrix": _pose(i)} for i in range(2)]
    data = {"fl_x": 9.0, "w": W, "h": H, "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    assert len(load_capture(tmp_path).frames) == 2  # two poses at t = 0: a static multi-view capture
    frames[1]["transform_matrix"] = _pose(0)
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    _expect(tmp_path, "transforms.json", "frames[1]", "frames[0]", "conflict")
