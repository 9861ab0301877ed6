"""Vidar .dat spike stream IO and the SpikeStream reader."""
from __future__ import annotations

import numpy as np
import pytest

from engine.errors import CaptureError
from engine.io.spikes import SpikeStream, count_frames, read_spikes, write_spikes


def _random_stream(n=7, h=6, w=16, seed=0):
    return (np.random.default_rng(seed).random((n, h, w)) < 0.3).astype(np.uint8)


def test_round_trip_byte_for_byte(tmp_path):
    rng = np.random.default_rng(5)
    raw = rng.integers(0, 256, size=9 * 6 * 16 // 8, dtype=np.uint8).tobytes()  # 9 frames 16x6
    src = tmp_path / "src.dat"
    src.write_bytes(raw)
    s = read_spikes(src, 6, 16)
    assert s.shape == (9, 6, 16) and s.dtype == np.uint8 and set(np.unique(s)) <= {0, 1}
    out = write_spikes(tmp_path / "out.dat", s)
    assert out.read_bytes() == raw
    # also without the flip
    write_spikes(tmp_path / "out2.dat", read_spikes(src, 6, 16, flipud=False), flipud=False)
    assert (tmp_path / "out2.dat").read_bytes() == raw


def test_bit_order_and_rows_bottom_up(tmp_path):
    # 2 rows x 8 cols, one frame: stored row 0 is the BOTTOM image row.
    # byte 0 = 0b00000101 -> stored pixels k=0 and k=2 fire (LSB first)
    # byte 1 = 0b10000000 -> stored pixel k=15 (row 1, col 7) fires
    p = tmp_path / "hand.dat"
    p.write_bytes(bytes([0b00000101, 0b10000000]))
    s = read_spikes(p, 2, 8)
    expect = np.zeros((1, 2, 8), np.uint8)
    expect[0, 1, 0] = expect[0, 1, 2] = 1  # bottom image row (index 1 top-down)
    expect[0, 0, 7] = 1                    # top image row
    assert np.array_equal(s, expect)
    raw = read_spikes(p, 2, 8, flipud=False)
    assert np.array_equal(raw, expect[:, ::-1])
    assert write_spikes(tmp_path / "w.dat", expect).read_bytes() == p.read_bytes()


def test_head_cols_dropped(tmp_path):
    s = _random_stream(3, 4, 12)
    p = write_spikes(tmp_path / "h.dat", s, head_cols=4)
    assert p.stat().st_size == 3 * 4 * 16 // 8
    assert np.array_equal(read_spikes(p, 4, 12, head_cols=4), s)
    # the head columns really are the leading bits of each stored row
    full = read_spikes(p, 4, 16)
    assert np.array_equal(full[:, :, 4:], s) and not full[:, :, :4].any()


@pytest.mark.parametrize("h, w, head", [(6, 16, 8), (4, 12, 4), (3, 8, 0), (5, 24, 0)])
def test_packed_fast_path_and_general_path_agree(h, w, head):
    from engine.io.spikes import decode_frames, encode_frames

    s = _random_stream(5, h, w, seed=h + w)
    for flip in (True, False):
        raw = encode_frames(s, flipud=flip, head_cols=head)
        fast = decode_frames(raw, h, w, flipud=flip, head_cols=head)  # packed-domain flip if aligned
        general = np.empty_like(s)
        decode_frames(raw, h, w, flipud=flip, head_cols=head, out=general)  # chunked unpack + copy
        assert np.array_equal(fast, s) and np.array_equal(general, s) and fast.flags.c_contiguous


def test_partial_file_error_and_allow_partial(tmp_path):
    s = _random_stream(5, 6, 16)
    p = write_spikes(tmp_path / "part.dat", s)
    with open(p, "ab") as fh:
        fh.write(b"\x01\x02\x03")
    with pytest.raises(CaptureError) as e:
        read_spikes(p, 6, 16)
    msg = str(e.value)
    assert "part.dat" in msg and "63" in msg and "12 bytes" in msg
    assert np.array_equal(read_spikes(p, 6, 16, allow_partial=True), s)
    assert count_frames(p, 6, 16, allow_partial=True) == 5


def test_start_count_slice_and_out_of_range(tmp_path):
    s = _random_stream(20, 6, 16)
    p = write_spikes(tmp_path / "s.dat", s)
    assert np.array_equal(read_spikes(p, 6, 16, start=5, count=7), s[5:12])
    assert np.array_equal(read_spikes(p, 6, 16, start=15), s[15:])
    with pytest.raises(CaptureError, match="s.dat"):
        read_spikes(p, 6, 16, start=18, count=5)


def test_missing_file(tmp_path):
    with pytest.raises(CaptureError, match="nope.dat"):
        read_spikes(tmp_path / "nope.dat", 6, 16)


def test_spike_stream_timing_and_slices(tmp_path):
    s = _random_stream(100, 6, 16, seed=3)
    p = write_spikes(tmp_path / "s.dat", s)
    st = SpikeStream(p, 16, 6, rate_hz=1000.0, t0=0.5, camera="spike0", co_located_with="rgb0")
    assert len(st) == st.num_frames == 100
    assert np.allclose(st.times, 0.5 + np.arange(100) / 1000.0)
    assert st.frame_index(0.5) == 0 and st.frame_index(0.5104) == 10 and st.frame_index(99.0) == 99
    frames, times = st.frames_between(0.510, 0.520)  # [t_a, t_b): frames 10..19
    assert np.array_equal(frames, s[10:20])
    assert np.allclose(times, 0.5 + np.arange(10, 20) / 1000.0)
    assert np.array_equal(st.window_counts(0.510, 0.520), s[10:20].sum(0).astype(np.float32))
    assert st.window_counts(0.510, 0.520).dtype == np.float32
    # consecutive windows partition the stream
    total = sum(st.window_counts(0.5 + a / 1000, 0.5 + (a + 10) / 1000) for a in range(0, 100, 10))
    assert np.array_equal(total, s.sum(0))
    assert st.frames_between(0.0, 0.1)[0].shape == (0, 6, 16)


def test_spike_stream_num_frames_limit(tmp_path):
    p = write_spikes(tmp_path / "s.dat", _random_stream(10, 6, 16))
    assert len(SpikeStream(p, 16, 6, 100.0, num_frames=4)) == 4
    with pytest.raises(CaptureError, match="s.dat"):
        SpikeStream(p, 16, 6, 100.0, num_frames=11)


# ----------------------------------------------------------------------------- command line

def _tiny_capture(root):
    import json

    from engine.io.images import write_png

    write_png(root / "rgb" / "a.png", np.zeros((6, 16, 3)))
    s = np.zeros((50, 6, 16), np.uint8)
    s[::2, :, :8] = 1  # left half fires every other frame
    write_spikes(root / "spike" / "s0.dat", s)
    cams = {"rgb0": {"w": 16, "h": 6, "fl_x": 10, "role": "train"},
            "spike0": {"w": 16, "h": 6, "fl_x": 10, "role": "train"}}
    data = {"cameras": cams,
            "frames": [{"file_path": "rgb/a.png", "camera": "rgb0", "time": 0.0,
                        "transform_matrix": np.eye(4).tolist()}],
            "spike_streams": [{"file_path": "spike/s0.dat", "camera": "spike0", "rate_hz": 1000,
                               "co_located_with": "rgb0"}]}
    (root / "transforms.json").write_text(json.dumps(data))


def test_cli_spikes_info_and_tfp(tmp_path, capsys):
    from engine.__main__ import main
    from engine.io.images import read_exr_channels, read_image

    _tiny_capture(tmp_path)
    out = tmp_path / "tfp.png"
    assert main(["spikes", str(tmp_path), "--t0", "0.01", "--t1", "0.03", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "spike0" in text and "50 frames" in text and "frames 10..29" in text and "rgb0" in text
    img = read_image(out)
    assert img.shape == (6, 16, 3) and np.allclose(img[:, :8], 1.0) and np.allclose(img[:, 8:], 0.0)
    assert main(["spikes", str(tmp_path), "--out", str(tmp_path / "tfp.exr")]) == 0
    assert np.allclose(read_exr_channels(tmp_path / "tfp.exr")["R"][:, :8], 0.5)
    assert main(["spikes", str(tmp_path), "--camera", "nope"]) == 2
    assert "nope" in capsys.readouterr().out


def test_cli_bench_decode_runs_and_checks(capsys):
    from tools.__main__ import main

    assert main(["bench-decode", "--width", "16", "--height", "4", "--frames", "9", "--repeat", "1",
                 "--python-frames", "2"]) == 0
    text = capsys.readouterr().out
    for name in ("read_spikes", "bare np.unpackbits", "community per-frame", "pure-Python per-byte", "MB/s"):
        assert name in text
