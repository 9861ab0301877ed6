"""Dynamic spike rendering (BulletTime4D, paper Eq. 11-17): rendered RGB -> spikes.

The light reaching the spike sensor is the image rendered at the spike camera's
co-located RGB view (Eq. 11; beam splitter, same pose), converted to linear luminance,
resampled to the spike resolution (Eq. 12) and passed through the sensor response (Eq. 13).
When the spike camera has a field of view of its own (a real Vidar sensor is 400x250, an RGB
camera 1080x720 or 4:3: other aspect, other lens), :func:`view_warp` maps each spike pixel
through its own intrinsics into the RGB view (co-located: a pure change of intrinsics), and
the luminance is sampled there (4x4 points per spike pixel, averaged) instead of rescaled; spike
pixels the RGB view does not cover are left out of the fit and of the loss (``SensorModel.valid``).
We use the linearised response

    light[p] = min(gain[p] * (scale * Y_lin[p] + dark_current), theta)   (per spike frame)

where ``Y_lin`` is Rec.709 luminance of the linear (``srgb_to_linear``) render,
``scale`` is the photometric factor between RGB intensity and spike light, ``gain`` is
the response non-uniformity map (mean 1) and ``dark_current`` the light-equivalent dark
rate (the same response as :mod:`engine.spike.simulate`; the clip at ``theta`` is the sensor's
one-spike-per-frame saturation). A pixel integrates light and fires when it reaches the
threshold ``theta``, keeping the remainder (Eq. 2). Shot and quantisation noise are zero-mean; they enter only as an
optional augmentation of the integrate-and-fire renderer.

Two renderers (DESIGN.md, "The spike camera model"):

* :func:`expected_counts` (default): with a uniformly random initial phase the expected
  number of spikes in ``n`` frames is exactly ``n * light / theta`` — unbiased and smooth.
* :func:`integrate_and_fire` (paper Eq. 14-16): ``m`` steps (m = 32 in the paper) of a
  reset-by-subtraction IF neuron on a constant light, with a surrogate gradient for the
  Heaviside (sigmoid or arctan), for timing-level losses.

Sensor parameters come from :func:`estimate_sensor`: the photometric ``scale`` and the
``dark_current`` are **estimated by least squares** of the observed spike rate (counts in a
short window around each RGB instant of the co-located camera) against the RGB frame's
downsampled linear luminance; the gain map is a per-pixel least-squares ratio over those
instants, shrunk towards 1 and normalised to mean 1. The scale is fixed during training
by default (``SpikeRenderer(learn_scale=True)`` adds a learned log-scale correction).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from ..colour import luminance, srgb_to_linear

__all__ = [
    "SensorModel", "SpikeRenderer", "rgb_to_luma_linear", "resample_to", "sensor_light",
    "expected_counts", "integrate_and_fire", "spike_count_loss", "cumulative_spike_loss",
    "estimate_sensor", "heaviside_surrogate", "view_warp", "same_field_of_view", "luma_in_spike_view",
    "pixel_grid_between",
]


# ----------------------------------------------------------------------------- sensor model

@dataclass
class SensorModel:
    """Spike sensor response (linearised Eq. 13). Light units: threshold units per frame."""

    width: int
    height: int
    scale: float = 1.0              # spike light per frame for unit linear luminance
    dark_current: float = 0.0       # light per frame with no light (dark rate * theta)
    threshold: float = 1.0          # theta
    gain: np.ndarray | None = None  # [h, w] float32, mean 1 (None: uniform)
    rate_hz: float = 20000.0
    info: dict = field(default_factory=dict)  # how it was estimated (fit residuals, ...)
    # the spike camera's own field of view (:func:`view_warp`): sample points [h*s, w*s, 2] in the
    # RGB view's grid_sample coordinates, and the spike pixels that view covers [h, w] (None: the
    # spike sensor sees the RGB view's field of view, a rescale)
    warp: np.ndarray | None = None
    valid: np.ndarray | None = None

    def gain_tensor(self, device=None, dtype=torch.float32) -> torch.Tensor | None:
        if self.gain is None:
            return None
        return torch.as_tensor(np.asarray(self.gain, dtype=np.float32), device=device, dtype=dtype)


# ----------------------------------------------------------------------------- light

def rgb_to_luma_linear(rgb_srgb: torch.Tensor) -> torch.Tensor:
    """sRGB-encoded render [..., H, W, 3] -> linear Rec.709 luminance [..., H, W]."""
    return luminance(srgb_to_linear(rgb_srgb.clamp(min=0.0)))


def resample_to(img: torch.Tensor, height: int, width: int, mode: str = "area") -> torch.Tensor:
    """Resample [..., H, W] to [..., height, width] (paper Eq. 12).

    ``mode='area'``: average over the sensor pixel's footprint (exact box filter when the
    factor is an integer; ``adaptive_avg_pool2d`` otherwise). ``'bilinear'``: antialiased
    bilinear (the paper's choice). Both are linear in the input, so light is conserved in
    the mean.
    """
    lead = img.shape[:-2]
    H, W = img.shape[-2:]
    x = img.reshape(-1, 1, H, W)
    if (H, W) == (height, width):
        out = x
    elif mode == "area":
        if H % height == 0 and W % width == 0:
            out = F.avg_pool2d(x, kernel_size=(H // height, W // width))
        else:
            out = F.adaptive_avg_pool2d(x, (height, width))
    elif mode == "bilinear":
        out = F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False,
                            antialias=(height < H or width < W))
    else:
        raise ValueError(f"unknown resample mode {mode!r} (area, bilinear)")
    return out.reshape(*lead, height, width)


WARP_SUPERSAMPLE = 4  # sample points per spike pixel and axis when the spike camera has its own field of view


def same_field_of_view(k_rgb, k_spike, rel_tol: float = 1e-3) -> bool:
    """Whether ``k_spike`` is ``k_rgb`` at another resolution (normalised intrinsics agree)."""
    a = np.array([k_rgb.fx / k_rgb.width, k_rgb.fy / k_rgb.height, k_rgb.cx / k_rgb.width, k_rgb.cy / k_rgb.height])
    b = np.array([k_spike.fx / k_spike.width, k_spike.fy / k_spike.height, k_spike.cx / k_spike.width,
                  k_spike.cy / k_spike.height])
    return bool(np.all(np.abs(a - b) <= rel_tol * np.maximum(np.abs(a), 1e-9)))


def pixel_grid_between(k_src, k_dst, supersample: int = 1) -> np.ndarray:
    """float32 [h*s, w*s, 2]: where the ``s x s`` sub-pixel centres of every pixel of camera
    ``k_src`` land in the image of the co-located camera ``k_dst`` (a pure change of intrinsics:
    through ``k_src`` to a ray, through ``k_dst`` to a pixel), in ``grid_sample`` coordinates
    (align_corners False; outside [-1, 1]: outside ``k_dst``'s image)."""
    s = max(1, int(supersample))
    x = ((np.arange(k_src.width * s) + 0.5) / s - k_src.cx) / k_src.fx
    y = ((np.arange(k_src.height * s) + 0.5) / s - k_src.cy) / k_src.fy
    gx = (k_dst.fx * x + k_dst.cx) / k_dst.width * 2.0 - 1.0
    gy = (k_dst.fy * y + k_dst.cy) / k_dst.height * 2.0 - 1.0
    return np.stack(np.meshgrid(gx, gy), -1).astype(np.float32)


def view_warp(k_rgb, k_spike, supersample: int = WARP_SUPERSAMPLE) -> tuple[np.ndarray, np.ndarray] | None:
    """None when the spike camera shares the co-located RGB camera's field of view; else
    (points float32 [h*s, w*s, 2], valid bool [h, w]): ``s x s`` points per spike pixel in the RGB
    image (:func:`pixel_grid_between`); ``valid``: every point of that pixel lands inside it."""
    if same_field_of_view(k_rgb, k_spike):
        return None
    s = max(1, int(supersample))
    grid = pixel_grid_between(k_spike, k_rgb, s)
    inside = (np.abs(grid) <= 1.0).all(-1)
    valid = inside.reshape(int(k_spike.height), s, int(k_spike.width), s).all(axis=(1, 3))
    return grid, valid


def luma_in_spike_view(luma: torch.Tensor, height: int, width: int, warp: np.ndarray | None = None,
                       mode: str = "area") -> torch.Tensor:
    """Linear luminance [..., H, W] of the co-located RGB view -> [..., height, width] at the spike
    sensor: a rescale (Eq. 12), or through ``warp`` (:func:`view_warp`) when the spike camera has
    its own field of view (the mean of its sample points per spike pixel)."""
    if warp is None:
        return resample_to(luma, height, width, mode)
    lead = luma.shape[:-2]
    H, W = luma.shape[-2:]
    grid = torch.as_tensor(warp, dtype=luma.dtype, device=luma.device)
    x = luma.reshape(-1, 1, H, W)
    pts = F.grid_sample(x, grid[None].expand(x.shape[0], -1, -1, -1), mode="bilinear", padding_mode="zeros",
                        align_corners=False)
    s = grid.shape[0] // height
    out = F.avg_pool2d(pts, s) if s > 1 else pts
    return out.reshape(*lead, height, width)


def sensor_light(rgb_srgb: torch.Tensor, sensor: SensorModel, *, mode: str = "area",
                 scale: torch.Tensor | float | None = None) -> torch.Tensor:
    """Rendered sRGB image(s) [..., H, W, 3] at the co-located view -> light per spike
    frame [..., h, w] at the spike resolution (Eq. 11-13)."""
    y = luma_in_spike_view(rgb_to_luma_linear(rgb_srgb), sensor.height, sensor.width, sensor.warp, mode)
    s = sensor.scale if scale is None else scale
    light = y * s + sensor.dark_current
    g = sensor.gain_tensor(device=light.device, dtype=light.dtype)
    if g is not None:
        light = light * g
    return light.clamp(max=float(sensor.threshold))


# ----------------------------------------------------------------------------- renderers

def expected_counts(light: torch.Tensor, num_frames: float, threshold: float = 1.0) -> torch.Tensor:
    """Expected spike count in ``num_frames`` frames of constant ``light`` (random phase)."""
    return light.clamp(min=0.0) * (float(num_frames) / float(threshold))


class _Heaviside(torch.autograd.Function):
    """H(x) = [x >= 0] forward; surrogate derivative backward."""

    @staticmethod
    def forward(ctx, x, alpha, kind):
        ctx.save_for_backward(x)
        ctx.alpha, ctx.kind = alpha, kind
        return (x >= 0).to(x.dtype)

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        a = ctx.alpha
        if ctx.kind == "sigmoid":
            s = torch.sigmoid(a * x)
            d = a * s * (1 - s)
        elif ctx.kind == "atan":
            d = (a / 2) / (1 + (math.pi / 2 * a * x) ** 2)
        else:  # pragma: no cover - validated by the caller
            raise ValueError(ctx.kind)
        return grad * d, None, None


def heaviside_surrogate(x: torch.Tensor, alpha: float = 4.0, kind: str = "sigmoid") -> torch.Tensor:
    """Heaviside step with a sigmoid (``alpha * s(1-s)``) or arctan surrogate gradient."""
    if kind not in ("sigmoid", "atan"):
        raise ValueError(f"unknown surrogate {kind!r} (sigmoid, atan)")
    return _Heaviside.apply(x, float(alpha), kind)


def integrate_and_fire(light: torch.Tensor, m: int = 32, threshold: float = 1.0, *,
                       v0: torch.Tensor | None = None, generator: torch.Generator | None = None,
                       surrogate: str = "sigmoid", alpha: float = 4.0, detach_reset: bool = True,
                       noise_std: float = 0.0) -> torch.Tensor:
    """Paper Eq. 14-16: ``m`` steps of an IF neuron driven by constant ``light`` [...].

    Returns spikes [m, ...] (0/1 forward, surrogate gradient backward). The membrane starts
    at ``v0`` (default: uniform random phase in [0, theta), so E[sum] = m * light / theta)
    and is reset by subtraction (the remainder is kept). ``detach_reset`` stops the gradient
    through the reset, as usual for surrogate-gradient SNNs, so d(count)/d(light) >= 0.
    ``noise_std`` adds Gaussian noise to the per-step light (shot-noise augmentation).
    """
    theta = float(threshold)
    if v0 is None:
        v0 = torch.rand(light.shape, generator=generator, dtype=light.dtype, device="cpu").to(light.device) * theta
    v = v0.to(light.dtype)
    out = []
    for _ in range(int(m)):
        x = light
        if noise_std > 0:
            x = x + noise_std * torch.randn(light.shape, generator=generator, dtype=light.dtype).to(light.device)
        v = v + x
        s = heaviside_surrogate(v - theta, alpha=alpha / theta, kind=surrogate)
        reset = s.detach() if detach_reset else s
        v = v - theta * reset
        out.append(s)
    return torch.stack(out, 0)


# ----------------------------------------------------------------------------- losses

def spike_count_loss(pred_counts: torch.Tensor, obs_counts: torch.Tensor, num_frames: float,
                     mask: torch.Tensor | None = None) -> torch.Tensor:
    """Paper Eq. 17 on window counts: L1 between rendered and captured spike rates
    (counts / frames, so the loss scale does not depend on the window length)."""
    d = (pred_counts - obs_counts).abs() / float(num_frames)
    if mask is not None:
        return (d * mask).sum() / mask.sum().clamp(min=1.0)
    return d.mean()


def cumulative_spike_loss(pred_spikes: torch.Tensor, obs_spikes: torch.Tensor) -> torch.Tensor:
    """Timing-level loss for spike trains [m, ...]: L1 between cumulative counts, averaged
    over steps and normalised by m. Insensitive to a one-step jitter, sensitive to rate."""
    m = pred_spikes.shape[0]
    return (pred_spikes.cumsum(0) - obs_spikes.to(pred_spikes.dtype).cumsum(0)).abs().mean() / m


# ----------------------------------------------------------------------------- renderer

class SpikeRenderer(torch.nn.Module):
    """Holds the sensor model; renders spike counts for a rendered co-located image.

    ``render_counts(img, num_frames)`` -> expected counts [.., h, w] (default path);
    ``render_spikes(img, m)`` -> IF spikes [m, .., h, w] with surrogate gradients.
    """

    def __init__(self, sensor: SensorModel, *, mode: str = "area", learn_scale: bool = False):
        super().__init__()
        self.sensor = sensor
        self.mode = mode
        self.log_scale_correction = torch.nn.Parameter(torch.zeros(()), requires_grad=learn_scale)

    def light(self, img_srgb: torch.Tensor) -> torch.Tensor:
        scale = self.sensor.scale * torch.exp(self.log_scale_correction.to(img_srgb.device))
        return sensor_light(img_srgb, self.sensor, mode=self.mode, scale=scale)

    def render_counts(self, img_srgb: torch.Tensor, num_frames: float) -> torch.Tensor:
        return expected_counts(self.light(img_srgb), num_frames, self.sensor.threshold)

    def render_spikes(self, img_srgb: torch.Tensor, m: int = 32, **kw) -> torch.Tensor:
        return integrate_and_fire(self.light(img_srgb), m, self.sensor.threshold, **kw)


# ----------------------------------------------------------------------------- estimation

def _luma_at_spike_res(rgb_srgb: np.ndarray, h: int, w: int, mode: str = "area",
                       warp: np.ndarray | None = None) -> np.ndarray:
    t = torch.as_tensor(np.ascontiguousarray(rgb_srgb, dtype=np.float32))
    return luma_in_spike_view(rgb_to_luma_linear(t), h, w, warp, mode).numpy()


def fit_sensor(luma: np.ndarray, rates: np.ndarray, *, width: int, height: int,
               threshold: float = 1.0, rate_hz: float = 20000.0, gain_shrink: float = 0.5,
               gain_clip: tuple[float, float] = (0.5, 2.0), per_pixel_gain: bool = True,
               valid: np.ndarray | None = None) -> SensorModel:
    """Least-squares sensor fit from paired images.

    ``luma`` [F, h, w]: linear luminance of RGB frames at the spike resolution;
    ``rates`` [F, h, w]: observed spikes per frame in short windows around the same instants.
    Model: ``rate * theta = gain * (scale * luma + dark)``. Global (scale, dark) by ordinary
    least squares over every unsaturated pixel of every frame (dark clamped to >= 0); then a
    per-pixel gain ``g = (sum x y + k) / (sum x^2 + k)`` with ``x = scale*luma + dark``,
    ``y = rate*theta`` and ``k = gain_shrink * mean_p(sum x^2)`` (ridge towards 1), clipped,
    normalised to mean 1. ``valid`` [h, w]: the pixels to fit (the others keep gain 1).
    """
    x = np.asarray(luma, dtype=np.float64).reshape(len(luma), -1)
    y = np.asarray(rates, dtype=np.float64).reshape(len(rates), -1) * threshold
    inside = np.ones(x.shape[1], bool) if valid is None else np.asarray(valid, bool).ravel()
    ok = ((y < 0.95 * threshold) & inside).ravel()  # saturated pixels say nothing about the slope
    if ok.sum() < 2:
        ok[:] = True
    A = np.stack([x.ravel(), np.ones(x.size)], 1)[ok]
    (a, d), *_ = np.linalg.lstsq(A, y.ravel()[ok], rcond=None)
    if d < 0:  # no negative dark current: refit through the origin
        d = 0.0
        a = float((x.ravel()[ok] * y.ravel()[ok]).sum() / max((x.ravel()[ok] ** 2).sum(), 1e-12))
    a = max(float(a), 1e-6)
    gain = None
    if per_pixel_gain and len(x) > 0:
        xs = a * x + d
        sxx = (xs * xs).sum(0)
        k = gain_shrink * max(float(sxx.mean()), 1e-12)
        g = ((xs * y).sum(0) + k) / (sxx + k)
        g = np.clip(g, *gain_clip)
        g = np.where(inside, g / g[inside].mean(), 1.0) if inside.any() else np.ones_like(g)
        gain = g.reshape(height, width).astype(np.float32)
    pred = np.minimum((a * x + d) * (gain.reshape(1, -1) if gain is not None else 1.0), threshold) / threshold
    err = np.abs(pred - y / threshold)
    resid = float(err[:, inside].mean() if inside.any() else err.mean())
    return SensorModel(width=width, height=height, scale=a, dark_current=float(d),
                       threshold=threshold, gain=gain, rate_hz=rate_hz,
                       info={"fit_l1_rate": resid, "frames": int(len(x)), "method": "least_squares"})


def estimate_sensor(capture, stream, *, window_s: float | None = None, mode: str = "area",
                    **kw) -> SensorModel:
    """Estimate the sensor model of ``stream`` from its co-located RGB frames.

    For each frame of the co-located camera inside the stream's time span, the observed
    rate is the spike count in ``[t - w/2, t + w/2]`` divided by the number of frames
    (``w`` defaults to 64 spike frames, short enough that the scene is nearly static).
    The RGB frame reaches the spike sensor through :func:`view_warp` when the two cameras'
    fields of view differ (the pixels it does not cover are not fitted; the model keeps the
    warp for the renders). Falls back to a uniform sensor (scale 1, no dark current) when
    there is no co-located RGB frame inside the stream.
    """
    h, w = int(stream.height), int(stream.width)
    rate = float(stream.rate_hz)
    if window_s is None:
        window_s = 64.0 / rate
    cam = getattr(stream, "co_located_with", None)
    warp = valid = None
    cameras = getattr(capture, "cameras", {}) or {}
    k_rgb = cameras[cam].intrinsics if cam in cameras else None
    k_spike = getattr(stream, "intrinsics", None)
    if k_rgb is not None and k_spike is not None:
        mapped = view_warp(k_rgb, k_spike)
        if mapped is not None:
            warp, valid = mapped
    t_lo, t_hi = float(stream.t0), float(stream.t_end)
    lumas, rates = [], []
    for fr in getattr(capture, "frames", []):
        if cam is None or fr.camera != cam:
            continue
        t = float(fr.time)
        a, b = max(t - window_s / 2, t_lo), min(t + window_s / 2, t_hi)
        i0, i1 = stream.index_range(a, b)
        if i1 - i0 < 4:
            continue
        counts = np.asarray(stream.window_counts(a, b), dtype=np.float64)
        n_eff = i1 - i0
        lumas.append(_luma_at_spike_res(fr.load_rgb(), h, w, mode, warp))
        rates.append(counts / n_eff)
    if not lumas:
        return SensorModel(width=w, height=h, rate_hz=rate, info={"method": "default"}, warp=warp, valid=valid)
    model = fit_sensor(np.stack(lumas), np.stack(rates), width=w, height=h, rate_hz=rate, valid=valid, **kw)
    model.warp, model.valid = warp, valid
    if valid is not None:
        model.info["covered_fraction"] = round(float(valid.mean()), 4)
    return model
