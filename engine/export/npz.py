"""The compact per-time cache of a trained run (``python -m engine export``).

:func:`export_npz` samples a :class:`engine.scene.model.Scene4D` at given instants and
stores each attribute that changes over time as a float16 residual from the canonical
state where that round-trips within tolerance; :func:`read_export` reads it back.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..errors import RunError
from ..scene.gaussians import num_sh_bases
from ..scene.model import Scene4D


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().to("cpu", torch.float32).numpy()


EXPORT_VERSION = 1
_F16_MAX = 60000.0


def _residual(values: np.ndarray, base: np.ndarray, tol: float):
    """float16 residual from ``base`` where it round-trips within ``tol``, else float32 values."""
    r = values - base[None]
    if np.all(np.isfinite(r)) and np.abs(r).max(initial=0) < _F16_MAX:
        r16 = r.astype(np.float16)
        err = np.abs(r16.astype(np.float32) - r).max(initial=0)
        if err <= tol:
            return r16, "residual_f16"
    return values.astype(np.float32), "absolute_f32"


def export_npz(scene: Scene4D, times, path) -> Path:
    """Write Gaussians at each of ``times`` to a compact .npz.

    Keys: ``version``, ``times`` [T], canonical ``means, quats, scales, opacities, colors, sh``
    (float32, at the canonical / static state), and per attribute that changes over time
    ``<name>_t`` [T, N, ...] with ``<name>_mode`` = "residual_f16" (add to the canonical
    array) or "absolute_f32". Attributes the deformation never changes have no ``_t`` entry.
    """
    path = Path(path)
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    with torch.no_grad():
        g = scene.model.gaussians
        canon = {"means": _np(g.means), "quats": _np(g.quats / g.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)),
                 "scales": _np(g.scales), "opacities": _np(g.opacities), "colors": _np(g.colors().clamp(0, 1))}
    arrays = {"version": np.array(EXPORT_VERSION), "times": times.astype(np.float32),
              "time_range": np.asarray(scene.time_range, np.float32),
              "sh": _np(g.sh[:, : num_sh_bases(g.active_sh_degree)]), **canon}
    extent = float(np.ptp(canon["means"], axis=0).max()) if len(canon["means"]) else 1.0
    tols = {"means": 1e-3 * max(extent, 1e-6), "quats": 2e-3, "scales": 1e-3 * max(extent, 1e-6),
            "opacities": 2e-3, "colors": 2e-3}
    per_time = {k: [] for k in canon}
    for t in times:
        a = scene.gaussians_at(float(t))
        for k in canon:
            per_time[k].append(a[k])
    for k, seq in per_time.items():
        stack = np.stack(seq) if len(seq) else np.zeros((0,) + canon[k].shape, np.float32)
        if stack.size and np.array_equal(stack, np.broadcast_to(canon[k], stack.shape)):
            continue
        data, mode = _residual(stack, canon[k], tols[k])
        arrays[f"{k}_t"] = data
        arrays[f"{k}_mode"] = np.array(mode)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(path)
    return path


def read_export(path, index: int | None = None) -> dict:
    """Read an export; with ``index`` return the Gaussians at ``times[index]`` (float32)."""
    path = Path(path)
    if not path.exists():
        raise RunError(path, "export file does not exist")
    try:
        z = np.load(path, allow_pickle=False)
        data = {k: z[k] for k in z.files}
    except Exception as exc:
        raise RunError(path, f"unreadable export: {exc}") from exc
    if index is None:
        return data
    out = {}
    for k in ("means", "quats", "scales", "opacities", "colors"):
        if f"{k}_t" in data:
            mode = str(data[f"{k}_mode"])
            v = data[f"{k}_t"][index].astype(np.float32)
            out[k] = v + data[k] if mode == "residual_f16" else v
        else:
            out[k] = data[k].astype(np.float32)
    out["time"] = float(data["times"][index])
    return out
