"""``python -m tools bench-decode``: spike-stream decode speed, ours vs the usual loaders.

Writes a synthetic Vidar ``.dat`` (default 400x250, 2000 frames) into a temporary folder
and decodes it, in one run, with

* ``read_spikes``  — this engine: ``np.memmap`` + ``np.unpackbits(bitorder="little")`` +
  row flip, in bounded chunks;
* bare ``np.unpackbits`` on the bytes already in memory (a lower bound: no file access,
  no flip, no copy into the output layout);
* the community's per-frame loader (as in SpikeCV / spikingjelly ``load_vidar_dat``):
  for every frame slice its bytes, build the 8 bit-planes with numpy shift/and, stack,
  transpose, reshape and flip;
* a per-byte pure-Python loop (for every frame ``f.read`` its bytes and loop over bytes
  and bits in Python), timed on a few frames and scaled to the whole stream.

All decoders are checked to give identical frames. Throughput is packed input megabytes
(10^6 bytes) per second; the file is freshly written, so it sits in the page cache and
this measures decoding, not the disk.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from engine.io.spikes import read_spikes, write_spikes

HELP = "benchmark spike .dat decoding: read_spikes vs per-frame loaders vs bare np.unpackbits"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--width", type=int, default=400)
    parser.add_argument("--height", type=int, default=250)
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--python-frames", type=int, default=4,
                        help="frames decoded by the pure-Python per-byte loop (scaled to --frames)")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs per method (best is kept)")
    parser.add_argument("--density", type=float, default=0.2, help="fraction of pixels firing per frame")
    parser.add_argument("--seed", type=int, default=0)


def community_load_vidar(path: Path, height: int, width: int, frame_cnt: int | None = None) -> np.ndarray:
    """The widely copied per-frame loader (SpikeCV / spikingjelly ``load_vidar_dat`` style)."""
    array = np.fromfile(path, dtype=np.uint8)
    len_per_frame = height * width // 8
    framecnt = frame_cnt if frame_cnt is not None else len(array) // len_per_frame
    spikes = []
    for i in range(framecnt):
        compr_frame = array[i * len_per_frame:(i + 1) * len_per_frame]
        blist = []
        for b in range(8):
            blist.append(np.right_shift(np.bitwise_and(compr_frame, np.left_shift(1, b)), b))
        frame_ = np.stack(blist).transpose()
        frame_ = np.flipud(frame_.reshape((height, width), order="C"))
        spikes.append(frame_)
    return np.array(spikes).astype(np.uint8)


def python_loop_load(path: Path, height: int, width: int, frame_cnt: int) -> np.ndarray:
    """Per-frame ``read`` + a Python loop over bytes and bits (the naive reference decoder)."""
    fb = height * width // 8
    out = np.zeros((frame_cnt, height, width), dtype=np.uint8)
    with open(path, "rb") as fh:
        for i in range(frame_cnt):
            data = fh.read(fb)
            frame = [0] * (height * width)
            for j, byte in enumerate(data):
                if byte:
                    for b in range(8):
                        if byte >> b & 1:
                            frame[8 * j + b] = 1
            out[i] = np.array(frame, dtype=np.uint8).reshape(height, width)[::-1]
    return out


def best_of(fn, repeat: int):
    best, result = float("inf"), None
    for _ in range(max(1, repeat)):
        t = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t)
    return best, result


def main(args) -> int:
    h, w, n = args.height, args.width, args.frames
    if (h * w) % 8:
        print(f"error: {w}x{h} is not a whole number of bytes per frame")
        return 2
    fb = h * w // 8
    mb = n * fb / 1e6
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory(prefix="bt4d_bench_") as tmp:
        path = Path(tmp) / "synthetic.dat"
        for s in range(0, n, 256):  # write in chunks: the unpacked stream can be large
            chunk = (rng.random((min(256, n - s), h, w)) < args.density).astype(np.uint8)
            write_spikes(path, chunk, append=True)
        raw = np.fromfile(path, dtype=np.uint8)
        print(f"decoding {n} frames of {w}x{h} ({mb:.1f} MB packed, {n * h * w / 1e6:.0f} MB unpacked), "
              f"best of {args.repeat}")

        rows = []
        t_ours, ours = best_of(lambda: read_spikes(path, h, w), args.repeat)
        rows.append(("read_spikes (memmap + unpackbits + flip)", t_ours, n))
        t_bare, bare = best_of(lambda: np.unpackbits(raw, bitorder="little"), args.repeat)
        rows.append(("bare np.unpackbits (bytes in memory)", t_bare, n))
        assert np.array_equal(bare.reshape(n, h, w)[:, ::-1], ours)
        del bare
        t_comm, comm = best_of(lambda: community_load_vidar(path, h, w), max(1, args.repeat - 1))
        rows.append(("community per-frame loader (8 bit-planes)", t_comm, n))
        assert np.array_equal(comm, ours), "community loader disagrees with read_spikes"
        del comm
        k = max(1, min(args.python_frames, n))
        t_py, py = best_of(lambda: python_loop_load(path, h, w, k), 1)
        assert np.array_equal(py, ours[:k]), "pure-Python loader disagrees with read_spikes"
        rows.append((f"pure-Python per-byte loop ({k} frames, scaled)", t_py * n / k, k))

    print(f"{'method':<48}{'seconds':>10}{'MB/s':>10}{'x slower than ours':>20}")
    for name, t, _ in rows:
        print(f"{name:<48}{t:>10.4f}{mb / t:>10.1f}{t / t_ours:>20.2f}")
    print(f"read_spikes is {t_comm / t_ours:.1f}x faster than the community per-frame loader and "
          f"{t_py * n / k / t_ours:.0f}x faster than the per-byte Python loop; bare np.unpackbits "
          f"is {t_ours / t_bare:.1f}x faster than read_spikes (no file access, flip or output layout).")
    return 0
