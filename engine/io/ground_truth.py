"""Ground truth a synthetic capture may carry (CAPTURE_FORMAT: ``depth_file_path`` and the
``ground_truth`` block; written by scripts/make_capture.py, parsed by engine.io.capture).

* :func:`load_depth` — a frame's planar depth EXR (metres along the viewing axis; ``inf``
  where no surface is);
* :func:`parse_depth_path`, :func:`parse_ground_truth` — the transforms.json records, checked;
* :class:`ObjectTruth` — moving objects' object-to-world matrices at ``rate_hz`` and
  surface samples in object space (:meth:`ObjectTruth.load`, :func:`points_at`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..cameras import Intrinsics
from ..errors import CaptureError
from . import images


@dataclass
class ObjectTruth:
    """``ground_truth.objects``: moving objects' object-to-world matrices at ``rate_hz`` from
    ``t0`` and surface samples in object space, in an npz (read with :meth:`load`)."""

    path: Path
    rate_hz: float
    t0: float
    names: list[str]

    def load(self) -> dict[str, np.ndarray]:
        """``times`` float64 [T]; per name ``<name>`` float64 [T, 4, 4] and ``<name>_points``
        float32 [P, 3]. Shapes and finiteness are checked (CaptureError naming the npz)."""
        try:
            with np.load(self.path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except FileNotFoundError:
            raise CaptureError(self.path, "ground-truth objects file does not exist") from None
        except Exception as exc:
            raise CaptureError(self.path, f"cannot read ground-truth objects npz: {exc}") from None
        if "times" not in data:
            raise CaptureError(self.path, "missing array 'times'")
        times = np.asarray(data["times"], np.float64)
        if times.ndim != 1 or len(times) == 0 or not np.all(np.isfinite(times)):
            raise CaptureError(self.path, f"'times' must be a non-empty finite [T] array, got shape {times.shape}")
        out = {"times": times}
        for name in self.names:
            for key, shape in ((name, (len(times), 4, 4)), (f"{name}_points", (None, 3))):
                if key not in data:
                    raise CaptureError(self.path, f"missing array {key!r} (object {name!r} is listed in names)")
                a = np.asarray(data[key], np.float64 if key == name else np.float32)
                if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
                    want = "x".join("P" if s is None else str(s) for s in shape)
                    raise CaptureError(self.path, f"array {key!r} has shape {a.shape}, expected {want}")
                if not np.all(np.isfinite(a)):
                    raise CaptureError(self.path, f"array {key!r} contains non-finite numbers")
                out[key] = a
        return out


@dataclass
class GroundTruth:
    """The optional ``ground_truth`` block of transforms.json."""

    objects: ObjectTruth | None = None


def load_depth(path: str | Path, intrinsics: Intrinsics | None = None) -> np.ndarray:
    """float32 [H, W] planar depth from a ground-truth depth EXR (channel ``Z``, or its only
    channel); > 1e9 and non-finite values become ``inf`` (no surface)."""
    path = Path(path)
    chans = images.read_exr_channels(path)
    if "Z" in chans:
        z = chans["Z"]
    elif len(chans) == 1:
        z = next(iter(chans.values()))
    else:
        raise CaptureError(path, f"depth EXR has no 'Z' channel; channels are {sorted(chans)}")
    z = np.array(z, dtype=np.float32)
    if intrinsics is not None and z.shape != (intrinsics.height, intrinsics.width):
        raise CaptureError(path, f"depth is {z.shape[1]}x{z.shape[0]} pixels but the camera expects "
                                 f"{intrinsics.width}x{intrinsics.height}")
    if np.any(np.isnan(z)):
        raise CaptureError(path, f"depth contains NaN in {int(np.isnan(z).sum())} pixel(s)")
    if np.any(z[np.isfinite(z)] <= 0):
        raise CaptureError(path, "depth must be positive (planar depth in metres; inf where no surface)")
    z[~(z <= 1e9)] = np.inf
    return z


def pose_at(times: np.ndarray, mats: np.ndarray, t: float | np.ndarray) -> np.ndarray:
    """Object-to-world matrices ``mats`` [T, 4, 4] sampled at ``times`` [T], at time(s) ``t``:
    float64 [4, 4] (scalar t) or [N, 4, 4], linearly interpolated between the two nearest
    samples (1 kHz in the generator: the chord error of a rotation is below a millimetre
    there); times outside are clamped."""
    times = np.asarray(times, np.float64)
    tq = np.clip(np.atleast_1d(np.asarray(t, dtype=np.float64)), times[0], times[-1])
    if len(times) > 1:
        i1 = np.clip(np.searchsorted(times, tq, side="right"), 1, len(times) - 1)
    else:
        i1 = np.zeros(len(tq), int)
    i0 = np.maximum(i1 - 1, 0)
    span = np.where(times[i1] > times[i0], times[i1] - times[i0], 1.0)
    w = np.clip((tq - times[i0]) / span, 0.0, 1.0)[:, None, None]
    out = (1.0 - w) * mats[i0] + w * mats[i1]
    return out[0] if np.ndim(t) == 0 else out


def points_at(truth: dict[str, np.ndarray], name: str, t: float | np.ndarray) -> np.ndarray:
    """World positions of object ``name``'s surface samples at time(s) ``t``: float64 [P, 3]
    (scalar t) or [N, P, 3]. ``truth`` is :meth:`ObjectTruth.load`'s dict; the poses are
    :func:`pose_at`'s."""
    pts = np.concatenate([truth[f"{name}_points"].astype(np.float64),
                          np.ones((len(truth[f"{name}_points"]), 1))], axis=1)
    mats = pose_at(truth["times"], truth[name], np.atleast_1d(np.asarray(t, dtype=np.float64)))
    out = np.einsum("nij,pj->npi", mats, pts)[..., :3]
    return out[0] if np.ndim(t) == 0 else out


def parse_depth_path(ctx, root: Path, d: dict, where: str) -> Path | None:
    """A frame record's ``depth_file_path`` (absolute; None when absent), checked to exist.
    ``ctx``: the capture's :class:`engine.io.records.CheckContext` (errors name its file)."""
    if "depth_file_path" not in d:
        return None
    dfp = ctx.string(d["depth_file_path"], f"{where}.depth_file_path")
    depth = Path(os.path.normpath(root / dfp))
    if not depth.is_file():
        ctx.fail(f"{where}.depth_file_path", f"depth file {dfp!r} does not exist ({depth})")
    return depth


def parse_ground_truth(ctx, root: Path, gt) -> GroundTruth:
    """The ``ground_truth`` block of transforms.json, checked (files exist, types)."""
    if not isinstance(gt, dict):
        ctx.fail("ground_truth", f"must be an object, got {type(gt).__name__}")
    out = GroundTruth()
    if "objects" in gt:
        where = "ground_truth.objects"
        o = gt["objects"]
        fp = ctx.string(ctx.get(o, "file_path", where), f"{where}.file_path")
        path = Path(os.path.normpath(root / fp))
        if not path.is_file():
            ctx.fail(f"{where}.file_path", f"ground-truth objects file {fp!r} does not exist ({path})")
        rate = ctx.num(ctx.get(o, "rate_hz", where), f"{where}.rate_hz", positive=True)
        t0 = ctx.num(o.get("t0", 0.0), f"{where}.t0")
        names = ctx.get(o, "names", where)
        if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
            ctx.fail(f"{where}.names", f"must be a list of non-empty strings, got {names!r}")
        if len(set(names)) != len(names) or "times" in names:
            ctx.fail(f"{where}.names", f"must be distinct and not 'times', got {names!r}")
        out.objects = ObjectTruth(path, rate, t0, list(names))
    return out
