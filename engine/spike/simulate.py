"""The spike camera model (BulletTime4D paper Eq. 2 and 13) and classic reconstructions.

Integrate-and-fire, per pixel::

    charge_i = charge_{i-1} + min(gain * (light(t_i) + dark_current), threshold)   [+ shot noise]
    spike_i  = charge_i >= threshold ;  charge_i -= threshold where it fired   (remainder kept)

* Units: ``light`` is the (linear) charge integrated during one spike frame, so with
  ``threshold=1`` a pixel of light 0.25 fires every 4th frame.
* Spike frame ``i`` is at time ``t_i = t0 + i / rate_hz``; the light is sampled there.
* Each pixel starts at a uniformly random phase in ``[0, threshold)``
  (``initial_phase="uniform"``), so the expected number of spikes in any window equals the
  integrated light / threshold exactly.
* Saturation: the sensor reads one bit per frame, so a pixel fires at most once per frame;
  the per-frame increment is clipped to ``threshold`` (light above it is lost) and negative
  light to 0. The expected count per frame is therefore ``min(gain*(light+dark), θ) / θ``.
* ``shot_noise=True`` replaces each frame's increment ``q`` by
  ``Poisson(q * photons_per_threshold / θ) * θ / photons_per_threshold`` (photon noise; the
  mean is unchanged). This costs one Poisson draw per pixel per frame (slower).

Frames are simulated in chunks (vectorized over pixels, a loop over frames), so long
streams can be written straight to disk with :func:`simulate_spikes_to_file` without
holding them in memory.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from ..io.spikes import write_spikes

LightSource = np.ndarray | Callable[[float], np.ndarray]


def make_gain_map(h: int, w: int, std: float, seed: int = 0, *, mean: float = 1.0) -> np.ndarray:
    """Per-pixel response non-uniformity: float32 [h, w] ~ N(mean, std), clipped at 0."""
    rng = np.random.default_rng(seed)
    return np.clip(rng.normal(mean, std, size=(h, w)), 0.0, None).astype(np.float32)


class _LightSampler:
    """light(t) -> float64 [H, W] for an array sampled at ``light_times`` or a callable."""

    def __init__(self, light, light_times, num_frames: int, rate_hz: float, t0: float):
        self.fn = None
        if callable(light):
            self.fn = light
            probe = np.asarray(light(t0), dtype=np.float64)
            if probe.ndim != 2:
                raise ValueError(f"light(t) must return an (H, W) array, got shape {probe.shape}")
            self.shape = probe.shape
            return
        arr = np.asarray(light)
        if arr.dtype not in (np.float32, np.float64):
            arr = arr.astype(np.float64)
        if arr.ndim == 2:
            arr = arr[None]
        if arr.ndim != 3:
            raise ValueError(f"light must be (T, H, W) or (H, W), got shape {np.shape(light)}")
        self.arr = arr
        self.shape = arr.shape[1:]
        T = arr.shape[0]
        if light_times is None:
            if T == 1:
                self.times = None
            elif T == num_frames:  # one light image per spike frame
                self.times = t0 + np.arange(T, dtype=np.float64) / rate_hz
            else:
                raise ValueError(f"light has {T} samples but no light_times; give light_times "
                                 f"(seconds) or one sample per spike frame ({num_frames})")
        else:
            lt = np.asarray(light_times, dtype=np.float64).reshape(-1)
            if lt.shape[0] != T:
                raise ValueError(f"light_times has {lt.shape[0]} entries for {T} light samples")
            if T > 1 and not np.all(np.diff(lt) > 0):
                raise ValueError("light_times must be strictly increasing")
            self.times = lt if T > 1 else None

    def chunk_plan(self, times: np.ndarray):
        """(source (S, H, W), k (n,) int64, w (n,) float64): light(t_j) = (1-w)src[k] + w src[k+1]."""
        n = len(times)
        if self.fn is not None:
            src = np.stack([np.asarray(self.fn(float(t)), dtype=np.float64) for t in times])
            return src, np.arange(n, dtype=np.int64), np.zeros(n)
        if self.times is None:
            return self.arr, np.zeros(n, dtype=np.int64), np.zeros(n)
        lt = self.times
        k = np.clip(np.searchsorted(lt, times, side="right") - 1, 0, len(lt) - 2)
        w = np.clip((times - lt[k]) / (lt[k + 1] - lt[k]), 0.0, 1.0)
        lo, hi = int(k.min()), int(k.max()) + 2  # only the samples this chunk touches
        return self.arr[lo:hi], (k - lo).astype(np.int64), w.astype(np.float64)

    def __call__(self, t: float, out: np.ndarray) -> np.ndarray:
        if self.fn is not None:
            out[...] = self.fn(t)
            return out
        if self.times is None:
            out[...] = self.arr[0]
            return out
        lt = self.times
        k = int(np.searchsorted(lt, t, side="right")) - 1
        k = min(max(k, 0), len(lt) - 2)
        w = (t - lt[k]) / (lt[k + 1] - lt[k])
        w = min(max(w, 0.0), 1.0)
        if w == 0.0:
            out[...] = self.arr[k]
        elif w == 1.0:
            out[...] = self.arr[k + 1]
        else:
            np.multiply(self.arr[k], 1.0 - w, out=out)
            out += w * self.arr[k + 1]
        return out


def _fire_rows(src, k, w, gain, use_gain, dark, theta, charge, out):
    """Fused integrate-and-fire over a chunk: frame j's light is (1-w[j]) src[k[j]] + w[j] src[k[j]+1].

    src (S, P) light samples, gain (P,) (used if use_gain), charge (P,) updated in place,
    out (n, P) uint8 receives the spikes. Compiled with numba (see :func:`_fire_kernel`).
    """
    n, P = out.shape
    for j in range(n):
        kj = k[j]
        wj = w[j]
        k1 = kj + 1 if wj > 0.0 else kj
        for p in range(P):
            q = (1.0 - wj) * src[kj, p] + wj * src[k1, p] + dark
            if use_gain:
                q *= gain[p]
            if q < 0.0:
                q = 0.0
            elif q > theta:
                q = theta
            c = charge[p] + q
            if c >= theta:
                out[j, p] = 1
                c -= theta
            else:
                out[j, p] = 0
            charge[p] = c


_KERNEL = None


def _fire_kernel():
    """numba-compiled :func:`_fire_rows`, or None (numpy fallback) when numba is unavailable."""
    global _KERNEL
    if _KERNEL is None:
        try:
            import numba  # lazy: optional, and its import costs ~0.3 s; numpy fallback below
        except ImportError:
            _KERNEL = False
            return None
        try:
            _KERNEL = numba.njit(cache=True, nogil=True)(_fire_rows)
        except RuntimeError:  # no writable cache location
            _KERNEL = numba.njit(nogil=True)(_fire_rows)
    return _KERNEL or None


def iter_spike_chunks(light: LightSource, *, rate_hz: float, num_frames: int, t0: float = 0.0,
                      light_times=None, threshold: float = 1.0, gain=None, dark_current: float = 0.0,
                      shot_noise: bool = False, photons_per_threshold: float = 1000.0, seed: int = 0,
                      initial_phase="uniform", chunk_frames: int = 512) -> Iterator[np.ndarray]:
    """Yield uint8 (<= chunk_frames, H, W) chunks of the simulated stream, in order.

    Arguments as :func:`simulate_spikes`.
    """
    if rate_hz <= 0 or num_frames < 0 or threshold <= 0:
        raise ValueError("rate_hz and threshold must be positive and num_frames >= 0")
    sampler = _LightSampler(light, light_times, num_frames, rate_hz, t0)
    H, W = sampler.shape
    theta = float(threshold)
    rng = np.random.default_rng(seed)
    g = None if gain is None else np.broadcast_to(np.asarray(gain, dtype=np.float64), (H, W))
    if isinstance(initial_phase, str):
        if initial_phase == "uniform":
            charge = rng.uniform(0.0, theta, size=(H, W))
        elif initial_phase == "zero":
            charge = np.zeros((H, W))
        else:
            raise ValueError(f"initial_phase must be 'uniform', 'zero' or an array, got {initial_phase!r}")
    else:
        charge = np.array(np.broadcast_to(np.asarray(initial_phase, dtype=np.float64), (H, W)))
    scale = float(photons_per_threshold) / theta
    kernel = None if shot_noise else _fire_kernel()
    gflat = None if g is None else np.ascontiguousarray(g, dtype=np.float64).reshape(-1)
    for c0 in range(0, num_frames, chunk_frames):
        n = min(chunk_frames, num_frames - c0)
        chunk = np.empty((n, H, W), dtype=np.uint8)
        if kernel is not None:
            # fused compiled loop: light interpolation, gain, clip, integrate, fire
            sub = n if sampler.fn is None else 32  # a callable's samples are materialised
            flat = chunk.reshape(n, -1)
            for s0 in range(0, n, sub):
                m = min(sub, n - s0)
                src, k, w = sampler.chunk_plan(t0 + (c0 + s0 + np.arange(m)) / rate_hz)
                kernel(src.reshape(src.shape[0], -1), k, w,
                       gflat if gflat is not None else np.ones(1), gflat is not None,
                       float(dark_current), theta, charge.reshape(-1), flat[s0:s0 + m])
            yield chunk
            continue
        inc = np.empty((H, W), dtype=np.float64)
        fired = chunk.view(np.bool_)
        for j in range(n):
            t = t0 + (c0 + j) / rate_hz
            sampler(t, inc)
            if dark_current:
                inc += dark_current
            if g is not None:
                inc *= g
            np.clip(inc, 0.0, theta, out=inc)
            if shot_noise:
                inc[...] = rng.poisson(inc * scale) / scale
                np.minimum(inc, theta, out=inc)
            charge += inc
            np.greater_equal(charge, theta, out=fired[j])
            np.subtract(charge, theta, out=charge, where=fired[j])
        yield chunk


def simulate_spikes(light: LightSource, *, rate_hz: float, num_frames: int, t0: float = 0.0,
                    light_times=None, threshold: float = 1.0, gain=None, dark_current: float = 0.0,
                    shot_noise: bool = False, photons_per_threshold: float = 1000.0, seed: int = 0,
                    initial_phase="uniform", chunk_frames: int = 512) -> np.ndarray:
    """Simulate a spike camera -> uint8 (num_frames, H, W) of 0/1 (rows top-down).

    light: LINEAR light, either an array (T, H, W) sampled at ``light_times`` (seconds,
        strictly increasing; linearly interpolated to each spike frame time, held constant
        outside), or an (H, W) / (1, H, W) array (static scene), or (num_frames, H, W) with
        ``light_times=None`` (one sample per spike frame), or a callable ``t -> (H, W)``.
        Units: charge per spike frame (threshold 1, light 0.25 -> fires every 4th frame).
    gain: per-pixel response map [H, W] (see :func:`make_gain_map`), default ones.
    dark_current: light units added to every pixel before the gain.
    shot_noise / photons_per_threshold: Poisson photon noise on each frame's charge.
    initial_phase: "uniform" (random in [0, threshold)), "zero", or an [H, W] array.
    seed: seeds the phase and the noise.
    """
    sampler_shape = _LightSampler(light, light_times, num_frames, rate_hz, t0).shape
    out = np.empty((num_frames, *sampler_shape), dtype=np.uint8)
    i = 0
    for chunk in iter_spike_chunks(light, rate_hz=rate_hz, num_frames=num_frames, t0=t0,
                                   light_times=light_times, threshold=threshold, gain=gain,
                                   dark_current=dark_current, shot_noise=shot_noise,
                                   photons_per_threshold=photons_per_threshold, seed=seed,
                                   initial_phase=initial_phase, chunk_frames=chunk_frames):
        out[i:i + len(chunk)] = chunk
        i += len(chunk)
    return out


def simulate_spikes_to_file(path: str | Path, light: LightSource, *, flipud: bool = True,
                            **kwargs) -> Path:
    """Like :func:`simulate_spikes` but streams the packed frames into a Vidar ``.dat`` file
    (written to a temporary name, then moved into place). Returns the path."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.sim.tmp")
    tmp.unlink(missing_ok=True)
    tmp.parent.mkdir(parents=True, exist_ok=True)
    tmp.touch()
    try:
        for chunk in iter_spike_chunks(light, **kwargs):
            write_spikes(tmp, chunk, flipud=flipud, append=True)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


# ----------------------------------------------------------------------------- reconstructions

def _window(n: int, window: int | None, index: int | None) -> tuple[int, int]:
    if window is None or window >= n:
        return 0, n
    window = max(1, int(window))
    centre = n // 2 if index is None else int(index)
    a = centre - window // 2
    a = min(max(a, 0), n - window)
    return a, a + window


def tfp(spikes: np.ndarray, window: int | None = None, *, index: int | None = None,
        threshold: float = 1.0) -> np.ndarray:
    """Texture From Playback: mean spike count over a window x threshold -> float32 [H, W].

    The window is ``window`` frames centred on ``index`` (default: the middle of the
    stream), shifted to lie inside it; ``window=None`` uses every frame. The result is in
    the simulator's light units (charge per frame), i.e. an unbiased light estimate below
    saturation (gain and dark current included).
    """
    s = np.asarray(spikes)
    if s.ndim != 3 or s.shape[0] == 0:
        raise ValueError(f"spikes must be a non-empty (n, H, W) array, got shape {s.shape}")
    a, b = _window(s.shape[0], window, index)
    return (s[a:b].sum(axis=0, dtype=np.float64) * (threshold / (b - a))).astype(np.float32)


def tfi(spikes: np.ndarray, index: int, *, threshold: float = 1.0, max_window: int | None = None) -> np.ndarray:
    """Texture From Interval: threshold / inter-spike interval around frame ``index``.

    For each pixel, ``prev`` = last spike at or before ``index``, ``next`` = first spike
    after it; the estimate is ``threshold / (next - prev)`` -> float32 [H, W].
    Bounds: a missing ``prev`` is taken as frame -1 (just before the searched range) and a
    missing ``next`` as the frame just after it, so the value is then an upper bound on the
    light; pixels with no spike in the searched range give 0. ``max_window`` limits the
    search to ``index - max_window .. index + max_window`` (default: the whole stream).
    """
    s = np.asarray(spikes)
    if s.ndim != 3:
        raise ValueError(f"spikes must be (n, H, W), got shape {s.shape}")
    n = s.shape[0]
    index = int(index)
    if not 0 <= index < n:
        raise ValueError(f"index {index} outside the stream of {n} frames")
    lo = 0 if max_window is None else max(0, index - int(max_window))
    hi = n if max_window is None else min(n, index + int(max_window) + 1)
    before = s[lo:index + 1][::-1] != 0          # frame index, index-1, ...
    after = s[index + 1:hi] != 0                 # frame index+1, ...
    has_prev = before.any(axis=0)
    has_next = after.any(axis=0) if after.shape[0] else np.zeros(s.shape[1:], dtype=bool)
    prev = np.where(has_prev, index - before.argmax(axis=0), lo - 1)
    nxt = np.where(has_next, index + 1 + (after.argmax(axis=0) if after.shape[0] else 0), hi)
    interval = (nxt - prev).astype(np.float64)
    out = np.where(has_prev | has_next, threshold / interval, 0.0)
    return out.astype(np.float32)
