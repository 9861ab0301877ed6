"""Spike streams in the raw Vidar ``.dat`` layout (see CAPTURE_FORMAT.md).

Layout: frames one after another, no header. A frame is ``height`` rows of
``head_cols + width`` bits; pixel ``k`` of the frame (row-major over the stored rows) is
bit ``k % 8`` of byte ``k // 8``, least significant bit first. Rows are stored bottom-up:
the first stored row is the bottom row of the image. ``flipud=True`` (the default) returns
images top-down (row 0 = top), the orientation every other part of the engine uses.

``head_cols``: some Vidar recordings carry extra columns at the *start* of every stored
row (a per-row header). They are dropped: the returned image is columns
``head_cols .. head_cols + width - 1`` of each stored row (its last ``width`` columns).
:func:`write_spikes` writes zeros there.

Decoding is fully vectorized (``np.memmap`` + ``np.unpackbits(bitorder="little")``) and
reads only the requested frames from disk.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..cameras import View
from ..errors import CaptureError
from .fileio import atomic_write

# frames decoded per unpackbits call (bounds temporary memory for long reads)
_CHUNK_BYTES = 32 << 20


def frame_bytes(height: int, width: int, head_cols: int = 0) -> int:
    """Bytes per stored frame. The frame's bit count must be a multiple of 8."""
    bits = int(height) * (int(width) + int(head_cols))
    if height <= 0 or width <= 0 or head_cols < 0:
        raise ValueError(f"bad spike frame size {width}x{height} (head_cols={head_cols})")
    if bits % 8:
        raise ValueError(f"a spike frame of {height} x {width + head_cols} = {bits} bits "
                         "is not a whole number of bytes")
    return bits // 8


def count_frames(path: str | Path, height: int, width: int, *, head_cols: int = 0,
                 allow_partial: bool = False) -> int:
    """Number of whole frames in a ``.dat`` file; CaptureError if the size is not whole frames."""
    path = Path(path)
    fb = _frame_bytes_checked(path, height, width, head_cols)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise CaptureError(path, "spike file does not exist") from None
    n, rest = divmod(size, fb)
    if rest and not allow_partial:
        raise CaptureError(
            path,
            f"spike file size {size} bytes is not a whole number of frames of {fb} bytes "
            f"({width}x{height}{f' + {head_cols} head columns' if head_cols else ''}): "
            f"{n} whole frames and {rest} bytes left over (damaged or wrong width/height?)",
        )
    return n


def _frame_bytes_checked(path: Path, height: int, width: int, head_cols: int) -> int:
    try:
        return frame_bytes(height, width, head_cols)
    except ValueError as exc:
        raise CaptureError(path, str(exc)) from None


def decode_frames(raw: np.ndarray, height: int, width: int, *, flipud: bool = True,
                  head_cols: int = 0, out: np.ndarray | None = None) -> np.ndarray:
    """Packed bytes (n * frame_bytes,) or (n, frame_bytes) -> uint8 (n, height, width) of 0/1."""
    fb = frame_bytes(height, width, head_cols)
    raw = np.asarray(raw, dtype=np.uint8).reshape(-1, fb)
    n = raw.shape[0]
    row_bits = width + head_cols
    if out is None and row_bits % 8 == 0 and head_cols % 8 == 0:
        # Byte-aligned rows (the usual case): drop head columns and flip rows in the packed
        # domain (8x less data), then one unpackbits writes the final array directly.
        packed = raw.reshape(n, height, row_bits // 8)[:, :, head_cols // 8:]
        if flipud:
            packed = packed[:, ::-1, :]
        return np.unpackbits(packed, axis=-1, bitorder="little")
    if out is None:
        out = np.empty((n, height, width), dtype=np.uint8)
    step = max(1, _CHUNK_BYTES // (fb * 8))
    for s in range(0, n, step):
        bits = np.unpackbits(raw[s:s + step], axis=1, bitorder="little")
        bits = bits.reshape(-1, height, width + head_cols)
        if head_cols:
            bits = bits[:, :, head_cols:]
        if flipud:
            bits = bits[:, ::-1, :]
        out[s:s + step] = bits
    return out


def encode_frames(spikes: np.ndarray, *, flipud: bool = True, head_cols: int = 0) -> np.ndarray:
    """uint8/bool (n, height, width) -> packed bytes (n, frame_bytes). Non-zero means a spike."""
    s = np.asarray(spikes)
    if s.ndim == 2:
        s = s[None]
    if s.ndim != 3:
        raise ValueError(f"spikes must be (n, height, width), got shape {s.shape}")
    n, h, w = s.shape
    fb = frame_bytes(h, w, head_cols)
    if flipud:
        s = s[:, ::-1, :]
    bits = s != 0
    if head_cols:
        bits = np.concatenate([np.zeros((n, h, head_cols), dtype=bool), bits], axis=2)
    return np.packbits(bits.reshape(n, -1), axis=1, bitorder="little").reshape(n, fb)


def read_spikes(path: str | Path, height: int, width: int, *, flipud: bool = True, head_cols: int = 0,
                start: int = 0, count: int | None = None, allow_partial: bool = False) -> np.ndarray:
    """Read frames ``start .. start+count-1`` of a Vidar ``.dat`` file.

    Returns uint8 (count, height, width) of 0/1, rows top-down when ``flipud`` (default).
    ``count=None`` reads to the end. A file that is not a whole number of frames raises
    CaptureError unless ``allow_partial`` (then the trailing partial frame is ignored).
    Reading past the end raises CaptureError.
    """
    path = Path(path)
    n = count_frames(path, height, width, head_cols=head_cols, allow_partial=allow_partial)
    fb = frame_bytes(height, width, head_cols)
    start = int(start)
    if count is None:
        count = n - start
    count = int(count)
    if start < 0 or count < 0 or start + count > n:
        raise CaptureError(path, f"frames {start}..{start + count - 1} requested but the file holds {n} frames")
    if count == 0:
        return np.zeros((0, height, width), dtype=np.uint8)
    mm = np.memmap(path, dtype=np.uint8, mode="r", offset=start * fb, shape=(count * fb,))
    try:
        return decode_frames(mm, height, width, flipud=flipud, head_cols=head_cols)
    finally:
        del mm


def write_spikes(path: str | Path, spikes: np.ndarray, *, flipud: bool = True, head_cols: int = 0,
                 append: bool = False) -> Path:
    """Write spikes (n, height, width; non-zero = spike) as a Vidar ``.dat`` file.

    The write is atomic (temporary file in the same folder, then ``os.replace``) unless
    ``append=True``, which appends frames to an existing file (for streamed writing).
    ``read_spikes`` + ``write_spikes`` round-trips a file byte for byte.
    """
    path = Path(path)
    packed = encode_frames(spikes, flipud=flipud, head_cols=head_cols)
    path.parent.mkdir(parents=True, exist_ok=True)
    if append:
        with open(path, "ab") as fh:
            fh.write(packed.tobytes())
        return path
    return atomic_write(path, lambda fh: fh.write(packed.tobytes()), fsync=False)


class SpikeStream:
    """A spike stream on disk with its timing; reads slices lazily through ``np.memmap``.

    Spike frame ``i`` is at time ``t0 + i / rate_hz`` (seconds). Time windows are
    half-open: ``[t_a, t_b)`` holds the frames whose time ``t`` satisfies ``t_a <= t < t_b``
    (a tolerance of 1e-6 frame absorbs float rounding), so consecutive windows partition
    the stream.

    ``num_frames``: if given, the stream uses the first ``num_frames`` frames; a file
    holding fewer raises CaptureError. ``camera`` / ``co_located_with`` are camera names,
    ``c2w`` the OpenGL camera-to-world pose, ``intrinsics`` an
    :class:`engine.cameras.Intrinsics` (both optional; they come from the capture).
    """

    def __init__(self, path: str | Path, width: int, height: int, rate_hz: float, t0: float = 0.0,
                 num_frames: int | None = None, camera: str | None = None,
                 co_located_with: str | None = None, c2w=None, intrinsics=None, *,
                 flipud: bool = True, head_cols: int = 0, allow_partial: bool = False):
        self.path = Path(path)
        self.width = int(width)
        self.height = int(height)
        self.rate_hz = float(rate_hz)
        self.t0 = float(t0)
        self.camera = camera
        self.co_located_with = co_located_with
        self.c2w = None if c2w is None else np.asarray(c2w, dtype=np.float64).reshape(4, 4)
        self.intrinsics = intrinsics
        self.flipud = flipud
        self.head_cols = int(head_cols)
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise CaptureError(self.path, f"spike stream rate_hz must be a positive number, got {rate_hz!r}")
        if not np.isfinite(self.t0):
            raise CaptureError(self.path, f"spike stream t0 must be finite, got {t0!r}")
        self._frame_bytes = _frame_bytes_checked(self.path, self.height, self.width, self.head_cols)
        on_disk = count_frames(self.path, self.height, self.width, head_cols=self.head_cols,
                               allow_partial=allow_partial)
        if num_frames is None:
            self.num_frames = on_disk
        else:
            num_frames = int(num_frames)
            if num_frames < 0 or num_frames > on_disk:
                raise CaptureError(self.path, f"num_frames is {num_frames} but the file holds {on_disk} frames")
            self.num_frames = num_frames

    # ------------------------------------------------------------------ timing
    def __len__(self) -> int:
        return self.num_frames

    def __repr__(self) -> str:
        return (f"SpikeStream({self.path.name!r}, {self.width}x{self.height}, {self.num_frames} frames "
                f"@ {self.rate_hz:g} Hz, t0={self.t0:g}, camera={self.camera!r})")

    @property
    def duration(self) -> float:
        """Seconds covered: ``num_frames / rate_hz``."""
        return self.num_frames / self.rate_hz

    @property
    def t_end(self) -> float:
        """Time just after the last frame: ``t0 + num_frames / rate_hz``."""
        return self.t0 + self.duration

    @property
    def times(self) -> np.ndarray:
        """float64 (num_frames,): time of each spike frame."""
        return self.t0 + np.arange(self.num_frames, dtype=np.float64) / self.rate_hz

    def frame_index(self, t: float) -> int:
        """Index of the frame nearest to time ``t``, clipped to the stream."""
        i = int(np.floor((float(t) - self.t0) * self.rate_hz + 0.5))
        return min(max(i, 0), max(self.num_frames - 1, 0))

    def _bound(self, t: float) -> int:
        """First frame index whose time is >= t (clipped to [0, num_frames])."""
        x = (float(t) - self.t0) * self.rate_hz
        i = int(np.ceil(x - 1e-6))
        return min(max(i, 0), self.num_frames)

    def index_range(self, t_a: float, t_b: float) -> tuple[int, int]:
        """(start, stop) frame indices of the half-open window ``[t_a, t_b)``."""
        a, b = self._bound(t_a), self._bound(t_b)
        return a, max(a, b)

    # ------------------------------------------------------------------ data
    def read(self, start: int = 0, count: int | None = None) -> np.ndarray:
        """uint8 (count, height, width) frames ``start .. start+count-1`` (top-down rows)."""
        if count is None:
            count = self.num_frames - start
        if start < 0 or count < 0 or start + count > self.num_frames:
            raise CaptureError(self.path,
                               f"frames {start}..{start + count - 1} requested; the stream has {self.num_frames}")
        if count == 0:
            return np.zeros((0, self.height, self.width), dtype=np.uint8)
        fb = self._frame_bytes
        mm = np.memmap(self.path, dtype=np.uint8, mode="r", offset=start * fb, shape=(count * fb,))
        try:
            return decode_frames(mm, self.height, self.width, flipud=self.flipud, head_cols=self.head_cols)
        finally:
            del mm

    def frames_between(self, t_a: float, t_b: float) -> tuple[np.ndarray, np.ndarray]:
        """Frames in ``[t_a, t_b)``: (uint8 (n, H, W), float64 times (n,)). Reads only that slice."""
        a, b = self.index_range(t_a, t_b)
        return self.read(a, b - a), self.t0 + np.arange(a, b, dtype=np.float64) / self.rate_hz

    def window_counts(self, t_a: float, t_b: float) -> np.ndarray:
        """float32 [H, W]: number of spikes per pixel in ``[t_a, t_b)``."""
        a, b = self.index_range(t_a, t_b)
        out = np.zeros((self.height, self.width), dtype=np.float32)
        if b <= a:
            return out
        fb = self._frame_bytes
        step = max(1, _CHUNK_BYTES // (fb * 8))
        acc = np.zeros((self.height, self.width), dtype=np.int64)
        for s in range(a, b, step):
            acc += self.read(s, min(step, b - s)).sum(axis=0, dtype=np.int64)
        out[:] = acc
        return out

    def view(self, t: float):
        """The spike camera as an :class:`engine.cameras.View` at time ``t`` (needs c2w + intrinsics)."""

        if self.c2w is None or self.intrinsics is None:
            raise ValueError(f"spike stream {self.path} has no pose/intrinsics attached")
        return View(self.intrinsics, self.c2w.copy(), float(t), self.camera or self.path.stem,
                    {"spike_stream": str(self.path)})
