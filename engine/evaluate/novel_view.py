"""Novel-view geometry metrics (issue 14): does the reconstruction hold up where no camera stood?

Per eval camera of a capture with ground-truth depth (``depth_file_path``, written by
scripts/make_capture.py), :func:`evaluate_novel_views` reports

* ``psnr_rgb`` / ``ssim_rgb``: at the RGB instants (both train cameras saw the scene then),
  ``psnr_between`` / ``ssim_between``: at eval instants strictly between them;
* ``coverage``: share of the pixels the ground truth covers (finite GT depth) that the render
  covers with alpha > 0.5 (:func:`coverage`) — holes show here;
* ``depth_med`` / ``depth_p90``: median and 90th percentile of the relative depth error
  ``|d - d_gt| / d_gt`` of the rendered expected depth (the rasterizer's ``meta["depths"]``,
  already divided by alpha: the alpha-weighted mean camera-space z of the Gaussians) over the
  pixels both cover (:func:`depth_error`) — floaters and flattened geometry show here;
* ``psnr_observed`` beside ``psnr`` (whole image): PSNR over the pixels some train camera saw
  (:func:`observed_mask`: the eval pixel's GT surface point, back-projected from GT depth,
  lands inside a train image and is not hidden there, judged with that view's GT depth), so
  what no camera could see is kept apart from what is wrong; ``observed`` is that share;
* ``psnr_moving``: PSNR over pixels whose ground truth changes to the neighbouring eval frame
  of that camera (``engine.evaluate.metrics.motion_masks``: what moves), averaged over frames having any.

Train-view GT depth exists at the RGB instants only; for an eval instant between them the
observed mask uses the train views at the nearest RGB instant (the static set, which is what
the mask is about, is the same; a moving object may be off by a fraction of a frame's motion).

It writes one PNG strip per eval camera and chosen instant: ground truth | render |
depth-error heat map (:func:`error_heatmap`: green 0 % -> yellow 5 % -> red >= 10 %;
magenta: a hole, the GT has a surface and the render has alpha <= 0.5; dark grey: no GT
surface), and ``novel_view.json`` with the per-camera table.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..cameras import View
from ..errors import RunError
from ..io.checkpoint import write_json
from ..io.images import write_png
from .metrics import is_interframe, motion_masks, psnr, ssim

ALPHA_COVERED = 0.5   # a pixel the render covers: alpha above this (issue 14's definition)
OBSERVED_REL_TOL = 0.02  # a GT point is visible in a train view if not behind its GT depth by > 2 %
HEAT_MAX = 0.10        # heat map saturates (red) at 10 % relative depth error
TIME_TOL = 1e-4


# ----------------------------------------------------------------------------- pixel metrics

def coverage(alpha: np.ndarray, gt_depth: np.ndarray, threshold: float = ALPHA_COVERED) -> float:
    """Share of GT-covered pixels (finite ``gt_depth`` [H,W]) with ``alpha`` [H,W] > threshold
    (nan when the GT covers nothing)."""
    gt = np.isfinite(gt_depth)
    if not gt.any():
        return float("nan")
    return float((np.asarray(alpha) > threshold)[gt].mean())


def relative_depth_error(depth: np.ndarray, alpha: np.ndarray, gt_depth: np.ndarray,
                         threshold: float = ALPHA_COVERED) -> np.ndarray:
    """float32 [H,W]: ``|d - d_gt| / d_gt`` where both cover (GT finite, alpha > threshold,
    rendered depth > 0), nan elsewhere."""
    both = np.isfinite(gt_depth) & (np.asarray(alpha) > threshold) & (np.asarray(depth) > 0)
    err = np.full(gt_depth.shape, np.nan, np.float32)
    err[both] = np.abs(depth[both] - gt_depth[both]) / gt_depth[both]
    return err


def depth_error(depth, alpha, gt_depth, threshold: float = ALPHA_COVERED) -> tuple[float, float]:
    """(median, 90th percentile) of the relative depth error over pixels both cover (nan, nan
    when none)."""
    err = relative_depth_error(depth, alpha, gt_depth, threshold)
    v = err[np.isfinite(err)]
    if v.size == 0:
        return float("nan"), float("nan")
    return float(np.median(v)), float(np.percentile(v, 90))


# ----------------------------------------------------------------------------- observed mask

def backproject(view: View, depth: np.ndarray) -> np.ndarray:
    """float64 [H,W,3] world points of the pixel centres at planar ``depth`` [H,W] (inf stays
    non-finite)."""
    k = view.intrinsics
    u = (np.arange(k.width) + 0.5 - k.cx) / k.fx
    v = (np.arange(k.height) + 0.5 - k.cy) / k.fy
    uu, vv = np.meshgrid(u, v)
    z = np.asarray(depth, np.float64)
    cam = np.stack([uu * z, vv * z, z, np.ones_like(z)], axis=-1)  # OpenCV camera frame
    c2w_cv = np.linalg.inv(view.viewmat)
    with np.errstate(invalid="ignore"):
        return (cam @ c2w_cv.T)[..., :3]


def visible_in(view: View, depth: np.ndarray, points: np.ndarray, rel_tol: float = OBSERVED_REL_TOL) -> np.ndarray:
    """bool [...]: world ``points`` [...,3] that project inside ``view``'s image and are not
    hidden there: their camera z is at most (1 + rel_tol) x the largest GT depth of the 2x2
    pixels around the projection (``depth`` [H,W] is that view's GT planar depth)."""
    k = view.intrinsics
    shape = points.shape[:-1]
    p = points.reshape(-1, 3)
    ok = np.all(np.isfinite(p), axis=1)
    cam = np.c_[np.where(ok[:, None], p, 0.0), np.ones(len(p))] @ view.viewmat.T
    z = cam[:, 2]
    ok &= z > 1e-6
    zs = np.where(ok, z, 1.0)
    u = k.fx * cam[:, 0] / zs + k.cx
    v = k.fy * cam[:, 1] / zs + k.cy
    ok &= (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
    # the 2x2 pixel centres around (u, v): a point on a depth edge counts as seen if either side does
    u0 = np.clip(np.floor(u - 0.5).astype(np.int64), 0, k.width - 1)
    v0 = np.clip(np.floor(v - 0.5).astype(np.int64), 0, k.height - 1)
    u1, v1 = np.minimum(u0 + 1, k.width - 1), np.minimum(v0 + 1, k.height - 1)
    d = np.asarray(depth, np.float64)
    near = np.stack([d[v0, u0], d[v0, u1], d[v1, u0], d[v1, u1]], axis=1)
    near = np.where(np.isfinite(near), near, -np.inf).max(axis=1)
    ok &= z <= near * (1.0 + rel_tol)
    return ok.reshape(shape)


def observed_mask(view: View, depth: np.ndarray, train: list[tuple[View, np.ndarray]],
                  rel_tol: float = OBSERVED_REL_TOL) -> np.ndarray:
    """bool [H,W]: eval pixels whose GT surface point (from ``depth``, the eval view's GT
    planar depth) some train view in ``train`` [(view, its GT depth)] sees."""
    pts = backproject(view, depth)
    seen = np.zeros(depth.shape, bool)
    for tv, td in train:
        seen |= visible_in(tv, td, pts, rel_tol)
    return seen & np.isfinite(depth)


# ----------------------------------------------------------------------------- images

def error_heatmap(err: np.ndarray, gt_depth: np.ndarray, alpha: np.ndarray,
                  threshold: float = ALPHA_COVERED, vmax: float = HEAT_MAX) -> np.ndarray:
    """float32 [H,W,3] in [0,1]: relative depth error green (0) -> yellow -> red (>= vmax);
    magenta where the GT has a surface the render leaves uncovered; dark grey: no GT surface."""
    x = np.clip(np.nan_to_num(err, nan=0.0) / vmax, 0.0, 1.0)
    r = np.clip(2.0 * x, 0.0, 1.0)
    g = np.clip(2.0 * (1.0 - x), 0.0, 1.0) * 0.85
    img = np.stack([r, g, np.zeros_like(x)], axis=-1).astype(np.float32)
    hole = np.isfinite(gt_depth) & ~(np.asarray(alpha) > threshold)
    img[hole] = (1.0, 0.0, 1.0)
    img[~np.isfinite(gt_depth)] = (0.2, 0.2, 0.2)
    return img


def write_strip(path, gt: np.ndarray, render: np.ndarray, heat: np.ndarray, gap: int = 2) -> Path:
    """One PNG: ground truth | render | depth-error heat map, side by side."""
    h = gt.shape[0]
    sep = np.ones((h, gap, 3), np.float32)
    return write_png(path, np.concatenate([gt, sep, render, sep, heat], axis=1))


# ----------------------------------------------------------------------------- the table

def _nanmean(values) -> float | None:
    v = [x for x in values if x is not None and not math.isnan(x)]
    return float(np.mean(v)) if v else None


def evaluate_novel_views(scene, cap, out_dir=None, *, strip_times=None, log=None) -> dict:
    """Per eval camera metrics (module docstring) of ``scene`` (:class:`Scene4D`, e.g. from
    ``load_run``) on capture ``cap``; eval frames without GT depth are skipped (RunError when
    none has it). ``out_dir``: where to write strips (``<camera>_<t_ms>ms.png``) for the eval
    instants nearest each of ``strip_times`` (default: the first RGB instant and the first
    instant between two). Returns {"cameras": {name: row}, "frames": [per-frame rows]}."""
    rgb_times = sorted({float(f.time) for f in cap.frames})
    train_at: dict[float, list] = {}
    for f in cap.frames:
        if f.depth_file_path is not None:
            train_at.setdefault(float(f.time), []).append(f)
    evals = [f for f in cap.eval_frames if f.depth_file_path is not None]
    if not evals:
        raise RunError(Path(cap.root), "no eval frame carries ground-truth depth (depth_file_path); "
                                       "render the capture with scripts/make_capture.py --depth")
    if strip_times is None:
        mids = [0.5 * (a + b) for a, b in zip(rgb_times, rgb_times[1:])]
        strip_times = [rgb_times[0]] + mids[:1]
    train_cache: dict[float, list] = {}

    def train_views(t: float):
        if not train_at:
            return []
        key = min(train_at, key=lambda s: abs(s - t))
        if key not in train_cache:
            train_cache[key] = [(f.view(), f.load_depth()) for f in train_at[key]]
        return train_cache[key]

    by_cam: dict[str, list] = {}
    for f in evals:
        by_cam.setdefault(f.camera, []).append(f)
    rows = []
    for cam, fs in by_cam.items():
        fs = sorted(fs, key=lambda fr: fr.time)
        strip_pick = {min(fs, key=lambda fr: abs(fr.time - s)).path for s in strip_times}
        gts = [fr.load_rgb() for fr in fs]
        for fr, gt, moving in zip(fs, gts, motion_masks(gts)):
            view = fr.view()
            gt_depth = fr.load_depth()
            out = scene.render([view])[0]
            pred, alpha, depth = out["rgb"], out["alpha"], out["depth"]
            seen = observed_mask(view, gt_depth, train_views(fr.time))
            d_med, d_p90 = depth_error(depth, alpha, gt_depth)
            at_rgb = min(abs(fr.time - t) for t in rgb_times) <= TIME_TOL if rgb_times else False
            rows.append({"camera": cam, "time": float(fr.time), "rgb_instant": bool(at_rgb),
                         "between": is_interframe(fr.time, rgb_times), "psnr": psnr(pred, gt),
                         "ssim": ssim(pred, gt), "psnr_observed": psnr(pred, gt, seen) if seen.any() else float("nan"),
                         "psnr_moving": psnr(pred, gt, moving) if moving.any() else float("nan"),
                         "observed": float(seen.mean()), "coverage": coverage(alpha, gt_depth),
                         "depth_med": d_med, "depth_p90": d_p90})
            if out_dir is not None and fr.path in strip_pick:
                heat = error_heatmap(relative_depth_error(depth, alpha, gt_depth), gt_depth, alpha)
                write_strip(Path(out_dir) / f"{cam}_{fr.time * 1000:06.1f}ms.png", gt, pred, heat)
        if log:
            log(f"  {cam}: {len(fs)} frames")
    table = {}
    for cam in by_cam:
        r = [x for x in rows if x["camera"] == cam]
        at, bt = [x for x in r if x["rgb_instant"]], [x for x in r if x["between"]]
        table[cam] = {
            "n": len(r),
            "psnr_rgb": _nanmean(x["psnr"] for x in at), "psnr_between": _nanmean(x["psnr"] for x in bt),
            "ssim_rgb": _nanmean(x["ssim"] for x in at), "ssim_between": _nanmean(x["ssim"] for x in bt),
            "psnr": _nanmean(x["psnr"] for x in r), "psnr_observed": _nanmean(x["psnr_observed"] for x in r),
            "psnr_moving": _nanmean(x["psnr_moving"] for x in r),
            "observed": _nanmean(x["observed"] for x in r), "coverage": _nanmean(x["coverage"] for x in r),
            "depth_med": _nanmean(x["depth_med"] for x in r), "depth_p90": _nanmean(x["depth_p90"] for x in r),
        }
    result = {"cameras": table, "frames": rows}
    if out_dir is not None:
        write_json(Path(out_dir) / "novel_view.json", result)
    return result


COLUMNS = (("psnr_rgb", "PSNR@rgb", "{:.2f}"), ("psnr_between", "PSNR@btw", "{:.2f}"),
           ("ssim_rgb", "SSIM@rgb", "{:.3f}"), ("ssim_between", "SSIM@btw", "{:.3f}"),
           ("psnr", "PSNR all", "{:.2f}"), ("psnr_observed", "PSNR obs", "{:.2f}"),
           ("psnr_moving", "PSNR mov", "{:.2f}"),
           ("observed", "obs %", "{:.1%}"), ("coverage", "cover %", "{:.1%}"),
           ("depth_med", "dErr med", "{:.1%}"), ("depth_p90", "dErr p90", "{:.1%}"))


def format_table(table: dict, angles: dict | None = None) -> str:
    """Markdown table: one row per eval camera (``angles``: camera -> label, e.g. '20° side')."""
    head = "| camera | " + " | ".join(c[1] for c in COLUMNS) + " |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 1)]
    for cam, row in table.items():
        label = f"{cam} ({angles[cam]})" if angles and cam in angles else cam
        cells = ["–" if row.get(k) is None else fmt.format(row[k]) for k, _, fmt in COLUMNS]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
