"""The Blender side's one door to the engine: every engine name that ``bt4d_addon/`` and
``operators/`` use is imported here and nowhere else, so the edges are in one file.

Where the engine is: inside the extension package the add-on is
``bl_ext.<repo>.bullettime4d.bt4d_addon`` and the engine its sibling ``..engine``; imported
from a checkout's root (``scripts/make_capture.py``, some tests) it is the top-level
``engine``. Both import blocks below name the same things.

Cheap at registration: only numpy engine modules load when the add-on is enabled. The torch
modules (training, evaluation, the trained model, render-to-file) load on first use, because
Blender ships without torch (Preferences installs it after the add-on is enabled) and
importing it costs seconds; they are only needed by worker jobs.

No bpy here.
"""
from __future__ import annotations

import functools
from types import SimpleNamespace

_IN_EXTENSION = "." in (__package__ or "")

if _IN_EXTENSION:
    from ..engine.cameras import Intrinsics, View, look_at_c2w
    from ..engine.colour import srgb_to_linear
    from ..engine.errors import CaptureError
    from ..engine.io.capture import load_capture
    from ..engine.io.images import read_image_size
else:  # bt4d_addon imported from the checkout's root
    from engine.cameras import Intrinsics, View, look_at_c2w
    from engine.colour import srgb_to_linear
    from engine.errors import CaptureError
    from engine.io.capture import load_capture
    from engine.io.images import read_image_size

__all__ = ["CaptureError", "Intrinsics", "View", "evaluate", "load_capture", "load_run", "look_at_c2w",
           "read_image_size", "srgb_to_linear", "train", "write_renders"]


@functools.cache
def _torch_side() -> SimpleNamespace:
    """The torch-backed engine functions, imported on first use (see the module docstring)."""
    if _IN_EXTENSION:
        from ..engine.evaluate import evaluate
        from ..engine.export.render_views import write_renders
        from ..engine.scene.model import load_run
        from ..engine.train import train
    else:
        from engine.evaluate import evaluate
        from engine.export.render_views import write_renders
        from engine.scene.model import load_run
        from engine.train import train
    return SimpleNamespace(evaluate=evaluate, load_run=load_run, train=train, write_renders=write_renders)


def train(capture_path, run_dir, **kwargs) -> dict:
    """``engine.train.train``: train a capture into a run folder; returns its summary."""
    return _torch_side().train(capture_path, run_dir, **kwargs)


def evaluate(run_dir) -> dict:
    """``engine.evaluate.evaluate``: held-out metrics of a run."""
    return _torch_side().evaluate(run_dir)


def load_run(run_dir, device="cpu"):
    """``engine.scene.model.load_run``: a run folder as a ``Scene4D`` (``sample``, ``render``)."""
    return _torch_side().load_run(run_dir, device=device)


def write_renders(scene4d, views, out_dir, fmt: str = "png", **kwargs) -> list:
    """``engine.export.render_views.write_renders``: the engine's one render-to-file (its EXR and
    PNG conventions are documented there)."""
    return _torch_side().write_renders(scene4d, views, out_dir, fmt, **kwargs)
