"""BulletTime4D engine: capture IO, spike camera, Gaussian rasterizer, 4D training.

Plain Python + numpy + torch. Never imports ``bpy``: the same code runs inside Blender,
in ``python -m engine`` on a render node, and on a GPU box.

Light names (numpy only) import eagerly; torch-heavy names and the sub-packages resolve on
first use so that ``import engine`` stays cheap for the Blender UI. A sub-package name
(``engine.train``, ``engine.evaluate``, ...) is always the sub-package, never a function.
"""
from __future__ import annotations

import importlib
import os

# torch and numba each run an OpenMP pool; with the default busy-wait policy the two pools
# spin against each other between parallel regions (measured: 5x slower rasterizer on 2
# cores, 1.1 s vs 0.22 s per step at 320x240 with 50k Gaussians). libgomp reads this when it
# loads, so it must be set before torch or numba's OpenMP layer is imported: this package is
# imported first by everything that uses them (the extension, ``python -m engine``,
# ``python -m tools``). An explicit user value wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .cameras import Intrinsics, View, look_at_c2w, project_points, viewmat_from_c2w_gl  # noqa: E402
from .errors import CaptureError, RunError  # noqa: E402

# public name -> submodule that defines it (imported on first access)
_LAZY = {
    "load_capture": ".io.capture",
    "Capture": ".io.capture",
    "read_spikes": ".io.spikes",
    "write_spikes": ".io.spikes",
    "SpikeStream": ".io.spikes",
    "simulate_spikes": ".spike.simulate",
    "tfp": ".spike.simulate",
    "tfi": ".spike.simulate",
    "rasterization": ".raster",
    "load_run": ".scene.model",
}
# sub-packages, imported on first attribute access (``import engine; engine.train.train(...)``)
_SUBPACKAGES = ("io", "raster", "spike", "scene", "geometry", "evaluate", "train", "export", "cli")

__all__ = ["Intrinsics", "View", "CaptureError", "RunError", "look_at_c2w", "project_points",
           "viewmat_from_c2w_gl", *_LAZY]


def __getattr__(name: str):
    if name in _SUBPACKAGES:
        return importlib.import_module(f".{name}", __name__)  # the import binds engine.<name>
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
