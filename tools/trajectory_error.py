#!/usr/bin/env python
"""Trajectory error of the Gaussians on moving objects at between-frame instants (issue 11).

PSNR says whether pixels match; this says whether the 3D motion is right. It reads the
capture's optional ground truth (``transforms.json`` -> ``ground_truth.objects``: an npz
with ``times`` [T], per object ``<name>`` [T, 4, 4] object-to-world and ``<name>_points``
[P, 3] surface samples in object space; written by ``scripts/make_capture.py``)::

    .venv/bin/python tools/trajectory_error.py CAPTURE RUN [RUN ...] [--per-interval 4] [--json OUT]

Method: at the first RGB instant ``t0`` a Gaussian (opacity > 0.1) belongs to the object
whose surface samples lie within ``--radius`` (default: 3x the samples' median spacing) of
its position; it is pinned to that object (object-space point ``p = M(t0)^-1 x(t0)``), and
at each between-frame instant ``t`` (``--per-interval`` evenly spaced points strictly inside
each RGB interval) its error is ``e = x(t) - M(t) p``. ``e`` is split at the spike camera:
along its viewing ray through ``M(t) p`` (``ray_mm``) and across it (``plane_mm``), and the
across part in spike pixels (``plane_px``: distance between the two projections). Prints
per run and object the mean of each (Gaussians weighted by opacity) and the counts.

``--visible``: instead of every Gaussian with opacity > 0.1 near the object, only those the
spike camera sees at ``t0``, weighted by their blending weight there (``visible_weights``:
the sum over the spike view's pixels of ``T_i alpha_i``, read as the gradient of the rendered
image's sum with respect to each Gaussian's colour), threshold 0.1 of a pixel. The Gaussians
inside or behind a surface, which no render shows and no loss moves, otherwise dominate the
means and medians.

Also ``wobble_mm``: how far the distance from the spike camera ``rho = |x - c|`` of each such
Gaussian departs between frames from the cubic Hermite curve (Catmull-Rom tangents) through
its own ``rho`` at the RGB instants -- the in-between motion along the spike camera's rays,
which the spike view cannot see (docs/experiments/spike-flow.md) -- and ``gt_wobble_mm``,
the same for the true positions (what that curve cannot follow of the real motion).

And ``phase_mm``: the mean |error| (3D, same weights) by place in the RGB interval, first at the
RGB instants that open an interval, then at each of the ``--per-interval`` instants: whether an
object's error is there at the instants already or grows between them (``--per-interval 3``:
0, 1/4, 1/2, 3/4 of the interval).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from engine.cameras import project_points  # noqa: E402
from engine.errors import CaptureError  # noqa: E402
from engine.io.ground_truth import pose_at  # noqa: E402


def load_object_truth(capture_root) -> dict:
    """{"times" [T], "objects": {name: (mats [T,4,4], points [P,3])}} of a capture's
    ``ground_truth.objects`` block; CaptureError naming the file when absent or bad."""
    root = Path(capture_root)
    tj = root / "transforms.json"
    meta = json.loads(tj.read_text())
    block = (meta.get("ground_truth") or {}).get("objects")
    if not block:
        raise CaptureError(tj, "no ground_truth.objects block: the capture has no object trajectories")
    path = root / block["file_path"]
    try:
        z = np.load(path, allow_pickle=False)
        times = np.asarray(z["times"], np.float64)
        objs = {}
        for name in block["names"]:
            mats, pts = np.asarray(z[name], np.float64), np.asarray(z[f"{name}_points"], np.float64)
            if mats.shape != (len(times), 4, 4) or pts.ndim != 2 or pts.shape[1] != 3:
                raise CaptureError(path, f"object {name!r}: expected [T,4,4] and [P,3], got {mats.shape}, {pts.shape}")
            objs[name] = (mats, pts)
    except (OSError, KeyError, ValueError) as exc:
        raise CaptureError(path, f"unreadable object ground truth: {exc}") from exc
    return {"times": times, "objects": objs}


def object_pose(truth: dict, name: str, t: float) -> np.ndarray:
    """Object-to-world [4,4] at ``t`` (:func:`engine.io.ground_truth.pose_at`)."""
    return pose_at(truth["times"], truth["objects"][name][0], float(t))


def assign(positions: np.ndarray, truth: dict, t0: float, radius: float | None = None) -> tuple[np.ndarray, list]:
    """Object index per Gaussian (-1: none) and the object names, from positions at ``t0``."""
    names = list(truth["objects"])
    best = np.full(len(positions), np.inf)
    owner = np.full(len(positions), -1)
    for k, name in enumerate(names):
        pts = truth["objects"][name][1]
        M = object_pose(truth, name, t0)
        world = pts @ M[:3, :3].T + M[:3, 3]
        if radius is None:
            sub = world[:: max(1, len(world) // 500)]
            d = np.linalg.norm(sub[:, None] - sub[None], axis=-1)
            np.fill_diagonal(d, np.inf)
            r = 3.0 * float(np.median(d.min(1)))
        else:
            r = radius
        for s in range(0, len(positions), 2048):
            d = np.linalg.norm(positions[s:s + 2048, None] - world[None], axis=-1).min(1)
            take = (d < r) & (d < best[s:s + 2048])
            owner[s:s + 2048][take] = k
            best[s:s + 2048][take] = d[take]
    return owner, names


def hermite_curve(rgb_times, values, t: float) -> np.ndarray:
    """Cubic Hermite (Catmull-Rom tangents) through ``values`` [F] x [N] at ``rgb_times`` [F], at
    ``t``; one-sided differences at the capture's first and last interval."""
    rgb_times = np.asarray(rgb_times, dtype=np.float64)
    k = int(np.clip(np.searchsorted(rgb_times, t, side="right") - 1, 0, len(rgb_times) - 2))
    ta, tb = rgb_times[k], rgb_times[k + 1]
    h = tb - ta
    if h <= 0:
        raise ValueError(f"RGB instants must increase: {ta} .. {tb}")
    s = min(1.0, max(0.0, (float(t) - ta) / h))
    ra, rb = np.asarray(values[k], np.float64), np.asarray(values[k + 1], np.float64)
    slope = (rb - ra) / h
    ma = (rb - np.asarray(values[k - 1], np.float64)) / (tb - rgb_times[k - 1]) if k >= 1 else slope
    mb = ((np.asarray(values[k + 2], np.float64) - ra) / (rgb_times[k + 2] - ta)
          if k + 2 < len(rgb_times) else slope)
    s2, s3 = s * s, s * s * s
    h00, h10, h01, h11 = 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2
    return h00 * ra + h10 * h * ma + h01 * rb + h11 * h * mb


def trajectory_errors(positions_at, opacities: np.ndarray, truth: dict, rgb_times, spike_view, *,
                      per_interval: int = 4, radius: float | None = None) -> dict:
    """``positions_at(t) -> [N, 3]``; returns {object: {ray_mm, plane_mm, plane_px, gaussians, instants}}."""
    rgb_times = sorted(rgb_times)
    t0 = rgb_times[0]
    x0 = positions_at(t0)
    owner, names = assign(x0, truth, t0, radius)
    owner[opacities <= 0.1] = -1
    instants = [(a + (b - a) * (i + 1) / (per_interval + 1), i + 1) for a, b in zip(rgb_times, rgb_times[1:])
                for i in range(per_interval)]  # (time, place in the interval: 1 .. per_interval)
    cam_c = np.asarray(spike_view.c2w, np.float64)[:3, 3]
    out = {}
    acc = {k: {"ray": [], "plane": [], "px": [], "w": [], "wob": [], "gt_wob": []} for k in range(len(names))}
    # |error| by place in the interval: [0] at the RGB instants that open an interval, [i] at its i-th instant
    by_phase = {k: [[0.0, 0.0] for _ in range(per_interval + 1)] for k in range(len(names))}
    M0s = {name: object_pose(truth, name, t0) for name in names}

    def truth_at(name, sel, t):
        M0, Mt = M0s[name], object_pose(truth, name, t)
        p = (x0[sel] - M0[:3, 3]) @ M0[:3, :3]  # object space (rotation inverse = transpose)
        return p @ Mt[:3, :3].T + Mt[:3, 3]

    rho = lambda v: np.linalg.norm(v - cam_c, axis=1)  # noqa: E731
    x_rgb = [positions_at(T) for T in rgb_times]
    rho_rgb = [rho(x) for x in x_rgb]
    gt_rgb = {name: [truth_at(name, owner == k, T) for T in rgb_times] for k, name in enumerate(names)}
    rho_gt_rgb = {name: [rho(gt) for gt in gts] for name, gts in gt_rgb.items()}
    for i, x in enumerate(x_rgb[:-1]):
        for k, name in enumerate(names):
            sel = owner == k
            if sel.any():
                e = np.linalg.norm(x[sel] - gt_rgb[name][i], axis=1)
                by_phase[k][0][0] += float((e * opacities[sel]).sum())
                by_phase[k][0][1] += float(opacities[sel].sum())
    for t, phase in instants:
        x = positions_at(t)
        for k, name in enumerate(names):
            sel = owner == k
            if not sel.any():
                continue
            gt = truth_at(name, sel, t)
            e = x[sel] - gt
            ph = by_phase[k][phase]
            ph[0] += float((np.linalg.norm(e, axis=1) * opacities[sel]).sum())
            ph[1] += float(opacities[sel].sum())
            ray = gt - cam_c
            ray /= np.linalg.norm(ray, axis=1, keepdims=True)
            along = (e * ray).sum(1)
            across = np.linalg.norm(e - along[:, None] * ray, axis=1)
            uv_g, _ = project_points(spike_view, x[sel])
            uv_t, _ = project_points(spike_view, gt)
            a = acc[k]
            a["ray"].append(np.abs(along))
            a["plane"].append(across)
            a["px"].append(np.linalg.norm(uv_g - uv_t, axis=1))
            a["w"].append(opacities[sel])
            a["wob"].append(np.abs(rho(x[sel]) - hermite_curve(rgb_times, [r[sel] for r in rho_rgb], t)))
            a["gt_wob"].append(np.abs(rho(gt) - hermite_curve(rgb_times, rho_gt_rgb[name], t)))
    for k, name in enumerate(names):
        a = acc[k]
        if not a["w"]:
            out[name] = {"gaussians": 0}
            continue
        w = np.concatenate(a["w"])
        mean = lambda v: float((np.concatenate(v) * w).sum() / w.sum())  # noqa: E731
        med = lambda v: float(np.median(np.concatenate(v)))  # noqa: E731 (robust to a few strays)
        out[name] = {"ray_mm": 1000 * mean(a["ray"]), "plane_mm": 1000 * mean(a["plane"]),
                     "plane_px": mean(a["px"]), "ray_mm_median": 1000 * med(a["ray"]),
                     "plane_mm_median": 1000 * med(a["plane"]), "plane_px_median": med(a["px"]),
                     "wobble_mm": 1000 * mean(a["wob"]), "wobble_mm_median": 1000 * med(a["wob"]),
                     "gt_wobble_mm": 1000 * mean(a["gt_wob"]),
                     "phase_mm": [1000 * num / max(den, 1e-12) for num, den in by_phase[k]],
                     "gaussians": int((owner == k).sum()), "instants": len(instants)}
    return out


def visible_weights(g: dict, view) -> np.ndarray:
    """[N] blending weight of each Gaussian summed over ``view``'s pixels (``sum T_i alpha_i``):
    the gradient of the render's summed first channel w.r.t. each Gaussian's colour. ``g`` is
    ``Scene4D.gaussians_at(t)``."""
    import torch

    from engine.raster import rasterization
    from engine.scene.model import view_tensors

    vt = view_tensors(view, "cpu")
    t = {k: torch.as_tensor(g[k], dtype=torch.float32) for k in ("means", "quats", "scales", "opacities", "colors")}
    colors = t["colors"].clone().requires_grad_(True)
    img, _, _ = rasterization(t["means"], t["quats"], t["scales"], t["opacities"], colors, vt["viewmat"], vt["K"],
                              vt["width"], vt["height"], render_depth=False)
    img[..., 0].sum().backward()
    return colors.grad[:, 0].numpy().astype(np.float64)


def main(argv=None) -> int:
    import torch

    from engine.io.capture import load_capture
    from engine.scene.model import load_run
    from engine.train.guidance.spike_guidance import spike_stream_info

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--per-interval", type=int, default=4)
    ap.add_argument("--radius", type=float, default=None)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--visible", action="store_true",
                    help="only the Gaussians the spike camera sees at t0, weighted by their blending weight")
    args = ap.parse_args(argv)
    cap = load_capture(args.capture)
    truth = load_object_truth(cap.root)
    info = spike_stream_info(cap)
    if info is None:
        raise SystemExit(f"{args.capture}: no spike stream co-located with an RGB camera")
    view = info.open().view(0.0)
    rgb_times = sorted({float(f.time) for f in cap.frames})
    res = {}
    for run in args.runs:
        scene = load_run(run)
        if args.visible:
            opac = visible_weights(scene.gaussians_at(rgb_times[0]), view)
        else:
            with torch.no_grad():
                opac = scene.gaussians_at(rgb_times[0])["opacities"]
        r = trajectory_errors(lambda t: scene.gaussians_at(t)["means"].astype(np.float64), opac, truth, rgb_times,
                              view, per_interval=args.per_interval, radius=args.radius)
        res[run] = r
        for name, v in r.items():
            if v.get("gaussians"):
                print(f"{run} {name}: along spike ray {v['ray_mm']:.1f} mm (median {v['ray_mm_median']:.1f}), "
                      f"image plane {v['plane_mm']:.1f} mm (median {v['plane_mm_median']:.1f}) = {v['plane_px']:.2f} "
                      f"spike px (median {v['plane_px_median']:.2f}); wobble along the ray off the Hermite curve "
                      f"{v['wobble_mm']:.1f} mm (median {v['wobble_mm_median']:.1f}; truth {v['gt_wobble_mm']:.1f}); "
                      f"{v['gaussians']} Gaussians, "
                      f"{v['instants']} instants")
                phases = ", ".join(f"{i / (args.per_interval + 1):.2f}: {mm:.1f}" for i, mm in enumerate(v["phase_mm"]))
                print(f"{run} {name}: |error| by place in the interval (mm) {phases}")
            else:
                print(f"{run} {name}: no Gaussians on the object")
    if args.json:
        args.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
