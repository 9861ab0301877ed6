"""scripts/make_capture.py: a tiny capture rendered with Cycles loads and is consistent."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from blender_util import NEEDS_BPY

from engine.colour import luminance, srgb_to_linear
from engine.io.capture import load_capture
from engine.io.images import read_image

REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("gen") / "cap"
    cmd = [sys.executable, str(REPO_ROOT / "scripts" / "make_capture.py"), "--out", str(out),
           "--seconds", "0.05", "--rgb-size", "64x48", "--spike-size", "32x24", "--eval-fps", "100",
           "--samples", "4", "--light-hz", "500", "--seed", "3"]
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-4000:]
    return out


@pytest.mark.slow
@NEEDS_BPY
def test_generated_capture_loads_with_the_expected_rig(tiny_capture):
    cap = load_capture(tiny_capture)
    assert set(cap.cameras) == {"rgb0", "rgb1", "spike0", "eval0"}
    assert {n: c.role for n, c in cap.cameras.items()} == {"rgb0": "train", "rgb1": "train",
                                                          "spike0": "train", "eval0": "eval"}
    assert (cap.cameras["rgb0"].width, cap.cameras["rgb0"].height) == (64, 48)
    assert (cap.cameras["spike0"].width, cap.cameras["spike0"].height) == (32, 24)
    # 0.05 s at 30 FPS: frames at 0 and 1/30 s; at 100 FPS: 0 .. 0.05 s
    assert sorted(f.time for f in cap.frames if f.camera == "rgb0") == pytest.approx([0.0, 1 / 30])
    assert len([f for f in cap.frames if f.camera == "rgb1"]) == 2
    assert [f.time for f in cap.eval_frames] == pytest.approx(np.arange(6) / 100)
    (s,) = cap.spike_streams
    assert (s.camera, s.rate_hz, s.num_frames, s.t0, s.co_located_with) == ("spike0", 20000.0, 1000, 0.0, "rgb0")
    assert s.path.stat().st_size == 1000 * 32 * 24 // 8
    # spike camera: same pose and field of view as rgb0
    rgb0 = cap.frames_by_camera()["rgb0"][0]
    np.testing.assert_allclose(s.c2w, rgb0.c2w)
    k, ks = cap.cameras["rgb0"].intrinsics, cap.cameras["spike0"].intrinsics
    assert ks.fx / ks.width == pytest.approx(k.fx / k.width) and ks.cy / ks.height == pytest.approx(k.cy / k.height)
    # the stereo baseline is 10-15 % of the distance to the scene
    rgb1 = cap.frames_by_camera()["rgb1"][0]
    base = np.linalg.norm(rgb1.c2w[:3, 3] - rgb0.c2w[:3, 3])
    assert 0.08 < base / np.linalg.norm(rgb0.c2w[:3, 3] - np.array([0, 0.3, 0.9])) < 0.16
    for f in cap.frames + cap.eval_frames:
        assert f.load_rgb().shape == (f.intrinsics.height, f.intrinsics.width, 3)


@pytest.mark.slow
@NEEDS_BPY
def test_spikes_agree_with_the_co_located_rgb_frame(tiny_capture):
    """Spike counts over a window ~ linear luminance of rgb0 / 3 (white fires every 3rd frame)."""
    cap = load_capture(tiny_capture)
    sim = json.loads((tiny_capture / "transforms.json").read_text())["spike_streams"][0]["sim"]
    spikes = cap.spike_stream("spike0").read()
    assert spikes.shape == (1000, 24, 32) and set(np.unique(spikes)) <= {0, 1}
    rate = spikes[:200].mean(0)  # first 10 ms
    rgb = cap.frames_by_camera()["rgb0"][0].load_rgb()
    lum = luminance(srgb_to_linear(rgb)).reshape(24, 2, 32, 2).mean((1, 3))
    assert np.corrcoef(rate.ravel(), lum.ravel())[0, 1] > 0.8
    assert rate.mean() == pytest.approx(lum.mean() * sim["light_scale"], rel=0.25)
    assert rate.max() <= 0.6  # nothing saturates to fire every frame


@pytest.mark.slow
@NEEDS_BPY
def test_rgb_frames_are_plain_srgb_pngs(tiny_capture):
    cap = load_capture(tiny_capture)
    f = cap.frames[0]
    assert f.path.suffix == ".png"
    img = read_image(f.path)
    assert img.dtype == np.float32 and 0.0 <= img.min() and img.max() <= 1.0
    assert img[..., :3].std() > 0.05  # textured, not a flat render


def test_demo_capture_is_small_and_moving(demo_capture):
    """The shipped demo: <= 6 MB, and its objects move a lot between 30 FPS frames."""
    size = sum(p.stat().st_size for p in demo_capture.rglob("*") if p.is_file())
    assert size <= 6e6
    cap = load_capture(demo_capture)
    frames = cap.frames_by_camera()["rgb0"]
    assert len(frames) == 7 and len(cap.eval_frames) == 61
    assert cap.spike_streams[0].num_frames == 4000
    a, b = frames[2].load_rgb(), frames[3].load_rgb()
    changed = (np.abs(a - b).max(-1) > 0.1).mean()
    assert changed > 0.02  # a visible part of the image changes between consecutive frames
    # the middle eval frame differs from the mean of its RGB neighbours (interpolation fails)
    mid = [f for f in cap.eval_frames if abs(f.time - (frames[2].time + frames[3].time) / 2) < 1e-6]
    assert mid
    err = np.abs(mid[0].load_rgb() - 0.5 * (a + b)).mean()
    assert err > 0.01


@pytest.mark.slow
@NEEDS_BPY
def test_object_ground_truth_follows_the_motion(tiny_capture):
    """Every generated capture carries ground_truth.objects: poses at the light rate."""
    sys.path.insert(0, str(REPO_ROOT / "scripts"))
    import capture_classic

    cap = load_capture(tiny_capture)
    obj = cap.ground_truth.objects
    assert obj.names == ["ball", "cube", "torus"] and obj.rate_hz == 500.0
    truth = obj.load()
    assert truth["times"] == pytest.approx(np.arange(len(truth["times"])) / 500.0)
    for i in (0, 7, len(truth["times"]) - 1):
        for name, (loc, _) in capture_classic.object_poses(truth["times"][i]).items():
            np.testing.assert_allclose(truth[name][i][:3, 3], loc, atol=1e-6)
    assert all(f.depth_file_path is None for f in cap.frames)  # depth is opt-in outside --preset novel


@NEEDS_BPY
def test_bad_eval_angles_are_refused(tmp_path):
    cmd = [sys.executable, str(REPO_ROOT / "scripts" / "make_capture.py"), "--out", str(tmp_path / "x"),
           "--eval-angles", "side10,left20"]
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=120)
    assert proc.returncode == 2 and "'left20' is not side<deg> or up<deg>" in proc.stdout
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
@NEEDS_BPY
def test_a_vidar_shaped_spike_sensor_is_a_camera_of_its_own(tmp_path):
    """--spike-size of another shape than the RGB (Vidar: 400x250, 16:10) renders the spike light
    through its own lens (square pixels, the RGB horizontal field of view), and the engine maps the
    RGB frame onto it (engine.spike.render.view_warp) better than squashing it would."""
    import torch

    from engine.spike.render import estimate_sensor, resample_to, rgb_to_luma_linear, sensor_light

    out = tmp_path / "cap"
    cmd = [sys.executable, str(REPO_ROOT / "scripts" / "make_capture.py"), "--out", str(out),
           "--seconds", "0.05", "--rgb-size", "64x48", "--spike-size", "40x25", "--eval-fps", "100",
           "--samples", "4", "--light-hz", "500", "--seed", "3"]
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-4000:]
    cap = load_capture(out)
    k, ks = cap.cameras["rgb0"].intrinsics, cap.cameras["spike0"].intrinsics
    assert (ks.width, ks.height) == (40, 25) and ks.fx == pytest.approx(ks.fy)
    assert ks.fx / ks.width == pytest.approx(k.fx / k.width)  # the same horizontal field of view
    stream = cap.spike_streams[0].open()
    sensor = estimate_sensor(cap, stream)
    assert sensor.warp is not None and sensor.valid.all()  # 16:10 inside 4:3: every spike pixel is covered
    rgb = torch.as_tensor(cap.frames_by_camera()["rgb0"][0].load_rgb(), dtype=torch.float32)
    rate = stream.read(0, 200).mean(0)
    through_lens = sensor_light(rgb, sensor).numpy().ravel()
    squashed = resample_to(rgb_to_luma_linear(rgb), 25, 40).numpy().ravel()
    c_lens, c_squash = np.corrcoef(rate.ravel(), through_lens)[0, 1], np.corrcoef(rate.ravel(), squashed)[0, 1]
    assert c_lens > 0.8 and c_lens > c_squash + 0.02, (c_lens, c_squash)


@NEEDS_BPY
def test_real_size_preset_is_the_papers_rig():
    """Issue 43: --preset real is the paper's rig (RGB 1080x720, a Vidar-shaped 400x250 spike
    camera, at least 0.5 s) with the simulated sensor noise on; a benchmark input only."""
    sys.path.insert(0, str(REPO_ROOT / "scripts"))
    import make_capture

    real = make_capture.PRESETS["real"]
    assert real["rgb_size"] == (1080, 720) and real["spike_size"] == (400, 250) and real["seconds"] >= 0.5
    assert make_capture.SPIKE_HZ == 20000.0
    assert make_capture.GAIN_STD > 0 and make_capture.DARK_CURRENT > 0 and make_capture.PHOTONS_PER_THRESHOLD > 0
