"""Gaussians as PLY files in the original 3D Gaussian Splatting layout (what splat viewers,
editors and game-engine importers read), one file per instant, via ``plyfile``.

One vertex per Gaussian, float32, binary little-endian, properties in 3DGS's order
(``GaussianModel.construct_list_of_attributes``)::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_{3(K-1)-1}
    opacity  scale_0 scale_1 scale_2  rot_0 rot_1 rot_2 rot_3

``opacity`` is the logit, ``scale_*`` are logs, ``rot_*`` is w x y z, ``f_dc`` the SH DC
coefficient (colour = 0.5 + 0.2820948 * f_dc), and ``f_rest`` is channel-major as 3DGS
flattens ``features_rest.transpose(1, 2)``: ``f_rest_{c * (K-1) + j}`` is coefficient j+1 of
channel c. Normals are zero (3DGS writes zeros too).

A sequence is ``DIR/frame_000000.ply ...`` plus ``DIR/index.json`` (times, counts, the
coordinate convention). Every file is written atomically (a temporary file renamed in).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from ..errors import RunError
from ..io.fileio import atomic_path, atomic_write
from .splats import check_splats, sh_degree_of

INDEX_NAME = "index.json"
INDEX_FORMAT = "bullettime4d-ply-sequence"
INDEX_VERSION = 1
FRAME_PATTERN = "frame_{:06d}.ply"
COORDINATES = {
    "world": "capture world = Blender world: right-handed, +Z up, metres",
    "up_axis": "+Z",
    "rotation": "quaternion w x y z (rot_0..rot_3), object to world",
    "colour": "sRGB-encoded display colour = max(0, 0.5 + SH(dir)), dir = mean - camera centre",
}


class PlyFormatError(RunError):
    """A PLY file or sequence index is missing, unreadable or lacks a property."""



def property_names(num_rest: int) -> list[str]:
    """3DGS's vertex properties for ``num_rest`` f_rest values (= 3 * (K-1))."""
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(num_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def splats_to_vertex_array(s: dict) -> np.ndarray:
    """Splat dict -> structured float32 array with 3DGS's fields (see module doc)."""
    n = check_splats(s)
    sh = np.asarray(s["sh"], np.float32)
    rest = sh[:, 1:].transpose(0, 2, 1).reshape(n, -1)  # [N, 3*(K-1)], channel-major
    cols = np.concatenate([
        np.asarray(s["means"], np.float32), np.zeros((n, 3), np.float32), sh[:, 0], rest,
        np.asarray(s["opacity_logits"], np.float32)[:, None], np.asarray(s["log_scales"], np.float32),
        np.asarray(s["quats"], np.float32)], axis=1)
    names = property_names(rest.shape[1])
    out = np.empty(n, dtype=[(p, "<f4") for p in names])
    for i, p in enumerate(names):
        out[p] = cols[:, i]
    return out


def write_ply(path, splats: dict) -> Path:
    """Write one instant as a binary little-endian 3DGS PLY (atomically)."""
    el = PlyElement.describe(splats_to_vertex_array(splats), "vertex")
    data = PlyData([el], text=False, byte_order="<")
    return atomic_write(path, data.write, fsync=False)


def read_ply(path) -> dict:
    """Read a 3DGS PLY -> splat dict. PlyFormatError naming the file and any missing property."""
    path = Path(path)
    if not path.is_file():
        raise PlyFormatError(path, "PLY file does not exist")
    try:
        ply = PlyData.read(str(path))
    except Exception as exc:  # plyfile raises several types on torn / foreign files
        raise PlyFormatError(path, f"unreadable PLY: {exc.__class__.__name__}: {exc}") from exc
    if "vertex" not in ply:
        raise PlyFormatError(path, "no 'vertex' element")
    v = ply["vertex"].data
    present = set(v.dtype.names or ())
    num_rest = sum(1 for p in present if p.startswith("f_rest_"))
    if num_rest % 3 or (num_rest // 3 + 1) not in (1, 4, 9, 16):
        raise PlyFormatError(path, f"{num_rest} f_rest properties is not 3 * ((degree+1)^2 - 1) for an SH degree 0..3")
    needed = [p for p in property_names(num_rest) if p not in ("nx", "ny", "nz")]
    missing = [p for p in needed if p not in present]
    if missing:
        raise PlyFormatError(path, f"missing vertex propert{'y' if len(missing) == 1 else 'ies'} {', '.join(missing)}")
    col = lambda names: np.stack([np.asarray(v[p], np.float32) for p in names], axis=1)  # noqa: E731
    n, k = len(v), num_rest // 3 + 1
    sh = np.empty((n, k, 3), np.float32)
    sh[:, 0] = col(["f_dc_0", "f_dc_1", "f_dc_2"])
    if k > 1:
        sh[:, 1:] = col([f"f_rest_{i}" for i in range(num_rest)]).reshape(n, 3, k - 1).transpose(0, 2, 1)
    out = {"means": col(["x", "y", "z"]), "quats": col([f"rot_{i}" for i in range(4)]),
           "log_scales": col([f"scale_{i}" for i in range(3)]), "opacity_logits": np.asarray(v["opacity"], np.float32),
           "sh": sh}
    if not all(np.all(np.isfinite(a)) for a in out.values()):
        raise PlyFormatError(path, "non-finite values (nan/inf) in the Gaussians")
    return out


def write_sequence(out_dir, times, splats_of_time, *, fps: float | None = None, source: str | None = None,
                   background=None, progress=None) -> Path:
    """Write ``DIR/frame_000000.ply ...`` for each of ``times`` plus ``DIR/index.json``.

    ``splats_of_time(t) -> splat dict`` supplies each instant. The index is written last, so
    a sequence whose index exists is complete. Returns the index path.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    times = [float(t) for t in np.asarray(times, np.float64).reshape(-1)]
    if not times:
        raise PlyFormatError(out_dir, "no instants to export")
    frames = []
    for i, t in enumerate(times):
        s = splats_of_time(t)
        name = FRAME_PATTERN.format(i)
        write_ply(out_dir / name, s)
        frames.append({"file": name, "time": t, "count": int(np.shape(s["means"])[0]),
                       "sh_degree": sh_degree_of(s["sh"])})
        if progress is not None:
            progress(i + 1, len(times))
    index = {"format": INDEX_FORMAT, "version": INDEX_VERSION, "layout": "3dgs",
             "fps": None if fps is None else float(fps), "num_frames": len(frames),
             "time_range": [times[0], times[-1]], "coordinates": COORDINATES,
             "background": None if background is None else [float(b) for b in background],
             "source": source, "frames": frames}
    path = out_dir / INDEX_NAME
    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(index, indent=1) + "\n")
    return path


def read_index(path) -> dict:
    """Read a sequence's ``index.json`` (a folder or the file). PlyFormatError if unusable."""
    path = Path(path)
    if path.is_dir():
        path = path / INDEX_NAME
    if not path.is_file():
        raise PlyFormatError(path, "PLY sequence index does not exist")
    try:
        index = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise PlyFormatError(path, f"unreadable index: {exc}") from exc
    if not isinstance(index, dict) or index.get("format") != INDEX_FORMAT:
        raise PlyFormatError(path, f"not a {INDEX_FORMAT} index")
    if int(index.get("version", 0)) > INDEX_VERSION:
        raise PlyFormatError(path, f"index version {index.get('version')} is newer than this engine reads "
                                   f"({INDEX_VERSION})")
    frames = index.get("frames")
    if not isinstance(frames, list) or not all(isinstance(f, dict) and "file" in f and "time" in f for f in frames):
        raise PlyFormatError(path, "'frames' must be a list of {file, time, count}")
    return index


def read_sequence_frame(index_path, i: int) -> dict:
    """Splats of frame ``i`` of a sequence (by its index)."""
    index_path = Path(index_path)
    folder = index_path if index_path.is_dir() else index_path.parent
    frames = read_index(index_path)["frames"]
    return read_ply(folder / frames[i]["file"])
