"""Splats: one instant of Gaussians in 3DGS's stored parameterisation, as numpy arrays.

The exchange form that the PLY writer (``ply.py``) and the compact 4D cache (``compact.py``)
take and give back, and that :func:`render_splats` rasterizes with the engine's rasterizer:

* ``means``          float32 [N,3]   capture world (= Blender world: right-handed, +Z up, metres)
* ``quats``          float32 [N,4]   rotation, w x y z (normalised when used, as in 3DGS)
* ``log_scales``     float32 [N,3]   natural log of the axis scales (metres)
* ``opacity_logits`` float32 [N]     logit of the opacity
* ``sh``             float32 [N,K,3] SH coefficients, K = (degree+1)^2, 3DGS convention:
  colour(dir) = max(0, 0.5 + SH(dir)), DC term scaled by SH_C0 = 0.2820948

:func:`splats_at` samples a trained model (``Model4D``) at one instant: the deformation's
per-instant colour offset (if any) is folded into the DC coefficient, which reproduces the
model's render exactly for SH degree 0 and whenever the model's inner clamp at 0 is inactive.
"""
from __future__ import annotations

import numpy as np
import torch

from ..raster import rasterization
from ..raster.holes import fill_uncovered
from ..scene.gaussians import SH_C0, eval_sh, num_sh_bases

SPLAT_KEYS = ("means", "quats", "log_scales", "opacity_logits", "sh")
# logits of opacities saturated in float32 (sigmoid(x) == 1 for x > 16.6) stay finite
_OPACITY_EPS = 1e-7


def check_splats(s: dict, where: str = "splats") -> int:
    """Validate shapes/finiteness of a splat dict; returns N. ValueError naming ``where``."""
    missing = [k for k in SPLAT_KEYS if k not in s]
    if missing:
        raise ValueError(f"{where}: missing {', '.join(missing)}")
    n = int(np.shape(s["means"])[0])
    want = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,)}
    for k, shape in want.items():
        if tuple(np.shape(s[k])) != shape:
            raise ValueError(f"{where}: {k} has shape {tuple(np.shape(s[k]))}, expected {shape}")
    sh = np.shape(s["sh"])
    if len(sh) != 3 or sh[0] != n or sh[2] != 3 or sh[1] not in (1, 4, 9, 16):
        raise ValueError(f"{where}: sh has shape {tuple(sh)}, expected [N,K,3] with K in 1, 4, 9, 16")
    return n


def sh_degree_of(sh) -> int:
    return int(round(np.sqrt(np.shape(sh)[1]))) - 1


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().to("cpu", torch.float32).numpy()


def splats_at(model, t: float) -> dict:
    """Splats of a ``Model4D`` at capture time ``t`` (seconds)."""
    with torch.no_grad():
        a = model.attributes(float(t), campos=None)  # colours: DC (+ deformation offset) only
        g = model.gaussians
        sh = g.sh[:, : num_sh_bases(g.active_sh_degree)].detach().clone()
        sh[:, 0] = (a["colors"] - 0.5) / SH_C0
        op = a["opacities"].double().clamp(_OPACITY_EPS, 1 - _OPACITY_EPS)
        return {"means": _np(a["means"]), "quats": _np(a["quats"]), "log_scales": _np(torch.log(a["scales"])),
                "opacity_logits": _np(torch.log(op / (1 - op))), "sh": _np(sh)}


def splats_to_tensors(s: dict, device="cpu") -> dict:
    """Rasterizer-ready activated tensors: means, quats, scales, opacities, sh."""
    t = {k: torch.as_tensor(np.asarray(s[k], np.float32), device=device) for k in SPLAT_KEYS}
    return {"means": t["means"], "quats": t["quats"], "scales": torch.exp(t["log_scales"]),
            "opacities": torch.sigmoid(t["opacity_logits"]), "sh": t["sh"]}


def render_splats(s: dict, vt: dict, background=(0.0, 0.0, 0.0), near_plane: float = 0.01,
                  backend: str = "auto", fill_holes: bool = False) -> dict:
    """Render splats into one view (``engine.scene.model.view_tensors`` dict) with the engine's
    rasterizer -> ``rgb [H,W,3]`` in [0,1], ``alpha [H,W]``, ``depth [H,W]`` (float32 numpy),
    as ``Scene4D.render`` gives them (``fill_holes`` as there)."""
    with torch.no_grad():
        a = splats_to_tensors(s, vt["viewmat"].device)
        deg = sh_degree_of(a["sh"])
        colors = (eval_sh(deg, a["sh"], a["means"] - vt["campos"]) + 0.5).clamp_min(0.0)
        bg = torch.as_tensor(background, dtype=torch.float32, device=a["means"].device).reshape(1, 3)
        rgb, alpha, meta = rasterization(a["means"], a["quats"], a["scales"], a["opacities"], colors, vt["viewmat"],
                                         vt["K"], vt["width"], vt["height"], backgrounds=bg, render_depth=True,
                                         near_plane=near_plane, backend=backend)
        if fill_holes:
            rgb = fill_uncovered(rgb[0], alpha[0], background)[None]
        depth = meta.get("depths")
        return {"rgb": _np(rgb[0].clamp(0, 1)), "alpha": _np(alpha[0, ..., 0]),
                "depth": _np(depth[0, ..., 0]) if depth is not None else np.zeros(alpha.shape[1:3], np.float32)}
