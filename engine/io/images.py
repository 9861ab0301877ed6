"""Image IO: PNG (8/16-bit, sRGB-encoded) and EXR (linear), with atomic writes.

* :func:`read_image` / :func:`read_image_rgba` return float32 arrays **as stored**: PNG
  values are divided by 255 or 65535 (so they are sRGB-encoded display values), EXR
  values are linear light. :func:`read_image_srgb` applies the project convention (the
  engine trains on sRGB-encoded values in [0, 1]): EXR is encoded with
  ``linear_to_srgb`` and clipped to [0, 1].
* Pillow truncates 16-bit RGB(A) PNGs to 8 bits, so 16-bit PNGs are decoded here
  (zlib + the PNG row filters; Average/Paeth rows go through a small numba kernel).
  8-bit and palette PNGs, and other formats Pillow knows (JPEG...), go through Pillow.
* :func:`write_png` / :func:`write_exr` write a temporary file in the target directory and
  ``os.replace`` it into place, so readers never see a half-written image.

Errors for unreadable or damaged files raise :class:`engine.errors.CaptureError` naming
the file.
"""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from ..colour import linear_to_srgb
from ..errors import CaptureError
from .fileio import atomic_path, atomic_write

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
EXR_MAGIC = b"\x76\x2f\x31\x01"
_PNG_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}  # colour type -> samples per pixel (no palette)


# ----------------------------------------------------------------------------- helpers

def _kind(path: Path) -> str:
    """'png', 'exr' or 'other', by magic bytes (falls back to the suffix)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
    except FileNotFoundError:
        raise CaptureError(path, "image file does not exist") from None
    except OSError as exc:
        raise CaptureError(path, f"cannot read image: {exc}") from None
    if head.startswith(PNG_SIGNATURE):
        return "png"
    if head.startswith(EXR_MAGIC):
        return "exr"
    suffix = path.suffix.lower()
    if suffix in (".png", ".exr"):
        raise CaptureError(path, f"not a valid {suffix[1:].upper()} file (bad magic bytes)")
    return "other"


def _to_rgba(img: np.ndarray) -> np.ndarray:
    """[H,W], [H,W,1..4] float -> [H,W,4] (alpha 1 when absent)."""
    if img.ndim == 2:
        img = img[:, :, None]
    c = img.shape[2]
    h, w = img.shape[:2]
    out = np.empty((h, w, 4), dtype=np.float32)
    if c in (1, 2):
        out[..., :3] = img[..., :1]
        out[..., 3] = img[..., 1] if c == 2 else 1.0
    else:
        out[..., :3] = img[..., :3]
        out[..., 3] = img[..., 3] if c == 4 else 1.0
    return out


# ----------------------------------------------------------------------------- PNG

def _png_chunks(path: Path, data: bytes):
    if not data.startswith(PNG_SIGNATURE):
        raise CaptureError(path, "not a PNG file")
    pos = 8
    n = len(data)
    while pos + 8 <= n:
        length, ctype = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + length]
        if len(body) != length:
            raise CaptureError(path, f"truncated PNG chunk {ctype!r}")
        yield ctype, body
        if ctype == b"IEND":
            return
        pos += 12 + length
    raise CaptureError(path, "truncated PNG (no IEND chunk)")


def _png_header(path: Path, head: bytes) -> tuple[int, int, int, int, int]:
    """(width, height, bit depth, colour type, interlace) from the first 33 bytes."""
    if len(head) < 33 or not head.startswith(PNG_SIGNATURE) or head[12:16] != b"IHDR":
        raise CaptureError(path, "not a PNG file or missing IHDR header")
    w, h, depth, ctype, _comp, _filt, interlace = struct.unpack(">IIBBBBB", head[16:29])
    return w, h, depth, ctype, interlace


def _unfilter_rows(raw, height, stride, bpp, out):
    """Undo PNG filters row by row (all five types). Compiled with numba when available.

    Returns -1, or the index of the first row with an unknown filter type.
    """
    prev = np.zeros(stride, dtype=np.uint8)
    for r in range(height):
        base = r * (stride + 1)
        ft = raw[base]
        if ft > 4:
            return r
        for i in range(stride):
            x = np.int32(raw[base + 1 + i])
            a = np.int32(out[r, i - bpp]) if i >= bpp else np.int32(0)
            b = np.int32(prev[i])
            c = np.int32(prev[i - bpp]) if i >= bpp else np.int32(0)
            if ft == 0:
                v = x
            elif ft == 1:
                v = x + a
            elif ft == 2:
                v = x + b
            elif ft == 3:
                v = x + (a + b) // 2
            else:
                p = a + b - c
                pa = abs(p - a)
                pb = abs(p - b)
                pc = abs(p - c)
                if pa <= pb and pa <= pc:
                    v = x + a
                elif pb <= pc:
                    v = x + b
                else:
                    v = x + c
            out[r, i] = np.uint8(v & 0xFF)
        prev[:] = out[r]
    return -1


_UNFILTER = None


def _unfilter_impl():
    """The compiled row decoder, or the plain-Python one if numba is unavailable."""
    global _UNFILTER
    if _UNFILTER is None:
        _UNFILTER = _unfilter_rows
        try:
            import numba  # lazy: optional; the plain-Python decoder is the fallback

            try:
                _UNFILTER = numba.njit(cache=True)(_unfilter_rows)
            except RuntimeError:  # no writable cache location
                _UNFILTER = numba.njit(_unfilter_rows)
        except ImportError:
            pass
    return _UNFILTER


def _png_unfilter(path: Path, raw: np.ndarray, height: int, stride: int, bpp: int) -> np.ndarray:
    """Undo the PNG row filters -> (height, stride) uint8."""
    if raw.size != height * (stride + 1):
        raise CaptureError(path, f"PNG pixel data has {raw.size} bytes, expected {height * (stride + 1)}")
    rows = raw.reshape(height, stride + 1)
    ftypes = rows[:, 0]
    if ftypes.max(initial=0) > 4:
        raise CaptureError(path, f"PNG row uses unknown filter type {int(ftypes.max())}")
    data = rows[:, 1:]
    if np.all(ftypes <= 2):  # vectorized path (None / Sub / Up)
        out = np.empty((height, stride), dtype=np.uint8)
        prev = np.zeros(stride, dtype=np.uint8)
        for r in range(height):
            ft = ftypes[r]
            if ft == 0:
                out[r] = data[r]
            elif ft == 2:
                np.add(data[r], prev, out=out[r])  # uint8 wraps modulo 256
            else:  # Sub: running sum per byte lane, modulo 256
                lanes = data[r].reshape(-1, bpp)
                out[r] = np.cumsum(lanes, axis=0, dtype=np.uint8).reshape(-1)
            prev = out[r]
        return out
    out = np.empty((height, stride), dtype=np.uint8)
    bad = _unfilter_impl()(raw, height, stride, bpp, out)
    if bad >= 0:
        raise CaptureError(path, f"PNG row {bad} uses an unknown filter type")
    return out


def _read_png16(path: Path, data: bytes) -> np.ndarray:
    """Decode a 16-bit, non-interlaced PNG -> uint16 [H, W, C]."""
    w, h, depth, ctype, interlace = _png_header(path, data[:33])
    if ctype not in _PNG_CHANNELS:
        raise CaptureError(path, f"unsupported 16-bit PNG colour type {ctype}")
    if interlace:
        raise CaptureError(path, "interlaced (Adam7) 16-bit PNGs are not supported; re-save without interlacing")
    idat = b"".join(body for kind, body in _png_chunks(path, data) if kind == b"IDAT")
    try:
        raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8)
    except zlib.error as exc:
        raise CaptureError(path, f"damaged PNG pixel data: {exc}") from None
    channels = _PNG_CHANNELS[ctype]
    bpp = 2 * channels
    rows = _png_unfilter(path, raw, h, w * bpp, bpp)
    return rows.view(">u2").reshape(h, w, channels).astype(np.uint16)


def _read_png(path: Path) -> np.ndarray:
    """-> float32 [H, W, C] in [0, 1], C in 1..4 as stored."""
    data = path.read_bytes()
    _w, _h, depth, _ctype, _il = _png_header(path, data[:33])
    if depth == 16:
        return _read_png16(path, data).astype(np.float32) / 65535.0
    return _read_pillow(path)


def _read_pillow(path: Path) -> np.ndarray:
    from PIL import Image  # lazy: only 8-bit PNG / JPEG need Pillow (the UI imports this module)

    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            if mode in ("I;16", "I;16B", "I;16L", "I"):
                arr = np.asarray(im, dtype=np.float32) / 65535.0
                return arr[:, :, None]
            has_alpha = mode in ("RGBA", "LA", "PA", "RGBa", "La") or "transparency" in im.info
            im = im.convert("RGBA" if has_alpha else "RGB")
            return np.asarray(im, dtype=np.float32) / 255.0
    except CaptureError:
        raise
    except Exception as exc:  # PIL raises many kinds for damaged files
        raise CaptureError(path, f"cannot decode image: {exc}") from None


# ----------------------------------------------------------------------------- EXR

def read_exr_channels(path: str | Path) -> dict[str, np.ndarray]:
    """All channels of a (single-part) EXR file: name -> float32 [H, W]."""
    import OpenEXR  # lazy: only EXR files need it (the UI imports this module)

    path = Path(path)
    _kind(path)
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            return {name: np.asarray(ch.pixels, dtype=np.float32) for name, ch in f.channels().items()}
    except CaptureError:
        raise
    except Exception as exc:
        raise CaptureError(path, f"cannot read EXR: {exc}") from None


def _pick_exr_rgba(path: Path, chans: dict[str, np.ndarray]) -> np.ndarray:
    """R,G,B(,A) from plain names or the first layer ('View Layer.Combined.R') having them."""
    def find(prefix: str):
        if all(prefix + c in chans for c in "RGB"):
            rgb = [chans[prefix + c] for c in "RGB"]
            a = chans.get(prefix + "A")
            return np.stack(rgb + ([a] if a is not None else []), axis=-1)
        return None

    img = find("")
    if img is None:
        prefixes = sorted({n[:-1] for n in chans if n.endswith(".R")})
        for p in prefixes:
            img = find(p)
            if img is not None:
                break
    if img is None:
        for gray in ("Y", "L"):
            if gray in chans:
                img = chans[gray][:, :, None]
                break
    if img is None:
        raise CaptureError(path, f"EXR has no R,G,B (or Y) channels; channels are {sorted(chans)}")
    return _to_rgba(img.astype(np.float32, copy=False))


# ----------------------------------------------------------------------------- public API

def read_image_rgba(path: str | Path) -> np.ndarray:
    """float32 [H, W, 4] as stored (PNG: encoded / 255 or 65535; EXR: linear). Alpha 1 if absent."""
    path = Path(path)
    kind = _kind(path)
    if kind == "exr":
        return _pick_exr_rgba(path, read_exr_channels(path))
    img = _read_png(path) if kind == "png" else _read_pillow(path)
    return _to_rgba(img)


def read_image(path: str | Path) -> np.ndarray:
    """float32 [H, W, 3] as stored, alpha dropped (PNG sRGB-encoded in [0,1]; EXR linear)."""
    return np.ascontiguousarray(read_image_rgba(path)[..., :3])


def is_linear_file(path: str | Path) -> bool:
    """True for files whose values are linear light (EXR, by magic bytes), False otherwise."""
    return _kind(Path(path)) == "exr"


def read_image_srgb(path: str | Path) -> np.ndarray:
    """float32 [H, W, 3] sRGB-encoded in [0, 1] (the engine's training convention).

    EXR (linear) is encoded with ``linear_to_srgb`` and clipped; PNG is returned as stored.
    """
    path = Path(path)
    img = read_image(path)
    if _kind(path) == "exr":
        img = np.clip(linear_to_srgb(img), 0.0, 1.0).astype(np.float32)
    return img


def read_image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) from the file header only (no pixel decoding)."""
    path = Path(path)
    kind = _kind(path)
    if kind == "png":
        with open(path, "rb") as fh:
            w, h, *_ = _png_header(path, fh.read(33))
        return int(w), int(h)
    if kind == "exr":
        import OpenEXR  # lazy: only EXR files need it (the UI imports this module)

        try:
            with OpenEXR.File(str(path), header_only=True) as f:
                lo, hi = f.header()["dataWindow"]
        except Exception as exc:
            raise CaptureError(path, f"cannot read EXR header: {exc}") from None
        return int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)
    from PIL import Image  # lazy: only 8-bit PNG / JPEG need Pillow (the UI imports this module)

    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except Exception as exc:
        raise CaptureError(path, f"cannot read image header: {exc}") from None


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)


def encode_png(img: np.ndarray, bits: int = 8) -> bytes:
    """PNG bytes of a float image in [0, 1] ([H,W], [H,W,1..4]); values are stored as given."""
    a = np.asarray(img, dtype=np.float64)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 2, 3, 4):
        raise ValueError(f"write_png needs [H,W] or [H,W,C<=4], got shape {np.shape(img)}")
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits}")
    h, w, c = a.shape
    scale = 255.0 if bits == 8 else 65535.0
    q = np.rint(np.clip(np.nan_to_num(a, nan=0.0), 0.0, 1.0) * scale)
    q = q.astype(">u2" if bits == 16 else np.uint8)
    rows = q.reshape(h, -1).view(np.uint8).reshape(h, w * c * (bits // 8))
    # filter type 2 (Up): a cheap, vectorized filter that compresses smooth images well
    filt = np.empty((h, rows.shape[1] + 1), dtype=np.uint8)
    filt[:, 0] = 2
    filt[0, 1:] = rows[0]
    np.subtract(rows[1:], rows[:-1], out=filt[1:, 1:])
    ctype = {1: 0, 2: 4, 3: 2, 4: 6}[c]
    ihdr = struct.pack(">IIBBBBB", w, h, bits, ctype, 0, 0, 0)
    return (PNG_SIGNATURE + _png_chunk(b"IHDR", ihdr)
            + _png_chunk(b"IDAT", zlib.compress(filt.tobytes(), 6)) + _png_chunk(b"IEND", b""))


def write_png(path: str | Path, img: np.ndarray, bits: int = 8) -> Path:
    """Write a float image in [0, 1] (sRGB-encoded; clipped) as an 8- or 16-bit PNG, atomically."""
    path = Path(path)
    data = encode_png(img, bits)
    return atomic_write(path, lambda fh: fh.write(data), fsync=False)


def write_exr(path: str | Path, channels: dict[str, np.ndarray] | np.ndarray, *, half: bool = False) -> Path:
    """Write an EXR atomically. ``channels``: name -> [H, W] array (e.g. R, G, B, A, Z), or an
    [H, W, 3|4] array (taken as R, G, B(, A)). Values are written as given (linear light).
    ``half=True`` stores float16 (Z and other non-colour channels stay float32)."""
    import OpenEXR  # lazy: only EXR files need it (the UI imports this module)

    path = Path(path)
    if isinstance(channels, np.ndarray):
        arr = channels
        if arr.ndim != 3 or arr.shape[2] not in (3, 4):
            raise ValueError(f"write_exr needs [H,W,3|4] or a channel dict, got shape {arr.shape}")
        channels = {n: arr[..., i] for i, n in enumerate("RGBA"[: arr.shape[2]])}
    if not channels:
        raise ValueError("write_exr needs at least one channel")
    shapes = {np.shape(v) for v in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"write_exr channels must share one [H, W] shape, got {shapes}")
    out = {}
    for name, v in channels.items():
        dt = np.float16 if (half and name in ("R", "G", "B", "A")) else np.float32
        out[name] = np.ascontiguousarray(np.asarray(v, dtype=dt))
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path, ".exr") as tmp, OpenEXR.File(header, out) as f:
        f.write(tmp)
    return path
