"""Two-stage baselines of the paper's Table 1, as training-data variants of the RGB-only model.

Each baseline synthesises in-between RGB frames (default 9 per interval: 30 -> 300 FPS) and
adds them to the capture's training frames; the RGB-only model then trains on them with the
frame loss as if they were real:

* ``repeat``        — hold the previous frame (30 fps repeated 10x);
* ``interp-linear`` — linear blend of the two neighbouring frames;
* ``interp-flow``   — flow-based interpolation (:func:`engine.train.frames.interpolation.flow_interpolate`,
                      our RIFE / SimpleFlow stand-in);
* ``spike2img``     — grey image from the spike stream (TFP over a short window, or TFI),
                      calibrated to linear luminance with the estimated sensor model,
                      upsampled to the RGB resolution, then coloured by Reinhard et al.
                      (2002) colour transfer in l-alpha-beta from the nearest RGB frame
                      (``colour='reinhard'``); ``colour='chroma'`` instead keeps the nearest
                      frame's per-pixel chromaticity (rgb / luminance). Only the spike
                      camera's co-located view gets spike frames.

``baseline_frames`` returns :class:`SyntheticFrame` records that quack like
:class:`engine.io.capture.Frame` (``camera, time, c2w, intrinsics, role, load_rgb(), view()``);
``with_baseline`` returns a copy of the capture with them appended to ``frames``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ...cameras import View
from ...colour import linear_to_srgb, luminance, srgb_to_linear
from ...spike.render import estimate_sensor, pixel_grid_between, same_field_of_view
from ...spike.simulate import tfi, tfp
from .interpolation import flow_interpolate

__all__ = ["KINDS", "SyntheticFrame", "baseline_frames", "with_baseline", "reinhard_transfer",
           "spike_to_gray", "rgb_to_lab_reinhard", "lab_reinhard_to_rgb"]

KINDS = ("repeat", "interp-linear", "interp-flow", "spike2img")


@dataclass
class SyntheticFrame:
    """A generated training frame (sRGB-encoded float32 [H, W, 3])."""

    image: np.ndarray
    camera: str
    time: float
    c2w: np.ndarray
    intrinsics: object = None
    role: str = "train"
    path: Path | None = None
    extra: dict = field(default_factory=dict)
    # False: its instant is no RGB instant (no trajectory knot, carry, birth, spike interval or
    # stereo pair: ``baseline_frames(knots=False)``, TrainConfig.baseline_instants="real")
    knot: bool = True

    def load_rgb(self, background=None) -> np.ndarray:
        return self.image

    def load_rgba(self) -> np.ndarray:
        a = np.ones(self.image.shape[:2] + (1,), np.float32)
        return np.concatenate([self.image, a], -1)

    def load_alpha(self) -> np.ndarray:
        return np.ones(self.image.shape[:2], np.float32)

    def view(self) -> View:
        return View(self.intrinsics, np.array(self.c2w, dtype=np.float64), float(self.time),
                    f"{self.camera}/synthetic@{self.time:.6f}", {"camera": self.camera, "role": self.role,
                                                                **self.extra})


# ----------------------------------------------------------------------------- colour transfer

_RGB2LMS = np.array([[0.3811, 0.5783, 0.0402], [0.1967, 0.7244, 0.0782], [0.0241, 0.1288, 0.8444]])
_LMS2RGB = np.linalg.inv(_RGB2LMS)
_LMS2LAB = np.diag([1 / np.sqrt(3), 1 / np.sqrt(6), 1 / np.sqrt(2)]) @ np.array(
    [[1, 1, 1], [1, 1, -2], [1, -1, 0]], dtype=np.float64)
_LAB2LMS = np.linalg.inv(_LMS2LAB)


def rgb_to_lab_reinhard(rgb_lin: np.ndarray) -> np.ndarray:
    """Linear RGB [..., 3] -> Reinhard's l-alpha-beta (log10 LMS, decorrelated)."""
    lms = np.clip(rgb_lin @ _RGB2LMS.T, 1e-4, None)
    return np.log10(lms) @ _LMS2LAB.T


def lab_reinhard_to_rgb(lab: np.ndarray) -> np.ndarray:
    return (10.0 ** (lab @ _LAB2LMS.T)) @ _LMS2RGB.T


def reinhard_transfer(src_lin: np.ndarray, ref_lin: np.ndarray) -> np.ndarray:
    """Reinhard et al. 2002: match the mean and std of each l-alpha-beta channel of
    ``src`` (linear RGB [H, W, 3]) to those of ``ref``; returns linear RGB, clipped to >= 0."""
    s, r = rgb_to_lab_reinhard(src_lin.astype(np.float64)), rgb_to_lab_reinhard(ref_lin.astype(np.float64))
    sm, ss = s.reshape(-1, 3).mean(0), s.reshape(-1, 3).std(0)
    rm, rs = r.reshape(-1, 3).mean(0), r.reshape(-1, 3).std(0)
    out = (s - sm) * np.where(ss > 1e-6, rs / np.maximum(ss, 1e-6), 0.0) + rm
    return np.clip(lab_reinhard_to_rgb(out), 0.0, None)


def spike_to_gray(stream, t: float, sensor, *, method: str = "tfp", window: int = 64) -> np.ndarray:
    """Linear luminance [h, w] at time ``t`` from spikes: TFP over ``window`` frames centred
    on ``t`` (or TFI at ``t``), with the sensor response inverted
    (``Y = (light / gain - dark) / scale``)."""

    half = window / 2.0 / stream.rate_hz
    if method == "tfp":
        spikes, _ = stream.frames_between(t - half, t + half)
        light = tfp(spikes, None, threshold=sensor.threshold) if len(spikes) else np.zeros(
            (stream.height, stream.width), np.float32)
    elif method == "tfi":
        spikes, times = stream.frames_between(t - 4 * half, t + 4 * half)
        idx = int(np.clip(np.searchsorted(times, t), 0, max(len(times) - 1, 0)))
        light = tfi(spikes, idx, threshold=sensor.threshold)
    else:
        raise ValueError(f"unknown spike2img method {method!r} (tfp, tfi)")
    g = 1.0 if sensor.gain is None else np.maximum(np.asarray(sensor.gain), 1e-3)
    return np.clip((light / g - sensor.dark_current) / max(sensor.scale, 1e-6), 0.0, None).astype(np.float32)


def _upsample(img: np.ndarray, h: int, w: int) -> np.ndarray:
    t = torch.as_tensor(img, dtype=torch.float32)[None, None]
    return torch.nn.functional.interpolate(t, size=(h, w), mode="bilinear", align_corners=False)[0, 0].numpy()


def spike_image_in_rgb_view(gray: np.ndarray, k_spike, k_rgb, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """A spike-camera image [h, w] seen from the co-located RGB camera ``k_rgb``: (image [H, W],
    covered bool [H, W]). The same field of view: a bilinear upsample, all covered; a spike camera
    with its own lens (``engine.spike.render.view_warp``): each RGB pixel's ray through the spike
    intrinsics, the pixels outside the spike image not covered. ``size``: (H, W) of the RGB image."""
    H, W = size
    if k_spike is None or k_rgb is None or same_field_of_view(k_rgb, k_spike):
        return _upsample(gray, H, W), np.ones((H, W), bool)
    grid = torch.as_tensor(pixel_grid_between(k_rgb, k_spike))[None]
    src = torch.as_tensor(gray, dtype=torch.float32)[None, None]
    out = torch.nn.functional.grid_sample(src, grid, mode="bilinear", padding_mode="border", align_corners=False)
    covered = (grid[0].abs() <= 1.0).all(-1).numpy()
    return out[0, 0].numpy(), covered


def _colourise(gray_lin: np.ndarray, ref_srgb: np.ndarray, colour: str) -> np.ndarray:
    ref_lin = srgb_to_linear(ref_srgb.astype(np.float32))
    if colour == "reinhard":
        out = reinhard_transfer(np.repeat(gray_lin[..., None], 3, -1), ref_lin)
    elif colour == "chroma":
        y = luminance(ref_lin)
        chroma = ref_lin / np.maximum(y, 1e-4)[..., None]
        out = chroma * gray_lin[..., None]
    else:
        raise ValueError(f"unknown colour method {colour!r} (reinhard, chroma)")
    return np.clip(linear_to_srgb(out.astype(np.float32)), 0.0, 1.0).astype(np.float32)


# ----------------------------------------------------------------------------- frames

def _pairs(frames):
    frames = sorted(frames, key=lambda f: f.time)
    return list(zip(frames[:-1], frames[1:]))


PER_INTERVAL = 9  # synthetic frames per RGB interval (30 -> 300 FPS)


def baseline_frames(capture, kind: str, *, per_interval: int | None = None, cameras=None, sensor=None,
                    spike_method: str = "tfp", colour: str = "reinhard", window: int = 64,
                    knots: bool = True) -> list[SyntheticFrame]:
    """Synthetic in-between frames for the baseline ``kind`` (see :data:`KINDS`).

    ``cameras``: training cameras to synthesise for (default: all training cameras; for
    ``spike2img``, the cameras co-located with a spike stream). ``sensor``: the spike
    sensor model (default: :func:`engine.spike.render.estimate_sensor`). ``knots`` False: the
    frames' ``knot`` is False (their instants are not RGB instants)."""
    if kind not in KINDS:
        raise ValueError(f"unknown baseline {kind!r}; choose from {', '.join(KINDS)}")
    per_interval = PER_INTERVAL if per_interval is None else int(per_interval)
    by_cam: dict[str, list] = {}
    for f in capture.frames:
        if getattr(f, "role", "train") == "train" and not getattr(f, "extra", {}).get("synthetic"):
            by_cam.setdefault(f.camera, []).append(f)
    streams = {}
    if kind == "spike2img":
        for info in capture.spike_streams:
            if info.co_located_with:
                streams[info.co_located_with] = info
    if cameras is None:
        cameras = list(streams) if kind == "spike2img" else list(by_cam)
    out: list[SyntheticFrame] = []
    for cam in cameras:
        pairs = _pairs(by_cam.get(cam, []))
        stream = sens = None
        if kind == "spike2img":
            if cam not in streams:
                continue
            stream = capture.spike_stream(streams[cam].camera)
            if sensor is None:
                sens = estimate_sensor(capture, stream)
            else:
                sens = sensor
        for fa, fb in pairs:
            a_img, b_img = fa.load_rgb(), fb.load_rgb()
            flows = None
            for j in range(1, per_interval + 1):
                eps = j / (per_interval + 1)
                t = fa.time + eps * (fb.time - fa.time)
                if kind == "repeat":
                    img = a_img
                elif kind == "interp-linear":
                    img = (1 - eps) * a_img + eps * b_img
                elif kind == "interp-flow":
                    res, flows = flow_interpolate(torch.as_tensor(a_img), torch.as_tensor(b_img), eps,
                                                  flows=flows, return_flows=True)
                    img = res.clamp(0, 1).numpy()
                else:
                    if not (stream.t0 <= t < stream.t_end):
                        continue
                    gray = spike_to_gray(stream, t, sens, method=spike_method, window=window)
                    ref = a_img if eps <= 0.5 else b_img
                    seen, covered = spike_image_in_rgb_view(gray, getattr(stream, "intrinsics", None), fa.intrinsics,
                                                            ref.shape[:2])
                    # where the spike camera does not see, the nearer RGB frame's own luminance
                    seen = np.where(covered, seen, luminance(srgb_to_linear(ref.astype(np.float32))))
                    img = _colourise(seen, ref, colour)
                out.append(SyntheticFrame(np.ascontiguousarray(img, dtype=np.float32), cam, float(t),
                                          np.array(fa.c2w),
                                          fa.intrinsics, "train", None, {"synthetic": kind}, bool(knots)))
    return out


INSTANTS = ("all", "real")


def with_baseline(capture, kind: str | None, *, instants: str = "all", **kw):
    """A copy of ``capture`` whose ``frames`` also hold the baseline's synthetic frames
    (``kind`` None: the capture itself). ``instants`` (the ``baseline.instants`` setting): "all"
    -- their instants are RGB instants too (paper Table 1: trained on as if real); "real" --
    they are not (``knot`` False): only the frame loss sees them."""
    if not kind:
        return capture
    if instants not in INSTANTS:
        raise ValueError(f"baseline instants must be one of {', '.join(INSTANTS)} (got {instants!r})")
    extra = baseline_frames(capture, kind, knots=instants == "all", **kw)
    return dataclasses.replace(capture, frames=list(capture.frames) + extra)
