"""BulletTime4D engine: capture IO, spike camera, Gaussian rasterizer, 4D training.

Plain Python + numpy + torch. Never imports ``bpy``: the same code runs inside Blender,
in ``python -m engine`` on a render node, and on a GPU box.

Light names (numpy only) import eagerly; torch-heavy names resolve on first use so that
``import engine`` stays cheap for the Blender UI.
"""
from __future__ import annotations

import importlib
import os

# torch and numba each run an OpenMP pool; with the default busy-wait policy the two pools
# spin against each other between parallel regions (measured: 5x slower rasterizer on 2
# cores). Must be set before torch is imported; an explicit user value wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .cameras import Intrinsics, View, look_at_c2w, project_points, viewmat_from_c2w_gl
from .errors import CaptureError, RunError

# public name -> submodule that defines it (imported on first access)
_LAZY = {
    "load_capture": ".capture",
    "Capture": ".capture",
    "read_spikes": ".spikes",
    "write_spikes": ".spikes",
    "SpikeStream": ".spikes",
    "simulate_spikes": ".spike_sim",
    "tfp": ".spike_sim",
    "tfi": ".spike_sim",
    "rasterization": ".raster",
    "train": ".train",
    "load_run": ".model",
}

__all__ = ["Intrinsics", "View", "CaptureError", "RunError", "look_at_c2w", "project_points",
           "viewmat_from_c2w_gl", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
