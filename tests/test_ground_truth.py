"""Capture ground truth (CAPTURE_FORMAT: depth_file_path, ground_truth.objects) loads, validates
and names the file on bad input."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from engine.errors import CaptureError
from engine.io.capture import load_capture
from engine.io.ground_truth import points_at, pose_at
from engine.io.images import write_exr, write_png

W, H = 8, 6


def _cam_c2w(x: float) -> list:
    m = np.eye(4)
    m[0, 3] = x
    m[2, 3] = 3.0
    return m.tolist()


def make_capture(root: Path, *, depth=True, truth=True, tweak=None) -> Path:
    """Two train cameras and one eval camera, 2 instants, depth EXRs and an objects npz."""
    root.mkdir(parents=True, exist_ok=True)
    cams = {n: {"w": W, "h": H, "fl_x": 10.0, "fl_y": 10.0, "cx": W / 2, "cy": H / 2,
                "role": "eval" if n == "eval0" else "train"} for n in ("rgb0", "rgb1", "eval0")}
    frames, evals = [], []
    for i, t in enumerate((0.0, 0.1)):
        for n, x in (("rgb0", -0.1), ("rgb1", 0.1), ("eval0", 0.0)):
            rel = f"rgb/{n}/{i:06d}.png"
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            img = np.full((H, W, 3), 0.5, np.float32)
            img[2:4, 2:4] = 0.5 + 0.4 * i  # something moves
            write_png(root / rel, img)
            rec = {"file_path": rel, "camera": n, "time": t, "transform_matrix": _cam_c2w(x)}
            if depth:
                drel = f"depth/{n}/{i:06d}.exr"
                (root / drel).parent.mkdir(parents=True, exist_ok=True)
                z = np.full((H, W), 3.0 + i, np.float32)
                z[0, 0] = np.inf
                z[0, 1] = 1e10  # "no surface" written as a huge number
                write_exr(root / drel, {"Z": z})
                rec["depth_file_path"] = drel
            (evals if n == "eval0" else frames).append(rec)
    data = {"version": 1, "cameras": cams, "frames": frames, "eval_frames": evals}
    if truth:
        times = np.arange(5) / 100.0
        mats = np.repeat(np.eye(4)[None], 5, axis=0)
        mats[:, 0, 3] = np.arange(5) * 0.01  # 1 m/s along x
        (root / "ground_truth").mkdir(exist_ok=True)
        np.savez(root / "ground_truth/objects.npz", times=times, ball=mats,
                 ball_points=np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], np.float32))
        data["ground_truth"] = {"objects": {"file_path": "ground_truth/objects.npz", "rate_hz": 100.0,
                                            "t0": 0.0, "names": ["ball"]}}
    if tweak:
        tweak(data)
    (root / "transforms.json").write_text(json.dumps(data))
    return root


def test_depth_and_objects_load(tmp_path):
    cap = load_capture(make_capture(tmp_path / "c"))
    assert all(f.depth_file_path is not None and f.depth_file_path.is_file() for f in cap.frames + cap.eval_frames)
    f = cap.eval_frames[1]
    z = f.load_depth()
    assert z.shape == (H, W) and z.dtype == np.float32
    assert np.isinf(z[0, 0]) and np.isinf(z[0, 1]) and z[1, 1] == pytest.approx(4.0)
    obj = cap.ground_truth.objects
    assert (obj.rate_hz, obj.t0, obj.names) == (100.0, 0.0, ["ball"])
    truth = obj.load()
    assert truth["ball"].shape == (5, 4, 4) and truth["ball_points"].shape == (2, 3)
    # between samples: linear; outside: clamped
    p = points_at(truth, "ball", 0.015)
    np.testing.assert_allclose(p, [[0.015, 0, 0], [0.015, 0, 1]], atol=1e-9)
    np.testing.assert_allclose(points_at(truth, "ball", [0.0, 1.0])[:, 0, 0], [0.0, 0.04])


def test_pose_at_interpolates_between_the_nearest_samples_and_clamps():
    times = np.array([0.0, 0.001, 0.002])
    mats = np.repeat(np.eye(4)[None], 3, 0)
    mats[:, 0, 3] = [0.0, 1.0, 4.0]
    mats[2, :3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # a quarter turn at the last sample
    np.testing.assert_allclose(pose_at(times, mats, 0.001), mats[1])
    np.testing.assert_allclose(pose_at(times, mats, 0.0015), 0.5 * (mats[1] + mats[2]))
    np.testing.assert_allclose(pose_at(times, mats, -1.0), mats[0])
    np.testing.assert_allclose(pose_at(times, mats, 9.0), mats[2])
    many = pose_at(times, mats, [0.0005, 0.0015])
    assert many.shape == (2, 4, 4)
    np.testing.assert_allclose(many[:, 0, 3], [0.5, 2.5])
    assert pose_at(times[:1], mats[:1], 0.3).shape == (4, 4)


def test_capture_without_ground_truth_loads_as_before(tmp_path):
    cap = load_capture(make_capture(tmp_path / "c", depth=False, truth=False))
    assert cap.ground_truth is None
    assert all(f.depth_file_path is None for f in cap.frames)
    with pytest.raises(CaptureError, match="no ground-truth depth"):
        cap.frames[0].load_depth()


@pytest.mark.parametrize("tweak, match", [
    (lambda d: d["frames"][0].update(depth_file_path="depth/nope.exr"), r"frames\[0\]\.depth_file_path: depth file"),
    (lambda d: d["eval_frames"][1].update(depth_file_path=7),
     r"eval_frames\[1\]\.depth_file_path: must be a non-empty string"),
    (lambda d: d.update(ground_truth=[1]), r"ground_truth: must be an object"),
    (lambda d: d["ground_truth"]["objects"].update(rate_hz=0), r"ground_truth\.objects\.rate_hz: must be positive"),
    (lambda d: d["ground_truth"]["objects"].update(names="ball"), r"names: must be a list"),
    (lambda d: d["ground_truth"]["objects"].update(file_path="gt/missing.npz"), r"does not exist"),
    (lambda d: d["ground_truth"]["objects"].pop("names"), r"missing key 'names'"),
])
def test_bad_records_name_transforms_json(tmp_path, tweak, match):
    root = make_capture(tmp_path / "c", tweak=tweak)
    with pytest.raises(CaptureError, match=match) as info:
        load_capture(root)
    assert "transforms.json" in str(info.value)


def test_bad_depth_files_name_the_exr(tmp_path):
    root = make_capture(tmp_path / "c")
    cap = load_capture(root)
    bad = cap.frames[0].depth_file_path
    write_exr(bad, {"Z": np.ones((H + 1, W), np.float32)})
    with pytest.raises(CaptureError, match=r"depth is 8x7 pixels but the camera expects 8x6") as info:
        cap.frames[0].load_depth()
    assert bad.name in str(info.value)
    write_exr(bad, {"R": np.ones((H, W)), "G": np.ones((H, W))})
    with pytest.raises(CaptureError, match="no 'Z' channel"):
        cap.frames[0].load_depth()
    z = np.ones((H, W), np.float32)
    z[2, 2] = np.nan
    write_exr(bad, {"Z": z})
    with pytest.raises(CaptureError, match="NaN"):
        cap.frames[0].load_depth()
    z[2, 2] = -1.0
    write_exr(bad, {"Z": z})
    with pytest.raises(CaptureError, match="positive"):
        cap.frames[0].load_depth()


def test_bad_objects_npz_names_the_npz(tmp_path):
    root = make_capture(tmp_path / "c")
    npz = root / "ground_truth/objects.npz"
    np.savez(npz, times=np.arange(3) / 100.0, ball=np.zeros((2, 4, 4)), ball_points=np.zeros((4, 3)))
    obj = load_capture(root).ground_truth.objects
    with pytest.raises(CaptureError, match=r"'ball' has shape \(2, 4, 4\), expected 3x4x4") as info:
        obj.load()
    assert "objects.npz" in str(info.value)
    np.savez(npz, times=np.arange(3) / 100.0, ball=np.zeros((3, 4, 4)))
    with pytest.raises(CaptureError, match="missing array 'ball_points'"):
        obj.load()
    npz.write_bytes(b"not an npz")
    with pytest.raises(CaptureError, match="cannot read"):
        obj.load()
