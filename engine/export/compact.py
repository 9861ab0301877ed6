"""Compact 4D cache: canonical Gaussians + quantized per-instant residuals, zstd-coded.

After DynTCG (shared/papers/dyntcg.txt, Sec. "Residual Compression"): consecutive instants
share most of their Gaussian parameters, so each instant is stored as a residual, quantized,
and entropy-coded. Here, per attribute ``a`` of shape [T,N,C] sampled at T instants:

1. **uniform quantization** on a fixed grid of step ``q_a``: ``k = round(x / q_a)`` (int32);
   the reconstruction error is at most ``q_a / 2`` everywhere, with no drift over time
   (DynTCG quantizes position finer than appearance; so do the default steps below);
2. **canonical + residuals**: the first instant's integers are the canonical Gaussians (one
   block); every later instant stores ``k_t - k_{t-1}``, its residual to the previous instant
   in the integer domain (lossless; a second block). Static Gaussians give runs of zeros,
   smooth motion small integers (second-order residuals measured no smaller on the demo).
   Residuals go Gaussian-major (each Gaussian's time series contiguous), zig-zag to unsigned,
   the narrowest integer width that holds them, split into byte planes;
3. **entropy coding** with zstandard (``zstandard`` package, level 15: on the demo 7 s to
   encode 61 instants x 20k Gaussians, level 19 was 5x slower for 8% less).

Default steps (``DEFAULT_STEPS``; ``means`` is relative to the scene extent = largest side of
the first instant's bounding box): means 2e-4 x extent, quaternion components (after
normalising) 1/512, log-scales 1/128, opacity logits 1/32, SH coefficients 1/256 (colour units,
i.e. the coefficient step is that / SH_C0 for the DC term). On the demo run these cost
<0.2 dB (docs/experiments/export-and-lpips.md); ``steps=`` overrides them per attribute.

File layout (little-endian)::

    b"BT4DC\\x00\\r\\n"  u32 version  u32 header_bytes  header (UTF-8 JSON)  blocks...

The header lists times, N, SH degree, steps, and per block its name, dtype, shape, offset,
compressed size and CRC-32 of the compressed bytes. A short file, a bad CRC, a block that
does not decode or an unknown version raise :class:`CompactFormatError` naming the file.
Writes are atomic.
"""
from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import zstandard

from ..errors import RunError
from ..io.fileio import atomic_write
from .splats import SPLAT_KEYS, check_splats

MAGIC = b"BT4DC\x00\r\n"
VERSION = 1
_PREFIX = struct.Struct("<8sII")
ATTR_CHANNELS = {"means": 3, "quats": 4, "log_scales": 3, "opacity_logits": 1}
SH_C0 = 0.28209479177387814
DEFAULT_STEPS = {"means": 2e-4, "quats": 1.0 / 512, "log_scales": 1.0 / 128, "opacity_logits": 1.0 / 32,
                 "sh": 1.0 / 256}
DEFAULT_LEVEL = 15


class CompactFormatError(RunError):
    """A compact cache file is missing, truncated, corrupted or of an unknown version."""



# ----------------------------------------------------------------------------- coding
def _zigzag(k: np.ndarray) -> np.ndarray:
    k = k.astype(np.int64)
    return ((k << 1) ^ (k >> 63)).astype(np.uint64)


def _unzigzag(z: np.ndarray) -> np.ndarray:
    z = z.astype(np.uint64)
    return ((z >> np.uint64(1)).astype(np.int64) ^ -(z & np.uint64(1)).astype(np.int64))


def _pack_ints(k: np.ndarray, level: int) -> tuple[bytes, dict]:
    """int array -> zstd bytes of zig-zagged byte planes; returns (bytes, block info)."""
    z = _zigzag(k.reshape(-1))
    width = 1
    top = int(z.max(initial=0))
    while width < 8 and top >= (1 << (8 * width)):
        width *= 2
    planes = z.astype(f"<u{width}").view(np.uint8).reshape(-1, width).T  # [width, n] byte planes
    data = zstandard.ZstdCompressor(level=level).compress(np.ascontiguousarray(planes).tobytes())
    return data, {"width": width, "shape": list(k.shape)}


def _unpack_ints(data: bytes, info: dict) -> np.ndarray:
    width, shape = int(info["width"]), tuple(int(s) for s in info["shape"])
    n = int(np.prod(shape))
    raw = zstandard.ZstdDecompressor().decompress(data, max_output_size=n * width)
    if len(raw) != n * width:
        raise ValueError(f"decoded {len(raw)} bytes, expected {n * width}")
    planes = np.frombuffer(raw, np.uint8).reshape(width, n).T
    z = np.ascontiguousarray(planes).view(f"<u{width}").reshape(-1)
    return _unzigzag(z).reshape(shape)


def quantize(x: np.ndarray, step: float) -> np.ndarray:
    """Uniform quantization: int64 ``round(x / step)`` (error <= step / 2)."""
    k = np.rint(np.asarray(x, np.float64) / float(step))
    if not np.all(np.isfinite(k)) or np.abs(k).max(initial=0) >= 2 ** 52:
        raise ValueError("values are not finite or too large for the quantization step")
    return k.astype(np.int64)


def attribute_steps(first: dict, steps: dict | None = None) -> dict:
    """Absolute quantization steps per attribute (``means`` scaled by the scene extent)."""
    s = {**DEFAULT_STEPS, **(steps or {})}
    means = np.asarray(first["means"], np.float64)
    extent = float(np.ptp(means, axis=0).max()) if len(means) else 1.0
    extent = extent if np.isfinite(extent) and extent > 0 else 1.0
    return {"means": s["means"] * extent, "quats": s["quats"], "log_scales": s["log_scales"],
            "opacity_logits": s["opacity_logits"], "sh": s["sh"] / SH_C0}


def _stack(frames: list[dict], key: str) -> np.ndarray:
    arrs = [np.asarray(f[key], np.float32) for f in frames]
    a = np.stack(arrs).reshape(len(frames), arrs[0].shape[0], -1)  # [T, N, C]
    if key == "quats":  # the renderer normalises; normalised components share one step
        a = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)
    return a


def encode(times, frames: list[dict], *, steps: dict | None = None, level: int = DEFAULT_LEVEL,
           meta: dict | None = None) -> bytes:
    """Encode T instants of splats (equal N, equal SH degree) into the cache's bytes."""
    times = np.asarray(times, np.float64).reshape(-1)
    if len(times) != len(frames) or not len(frames):
        raise ValueError(f"need one splat dict per time, got {len(frames)} for {len(times)} times")
    n = check_splats(frames[0], "instant 0")
    k_sh = int(np.shape(frames[0]["sh"])[1])
    for i, f in enumerate(frames):
        if check_splats(f, f"instant {i}") != n or np.shape(f["sh"])[1] != k_sh:
            raise ValueError(f"instant {i}: Gaussian count or SH degree differs from instant 0")
    abs_steps = attribute_steps(frames[0], steps)
    blocks, payload = [], []
    offset = 0
    for key in SPLAT_KEYS:
        k = quantize(_stack(frames, key), abs_steps[key]).transpose(2, 1, 0)  # [C, N, T]: per-Gaussian series
        # canonical (first instant) and residuals apart: their value ranges differ, and a
        # static Gaussian's residuals then form one long run of zeros
        for name, part in ((key, k[:, :, 0]), (f"{key}_residual", np.diff(k, axis=2))):
            data, info = _pack_ints(part, level)
            blocks.append({"name": name, **info, "offset": offset, "size": len(data), "crc32": zlib.crc32(data)})
            payload.append(data)
            offset += len(data)
    header = {"format": "bullettime4d-compact", "version": VERSION, "times": times.tolist(), "num_gaussians": n,
              "sh_bases": k_sh, "steps": abs_steps, "relative_steps": {**DEFAULT_STEPS, **(steps or {})},
              "zstd_level": int(level),
              "layout": "per attribute: canonical [C,N], residuals [C,N,T-1]; zigzag byte planes",
              "meta": meta or {}, "blocks": blocks}
    hb = json.dumps(header).encode()
    return _PREFIX.pack(MAGIC, VERSION, len(hb)) + hb + b"".join(payload)


def write_compact(path, times, splats_of_time, *, steps: dict | None = None, level: int = DEFAULT_LEVEL,
                  meta: dict | None = None, progress=None) -> Path:
    """Sample ``splats_of_time(t)`` at ``times`` and write the cache to ``path`` atomically."""
    times = np.asarray(times, np.float64).reshape(-1)
    frames = []
    for i, t in enumerate(times):
        frames.append(splats_of_time(float(t)))
        if progress is not None:
            progress(i + 1, len(times))
    data = encode(times, frames, steps=steps, level=level, meta=meta)
    return atomic_write(path, lambda fh: fh.write(data))


# ----------------------------------------------------------------------------- reading
class CompactCache:
    """A decoded cache: ``times`` [T], ``num_gaussians``, ``splats(i)``, ``splats_at(t)``."""

    def __init__(self, path: Path, header: dict, attrs: dict[str, np.ndarray]):
        self.path = Path(path)
        self.header = header
        self.times = np.asarray(header["times"], np.float64)
        self.num_gaussians = int(header["num_gaussians"])
        self.meta = dict(header.get("meta") or {})
        self._attrs = attrs  # name -> float32 [T, N, C]

    def __len__(self) -> int:
        return len(self.times)

    def splats(self, i: int) -> dict:
        """Splats of instant ``i`` (float32, shapes as in engine/export/splats.py)."""
        a = {k: v[i] for k, v in self._attrs.items()}
        return {"means": a["means"], "quats": a["quats"], "log_scales": a["log_scales"],
                "opacity_logits": a["opacity_logits"][:, 0], "sh": a["sh"].reshape(self.num_gaussians, -1, 3)}

    def splats_at(self, t: float) -> dict:
        """Splats at any ``t``: linear between the two nearest stored instants (clamped at
        the ends); quaternions normalised-lerped along the short way."""
        T = len(self.times)
        j = int(np.searchsorted(self.times, t, side="right"))
        if T == 1 or j <= 0:
            return self.splats(0)
        if j >= T:
            return self.splats(T - 1)
        t0, t1 = self.times[j - 1], self.times[j]
        w = float((t - t0) / (t1 - t0)) if t1 > t0 else 0.0
        a, b = self.splats(j - 1), self.splats(j)
        if w == 0.0:
            return a
        out = {k: ((1 - w) * a[k] + w * b[k]).astype(np.float32) for k in a if k != "quats"}
        qb = np.where((np.sum(a["quats"] * b["quats"], axis=1) < 0)[:, None], -b["quats"], b["quats"])
        q = (1 - w) * a["quats"] + w * qb
        out["quats"] = (q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)).astype(np.float32)
        return out


def _parse_header(data: bytes, path) -> tuple[dict, int]:
    """(header, payload offset) from a cache's bytes; CompactFormatError naming ``path``."""
    if len(data) < _PREFIX.size:
        raise CompactFormatError(path, f"truncated: {len(data)} bytes, shorter than the file prefix")
    magic, version, hlen = _PREFIX.unpack(data[:_PREFIX.size])
    if magic != MAGIC:
        raise CompactFormatError(path, "not a BulletTime4D compact cache (bad magic bytes)")
    if version > VERSION:
        raise CompactFormatError(path, f"cache version {version} is newer than this engine reads ({VERSION})")
    hb = data[_PREFIX.size:_PREFIX.size + hlen]
    if len(hb) < hlen:
        raise CompactFormatError(path, f"truncated inside the header ({len(hb)} of {hlen} bytes)")
    try:
        header = json.loads(hb.decode())
        blocks = {b["name"]: b for b in header["blocks"]}
        missing = [k for key in SPLAT_KEYS for k in (key, f"{key}_residual") if k not in blocks]
        int(header["num_gaussians"]), list(header["times"])
    except (ValueError, KeyError, TypeError) as exc:
        raise CompactFormatError(path, f"corrupted header: {exc}") from exc
    if missing:
        raise CompactFormatError(path, f"header lacks block(s) {', '.join(missing)}")
    return header, _PREFIX.size + hlen


def read_header(path) -> dict:
    """The header of a cache file (times, counts, steps, blocks); CompactFormatError if unusable."""
    return _parse_header(_read_bytes(path), path)[0]


def _read_bytes(path) -> bytes:
    path = Path(path)
    if not path.is_file():
        raise CompactFormatError(path, "compact cache does not exist")
    return path.read_bytes()


def read_compact(path) -> CompactCache:
    """Decode a cache file. CompactFormatError naming the file on any damage."""
    return decode(_read_bytes(path), path)


def decode(data: bytes, path="<bytes>") -> CompactCache:
    """Decode a cache from its bytes (``path`` names it in errors)."""
    header, start = _parse_header(data, path)
    end = start + max(int(b["offset"]) + int(b["size"]) for b in header["blocks"])
    if len(data) < end:
        raise CompactFormatError(path, f"truncated: {len(data)} bytes, the header promises {end}")
    payload = data[start:end]
    steps = header["steps"]
    T, n = len(header["times"]), int(header["num_gaussians"])
    attrs = {}
    ints = {}
    for b in header["blocks"]:
        name = b["name"]
        data = payload[int(b["offset"]): int(b["offset"]) + int(b["size"])]
        if zlib.crc32(data) != int(b["crc32"]):
            raise CompactFormatError(path, f"corrupted: block '{name}' fails its CRC-32 check")
        try:
            ints[name] = _unpack_ints(data, b)
        except (zstandard.ZstdError, ValueError) as exc:
            raise CompactFormatError(path, f"corrupted: block '{name}' does not decode: {exc}") from exc
    for key in SPLAT_KEYS:
        canon, resid = ints[key], ints[f"{key}_residual"]  # [C, N], [C, N, T-1]
        if canon.ndim != 2 or canon.shape[1] != n or resid.shape != canon.shape + (T - 1,):
            raise CompactFormatError(path, f"corrupted: block '{key}' has shape {canon.shape} / {resid.shape}, "
                                           f"expected [C,{n}] / [C,{n},{T - 1}]")
        k = np.concatenate([canon[:, :, None], resid], axis=2).cumsum(axis=2).transpose(2, 1, 0)  # [T, N, C]
        attrs[key] = (k * float(steps[key])).astype(np.float32)
    return CompactCache(path, header, attrs)
