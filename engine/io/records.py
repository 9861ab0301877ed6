"""Strict checks of the JSON records of a capture or camera file.

Every problem is a :class:`engine.errors.CaptureError` naming the file and the key path
inside it (``frames[3].fl_x: must be positive, got -1``). :func:`parse_intrinsics` is the
one intrinsics parser of the engine (captures and camera files alike).
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from ..cameras import Intrinsics
from ..errors import CaptureError

_IMAGE_SUFFIXES = (".png", ".exr", ".jpg", ".jpeg")


def read_json(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CaptureError(path, "file does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CaptureError(path, f"cannot read: {exc}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CaptureError(path, f"malformed JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}") from None
    if not isinstance(data, dict):
        raise CaptureError(path, f"top level must be a JSON object, got {type(data).__name__}")
    return data


class CheckContext:
    """Error context: the file being read."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, where: str, problem: str):
        raise CaptureError(self.path, f"{where}: {problem}" if where else problem)

    def get(self, d: dict, key: str, where: str):
        if not isinstance(d, dict):
            self.fail(where, f"must be a JSON object, got {type(d).__name__}")
        if key not in d:
            self.fail(where, f"missing key {key!r}")
        return d[key]

    def num(self, value, where: str, *, positive: bool = False, integer: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(where, f"must be a number, got {value!r}")
        v = float(value)
        if not math.isfinite(v):
            self.fail(where, f"must be a finite number, got {value!r}")
        if positive and v <= 0:
            self.fail(where, f"must be positive, got {value!r}")
        if integer:
            if v != int(v):
                self.fail(where, f"must be a whole number, got {value!r}")
            return int(v)
        return v

    def matrix(self, value, where: str) -> np.ndarray:
        try:
            m = np.array(value, dtype=np.float64)
        except (TypeError, ValueError):
            self.fail(where, "must be a 4x4 matrix of numbers (rows of 4)")
        if m.shape != (4, 4):
            self.fail(where, f"must be a 4x4 matrix, got shape {m.shape}")
        if not np.all(np.isfinite(m)):
            self.fail(where, "contains non-finite numbers (NaN or inf)")
        return m

    def string(self, value, where: str) -> str:
        if not isinstance(value, str) or not value:
            self.fail(where, f"must be a non-empty string, got {value!r}")
        return value

    def list_of(self, data: dict, key: str, *, required: bool) -> list:
        if key not in data:
            if required:
                self.fail("", f"missing key {key!r}")
            return []
        v = data[key]
        if not isinstance(v, list):
            self.fail(key, f"must be a list, got {type(v).__name__}")
        return v


def check_intrinsics(ctx: CheckContext, d: dict, where: str, defaults: dict | None = None,
                size_from=None) -> Intrinsics:
    """Intrinsics from fl_x/fl_y/cx/cy/w/h (or camera_angle_x/y), falling back to ``defaults``."""
    src = dict(defaults or {})
    src.update({k: v for k, v in d.items() if k in ("w", "h", "fl_x", "fl_y", "cx", "cy",
                                                     "camera_angle_x", "camera_angle_y")})
    if "w" not in src or "h" not in src:
        if size_from is None:
            ctx.fail(where, "missing key 'w'" if "w" not in src else "missing key 'h'")
        w, h = size_from()
    else:
        w = ctx.num(src["w"], f"{where}.w", positive=True, integer=True)
        h = ctx.num(src["h"], f"{where}.h", positive=True, integer=True)
    if "fl_x" in src:
        fx = ctx.num(src["fl_x"], f"{where}.fl_x", positive=True)
    elif "camera_angle_x" in src:
        ang = ctx.num(src["camera_angle_x"], f"{where}.camera_angle_x", positive=True)
        fx = 0.5 * w / math.tan(0.5 * ang)
    else:
        ctx.fail(where, "missing key 'fl_x' (or 'camera_angle_x')")
    if "fl_y" in src:
        fy = ctx.num(src["fl_y"], f"{where}.fl_y", positive=True)
    elif "camera_angle_y" in src:
        fy = 0.5 * h / math.tan(0.5 * ctx.num(src["camera_angle_y"], f"{where}.camera_angle_y", positive=True))
    else:
        fy = fx
    cx = ctx.num(src["cx"], f"{where}.cx") if "cx" in src else w / 2.0
    cy = ctx.num(src["cy"], f"{where}.cy") if "cy" in src else h / 2.0
    return Intrinsics(int(w), int(h), float(fx), float(fy), float(cx), float(cy))


def parse_intrinsics(d: dict, where: str, path, defaults: dict | None = None, size_from=None) -> Intrinsics:
    """Intrinsics of a camera record (``w, h, fl_x[, fl_y, cx, cy]`` or ``camera_angle_x``),
    checked strictly: a missing or non-numeric field is a :class:`CaptureError` naming
    ``path`` and ``where`` (the key path inside the file)."""
    return check_intrinsics(CheckContext(Path(path)), d, where, defaults, size_from)


def resolve_image(ctx: CheckContext, root: Path, file_path: str, where: str, *, try_suffixes: bool) -> Path:
    p = Path(os.path.normpath(root / file_path))  # root is absolute; no per-file realpath
    if p.is_file():
        return p
    if try_suffixes and p.suffix.lower() not in _IMAGE_SUFFIXES:
        for suf in (".png", ".exr"):
            q = p.with_name(p.name + suf)
            if q.is_file():
                return q
        ctx.fail(where, f"image file {file_path!r} does not exist (tried {p.name}.png and {p.name}.exr in {p.parent})")
    ctx.fail(where, f"image file {file_path!r} does not exist ({p})")
