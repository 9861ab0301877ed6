"""Two-stage baselines (paper Table 1) as training-data variants."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from engine.io.capture import load_capture
from engine.spike.render import _luma_at_spike_res, estimate_sensor
from engine.train.frames.baselines import (
    KINDS,
    baseline_frames,
    reinhard_transfer,
    rgb_to_lab_reinhard,
    spike_to_gray,
    with_baseline,
)


@pytest.fixture(scope="module")
def cap(demo_capture):
    return load_capture(demo_capture)


def _rgb0(cap):
    return sorted([f for f in cap.frames if f.camera == "rgb0"], key=lambda f: f.time)


def test_repeat_and_linear_frames(cap):
    fr = _rgb0(cap)
    rep = [f for f in baseline_frames(cap, "repeat", per_interval=4) if f.camera == "rgb0"]
    assert len(rep) == 4 * (len(fr) - 1)
    first = [f for f in rep if fr[0].time < f.time < fr[1].time]
    assert len(first) == 4 and all(np.array_equal(f.load_rgb(), fr[0].load_rgb()) for f in first)
    lin = baseline_frames(cap, "interp-linear", per_interval=1, cameras=["rgb0"])
    mid = [f for f in lin if fr[0].time < f.time < fr[1].time][0]
    assert np.allclose(mid.load_rgb(), 0.5 * (fr[0].load_rgb() + fr[1].load_rgb()), atol=1e-6)
    assert mid.view().intrinsics == fr[0].intrinsics and np.allclose(mid.view().c2w, fr[0].c2w)
    assert mid.extra["synthetic"] == "interp-linear"


def test_flow_frames_are_valid_images(cap):
    fl = baseline_frames(cap, "interp-flow", per_interval=1, cameras=["rgb1"])
    assert len(fl) == len(_rgb0(cap)) - 1 and all(f.camera == "rgb1" for f in fl)
    img = fl[0].load_rgb()
    assert img.dtype == np.float32 and img.shape == (120, 160, 3)
    assert 0.0 <= img.min() and img.max() <= 1.0


def test_spike2img_matches_the_co_located_frame(cap):
    stream = cap.spike_stream()
    sensor = estimate_sensor(cap, stream)
    f = _rgb0(cap)[2]
    gray = spike_to_gray(stream, f.time, sensor)
    y = _luma_at_spike_res(f.load_rgb(), stream.height, stream.width)
    assert np.corrcoef(gray.ravel(), y.ravel())[0, 1] > 0.95
    assert abs(gray.mean() - y.mean()) < 0.05
    tfi_gray = spike_to_gray(stream, f.time, sensor, method="tfi")
    assert np.corrcoef(tfi_gray.ravel(), y.ravel())[0, 1] > 0.8
    s2i = baseline_frames(cap, "spike2img", per_interval=2, sensor=sensor)
    assert {x.camera for x in s2i} == {"rgb0"}  # only the spike camera's co-located view
    assert len(s2i) == 2 * (len(_rgb0(cap)) - 1)
    chroma = baseline_frames(cap, "spike2img", per_interval=1, sensor=sensor, colour="chroma")
    assert chroma[0].load_rgb().shape == (120, 160, 3)
    with pytest.raises(ValueError):
        spike_to_gray(stream, f.time, sensor, method="magic")


def test_reinhard_transfer_matches_reference_statistics():
    rng = np.random.default_rng(0)
    src = rng.uniform(0.05, 0.5, size=(20, 20, 3))
    ref = rng.uniform(0.2, 0.9, size=(20, 20, 3)) * np.array([1.0, 0.5, 0.2])
    out = reinhard_transfer(src, ref)
    lo, lr = rgb_to_lab_reinhard(out), rgb_to_lab_reinhard(ref)
    assert np.allclose(lo.reshape(-1, 3).mean(0), lr.reshape(-1, 3).mean(0), atol=1e-3)
    assert np.allclose(lo.reshape(-1, 3).std(0), lr.reshape(-1, 3).std(0), atol=1e-3)


def test_with_baseline_appends_frames_and_rejects_unknown(cap):
    assert with_baseline(cap, None) is cap
    aug = with_baseline(cap, "repeat", per_interval=2)
    assert len(aug.frames) == len(cap.frames) + 2 * (len(cap.frames) - 2)
    assert len(cap.frames) == 14  # the original is untouched
    assert set(KINDS) == {"repeat", "interp-linear", "interp-flow", "spike2img"}
    with pytest.raises(ValueError):
        baseline_frames(cap, "rife")


def test_spike_images_reach_the_rgb_view_through_the_spike_cameras_lens():
    """The spike2img baseline with a spike camera of its own shape (a Vidar sensor is 400x250): its
    image is seen from the RGB camera through both lenses, not stretched over the RGB frame; RGB
    pixels outside the spike image are marked (the nearer RGB frame fills them)."""
    from engine.cameras import Intrinsics
    from engine.train.frames.baselines import spike_image_in_rgb_view

    def radiance(x, y):
        return 0.45 + 0.3 * np.sin(7 * x + 1.0) * np.cos(5 * y)

    def image(k):
        xx, yy = np.meshgrid((np.arange(k.width) + 0.5 - k.cx) / k.fx, (np.arange(k.height) + 0.5 - k.cy) / k.fy)
        return radiance(xx, yy).astype(np.float32)

    k_rgb = Intrinsics(160, 120, 150.0, 150.0, 80.0, 60.0)
    same, covered = spike_image_in_rgb_view(image(k_rgb.scaled(80, 60)), k_rgb.scaled(80, 60), k_rgb, (120, 160))
    assert covered.all() and np.abs(same - image(k_rgb)).mean() < 0.01
    k_spike = Intrinsics(100, 62, 100.0, 100.0, 50.0, 31.0)  # 16:10, narrower than the RGB view
    seen, covered = spike_image_in_rgb_view(image(k_spike), k_spike, k_rgb, (120, 160))
    assert 0.5 < covered.mean() < 1.0 and not covered[0, 0] and covered[60, 80]
    truth = image(k_rgb)
    stretched = torch.nn.functional.interpolate(torch.as_tensor(image(k_spike))[None, None], size=(120, 160),
                                                mode="bilinear", align_corners=False)[0, 0].numpy()
    err, err_stretched = np.abs(seen - truth)[covered].mean(), np.abs(stretched - truth)[covered].mean()
    assert err < 0.01 and err_stretched > 5 * err, (err, err_stretched)
