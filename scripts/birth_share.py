"""How much of the moving objects is made of born Gaussians (engine.train.births), and what
happens to the eval picture without their temporal fade (issue 11, "ghost" diagnosis).

    python scripts/birth_share.py RUN [RUN ...]

Per run and per eval frame class (at RGB instants / between): moving-pixel PSNR as trained,
with born Gaussians' temporal opacity forced to 1 ("no fade"), with born Gaussians removed,
and the share of the rendered alpha on moving pixels that born Gaussians give (alpha of a
render of born Gaussians only / alpha of the full render). Also the born Gaussians' curve
motion (mean |trajectory offset| across knots, metres) against the carried moving ones.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from engine.evaluate.metrics import is_interframe, motion_masks, psnr
from engine.io.capture import load_capture
from engine.scene.model import (
    ALWAYS_LOG_SCALE,
    TIME_CENTER,
    TIME_LOG_SCALE,
    TRAJ_MEANS,
    born_mask,
    load_run,
    view_tensors,
)


def _render(model, vt, t, keep=None, no_fade=False):
    g = model.gaussians
    saved = {}
    if no_fade and TIME_CENTER in g.extra_lrs:
        saved[TIME_LOG_SCALE] = getattr(g, TIME_LOG_SCALE).data.clone()
        getattr(g, TIME_LOG_SCALE).data.fill_(ALWAYS_LOG_SCALE)
    if keep is not None:
        saved["opacity_logits"] = g.opacity_logits.data.clone()
        g.opacity_logits.data[~keep] = -30.0
    try:
        with torch.no_grad():
            rgb, alpha, _, _ = model.render(vt, t, render_depth=False)
    finally:
        for k, v in saved.items():
            getattr(g, k).data.copy_(v)
    return rgb[0].clamp(0, 1).numpy(), alpha[0, ..., 0].numpy()


def main(runs):
    for run in runs:
        sc = load_run(run)
        cap = load_capture(sc.info["capture"])
        model, g = sc.model, sc.model.gaussians
        born = born_mask(g)
        print(f"{run}: {g.num_gaussians} Gaussians, {int(born.sum())} born")
        if TRAJ_MEANS in g.extra_lrs:
            off = getattr(g, TRAJ_MEANS).detach().norm(dim=-1).mean(-1)  # [N] mean |offset| over control points
            moving = off > 1e-3
            print(f"  mean |curve offset| m: born {off[born].mean():.4f} (moving>1mm {float((moving & born).sum())}),"
                  f" carried moving {off[moving & ~born].mean():.4f} ({int((moving & ~born).sum())})")
        rgb_times = sorted({float(f.time) for f in cap.frames})
        fs = sorted(cap.eval_frames, key=lambda f: (f.camera, f.time))
        acc = {}
        for cam in sorted({f.camera for f in fs}):
            cf = [f for f in fs if f.camera == cam]
            gts = [f.load_rgb() for f in cf]
            for f, gt, m in zip(cf, gts, motion_masks(gts, 0.04, 2)):
                if not m.any():
                    continue
                vt = view_tensors(cap.view(f), sc.device)
                t = float(f.time)
                full, a_all = _render(model, vt, t)
                nofade, _ = _render(model, vt, t, no_fade=True)
                noborn, _ = _render(model, vt, t, keep=~born)
                _, a_born = _render(model, vt, t, keep=born)
                k = "between" if is_interframe(t, rgb_times) else "instant"
                acc.setdefault(k, []).append((psnr(full, gt, m), psnr(nofade, gt, m), psnr(noborn, gt, m),
                                              float(a_born[m].sum() / max(a_all[m].sum(), 1e-9))))
        for k, v in sorted(acc.items()):
            v = np.array(v)
            print(f"  {k:8s} moving PSNR as trained {v[:, 0].mean():.2f} | no fade {v[:, 1].mean():.2f} |"
                  f" born removed {v[:, 2].mean():.2f} | born share of moving alpha {v[:, 3].mean():.2f} (n={len(v)})")


if __name__ == "__main__":
    main(sys.argv[1:])
