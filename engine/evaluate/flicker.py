"""Temporal flicker of static regions (CPOStream's E_warp with identity flow, exact for a
static camera): mean |R_t - R_{t-1}| over pixels whose ground truth does not change, and
the long-range drift |R_t - R_0| (E_warp's second term). What freezing
(:mod:`engine.train.skipping.freezing`) is meant to remove.
"""
from __future__ import annotations

import numpy as np

from ..io.capture import load_capture
from ..scene.model import load_run
from .metrics import motion_mask

__all__ = ["run_flicker", "static_flicker"]


def static_flicker(renders, gts, *, threshold: float = 0.04, dilate: int = 2) -> dict:
    """Temporal flicker of static regions of a static camera's consecutive renders.

    ``renders`` / ``gts``: time-sorted lists of [H,W,3] in [0,1]. Static pixels of a pair
    (t-1, t): ground truth changes by <= ``threshold`` (max over channels), dilated by
    ``dilate`` px (:func:`engine.evaluate.metrics.motion_mask`). Returns ``flicker`` = mean over pairs of
    mean |R_t - R_{t-1}| on static pixels (x255 in ``flicker_255``), ``drift`` = the same
    against the first frame (E_warp's second term), and the static fraction.
    """
    if len(renders) != len(gts) or len(renders) < 2:
        raise ValueError("need two or more renders with matching ground truths")
    pair, drift, frac = [], [], []
    r0 = np.asarray(renders[0], np.float32)[..., :3]
    g0 = np.asarray(gts[0], np.float32)[..., :3]
    for i in range(1, len(renders)):
        r = np.asarray(renders[i], np.float32)[..., :3]
        g = np.asarray(gts[i], np.float32)[..., :3]
        rp = np.asarray(renders[i - 1], np.float32)[..., :3]
        gp = np.asarray(gts[i - 1], np.float32)[..., :3]
        static = ~motion_mask(gp, g, None, threshold, dilate)
        frac.append(float(static.mean()))
        if static.any():
            pair.append(float(np.abs(r - rp)[static].mean()))
        static0 = ~motion_mask(g0, g, None, threshold, dilate)
        if static0.any():
            drift.append(float(np.abs(r - r0)[static0].mean()))
    f = float(np.mean(pair)) if pair else float("nan")
    return {"flicker": f, "flicker_255": f * 255.0, "drift": float(np.mean(drift)) if drift else float("nan"),
            "static_fraction": float(np.mean(frac)), "pairs": len(pair)}


def run_flicker(run_dir, capture=None, *, camera: str | None = None, max_frames: int | None = None,
                threshold: float = 0.04, dilate: int = 2) -> dict:
    """:func:`static_flicker` of a trained run on its capture's eval frames of one static
    camera (the first eval camera whose pose does not change, or ``camera``)."""
    scene = load_run(run_dir)
    if capture is None:
        capture = scene.info.get("capture")
    cap = load_capture(capture) if not hasattr(capture, "eval_frames") else capture
    by_cam: dict[str, list] = {}
    for f in cap.eval_frames:
        by_cam.setdefault(f.camera, []).append(f)
    chosen = None
    for name, fs in by_cam.items():
        if camera is not None and name != camera:
            continue
        poses = np.stack([np.asarray(f.c2w, np.float64) for f in fs])
        if len(fs) >= 2 and np.allclose(poses, poses[:1], atol=1e-9):
            chosen = (name, sorted(fs, key=lambda fr: fr.time))
            break
    if chosen is None:
        return {"flicker": float("nan"), "drift": float("nan"), "camera": None,
                "reason": "no static eval camera with two or more frames"}
    name, fs = chosen
    if max_frames:
        fs = fs[:max_frames]
    renders = [scene.render([cap.view(f)])[0]["rgb"] for f in fs]
    gts = [f.load_rgb() for f in fs]
    out = static_flicker(renders, gts, threshold=threshold, dilate=dilate)
    out["camera"] = name
    out["frames"] = len(fs)
    return out
