"""Helpers for tests that drive real training steps."""
from __future__ import annotations

import numpy as np


def term_values(trainer, name: str, steps: int = 8) -> list[float]:
    """Run ``trainer.step`` for steps 0..steps-1 (each step's total loss must be finite) and
    return the values the loss term ``name`` reported, in order (steps without it skipped)."""
    seen = []
    for step in range(steps):
        out = trainer.step(step)
        assert np.isfinite(out["loss"])
        if name in out["losses"]:
            seen.append(out["losses"][name])
    return seen


def trajectory_model(knots, n: int, seed: int = 0, spread: float = 0.1, centre=(0.0, 0.0, 0.0)):
    """A deforming ``Model4D`` of ``n`` Gaussians (normal around ``centre``, std ``spread``)
    with per-Gaussian trajectories over ``knots``, all at rest (zero curves), optimiser set up."""
    from engine.scene.gaussians import GaussianModel
    from engine.scene.model import Model4D
    from engine.train.config import get_preset

    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(n, 3)) * spread + np.asarray(centre, np.float64)
    g = GaussianModel(xyz, rng.uniform(size=(n, 3)))
    g.setup_optimizer(get_preset("fast").gaussians, 1.0)
    m = Model4D(g)
    m.add_trajectories(knots, 1e-3, 1e-3)
    m.use_deformation = True
    return m


def frame_items(cap) -> list[dict]:
    """A trainer's per-frame view tensors of every frame of ``cap`` on the CPU: image [1,H,W,3],
    index and camera (for tests that drive the spike guidance without a Trainer)."""
    import torch

    from engine.scene.model import view_tensors

    items = []
    for i, f in enumerate(cap.frames):
        vt = view_tensors(cap.view(f), "cpu")
        vt["image"] = torch.from_numpy(f.load_rgb())[None]
        vt["index"], vt["camera"] = i, f.camera
        items.append(vt)
    return items


# A guided run in a few steps on the demo capture (the spike-view terms' trainer tests)
GUIDED_TINY = {"iterations": 8, "static_fraction": 0.25, "init_max_points": 300, "init_random_points": 100,
               "densify_from": 2.0, "densify_until": 2.0, "block_interp": "linear", "between_colocated_p": 1.0,
               "time_curriculum": 0.0, "spike_skip_static": False, "fine_d_model": 16, "fine_channels": 8,
               "fine_k_sub": 4}


# engineering constants that were training settings before the config redesign: the old setting
# name -> (module, constant). Tests that need another value patch the constant for their duration.
CONSTANTS = {
    "lazy_min_columns": ("engine.scene.gaussians", "LAZY_MIN_COLUMNS"),
    "lazy_rgb_only": ("engine.scene.gaussians", "LAZY_RGB_ONLY"),
    "birth_stride": ("engine.train.motion.births", "STRIDE"),
    "birth_max": ("engine.train.motion.births", "MAX_PER_FRAME"),
    "traj_carry_hidden": ("engine.train.motion.scene_flow", "CARRY_HIDDEN"),
    "spike_flow_steps": ("engine.train.guidance.spike_flow_cache", "FLOW_STEPS"),
    "spike_flow_upsample": ("engine.train.guidance.spike_flow_cache", "UPSAMPLE"),
    "spike_flow_prefetch": ("engine.train.guidance.spike_flow_cache", "PREFETCH"),
    "spike_flow_surface_every": ("engine.train.guidance.spike_flow", "SURFACE_EVERY"),
    "spike_flow_min_px": ("engine.train.guidance.spike_flow", "MIN_PX"),
    "quiet_curves_refresh": ("engine.train.guidance.quiet_curves", "REFRESH"),
    "quiet_curves_dilate": ("engine.train.guidance.quiet_curves", "DILATE"),
    "fine_encoder_every": ("engine.train.guidance.spike_guidance", "FINE_ENCODER_EVERY"),
    "baseline_per_interval": ("engine.train.frames.baselines", "PER_INTERVAL"),
}


def patch_constants(monkeypatch, over: dict) -> dict:
    """Patch the constants that ``over`` names (old setting names, :data:`CONSTANTS`) with
    ``monkeypatch`` and return the rest of ``over`` (real settings, for ``get_preset``)."""
    import importlib

    rest = {}
    for k, v in over.items():
        if k in CONSTANTS:
            mod, name = CONSTANTS[k]
            monkeypatch.setattr(importlib.import_module(mod), name, v)
        else:
            rest[k] = v
    return rest


def fake_run(cfg=None, **fields):
    """A :class:`engine.train.run_context.RunContext` for a part tested without a trainer: the
    fast preset's settings, no capture, CPU, and any field given."""
    import torch

    from engine.train.config import get_preset
    from engine.train.run_context import RunContext

    base = {"capture": None, "device": torch.device("cpu"), "seed": 0, "items": [], "frame_times": [],
            "time_range": (0.0, 1.0), "fusion_cache": None}
    base.update(fields)
    return RunContext(cfg=cfg if cfg is not None else get_preset("fast"), **base)
