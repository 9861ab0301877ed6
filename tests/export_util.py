"""A small moving 4D model and a camera for the export tests (no training, runs in ms)."""
from __future__ import annotations

import numpy as np
import torch

from engine.cameras import Intrinsics, View, look_at_c2w
from engine.io.checkpoint import save_checkpoint
from engine.scene.deformation import DeformationField
from engine.scene.gaussians import GaussianModel
from engine.scene.model import Model4D, view_tensors

TIME_RANGE = (0.0, 0.2)


def moving_model(n: int = 300, sh_degree: int = 1, seed: int = 0) -> Model4D:
    """Gaussians in a unit box, view-dependent colour, a randomised deformation field that
    moves, turns, scales, fades and recolours them over TIME_RANGE."""
    rng = np.random.default_rng(seed)
    g = GaussianModel(rng.uniform(-0.5, 0.5, (n, 3)), rng.random((n, 3)), sh_degree=sh_degree, init_opacity=0.6)
    with torch.no_grad():
        g.active_sh_degree = sh_degree
        g.sh_rest.normal_(0.0, 0.15, generator=torch.Generator().manual_seed(seed))
        q = torch.randn(n, 4, generator=torch.Generator().manual_seed(seed + 1))
        g.quats.copy_(torch.nn.functional.normalize(q, dim=1))
        g.opacity_logits.uniform_(-2.0, 4.0, generator=torch.Generator().manual_seed(seed + 2))
    field = DeformationField([-1] * 3, [1] * 3, TIME_RANGE, features=4, resolution=6, multires=(1,),
                             time_resolution=5, width=16, deform_scale=True, deform_opacity=True, deform_color=True)
    gen = torch.Generator().manual_seed(seed + 3)
    with torch.no_grad():
        for name, p in field.named_parameters():  # time-varying features, small output heads
            default = 1.0 if ".3." in name else 0.0
            scale = {"grid.temporal": 1.0, "color_head.3": 0.2}.get(name.rsplit(".", 1)[0], default)
            p.add_(torch.randn(p.shape, generator=gen) * scale)
    return Model4D(g, field, background=(0.1, 0.2, 0.3)).eval()


def camera(t: float = 0.1, width: int = 64, height: int = 48, eye=(1.6, -1.9, 1.1)) -> View:
    return View(Intrinsics(width, height, 60.0, 60.0, width / 2, height / 2), look_at_c2w(eye, (0, 0, 0)), time=t)


def render_model(model: Model4D, view: View) -> np.ndarray:
    with torch.no_grad():
        rgb, _, _, _ = model.render(view_tensors(view, "cpu"), render_depth=False)
    return rgb[0].clamp(0, 1).numpy()


def write_run(run_dir, n: int, sh_degree: int = 1):
    """A one-step run folder holding ``moving_model(n, sh_degree)``: what the export
    front ends (CLI, Blender operators) open."""
    save_checkpoint(run_dir, {"model": moving_model(n=n, sh_degree=sh_degree).state(), "step": 1, "total_steps": 1,
                              "time_range": list(TIME_RANGE), "gaussians": n})
    return run_dir
