"""Scene flow of Gaussians between two RGB instants: 2D flow + per-instant stereo depth.

The time curriculum admits RGB instants in order; a Gaussian on a fast object (about its
own size per frame, issue 11) that starts the next instant where it was has no overlap
with its new image, so photometric gradients cannot find it. Both cameras see every RGB
instant, so stereo depth pins *where* the surface is at each instant and optical flow
says *which* pixel went where. :func:`carry_by_flow` moves each Gaussian that is the
visible surface at ``t_a`` (its depth agrees with the confident stereo depth at its pixel)
along the flow to ``t_b`` and lifts it with the stereo depth there::

    x_b = backproject(view, uv_a + flow_ab(uv_a), depth_b(uv_a + flow_ab(uv_a)))

Gaussians that do not move (|flow| below ``min_flow_px``) hold (:func:`junction_moves`);
those hidden, outside the image or on unconfident depth are left to the caller's fallback
(constant velocity).
Shapes: positions [N, 3] (world), images [H, W, 3] float, depth maps [H, W] (camera z,
the stereo's planar depth) with bool confidence masks [H, W].
"""
from __future__ import annotations

import threading

import cv2
import numpy as np
import torch

from ...cameras import View, project_points
from ...geometry.depth_priors import stereo_depth_priors
from ...scene.model import TRAJ_MEANS, born_mask
from ..frames.interpolation import lk_flow
from .nearest import nearest_within

__all__ = ["dense_flow", "image_flow", "carry_by_flow", "backproject_pixels", "propagate_to_hidden",
           "propagate_to_hidden_dense", "junction_moves", "carry_trajectories", "frame_image"]


def _grey8(img: np.ndarray) -> np.ndarray:
    """8-bit grey of a linear RGB image [H, W, >=3] (sRGB-like gamma: DIS works on 8-bit)."""
    rgb = np.clip(np.asarray(img, np.float32)[..., :3], 0.0, 1.0)
    grey = rgb @ np.array([0.299, 0.587, 0.114], np.float32)
    return (np.power(grey, 1.0 / 2.2) * 255.0 + 0.5).astype(np.uint8)


# True: dense_flow reuses one DIS object per thread and finest scale. Creating one per call cost
# ~2.5 of ~16 ms CPU per 160 x 120 flow (its buffers allocated afresh, measured); the flow is the same,
# bit for bit: calc() starts from scratch when no initial flow is passed (tests/test_step_cost.py).
# False: a new object per call, as before (bench-step's "stepcost-before" variant)
# x extent: Gaussians hidden from the train cameras take the motion of the nearest carried (or still)
# one within this distance (0: off); the carry's optical flow: lk (engine.train.frames.interpolation) | dis
CARRY_HIDDEN = 0.05
CARRY_FLOW = "lk"
REUSE_DIS = True
_DIS = threading.local()


def _dis(finest_scale: int | None, mean_normalization: bool = True):
    """OpenCV's DIS (medium preset, ``finest_scale`` set unless None, its patch mean
    normalisation on or off): this thread's own object when :data:`REUSE_DIS` (a DIS object
    must not run two flows at once), else a new one."""
    key = (None if finest_scale is None else int(finest_scale), bool(mean_normalization))
    cache = _DIS.__dict__.setdefault("by_scale", {}) if REUSE_DIS else {}
    dis = cache.get(key)
    if dis is None:
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        if key[0] is not None:
            dis.setFinestScale(key[0])
        dis.setUseMeanNormalization(key[1])
        cache[key] = dis
    return dis


def dense_flow(a_u8: np.ndarray, b_u8: np.ndarray, upsample: int = 2, finest_scale: int | None = 0,
               init: np.ndarray | None = None, mean_normalization: bool = True) -> np.ndarray:
    """OpenCV's DIS optical flow (medium preset) [h, w, 2] (x, y pixels) between 8-bit grey
    images with ``a(p) ~ b(p + flow(p))`` (OpenCV's ``calc(prev=a, next=b)`` convention).
    Small images (a spike frame is e.g. 80 x 60) are upsampled ``upsample`` x so DIS's
    patches and pyramid have room, and the flow is brought back to the input's pixels;
    ``finest_scale`` is DIS's finest pyramid level (0: full resolution; None: the preset's).
    ``init`` [h, w, 2] (input pixels): a flow DIS starts from instead of zero (a warm start:
    OpenCV takes a flow passed to ``calc`` as its initial estimate);
    ``mean_normalization``: DIS's per-patch mean normalisation."""
    h, w = a_u8.shape
    s = max(1, int(upsample))
    if s > 1:
        a_u8 = cv2.resize(a_u8, (w * s, h * s), interpolation=cv2.INTER_CUBIC)
        b_u8 = cv2.resize(b_u8, (w * s, h * s), interpolation=cv2.INTER_CUBIC)
    if init is not None:
        init = np.asarray(init, np.float32)
        if s > 1:
            init = cv2.resize(init, (w * s, h * s), interpolation=cv2.INTER_LINEAR) * float(s)
        init = np.ascontiguousarray(init, dtype=np.float32)
    dis = _dis(finest_scale, mean_normalization)
    flow = dis.calc(np.ascontiguousarray(a_u8), np.ascontiguousarray(b_u8), init)
    if s > 1:
        flow = cv2.resize(flow, (w, h), interpolation=cv2.INTER_AREA) / float(s)
    return flow.astype(np.float32)


def image_flow(img_a: np.ndarray, img_b: np.ndarray, method: str = "lk") -> np.ndarray:
    """Dense flow [H, W, 2] (x, y pixels) with ``a(p) ~ b(p + flow(p))``.

    ``method``: ``"lk"`` -- our block matching + Lucas-Kanade pyramid
    (engine.interpolation.lk_flow); ``"dis"`` -- OpenCV's DIS optical flow (Kroeger et al.,
    ECCV 2016; medium preset, with variational refinement) on the 8-bit grey images. On the
    fast scene's train pairs, moving pixels: 84 % pass the forward-backward check with DIS
    against 29 % with LK, at 14 ms against ~2.8 s per flow (2-core VM, load 6)."""
    if method == "dis":
        return dense_flow(_grey8(img_a), _grey8(img_b), upsample=1, finest_scale=None)
    if method != "lk":
        raise ValueError(f"unknown optical flow method {method!r}: expected lk or dis")
    a = torch.as_tensor(np.asarray(img_a, np.float32)[..., :3]).permute(2, 0, 1)[None]
    b = torch.as_tensor(np.asarray(img_b, np.float32)[..., :3]).permute(2, 0, 1)[None]
    return lk_flow(a, b)[0].permute(1, 2, 0).numpy()


def backproject_pixels(view: View, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World points [N, 3] of pixel coordinates ``uv`` [N, 2] (corner at (0, 0)) at camera
    z ``depth`` [N]: the inverse of :func:`engine.cameras.project_points`."""
    k = view.intrinsics
    z = np.asarray(depth, np.float64)
    cam = np.stack([(uv[:, 0] - k.cx) / k.fx * z, (uv[:, 1] - k.cy) / k.fy * z, z, np.ones_like(z)], 1)
    return (np.linalg.inv(view.viewmat) @ cam.T).T[:, :3]


def _sample(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    ui = np.clip(np.floor(uv[:, 0]).astype(int), 0, w - 1)
    vi = np.clip(np.floor(uv[:, 1]).astype(int), 0, h - 1)
    return img[vi, ui]


def carry_by_flow(positions: np.ndarray, view: View, flow_ab: np.ndarray, depth_a: np.ndarray, ok_a: np.ndarray,
                  depth_b: np.ndarray, ok_b: np.ndarray, *, depth_tol: float = 0.05,
                  min_flow_px: float = 0.5, return_still: bool = False):
    """(positions at ``t_b`` [N, 3], carried bool [N]) for Gaussians at ``positions`` (``t_a``)
    seen by the static camera ``view``; rows not carried are returned unchanged. With
    ``return_still`` also the bool [N] of visible surface Gaussians that do not move. (A
    forward-backward check of the flow was measured and dropped: docs/experiments/motion-representation.md.)"""
    pos = np.asarray(positions, np.float64)
    uv, z = project_points(view, pos)
    h, w = depth_a.shape
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    uv_c = np.where(inside[:, None], uv, 0.0)
    da = _sample(depth_a, uv_c)
    surface = inside & _sample(ok_a, uv_c) & (np.abs(z - da) <= depth_tol * np.maximum(da, 1e-9))
    f = _sample(flow_ab, uv_c)
    uv_b = uv_c + f
    inside_b = (uv_b[:, 0] >= 0) & (uv_b[:, 0] < w) & (uv_b[:, 1] >= 0) & (uv_b[:, 1] < h)
    uv_b = np.where(inside_b[:, None], uv_b, 0.0)
    db = _sample(depth_b, uv_b)
    fl = np.linalg.norm(f, axis=1)
    moving = fl >= min_flow_px
    carried = surface & inside_b & _sample(ok_b, uv_b) & moving
    out = pos.copy()
    if carried.any():
        # keep the Gaussian's offset from the surface along the ray (it sat at z, the surface at da)
        out[carried] = backproject_pixels(view, uv_b[carried], db[carried] + (z - da)[carried])
    if return_still:
        return out.astype(np.float32), carried, surface & ~moving
    return out.astype(np.float32), carried


def _hand_over(delta: np.ndarray, decided: np.ndarray):
    """(a copy of ``delta`` to fill, taken bool [N] all False, decided rows, undecided rows)."""
    return (np.asarray(delta, np.float32).copy(), np.zeros(len(decided), dtype=bool),
            np.nonzero(decided)[0], np.nonzero(~decided)[0])


def propagate_to_hidden(positions: np.ndarray, delta: np.ndarray, decided: np.ndarray, max_dist: float,
                        chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Give each undecided Gaussian (hidden at ``t_a``: inside or behind a moving object)
    the displacement of its nearest decided one (carried, or a still visible surface) within
    ``max_dist``: what lies under a surface moves with it, instead of staying behind as
    specks (measured on the novel scene's ball, issue 11). Returns (delta [N, 3], taken [N]).
    The exact grid search of :func:`engine.train.motion.nearest.nearest_within` (issue 13: the
    dense ``torch.cdist`` it replaces, :func:`propagate_to_hidden_dense`, cost ~0.2-1.2 s
    per admitted instant)."""
    if DENSE_SEARCH:
        return propagate_to_hidden_dense(positions, delta, decided, max_dist, chunk)
    pos = np.asarray(positions, np.float32)
    out, taken, src, dst = _hand_over(delta, decided)
    if len(src) == 0 or len(dst) == 0:
        return out, taken
    j, _ = nearest_within(pos[dst], pos[src], max_dist)
    ok = j >= 0
    out[dst[ok]] = out[src[j[ok]]]
    taken[dst[ok]] = True
    return out, taken


DENSE_SEARCH = False  # True: the dense torch.cdist search (bench-step's "nn-dense" variant)


@torch.no_grad()
def propagate_to_hidden_dense(positions: np.ndarray, delta: np.ndarray, decided: np.ndarray, max_dist: float,
                              chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """:func:`propagate_to_hidden` by a dense float32 ``torch.cdist`` (as before issue 13)."""
    pos = torch.as_tensor(np.asarray(positions, np.float32))
    out, taken, src, dst = _hand_over(delta, decided)
    if len(src) == 0 or len(dst) == 0:
        return out, taken
    ps = pos[torch.from_numpy(src)]
    for s in range(0, len(dst), chunk):
        idx = dst[s:s + chunk]
        d, j = torch.cdist(pos[torch.from_numpy(idx)], ps).min(dim=1)
        ok = (d <= max_dist).numpy()
        out[idx[ok]] = out[src[j.numpy()[ok]]]
        taken[idx[ok]] = True
    return out, taken


def instant_depth_priors(run, frames) -> dict:
    """The per-instant stereo depth of the train ``frames`` ({id(frame): (depth, ok)},
    :func:`stereo_depth_priors`), computed once per run and shared by the carry and the
    births (engine.train.motion.births)."""
    memo = run.memo
    if memo.get("stereo_priors") is None:
        memo["stereo_priors"] = stereo_depth_priors(run.capture, frames, fusion_cache=run.fusion_cache)
    return memo["stereo_priors"]


# False: the carry and the births read the frames from disk at each admission (bench-step's
# "step-before" variant)
ITEM_IMAGES = True


def frame_image(run, frame) -> np.ndarray:
    """The RGB image [H, W, 3] float32 of a train ``frame``: the copy the run holds
    (``run.items``, loaded once per run) when it trains on that frame, else read from
    disk (e.g. a frame early stopping holds back) -- the same numbers either way."""
    if not ITEM_IMAGES:
        return np.asarray(frame.load_rgb(), np.float32)[..., :3]
    cache = run.memo.get("item_images")
    if cache is None:
        cache = run.memo["item_images"] = {(it["camera"], round(float(it["time"]), 9)): it["image"]
                                           for it in run.items}
    img = cache.get((frame.camera, round(float(frame.time), 9)))
    if img is not None and img.device.type == "cpu":
        return img[0].numpy()
    return np.asarray(frame.load_rgb(), np.float32)[..., :3]


def junction_moves(positions: np.ndarray, per_camera,
                   hidden_radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Which Gaussians the carry places at the next RGB instant, and by how much.

    ``per_camera``: one ``(new positions, carried, still)`` of :func:`carry_by_flow` per train
    camera, in order (the first camera that carries a Gaussian decides its move). A Gaussian
    that a camera sees as a still surface (its flow under ``min_flow_px``) and no camera
    carries *holds* (delta 0): continuing its last segment's velocity compounded each
    instant's fitting noise into a drift of the static world (seed 154, RGB-only, 1000 steps:
    the median long-lived Gaussian 4 cm from its first junction at the last one;
    docs/experiments/carry-holds-still-surfaces.md). Hidden Gaussians take the move of their
    nearest decided neighbour within ``hidden_radius`` (world units; 0: off) when it moved.
    Returns (delta [N, 3], placed [N] bool, held [N] bool, by_flow [N] bool: moved by a
    camera's flow); rows not placed are left to the caller's constant-velocity fallback."""
    pos = np.asarray(positions, np.float32)
    todo = np.ones(len(pos), dtype=bool)
    still = np.zeros(len(pos), dtype=bool)
    delta = np.zeros_like(pos)
    for new, ok, st in per_camera:
        ok = ok & todo
        delta[ok] = new[ok] - pos[ok]
        todo &= ~ok
        still |= st
    by_flow = ~todo
    held = still & todo
    todo &= ~still
    if hidden_radius > 0:
        delta, taken = propagate_to_hidden(pos, delta, ~todo, hidden_radius)
        todo &= ~(taken & (np.abs(delta).sum(1) > 0))
    return delta, ~todo, held, by_flow


def carry_trajectories(run, frames, knots, i: int, j: int) -> dict:
    """Move the junction ``j`` of every Gaussian that is the visible surface at knot ``i`` in
    a train camera along that camera's optical flow, lifted by the stereo depth at
    ``knots[j]`` (``frames``: the train RGB frames); a still visible surface holds; hidden
    Gaussians follow their nearest decided neighbour (``traj_carry_hidden`` x extent); later
    knots hold the result (:func:`junction_moves`). Returns counts (run.json)."""
    pri = instant_depth_priors(run, frames)
    g = run.model.gaussians
    with torch.no_grad():
        pos_i = run.model.attributes(knots[i])["means"].detach().cpu().numpy()
    by_cam: dict = {}
    for f in frames:
        by_cam.setdefault(f.camera, {})[round(float(f.time), 9)] = f
    per_camera = []
    for at in by_cam.values():
        fa, fb = at.get(round(knots[i], 9)), at.get(round(knots[j], 9))
        if fa is None or fb is None or id(fa) not in pri or id(fb) not in pri:
            continue
        img_a, img_b = frame_image(run, fa), frame_image(run, fb)
        per_camera.append(carry_by_flow(pos_i, run.capture.view(fa), image_flow(img_a, img_b, CARRY_FLOW),
                                        *pri[id(fa)], *pri[id(fb)], return_still=True))
    delta, carried, held, by_flow = junction_moves(pos_i, per_camera, CARRY_HIDDEN * run.extent)
    if run.cfg.births.motion != "none":  # births.move_born moved those
        carried &= ~born_mask(g).cpu().numpy()
    if carried.any():
        tm = getattr(g, TRAJ_MEANS).data
        idx = torch.from_numpy(np.nonzero(carried)[0]).to(tm.device)
        d = torch.from_numpy(delta[carried]).to(tm)
        for k in range(j, len(knots)):
            tm[idx, 3 * k] = tm[idx, 3 * i] + d
    return {"from": float(knots[i]), "to": float(knots[j]), "carried": int(carried.sum()),
            "by_flow": int(by_flow.sum()), "held": int((held & carried).sum()), "total": int(len(carried))}
