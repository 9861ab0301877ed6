"""Open a result from either form: a run directory (checkpoint) or a compact 4D cache file.

:func:`load_result` is what the CLI (``eval``, ``render``, ``export``) and Blender's Load
Result call. A compact cache (``compact.py``) comes back as a :class:`CachedScene`, which
has the parts of ``Scene4D``'s interface that sampling and rendering use: ``time_range``,
``num_gaussians``, ``background``, ``info``, ``gaussians_at(t)``, ``splats_at(t)``,
``render(views)``. Between stored instants it interpolates linearly (``CompactCache.splats_at``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import RunError
from ..scene.gaussians import SH_C0
from ..scene.model import Scene4D, default_device, load_run, view_tensors
from .compact import MAGIC, CompactFormatError, read_compact
from .splats import render_splats, splats_at


def is_compact_cache(path) -> bool:
    """True when ``path`` is a file starting with the compact cache's magic bytes."""
    path = Path(path)
    if not path.is_file():
        return False
    with open(path, "rb") as fh:
        return fh.read(len(MAGIC)) == MAGIC


class CachedScene:
    """A compact cache, sampled and rendered like a trained run (numpy interface)."""

    def __init__(self, path, device="cpu"):
        self.cache = read_compact(path)
        self.path = Path(path)
        self.run_dir = self.path  # where a run's files would be; the cache itself
        meta = self.cache.meta
        self.info = {**(meta.get("run_info") or {}), "capture": meta.get("capture"), "source": meta.get("source"),
                     "time_range": [float(self.cache.times[0]), float(self.cache.times[-1])],
                     "compact_cache": str(path)}
        self.time_range = (float(self.cache.times[0]), float(self.cache.times[-1]))
        self.background = tuple(float(b) for b in meta.get("background", (0.0, 0.0, 0.0)))
        self.near_plane = float(meta.get("near_plane", 0.01))
        self.device = default_device(device)

    @property
    def num_gaussians(self) -> int:
        return self.cache.num_gaussians

    def splats_at(self, t: float) -> dict:
        return self.cache.splats_at(float(t))

    def gaussians_at(self, t: float) -> dict:
        """As ``Scene4D.gaussians_at``: means, quats (unit wxyz), scales (linear), opacities,
        colors (sRGB-encoded from the DC term, in [0, 1]), sh [N,K,3]."""
        s = self.splats_at(t)
        q = s["quats"] / np.maximum(np.linalg.norm(s["quats"], axis=1, keepdims=True), 1e-12)
        return {"means": s["means"], "quats": q.astype(np.float32), "scales": np.exp(s["log_scales"]),
                "opacities": (1.0 / (1.0 + np.exp(-s["opacity_logits"]))).astype(np.float32),
                "colors": np.clip(0.5 + SH_C0 * s["sh"][:, 0], 0.0, 1.0).astype(np.float32), "sh": s["sh"]}

    # K evenly spaced samples for Blender's Load Result: the same code as a run's
    sample = Scene4D.sample

    def render(self, views, background=None, time: float | None = None, fill_holes: bool = False) -> list[dict]:
        """Render each View at its own time (or ``time``): rgb [H,W,3], alpha, depth
        (``fill_holes`` as in ``Scene4D.render``)."""
        bg = self.background if background is None else background
        return [render_splats(self.splats_at(v.time if time is None else time), view_tensors(v, self.device), bg,
                              self.near_plane, fill_holes=fill_holes) for v in views]


def load_result(path, device="cpu"):
    """A run directory -> ``Scene4D``; a compact cache file -> :class:`CachedScene`.

    RunError naming the path when it is neither (or a CompactFormatError for a damaged cache).
    """
    path = Path(path)
    if path.is_file():
        if not is_compact_cache(path):
            raise RunError(path, "neither a run directory nor a BulletTime4D compact cache (.bt4c)")
        return CachedScene(path, device=device)
    return load_run(path, device=device)


def run_meta(scene) -> dict:
    """What a cache keeps of the run it came from (capture, background, near plane, run.json)."""
    info = dict(scene.info)
    return {"capture": info.get("capture"), "source": str(getattr(scene, "run_dir", "")),
            "background": [float(b) for b in scene.background],
            "near_plane": float(getattr(getattr(scene, "model", scene), "near_plane", 0.01)),
            "run_info": {k: info.get(k) for k in ("preset", "step", "total_steps") if info.get(k) is not None}}


def sample_splats(scene):
    """``t -> splats`` of a Scene4D (exact, from the model) or a CachedScene (interpolated)."""
    if isinstance(scene, CachedScene):
        return scene.splats_at
    return lambda t: splats_at(scene.model, t)


__all__ = ["CachedScene", "CompactFormatError", "is_compact_cache", "load_result", "run_meta", "sample_splats"]
