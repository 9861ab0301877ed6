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
    from ..engine.export.render_views import write_camera_file
    from ..engine.io.capture import load_capture
    from ..engine.io.images import read_image_size
else:  # bt4d_addon imported from the checkout's root
    from engine.cameras import Intrinsics, View, look_at_c2w
    from engine.colour import srgb_to_linear
    from engine.errors import CaptureError
    from engine.export.render_views import write_camera_file
    from engine.io.capture import load_capture
    from engine.io.images import read_image_size

__all__ = ["CaptureError", "Intrinsics", "View", "evaluate", "export_ply_sequence", "load_capture", "load_result",
           "load_run", "look_at_c2w", "read_image_size", "srgb_to_linear", "train", "write_camera_file",
           "write_renders"]


@functools.cache
def _torch_side() -> SimpleNamespace:
    """The torch-backed engine functions, imported on first use (see the module docstring)."""
    if _IN_EXTENSION:
        from ..engine.evaluate import evaluate
        from ..engine.export import cached, ply
        from ..engine.export.render_views import write_renders
        from ..engine.scene.model import load_run
        from ..engine.scene.observed import prune_unobserved
        from ..engine.train import train
    else:
        from engine.evaluate import evaluate
        from engine.export import cached, ply
        from engine.export.render_views import write_renders
        from engine.scene.model import load_run
        from engine.scene.observed import prune_unobserved
        from engine.train import train
    return SimpleNamespace(evaluate=evaluate, load_run=load_run, train=train, write_renders=write_renders,
                           cached=cached, ply=ply, prune_unobserved=prune_unobserved)


def train(capture_path, run_dir, **kwargs) -> dict:
    """``engine.train.train``: train a capture into a run folder; returns its summary."""
    return _torch_side().train(capture_path, run_dir, **kwargs)


def evaluate(run_dir) -> dict:
    """``engine.evaluate.evaluate``: held-out metrics of a run."""
    return _torch_side().evaluate(run_dir)


def load_run(run_dir, device="cpu", prune_unobserved: bool = False):
    """``engine.scene.model.load_run``: a run folder as a ``Scene4D`` (``sample``, ``render``);
    ``prune_unobserved``: without the Gaussians no train camera constrained
    (``engine.scene.observed.prune_unobserved``, against the capture the run recorded)."""
    side = _torch_side()
    scene4d = side.load_run(run_dir, device=device)
    if prune_unobserved:
        side.prune_unobserved(scene4d)
    return scene4d


def write_renders(scene4d, views, out_dir, fmt: str = "png", **kwargs) -> list:
    """``engine.export.render_views.write_renders``: the engine's one render-to-file (its EXR and
    PNG conventions are documented there)."""
    return _torch_side().write_renders(scene4d, views, out_dir, fmt, **kwargs)


def load_result(path, device="cpu"):
    """``engine.export.cached.load_result``: a run folder (``Scene4D``) or a compact cache
    (``.bt4c``, ``CachedScene``); both ``sample`` and ``render``."""
    return _torch_side().cached.load_result(path, device=device)


def export_ply_sequence(source, out_dir, fps: float, progress=None) -> dict:
    """Sample a run folder or compact cache at ``fps`` over its time range and write a 3DGS PLY
    sequence (``engine.export.ply.write_sequence``). Returns index path, frame and Gaussian counts."""
    side = _torch_side()
    scene4d = side.cached.load_result(source)
    t0, t1 = scene4d.time_range
    n = int((t1 - t0) * fps + 1e-6) + 1
    times = [t0 + i / fps for i in range(n)]
    meta = side.cached.run_meta(scene4d)
    index = side.ply.write_sequence(out_dir, times, side.cached.sample_splats(scene4d), fps=fps,
                                    source=meta["source"], background=meta["background"], progress=progress)
    return {"index": str(index), "frames": n, "gaussians": scene4d.num_gaussians}
