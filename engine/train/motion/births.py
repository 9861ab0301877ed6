"""Births: new Gaussians at an admitted RGB instant, where the render still misses the frame.

Why: on the fast scene the per-Gaussian curves of a fast, rotating object do not reach its
new place at late instants, and the optimiser answers with lower opacity (ghosts:
docs/experiments/motion-representation.md "Motion representation", time-curriculum table). Densification only
clones existing
Gaussians, curves included, so nothing can start at the new place. Spacetime Gaussians
(Li et al., CVPR 2024) give each Gaussian a temporal opacity and add points per frame; here,
when the time curriculum admits RGB instant ``t`` (after the carry has moved the curves
there), every train view at ``t`` is rendered, and at pixels where the render misses the
frame by more than ``birth_error`` (max over channels) and the per-instant stereo depth is
known, a Gaussian is born at the back-projected point with the frame's colour, a zero
(static) curve and a temporal opacity centred on ``t`` (std ``birth_lifespan`` x the frame
interval; the other Gaussians get an effectively infinite one, so they are unchanged).
Training then moves, widens or fades it like any other parameter.

Born Gaussians that move (``birth_motion``, issue 11 "ghost"; off by default): with a static
curve, a Gaussian born at ``T_j`` sits at its ``T_j`` place at every time and only fades;
where the carry cannot follow a fast object, the object between ``T_{j-1}`` and ``T_j`` is
the cross-fade of the two instants' motionless copies (fast scene, eval camera, run of main
6151c93: born Gaussians give 0.55 of the moving pixels' alpha; moving-pixel PSNR between
frames 16.25 dB, 13.76 with their fade removed, 13.43 with them removed:
a one-off study, docs/experiments/ (births)). With ``birth_motion`` each born Gaussian gets its junctions at
``T_{j-1}`` (held before) and ``T_{j+1}`` (held after; the carry then leaves it alone) from
:func:`backward_displacement`: the train cameras' correspondence ``T_j -> T_{j+-1}`` lifted by
the stereo depth there (the carry's :func:`carry_by_flow`): ``"lk"`` / ``"dis"`` optical flow,
``"match"`` one translation per born region (:func:`component_flow`); those it cannot decide,
and all of them with ``"nearest"``, take the displacement of the nearest Gaussian alive at
``T_j`` within ``scene_flow.CARRY_HIDDEN`` x extent. Measured at 1000 steps
(docs/experiments/motion-representation.md, "Births that move"): none of them pays yet.

How long they live (``birth_static_lifespan``, on at 16 with ``birth_depth_guard`` 0.8): the temporal std barely trains
(fast, 1000 steps: median 0.45 interval for an initial 0.5), and 73 % of the fast scene's births
sit on pixels a neighbouring RGB instant of the same camera repeats (:func:`unchanged_pixels`):
a static surface the render missed, which should not fade between instants. Those get
``birth_static_lifespan`` x the frame interval (16: fast +0.56 / +0.12 dB between instants,
demo +0.14 / +0.37, ``between`` -0.04 / +0.01; docs/experiments/motion-representation.md "How long born Gaussians
live").
Where the stereo match is wrong (periodic texture, low resolution) such a Gaussian floats in
front of the surface it shows for all that time; ``birth_depth_guard`` drops the static births
whose stereo depth lies well in front of an opaque render (:func:`stereo_in_front`;
docs/experiments/motion-representation.md "Births at a wrong stereo depth").
"""
from __future__ import annotations

import numpy as np
import torch

from ...scene.gaussians import inverse_sigmoid, rgb_to_sh
from ...scene.model import ALWAYS_LOG_SCALE, TIME_CENTER, TIME_LOG_SCALE, TRAJ_MEANS, temporal_opacity, view_tensors
from . import scene_flow
from .scene_flow import (
    backproject_pixels,
    carry_by_flow,
    frame_image,
    image_flow,
    instant_depth_priors,
    propagate_to_hidden,
)

__all__ = ["ALWAYS_LOG_SCALE", "BIRTH_MOTIONS", "birth_candidates", "unchanged_pixels", "stereo_in_front",
           "ensure_temporal_opacity", "spawn_at_instant", "backward_displacement", "component_flow", "move_born"]

STRIDE = 2              # px between candidate pixels
MAX_PER_FRAME = 2000    # most Gaussians born per admitted frame
OPACITY = 0.5           # a born Gaussian's peak opacity
MATCH_RADIUS = 0.25     # x image width: search radius of births.motion=match
BIRTH_MOTIONS = ("none", "lk", "dis", "match", "nearest")  # lk / dis: scene_flow.image_flow; match: component_flow

LR_TIME_CENTER = 5e-4    # s per step: a born Gaussian's centre can drift a few frames in 100 steps
LR_TIME_LOG_SCALE = 1e-2


def ensure_temporal_opacity(gaussians) -> None:
    """Give every Gaussian the temporal-opacity extras (once): centre 0, log std 30."""
    if TIME_CENTER in gaussians.extra_lrs:
        return
    n, dev = gaussians.num_gaussians, gaussians.means.device
    gaussians.add_extra(TIME_CENTER, torch.zeros(n, 1, device=dev), LR_TIME_CENTER)
    gaussians.add_extra(TIME_LOG_SCALE, torch.full((n, 1), ALWAYS_LOG_SCALE, device=dev), LR_TIME_LOG_SCALE)


def birth_candidates(render: np.ndarray, image: np.ndarray, depth: np.ndarray, depth_ok: np.ndarray,
                     threshold: float, stride: int, limit: int, rng: np.random.Generator):
    """Pixels (rows, cols) where ``render`` [H,W,3] misses ``image`` by more than ``threshold``
    (max over channels) and ``depth_ok``, on a ``stride`` grid, at most ``limit`` (random)."""
    miss = np.abs(render - image).max(axis=-1) > threshold
    grid = np.zeros_like(miss)
    grid[::stride, ::stride] = True
    rows, cols = np.nonzero(miss & depth_ok & grid & np.isfinite(depth) & (depth > 0))
    if len(rows) > limit:
        keep = np.sort(rng.choice(len(rows), size=limit, replace=False))
        rows, cols = rows[keep], cols[keep]
    return rows, cols


def unchanged_pixels(image: np.ndarray, neighbours: list, rows: np.ndarray, cols: np.ndarray,
                     threshold: float) -> np.ndarray:
    """bool [M]: pixels (``rows``, ``cols``) of ``image`` [H, W, 3] whose colour a neighbouring
    RGB instant's image of the same camera (``neighbours``: list of [H, W, 3]) repeats within
    ``threshold`` (max over channels): a static surface seen there for a frame interval, not a
    moving one (``birth_static_lifespan``). All False without neighbours."""
    out = np.zeros(len(rows), dtype=bool)
    for nb in neighbours:
        out |= np.abs(nb[rows, cols] - image[rows, cols]).max(axis=-1) <= threshold
    return out


def stereo_in_front(stereo: np.ndarray, render_depth: np.ndarray, render_alpha: np.ndarray,
                    ratio: float) -> np.ndarray:
    """bool [M]: the stereo depth is less than ``ratio`` x the render's expected depth where the
    render is opaque (alpha >= 0.5): the birth would float in front of a surface the model
    already has (``birth_depth_guard``)."""
    return (render_alpha >= 0.5) & (stereo < ratio * render_depth)


def spawn_at_instant(run, frames, t: float) -> dict:
    """Births at the train frames of instant ``t`` (see the module docstring). Returns the
    record ``{"birth_at", "born", "total"}``, also appended to ``run.info["births"]`` (run.json's
    ``births``)."""
    cfg, model = run.cfg, run.model
    if cfg.births.motion not in BIRTH_MOTIONS:  # before the model changes
        raise ValueError(f"unknown birth_motion {cfg.births.motion!r}; choose one of {', '.join(BIRTH_MOTIONS)}")
    g = model.gaussians
    pri = instant_depth_priors(run, frames)
    knots = model.trajectory["knots"]  # births follow the carry, which only curves have
    dt = float(np.median(np.diff(knots))) if len(knots) > 1 else 1.0 / 30.0
    rng = np.random.default_rng(int(run.seed) * 7919 + int(round(t * 1e6)))
    static_life = float(cfg.births.static_lifespan)
    guard = float(cfg.births.depth_guard)
    find_static = static_life > 0 or guard > 0
    by_key = {(f.camera, round(float(f.time), 9)): f for f in frames} if find_static else {}
    j = int(np.argmin([abs(k - t) for k in knots])) if len(knots) else 0
    pts, cols, sizes, still, guarded = [], [], [], [], 0
    for f in frames:
        if abs(float(f.time) - t) > 1e-6 or id(f) not in pri:
            continue
        view = run.capture.view(f)
        vt = view_tensors(view, run.device)
        with torch.no_grad():
            rgb, alpha, meta, _ = model.render(vt, t, render_depth=guard > 0)
        rgb = rgb[0].clamp(0, 1).cpu().numpy()
        img = frame_image(run, f)
        depth, ok = pri[id(f)]
        r, c = birth_candidates(rgb, img, depth, ok, cfg.births.error, int(STRIDE), int(MAX_PER_FRAME), rng)
        if find_static and len(r):
            nbrs = [frame_image(run, by_key[k]) for k in
                    ((f.camera, round(float(knots[i]), 9)) for i in (j - 1, j + 1) if 0 <= i < len(knots))
                    if k in by_key]
            unchanged = unchanged_pixels(img, nbrs, r, c, cfg.births.error)
            if guard > 0:
                keep = ~(unchanged & stereo_in_front(depth[r, c], meta["depths"][0, ..., 0].cpu().numpy()[r, c],
                                                     alpha[0, ..., 0].cpu().numpy()[r, c], guard))
                guarded += int((~keep).sum())
                r, c, unchanged = r[keep], c[keep], unchanged[keep]
            still.append(unchanged)
        if len(r) == 0:
            continue
        z = depth[r, c].astype(np.float64)
        pts.append(backproject_pixels(view, np.stack([c + 0.5, r + 0.5], 1), z))
        cols.append(img[r, c])
        sizes.append(z / view.intrinsics.fx * STRIDE * 0.5)  # half the grid step, in metres
    records = run.info.setdefault("births", [])
    if not pts:
        records.append({"birth_at": float(t), "born": 0, "total": g.num_gaussians})
        if guard > 0:
            records[-1]["guarded"] = guarded
        return records[-1]
    ensure_temporal_opacity(g)
    dev = g.means.device
    means = torch.as_tensor(np.concatenate(pts), dtype=torch.float32, device=dev)
    m = means.shape[0]
    life = np.full(m, float(cfg.births.lifespan))
    if static_life > 0:
        life[np.concatenate(still)] = static_life
    quats = torch.zeros(m, 4, device=dev)
    quats[:, 0] = 1.0
    rows = {n: torch.zeros((m, *getattr(g, n).shape[1:]), device=dev) for n in g.param_names}  # static curves
    rows.update({
        "means": means,
        "log_scales": torch.log(torch.as_tensor(np.concatenate(sizes), dtype=torch.float32, device=dev)
                                .clamp_min(1e-6))[:, None].repeat(1, 3),
        "quats": quats,
        "opacity_logits": inverse_sigmoid(torch.full((m,), float(OPACITY), device=dev)),
        "sh_dc": rgb_to_sh(torch.as_tensor(np.concatenate(cols), dtype=torch.float32, device=dev))[:, None, :],
        TIME_CENTER: torch.full((m, 1), float(t), device=dev),
        TIME_LOG_SCALE: torch.as_tensor(np.log(np.maximum(life * dt, 1e-6)), dtype=torch.float32,
                                        device=dev)[:, None],
    })
    g.append(rows)
    if model.static_mask is not None and model.static_mask.shape[0] == g.num_gaussians - m:
        model.static_mask = torch.cat([model.static_mask, torch.zeros(m, dtype=torch.bool, device=dev)])
    records.append({"birth_at": float(t), "born": int(m), "total": g.num_gaussians})
    if static_life > 0:
        records[-1]["static"] = int((life == static_life).sum())
    if guard > 0:
        records[-1]["guarded"] = guarded
    if cfg.births.motion != "none":
        records[-1].update(move_born(run, frames, knots, t, g.num_gaussians - m))
    return records[-1]


def backward_displacement(born: np.ndarray, cams: list, others: np.ndarray, others_delta: np.ndarray,
                          max_dist: float, use_flow: bool = True) -> tuple[np.ndarray, np.ndarray, int]:
    """Displacement ``T_j -> T_{j-1}`` [M, 3] of the Gaussians born at ``born`` [M, 3] (their
    places at ``T_j``) and the bool [M] of those that got one, with how many the flow decided.

    ``cams``: per train camera ``(view, flow [H, W, 2] from T_j to T_{j-1}, depth_j, ok_j,
    depth_{j-1}, ok_{j-1})`` (:func:`carry_by_flow`; a visible surface point with no flow is
    decided still). The rest take the displacement of the nearest of ``others`` [P, 3]
    (Gaussians alive at ``T_j``, at their ``T_j`` places, with ``others_delta`` [P, 3])
    within ``max_dist``."""
    born = np.asarray(born, np.float32)
    delta = np.zeros_like(born)
    decided = np.zeros(len(born), dtype=bool)
    for view, flow, d_a, ok_a, d_b, ok_b in (cams if use_flow else ()):
        new, ok, still = carry_by_flow(born, view, flow, d_a, ok_a, d_b, ok_b, return_still=True)
        ok &= ~decided
        delta[ok] = new[ok] - born[ok]
        decided |= ok | still
    n_flow = int(decided.sum())
    if max_dist > 0 and len(others) and not decided.all():
        pos = np.concatenate([born, np.asarray(others, np.float32)])
        d = np.concatenate([delta, np.asarray(others_delta, np.float32)])
        mask = np.concatenate([decided, np.ones(len(others), dtype=bool)])
        d, taken = propagate_to_hidden(pos, d, mask, max_dist)
        delta[~decided] = d[:len(born)][~decided]
        decided |= taken[:len(born)]
    return delta, decided, n_flow


def component_flow(img_a: np.ndarray, img_b: np.ndarray, mask_a: np.ndarray, radius: int,
                   min_area: int = 8) -> np.ndarray:
    """Flow [H, W, 2] (``a(p) ~ b(p + flow(p))``) that is one translation per connected
    component of ``mask_a`` [H, W] bool: where the component's pixels of ``img_a`` [H, W, 3]
    match ``img_b`` best (masked sum of squared differences, OpenCV ``matchTemplate``) within
    ``radius`` px; zero elsewhere. Why: optical flow misses motion of about an object's own
    size per frame (fast scene, train pairs T1 -> T0, moving pixels: DIS median |flow| 1.0 px,
    warp error 0.183 against 0.206 for zero flow; the ball moves ~20 px)."""
    import cv2

    a, b = np.ascontiguousarray(img_a[..., :3], np.float32), np.ascontiguousarray(img_b[..., :3], np.float32)
    h, w = mask_a.shape
    flow = np.zeros((h, w, 2), np.float32)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask_a.astype(np.uint8), connectivity=8)
    for k in range(1, n):
        x, y, bw, bh, area = (int(v) for v in stats[k])
        if area < min_area:
            continue
        templ, m = a[y:y + bh, x:x + bw], (labels[y:y + bh, x:x + bw] == k).astype(np.float32)
        x0, y0 = max(0, x - radius), max(0, y - radius)
        search = b[y0:min(h, y + bh + radius), x0:min(w, x + bw + radius)]
        if search.shape[0] < bh or search.shape[1] < bw:
            continue
        res = cv2.matchTemplate(search, templ, cv2.TM_SQDIFF, mask=np.repeat(m[..., None], 3, -1))
        sx, sy = cv2.minMaxLoc(np.nan_to_num(res, nan=np.inf))[2]
        flow[labels == k] = (x0 + sx - x, y0 + sy - y)
    return flow


def _born_mask(view, points: np.ndarray, shape, grow: int) -> np.ndarray:
    """bool [H, W]: the pixels of ``points`` [M, 3] in ``view``, grown by ``grow`` px."""
    import cv2

    from ...cameras import project_points

    uv, z = project_points(view, points)
    h, w = shape
    keep = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    mask = np.zeros((h, w), np.uint8)
    mask[uv[keep, 1].astype(int), uv[keep, 0].astype(int)] = 1
    return cv2.dilate(mask, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)).astype(bool)


def move_born(run, frames, knots, t: float, first: int) -> dict:
    """Write the junctions before and after ``t`` of the Gaussians born at ``t`` (rows
    ``first:``) from :func:`backward_displacement` towards ``T_{j-1}`` (held before it) and
    ``T_{j+1}`` (held after it; the carry leaves short-lived Gaussians alone when
    ``birth_motion`` is on) (``birth_motion``, module docstring). Returns counts for run.json's
    ``births`` record."""
    j = int(np.argmin([abs(k - t) for k in knots]))
    cfg, model = run.cfg, run.model
    g = model.gaussians
    tm = getattr(g, TRAJ_MEANS).data
    pri = instant_depth_priors(run, frames) if cfg.births.motion != "nearest" else {}
    by_cam: dict = {}
    for f in frames:
        by_cam.setdefault(f.camera, {})[round(float(f.time), 9)] = f
    with torch.no_grad():
        at_j = model.attributes(knots[j])["means"].detach().cpu().numpy()
        alive = temporal_opacity(getattr(g, TIME_CENTER), getattr(g, TIME_LOG_SCALE), knots[j]).cpu().numpy() > 0.5
    alive[first:] = False
    out = {}
    for side, i in (("back", j - 1), ("ahead", j + 1)):
        if not 0 <= i < len(knots):
            continue
        with torch.no_grad():
            at_i = model.attributes(knots[i])["means"].detach().cpu().numpy()
        cams = []
        for at in by_cam.values():
            fa, fb = at.get(round(knots[j], 9)), at.get(round(knots[i], 9))
            if fa is None or fb is None or id(fa) not in pri or id(fb) not in pri:
                continue
            img_a, img_b, view = frame_image(run, fa), frame_image(run, fb), run.capture.view(fa)
            if cfg.births.motion == "match":
                mask = _born_mask(view, at_j[first:], img_a.shape[:2], int(STRIDE))
                flow = component_flow(img_a, img_b, mask, int(round(MATCH_RADIUS * img_a.shape[1])))
            else:
                flow = image_flow(img_a, img_b, cfg.births.motion)
            cams.append((view, flow, *pri[id(fa)], *pri[id(fb)]))
        delta, decided, n_flow = backward_displacement(
            at_j[first:], cams, at_j[alive], (at_i - at_j)[alive], scene_flow.CARRY_HIDDEN * run.extent)
        idx = torch.from_numpy(first + np.nonzero(decided)[0]).to(tm.device)
        d = torch.from_numpy(delta[decided]).to(tm)
        for k in (range(i + 1) if i < j else range(i, len(knots))):
            tm[idx, 3 * k] = d
        out.update({f"moved_{side}": int(decided.sum()), f"by_flow_{side}": n_flow})
    return out
