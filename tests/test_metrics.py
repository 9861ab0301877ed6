"""PSNR / SSIM / motion mask / inter-frame classification."""
from __future__ import annotations

import math

import numpy as np
import pytest

from engine.evaluate.metrics import is_interframe, motion_mask, motion_masks, psnr, ssim


def test_psnr_known_values_and_mask():
    a = np.zeros((8, 8, 3), np.float32)
    b = np.full((8, 8, 3), 0.1, np.float32)
    assert psnr(a, b) == pytest.approx(20.0, abs=1e-4)
    c = a.copy()
    c[:4] = 0.1
    mask = np.zeros((8, 8), bool)
    mask[:4] = True
    assert psnr(a, c, mask) == pytest.approx(20.0, abs=1e-4)      # only the changed half
    assert psnr(a, c) == pytest.approx(20.0 + 10 * math.log10(2), abs=1e-4)
    assert math.isnan(psnr(a, c, np.zeros((8, 8), bool)))


def test_ssim_identity_and_degradation():
    rng = np.random.default_rng(0)
    img = rng.uniform(size=(32, 32, 3)).astype(np.float32)
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-5)
    noisy = np.clip(img + rng.normal(scale=0.2, size=img.shape), 0, 1).astype(np.float32)
    assert ssim(noisy, img) < 0.9
    assert ssim(img[:6, :6], img[:6, :6]) == pytest.approx(1.0, abs=1e-5)  # smaller than the window


def test_motion_mask_is_thresholded_and_dilated():
    a = np.zeros((20, 20, 3), np.float32)
    b = a.copy()
    b[10, 10] = 0.5
    c = a.copy()
    c[0, 0, 1] = 0.01  # below threshold
    m = motion_mask(a, b, None, threshold=0.04, dilate=2)
    assert m[10, 10] and m[8, 12] and not m[7, 10] and m.sum() == 25
    assert not motion_mask(a, c, None, threshold=0.04, dilate=0).any()
    ms = motion_masks([a, b, a], threshold=0.04, dilate=0)
    assert [int(x.sum()) for x in ms] == [1, 1, 1]


def test_interframe_classification():
    rgb = [0.0, 1 / 30, 2 / 30]
    assert not is_interframe(0.0, rgb)
    assert not is_interframe(10 / 300, rgb)          # on an RGB frame (float noise tolerated)
    assert is_interframe(1 / 300, rgb) and is_interframe(0.05, rgb)
    assert not is_interframe(0.1, rgb)                # after the last RGB frame
    assert not is_interframe(0.01, [0.0])


def test_static_mask_keeps_only_pixels_that_never_change():
    from engine.evaluate.metrics import static_mask

    rng = np.random.default_rng(0)
    base = rng.uniform(0.2, 0.8, (6, 8, 3)).astype(np.float32)
    frames = [base + rng.uniform(-0.01, 0.01, base.shape).astype(np.float32) for _ in range(5)]  # noise < tol
    frames[2][1, 2] += 0.2                       # something passes once
    frames[4][3, :, 0] = 0.0                     # a row changes in one channel
    m = static_mask(frames, tol=0.03)
    assert m.shape == (6, 8) and not m[1, 2] and not m[3].any()
    assert m.sum() == 6 * 8 - 1 - 8


def test_static_colour_shift_measures_repainting_between_instants():
    from engine.evaluate.metrics import static_colour_bias, static_colour_shift

    gt = np.full((4, 4, 3), 0.5, np.float32)
    mask = np.ones((4, 4), bool)
    mask[0] = False
    held = [static_colour_bias(gt + 0.02, gt, mask) for _ in range(4)]   # a constant error: no shift
    assert static_colour_shift(held, [False, True, True, False]) == pytest.approx(0.0, abs=1e-7)
    drift = gt.copy()
    drift[..., 2] += 0.05                                               # blue between the instants
    drift[0] = 1.0                                                      # outside the mask: ignored
    biases = [static_colour_bias(gt, gt, mask), static_colour_bias(drift, gt, mask), static_colour_bias(gt, gt, mask)]
    assert static_colour_shift(biases, [False, True, False]) == pytest.approx(0.05, abs=1e-6)
    assert static_colour_shift(biases, [False, False, False]) is None  # no frame between instants
    assert static_colour_bias(gt, gt, np.zeros((4, 4), bool)) is None
