"""Spike rendering (paper Eq. 11-17) against the spike simulator."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from engine.colour import linear_to_srgb
from engine.spike.render import (
    SensorModel,
    SpikeRenderer,
    cumulative_spike_loss,
    estimate_sensor,
    expected_counts,
    fit_sensor,
    heaviside_surrogate,
    integrate_and_fire,
    resample_to,
    sensor_light,
    spike_count_loss,
)
from engine.spike.simulate import make_gain_map, simulate_spikes


def _srgb_image(h=40, w=60, seed=0):
    rng = np.random.default_rng(seed)
    lin = rng.uniform(0.05, 0.9, size=(h, w, 3)).astype(np.float32)
    return torch.as_tensor(linear_to_srgb(lin))


def test_expected_counts_match_simulator_per_pixel():
    rng = np.random.default_rng(1)
    light = rng.uniform(0.02, 0.95, size=(30, 40))
    n = 257
    counts = simulate_spikes(light, rate_hz=20000, num_frames=n, seed=3).sum(0).astype(np.float64)
    pred = expected_counts(torch.as_tensor(light), n).numpy()
    # integrate-and-fire with a kept remainder: |count - n*light/theta| < 1 for every pixel
    assert np.abs(counts - pred).max() < 1.0 + 1e-9
    # and unbiased over a random phase: the mean error is ~0 (std ~ 0.29/sqrt(1200))
    assert abs((counts - pred).mean()) < 0.05


def test_rendered_counts_match_simulated_sensor_with_gain_and_dark():
    img = _srgb_image(40, 60)  # RGB resolution; spike sensor is 20 x 30 (factor 2)
    gain = make_gain_map(20, 30, 0.1, seed=2)
    sensor = SensorModel(width=30, height=20, scale=0.6, dark_current=0.02, threshold=1.0, gain=gain)
    light = sensor_light(img, sensor)  # [20, 30]
    assert light.shape == (20, 30)
    # the same physical light through the simulator: luminance at spike res, scale, dark, gain
    from engine.colour import luminance, srgb_to_linear
    y = luminance(srgb_to_linear(img.numpy()))
    y = y.reshape(20, 2, 30, 2).mean(axis=(1, 3)) * 0.6
    n = 400
    counts = simulate_spikes(y, rate_hz=20000, num_frames=n, gain=gain, dark_current=0.02, seed=5).sum(0)
    pred = SpikeRenderer(sensor).render_counts(img, n).detach().numpy()
    err = counts - pred
    assert np.abs(err).max() < 1.0 + 1e-4
    assert abs(err.mean()) < 0.08


def test_threshold_scales_counts():
    light = torch.full((4, 4), 0.5)
    assert torch.allclose(expected_counts(light, 100, threshold=2.0), torch.full((4, 4), 25.0))


def test_resample_area_and_bilinear_conserve_mean():
    x = torch.rand(2, 48, 64)
    for mode in ("area", "bilinear"):
        y = resample_to(x, 12, 16, mode)
        assert y.shape == (2, 12, 16)
        assert abs(float(y.mean() - x.mean())) < 0.02
    y = resample_to(x, 10, 13, "area")  # non-integer factor
    assert y.shape == (2, 10, 13)
    with pytest.raises(ValueError):
        resample_to(x, 12, 16, "nearest-ish")


def test_gradients_finite_and_brighter_gives_more_counts():
    img = _srgb_image(16, 16).clone().requires_grad_(True)
    sensor = SensorModel(width=8, height=8, scale=0.5, dark_current=0.01, gain=make_gain_map(8, 8, 0.1))
    r = SpikeRenderer(sensor)
    r.render_counts(img, 64).sum().backward()
    g = img.grad
    assert torch.isfinite(g).all()
    assert (g > 0).all()  # every channel of every pixel adds light
    # a black image also gets finite gradients
    z = torch.zeros(16, 16, 3, requires_grad=True)
    r.render_counts(z, 64).sum().backward()
    assert torch.isfinite(z.grad).all() and (z.grad > 0).all()


def test_spike_loss_gradient_points_to_observed_rate():
    sensor = SensorModel(width=4, height=4, scale=1.0)
    img = torch.full((8, 8, 3), 0.3, requires_grad=True)  # linear ~0.073
    obs = torch.full((4, 4), 0.5 * 64)  # observed brighter than rendered
    loss = spike_count_loss(SpikeRenderer(sensor).render_counts(img, 64), obs, 64)
    loss.backward()
    assert (img.grad < 0).all()  # descending brightens the render


def test_integrate_and_fire_unbiased_and_surrogate_sign():
    torch.manual_seed(0)
    light = torch.rand(2000) * 0.9 + 0.05
    m = 32
    gen = torch.Generator().manual_seed(1)
    s = integrate_and_fire(light, m, generator=gen)
    assert s.shape == (m, 2000)
    assert set(torch.unique(s).tolist()) <= {0.0, 1.0}
    counts = s.sum(0)
    assert (counts - m * light).abs().max() < 1.0 + 1e-5
    assert abs(float((counts - m * light).mean())) < 0.05
    # surrogate gradient: finite, and more light never means fewer spikes
    for kind in ("sigmoid", "atan"):
        x = light.clone().requires_grad_(True)
        integrate_and_fire(x, m, generator=torch.Generator().manual_seed(2), surrogate=kind).sum().backward()
        assert torch.isfinite(x.grad).all()
        assert (x.grad >= 0).all() and (x.grad > 0).float().mean() > 0.9


def test_integrate_and_fire_zero_phase_is_deterministic_and_keeps_remainder():
    light = torch.tensor([0.25, 0.5, 1.0, 0.0])
    s = integrate_and_fire(light, 8, v0=torch.zeros(4))
    assert s.sum(0).tolist() == [2.0, 4.0, 8.0, 0.0]
    # 0.25 fires on every 4th step (remainder kept, reset by subtraction)
    assert s[:, 0].tolist() == [0, 0, 0, 1, 0, 0, 0, 1]


def test_heaviside_surrogate_rejects_unknown_kind():
    with pytest.raises(ValueError):
        heaviside_surrogate(torch.zeros(2), kind="relu")


def test_cumulative_loss_zero_on_identical_trains_and_differentiable():
    light = torch.full((10,), 0.4, requires_grad=True)
    obs = integrate_and_fire(light.detach(), 32, v0=torch.zeros(10))
    pred = integrate_and_fire(light, 32, v0=torch.zeros(10))
    loss = cumulative_spike_loss(pred, obs)
    assert float(loss.detach()) == 0.0
    brighter = integrate_and_fire(light * 2, 32, v0=torch.zeros(10))
    l2 = cumulative_spike_loss(brighter, obs)
    l2.backward()
    assert float(l2.detach()) > 0 and torch.isfinite(light.grad).all()


def test_fit_sensor_recovers_scale_dark_and_gain():
    rng = np.random.default_rng(0)
    h, w, F = 20, 30, 12
    gain = make_gain_map(h, w, 0.15, seed=4)
    luma = rng.uniform(0.05, 0.8, size=(F, h, w))
    n = 2000
    rates = np.stack([simulate_spikes(lum * 0.7, rate_hz=20000, num_frames=n, gain=gain, dark_current=0.03,
                                      seed=i).sum(0) / n for i, lum in enumerate(luma)])
    s = fit_sensor(luma, rates, width=w, height=h, gain_shrink=0.01)
    # global fit sees gain * (0.7 L + 0.03) with E[gain] ~ 1
    assert abs(s.scale - 0.7 * gain.mean()) < 0.05
    assert abs(s.dark_current - 0.03 * gain.mean()) < 0.02
    corr = np.corrcoef(s.gain.ravel(), gain.ravel())[0, 1]
    assert corr > 0.95
    assert abs(s.gain.mean() - 1.0) < 1e-5
    assert s.info["fit_l1_rate"] < 0.02


def test_renderer_learned_scale_is_optional():
    s = SensorModel(width=4, height=4)
    assert not SpikeRenderer(s).log_scale_correction.requires_grad
    r = SpikeRenderer(s, learn_scale=True)
    img = torch.full((4, 4, 3), 0.5)
    r.render_counts(img, 10).sum().backward()
    assert r.log_scale_correction.grad is not None and float(r.log_scale_correction.grad.detach()) > 0


# --------------------------------------------------------------------- a spike camera with its own field of view

def _radiance(x, y):
    """Linear luminance of the direction (x, y) = (X/Z, Y/Z) seen from the co-located cameras."""
    return 0.45 + 0.3 * np.sin(7 * x + 1.0) * np.cos(5 * y) + 0.1 * np.sin(23 * x * y)


def _image_of(k, s=8):
    """The scene seen by pinhole ``k``: the luminance averaged over s x s points per pixel."""
    u = (np.arange(k.width * s) + 0.5) / s
    v = (np.arange(k.height * s) + 0.5) / s
    xx, yy = np.meshgrid((u - k.cx) / k.fx, (v - k.cy) / k.fy)
    return _radiance(xx, yy).reshape(k.height, s, k.width, s).mean(axis=(1, 3)).astype(np.float32)


def test_a_spike_camera_with_its_own_field_of_view_sees_the_rgb_view_through_its_lens():
    """A Vidar sensor is 400x250 (16:10) beside a 4:3 or 3:2 RGB camera with another lens: the RGB
    render reaches each spike pixel through the two cameras' intrinsics, not by squashing the image
    (which the same-field-of-view path keeps doing, unchanged)."""
    from engine.cameras import Intrinsics
    from engine.spike.render import luma_in_spike_view, same_field_of_view, view_warp

    k_rgb = Intrinsics(160, 120, 150.0, 150.0, 80.0, 60.0)
    assert view_warp(k_rgb, k_rgb.scaled(80, 60)) is None and same_field_of_view(k_rgb, k_rgb.scaled(40, 30))
    k_spike = Intrinsics(100, 62, 80.0, 80.0, 50.0, 31.0)  # square pixels, a wider lens, 16:10
    grid, valid = view_warp(k_rgb, k_spike)
    assert grid.shape == (62 * 4, 100 * 4, 2) and 0.5 < valid.mean() < 1.0
    assert not valid[:, 0].any() and valid[31, 50]  # the RGB view ends before the spike sensor's edge
    truth = _image_of(k_spike)
    rgb_luma = torch.as_tensor(_image_of(k_rgb))
    got = luma_in_spike_view(rgb_luma, 62, 100, grid).numpy()
    squashed = resample_to(rgb_luma, 62, 100).numpy()
    err, err_squash = np.abs(got - truth)[valid].mean(), np.abs(squashed - truth)[valid].mean()
    assert err < 0.01 and err_squash > 5 * err, (err, err_squash)


def test_estimate_sensor_fits_a_spike_camera_with_its_own_field_of_view(tmp_path):
    from types import SimpleNamespace

    from engine.cameras import Intrinsics
    from engine.colour import linear_to_srgb
    from engine.io.spikes import SpikeStream, write_spikes

    k_rgb = Intrinsics(160, 120, 150.0, 150.0, 80.0, 60.0)
    k_spike = Intrinsics(100, 62, 80.0, 80.0, 50.0, 31.0)
    lum = _image_of(k_rgb)
    rgb = linear_to_srgb(np.repeat(lum[..., None], 3, -1))  # grey: luminance = each channel
    seen = _image_of(k_spike)
    n = 4000
    spikes = simulate_spikes(seen * 0.6, rate_hz=20000, num_frames=n, dark_current=0.02, seed=3)
    write_spikes(tmp_path / "s.dat", spikes)
    stream = SpikeStream(tmp_path / "s.dat", 100, 62, 20000.0, 0.0, n, camera="spike0", co_located_with="rgb0",
                         intrinsics=k_spike)
    frames = [SimpleNamespace(camera="rgb0", time=t, load_rgb=lambda: rgb) for t in (0.02, 0.1, 0.18)]
    capture = SimpleNamespace(frames=frames, cameras={"rgb0": SimpleNamespace(intrinsics=k_rgb)})
    s = estimate_sensor(capture, stream)
    assert s.warp is not None and s.info["covered_fraction"] < 1.0
    assert abs(s.scale - 0.6) < 0.05 and abs(s.dark_current - 0.02) < 0.01
    assert np.all(s.gain[~s.valid] == 1.0)
    # the renderer predicts the observed counts through the spike camera's lens
    pred = SpikeRenderer(s).render_counts(torch.as_tensor(rgb, dtype=torch.float32), n).numpy()
    obs = spikes.sum(0)
    assert np.abs(pred - obs)[s.valid].mean() / n < 0.01
