"""Image IO (PNG 8/16-bit, EXR) and colour conversions."""
from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
import torch

from engine import colour
from engine.errors import CaptureError
from engine.io.images import (
    encode_png,
    read_exr_channels,
    read_image,
    read_image_rgba,
    read_image_size,
    read_image_srgb,
    write_exr,
    write_png,
)


@pytest.fixture
def img():
    rng = np.random.default_rng(1)
    return rng.random((13, 17, 3)).astype(np.float32)


def test_png8_round_trip(tmp_path, img):
    p = write_png(tmp_path / "a.png", img, bits=8)
    back = read_image(p)
    assert back.dtype == np.float32 and back.shape == (13, 17, 3)
    assert np.abs(back - img).max() <= 0.5 / 255 + 1e-6
    assert read_image_size(p) == (17, 13)


def test_png16_keeps_16_bit_precision(tmp_path, img):
    p = write_png(tmp_path / "a.png", img, bits=16)
    back = read_image(p)
    # 16-bit quantisation error, far below one 8-bit step
    assert np.abs(back - img).max() <= 0.5 / 65535 + 1e-7
    levels = np.unique(np.rint(back * 65535).astype(np.int64) % 256)
    assert len(levels) > 100  # low byte really carries information


def test_png16_rgba_alpha(tmp_path, img):
    rgba = np.concatenate([img, img[..., :1] * 0.5], axis=-1)
    p = write_png(tmp_path / "a.png", rgba, bits=16)
    back = read_image_rgba(p)
    assert back.shape == (13, 17, 4)
    assert np.allclose(back, rgba, atol=1e-5)
    assert read_image(p).shape == (13, 17, 3)


def _paeth(a, b, c):
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    return a if pa <= pb and pa <= pc else (b if pb <= pc else c)


def _encode_png16_filters(q: np.ndarray) -> bytes:
    """Reference 16-bit RGB encoder cycling through all five row filters (pure Python)."""
    h, w, _ = q.shape
    rows = q.astype(">u2").reshape(h, -1).view(np.uint8).reshape(h, -1).astype(int)
    bpp = 6
    out = bytearray()
    prev = [0] * rows.shape[1]
    for r in range(h):
        ft = r % 5
        cur = rows[r].tolist()
        out.append(ft)
        for i, x in enumerate(cur):
            a = cur[i - bpp] if i >= bpp else 0
            b = prev[i]
            c = prev[i - bpp] if i >= bpp else 0
            pred = [0, a, b, (a + b) // 2, _paeth(a, b, c)][ft]
            out.append((x - pred) & 0xFF)
        prev = cur

    def chunk(k, body):
        return struct.pack(">I", len(body)) + k + body + struct.pack(">I", zlib.crc32(k + body) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(bytes(out))) + chunk(b"IEND", b""))


@pytest.mark.slow
def test_png16_all_filter_types(tmp_path):
    rng = np.random.default_rng(2)
    q = rng.integers(0, 65536, size=(10, 7, 3), dtype=np.uint16)
    p = tmp_path / "f.png"
    p.write_bytes(_encode_png16_filters(q))
    back = read_image(p)
    assert np.array_equal(np.rint(back * 65535).astype(np.uint16), q)


def test_png16_python_fallback_decoder(tmp_path, monkeypatch):
    import engine.io.images as im

    q = np.random.default_rng(4).integers(0, 65536, size=(6, 5, 3), dtype=np.uint16)
    p = tmp_path / "f.png"
    p.write_bytes(_encode_png16_filters(q))
    monkeypatch.setattr(im, "_UNFILTER", im._unfilter_rows)  # as if numba were missing
    assert np.array_equal(np.rint(read_image(p) * 65535).astype(np.uint16), q)


def test_png8_written_by_pillow(tmp_path):
    from PIL import Image

    rng = np.random.default_rng(3)
    q = rng.integers(0, 256, size=(9, 11, 4), dtype=np.uint8)
    Image.fromarray(q, "RGBA").save(tmp_path / "p.png")
    back = read_image_rgba(tmp_path / "p.png")
    assert np.array_equal(np.rint(back * 255).astype(np.uint8), q)


def test_exr_round_trip_channels(tmp_path, img):
    z = np.arange(13 * 17, dtype=np.float32).reshape(13, 17)
    p = write_exr(tmp_path / "a.exr", {"R": img[..., 0] * 4, "G": img[..., 1], "B": img[..., 2], "A": img[..., 0],
                                      "Z": z})
    chans = read_exr_channels(p)
    assert set(chans) == {"R", "G", "B", "A", "Z"}
    assert np.array_equal(chans["Z"], z)
    rgba = read_image_rgba(p)
    assert np.array_equal(rgba[..., 0], img[..., 0] * 4)  # linear, unclipped, float32 exact
    assert np.array_equal(rgba[..., 3], img[..., 0])
    assert read_image_size(p) == (17, 13)
    # training convention: EXR is linear -> sRGB-encoded, clipped to [0, 1]
    enc = read_image_srgb(p)
    assert enc.max() <= 1.0
    assert np.allclose(enc[..., 1], colour.linear_to_srgb(img[..., 1]), atol=1e-6)


def test_exr_layered_names(tmp_path, img):
    p = write_exr(tmp_path / "l.exr", {f"ViewLayer.Combined.{c}": img[..., i] for i, c in enumerate("RGB")})
    assert np.allclose(read_image(p), img)


def test_writes_are_atomic_no_temp_left(tmp_path, img):
    write_png(tmp_path / "x.png", img)
    write_png(tmp_path / "x.png", img * 0.5, bits=16)  # overwrite in place
    write_exr(tmp_path / "x.exr", img)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.exr", "x.png"]


def test_bad_files_raise_capture_error(tmp_path, img):
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not a png at all")
    with pytest.raises(CaptureError, match="bad.png"):
        read_image(bad)
    trunc = tmp_path / "trunc.png"
    trunc.write_bytes(encode_png(img, 16)[:60])
    with pytest.raises(CaptureError, match="trunc.png"):
        read_image(trunc)
    with pytest.raises(CaptureError, match="missing.exr"):
        read_image(tmp_path / "missing.exr")


def test_srgb_numpy_round_trip_and_reference_values():
    x = np.linspace(0, 1, 101, dtype=np.float32)
    assert np.allclose(colour.linear_to_srgb(colour.srgb_to_linear(x)), x, atol=1e-6)
    assert colour.srgb_to_linear(1.0) == pytest.approx(1.0)
    assert colour.srgb_to_linear(0.5) == pytest.approx(0.2140, abs=1e-4)
    assert colour.linear_to_srgb(0.0) == 0.0
    assert colour.srgb_to_linear(x).dtype == np.float32


def test_srgb_torch_matches_numpy_and_grads_finite_at_zero():
    x = torch.tensor([0.0, 0.001, 0.03, 0.2, 0.9, 1.0], dtype=torch.float64, requires_grad=True)
    for f in (colour.srgb_to_linear, colour.linear_to_srgb):
        y = f(x)
        assert np.allclose(y.detach().numpy(), f(x.detach().numpy()))
        (g,) = torch.autograd.grad(y.sum(), x)
        assert torch.isfinite(g).all() and (g > 0).all()


def test_luminance():
    rgb = np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=np.float32)
    assert np.allclose(colour.luminance(rgb), [0.2126, 0.7152, 0.0722, 1.0])
    assert torch.allclose(colour.luminance(torch.from_numpy(rgb)), torch.tensor([0.2126, 0.7152, 0.0722, 1.0]))
