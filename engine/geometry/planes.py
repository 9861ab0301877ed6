"""Dominant planes of the fused static stereo cloud, carried beyond what the pair saw (issue 14).

A table-top or room capture is dominated by a few large planes (floor, wall, table top). Where
the two train cameras saw nothing -- beyond their image borders, or a weakly textured patch
that stereo could not match -- the planes still say where the surface is, while continuing the
depth map linearly from the border (``resolution.extrapolate_inverse_depth``) bends it wherever the
border crosses an object (docs/experiments/two-view-geometry.md: 4x the depth error at 20-30 deg).

* :func:`fit_planes` -- sequential RANSAC on the static cloud (numpy), each plane refined by a
  least-squares (SVD) fit to its inliers; only planes carrying ``min_share`` of the points count.
* :func:`ray_plane_depth` -- planar depth of the first plane a pixel's ray meets in front.
* :func:`plane_backdrop_points` -- points on the planes in a ring beyond one camera's image
  borders, coloured by the nearest border pixel.
* :func:`plane_fill` -- stereo holes inside the image take the plane depth where it agrees with
  the depth interpolated from their neighbours.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Plane:
    """``normal . x + offset = 0`` (world), ``normal`` unit length; ``inliers``: supporting points;
    ``bounds``: (axes [2, 3], low [2], high [2]) in the plane of the set it bounds (None: unbounded)."""

    normal: np.ndarray
    offset: float
    inliers: int
    bounds: tuple | None = None

    def distance(self, xyz: np.ndarray) -> np.ndarray:
        """Signed distance [N] of points [N, 3]."""
        return np.asarray(xyz, np.float64) @ self.normal + self.offset

    def within(self, xyz: np.ndarray) -> np.ndarray:
        """[...] bool: points [..., 3] (on the plane) within ``bounds`` widened by ``BOUNDS_MARGIN``
        of their extent on every side (a wall's plane does not continue metres under the floor)."""
        if self.bounds is None:
            return np.ones(np.shape(xyz)[:-1], bool)
        axes, lo, hi = self.bounds
        q = np.asarray(xyz, np.float64) @ np.asarray(axes).T
        m = BOUNDS_MARGIN * (hi - lo)
        return np.all((q >= lo - m) & (q <= hi + m), axis=-1)


def _refine(xyz: np.ndarray) -> tuple[np.ndarray, float]:
    c = xyz.mean(0)
    _, _, vt = np.linalg.svd(xyz - c, full_matrices=False)
    n = vt[-1] / np.linalg.norm(vt[-1])
    return n, float(-n @ c)


PARALLEL_COS = math.cos(math.radians(15.0))
BOUNDS_MARGIN = 0.5


def _in_plane_axes(normal: np.ndarray) -> np.ndarray:
    """[2, 3]: two orthonormal axes in the plane of ``normal`` (the world axis least along the
    normal, and the normal's cross product with it)."""
    a = np.eye(3)[int(np.argmin(np.abs(normal)))]
    a = a - normal * (a @ normal)
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(normal, a)])


def _extent(pts: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(axes [2, 3], 5 % [2], 95 % [2]) of points [N, 3] along the in-plane axes of ``normal``."""
    axes = _in_plane_axes(normal)
    q = np.percentile(pts @ axes.T, [5, 95], axis=0)
    return axes, q[0], q[1]


def fit_planes(xyz: np.ndarray, threshold: float, *, max_planes: int = 3, min_share: float = 0.05,
               min_span: float = 0.6, eyes: np.ndarray | None = None, max_behind: float = 0.1,
               iterations: int = 400, max_points: int = 20000, seed: int = 0) -> list[Plane]:
    """Up to ``max_planes`` dominant planes of a cloud [N, 3], largest first (sequential RANSAC:
    the best of ``iterations`` 3-point samples by inliers within ``threshold`` (m), refined twice
    by SVD on its inliers, whose points are removed before the next). A plane is kept when it
    bounds a set the way a floor or a wall does (issue 46; docs/experiments/floor-stereo-missed.md):
    - it carries ``min_share`` of the (subsampled) points (a weakly textured floor 2 m away that
      stereo matches only at its shadows holds ~9 %; the 15 % asked until then missed it);
    - its inliers spread over ``min_span`` of the whole cloud's extent along one in-plane axis
      (a cube's face or a turntable's top does not);
    - with the cameras' centres ``eyes``: at most ``max_behind`` of the cloud, or 1.5 x the plane's
      own share, lies on its far side from them (a plane fitted through the middle of a set has
      half the scene behind it; a textureless wall's stereo outliers scatter behind the wall);
    - it is not within 15 deg of parallel to a kept plane (what the first fit left of a surface).
    Each kept plane's ``bounds`` are the whole cloud's 5-95 % extent along it, stretched to take in
    the cameras' feet on it (a floor runs on to the viewer where stereo found nothing): a plane
    is not taken where it leaves the set (a wall's plane metres under the floor)."""
    pts = np.asarray(xyz, np.float64)
    pts = pts[np.isfinite(pts).all(1)]
    rng = np.random.default_rng(seed)
    if len(pts) > max_points:
        pts = pts[rng.choice(len(pts), max_points, replace=False)]
    total, cloud = len(pts), pts
    eyes = None if eyes is None else np.asarray(eyes, np.float64)
    planes: list[Plane] = []
    for _ in range(2 * max_planes):  # an object's face found on the way is set aside, not kept
        if len(planes) >= max_planes or len(pts) < max(3, min_share * total):
            break
        s = rng.integers(0, len(pts), (iterations, 3))
        a, b, c = pts[s[:, 0]], pts[s[:, 1]], pts[s[:, 2]]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n, axis=1)
        good = norm > 1e-12
        if not good.any():
            break
        n, a = n[good] / norm[good, None], a[good]
        off = -(n * a).sum(1)
        counts = np.zeros(len(n), np.int64)
        for i0 in range(0, len(n), 64):  # [64, N] distances at a time
            counts[i0:i0 + 64] = (np.abs(n[i0:i0 + 64] @ pts.T + off[i0:i0 + 64, None]) <= threshold).sum(1)
        best = int(counts.argmax())
        normal, offset = n[best], float(off[best])
        for _ in range(2):
            inl = np.abs(pts @ normal + offset) <= threshold
            if inl.sum() < 3:
                break
            normal, offset = _refine(pts[inl])
        inl = np.abs(pts @ normal + offset) <= threshold
        if inl.sum() < min_share * total:
            break
        axes, lo, hi = _extent(cloud, normal)
        _, inl_lo, inl_hi = _extent(pts[inl], normal)
        spread = (inl_hi - inl_lo) / np.maximum(hi - lo, 1e-9)
        # a plane almost parallel to a kept one is what the first fit left of the same surface
        parallel = any(abs(float(normal @ p.normal)) > PARALLEL_COS for p in planes)
        behind = 0.0
        if eyes is not None:  # the share of the cloud on the far side of the plane from the cameras
            side = np.sign(np.mean(eyes @ normal + offset)) or 1.0
            behind = float(((cloud @ normal + offset) * side < -3.0 * threshold).mean())
        # a textureless wall's own stereo scatters behind it in proportion to its support
        if spread.max() >= min_span and not parallel and behind <= max(max_behind, 1.5 * inl.sum() / total):
            if eyes is not None:  # a floor runs on to the cameras' feet, where stereo has nothing
                q = eyes @ axes.T
                lo, hi = np.minimum(lo, q.min(0)), np.maximum(hi, q.max(0))
            planes.append(Plane(normal, offset, int(inl.sum()), (axes, lo, hi)))
        pts = pts[~inl]
    return planes


def _rays(view, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World origin [3] and directions [..., 3] (camera z component 1, so the ray parameter is
    planar depth) through pixel coordinates (u, v) measured from the top-left corner."""
    k = view.intrinsics
    cam = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u, dtype=np.float64)], -1)
    c2w = np.linalg.inv(np.asarray(view.viewmat, np.float64))
    return c2w[:3, 3], cam @ c2w[:3, :3].T


def ray_plane_depth(view, planes: list[Plane], u: np.ndarray, v: np.ndarray, *,
                    max_depth: float = np.inf, bounded: bool = False) -> np.ndarray:
    """Planar depth [...] of the first plane each ray through (u, v) meets in front of the
    camera (a floor and a wall seen from inside their corner: the nearest hit is the surface),
    NaN where none within ``max_depth``; ``bounded``: only hits within each plane's set
    (:meth:`Plane.within`) count."""
    o, d = _rays(view, np.asarray(u, np.float64), np.asarray(v, np.float64))
    best = np.full(d.shape[:-1], np.inf)
    for p in planes:
        den = d @ p.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(o @ p.normal + p.offset) / den
        t = np.where((np.abs(den) > 1e-9) & (t > 0), t, np.inf)
        if bounded:  # only where the plane lies within the set (Plane.within)
            t = np.where(p.within(o + d * np.where(np.isfinite(t), t, 0.0)[..., None]), t, np.inf)
        best = np.minimum(best, t)
    return np.where(best <= max_depth, best, np.nan).astype(np.float32)


def plane_backdrop_points(view, median_image: np.ndarray, planes: list[Plane], fraction: float, *,
                          stride: int = 4, max_depth: float = np.inf, continued: np.ndarray | None = None):
    """Points on ``planes`` in a ring ``fraction`` x the image size wide beyond the borders of
    ``view``, one every ``stride`` px, coloured by the nearest border pixel of ``median_image``
    [H, W, 3]; ring pixels whose ray meets no plane get no point. ``continued``: the view's depth
    continued beyond its borders ([H + 2 py, W + 2 px], ``resolution.extrapolate_inverse_depth``);
    where a ray below the image meets no plane within the set's extent (:meth:`Plane.within`), the
    point takes that depth instead (a floor no plane was found for continues as itself, not on the
    wall's plane metres under it; beside and above the image the continuation bends at whatever
    crosses the border and grew fog: docs/experiments/floor-stereo-missed.md). Returns (xyz [N, 3],
    rgb [N, 3])."""
    k = view.intrinsics
    px, py = int(round(fraction * k.width)), int(round(fraction * k.height))
    empty = np.zeros((0, 3), np.float32)
    if px <= 0 and py <= 0 or not planes:
        return empty, empty
    col = cv2.copyMakeBorder(np.asarray(median_image, np.float32), py, py, px, px, cv2.BORDER_REPLICATE)
    He, We = k.height + 2 * py, k.width + 2 * px
    ring = np.ones((He, We), bool)
    ring[py:py + k.height, px:px + k.width] = False
    grid = np.zeros_like(ring)
    grid[stride // 2::stride, stride // 2::stride] = True
    vv, uu = np.nonzero(ring & grid)
    u, v = uu - px + 0.5, vv - py + 0.5
    depth = ray_plane_depth(view, planes, u, v, max_depth=max_depth)
    if continued is not None:
        # below the image the pair looks at the ground: a plane met there outside the set (a wall's
        # plane metres under a floor no plane was found for) gives way to the depth continued down
        # the columns, which a floor follows exactly (its inverse depth is affine in the pixel)
        below = np.flatnonzero(vv >= py + k.height)
        inside = ray_plane_depth(view, planes, u[below], v[below], max_depth=max_depth, bounded=True)
        cont = np.asarray(continued, np.float64)[vv[below], uu[below]]
        with np.errstate(invalid="ignore"):
            use = ~np.isfinite(inside) & (cont > 0) & (cont <= max_depth)
        depth[below] = np.where(np.isfinite(inside), inside, depth[below])
        depth[below[use]] = cont[use]
    hit = np.isfinite(depth)
    o, d = _rays(view, u[hit], v[hit])
    xyz = o + d * depth[hit, None]
    return xyz.astype(np.float32), col[vv[hit], uu[hit], :3].astype(np.float32)


def plane_fill(view, filled_depth: np.ndarray, ok: np.ndarray, planes: list[Plane], *,
               max_rel: float = 0.1) -> np.ndarray:
    """[H, W] depth: ``filled_depth`` (stereo where ``ok``, interpolated elsewhere) with the
    unknown pixels replaced by the plane depth where that agrees with the interpolation within
    ``max_rel`` (a weakly textured floor keeps its plane; a hole inside an object keeps the
    interpolation). Taking the plane also where the interpolation runs behind it (the floor's
    bottom rows: 22-42 % too far, 0.4-0.8 % on the plane) paid 0.3-0.5 dB on the two sets it was
    built on and -0.12...-0.02 on three unseen ones: not kept (docs/experiments/floor-stereo-missed.md)."""
    k = view.intrinsics
    v, u = np.mgrid[0:k.height, 0:k.width].astype(np.float64)
    pd = ray_plane_depth(view, planes, u + 0.5, v + 0.5)
    f = np.asarray(filled_depth, np.float32)
    with np.errstate(invalid="ignore"):
        agree = ~ok & np.isfinite(pd) & (np.abs(pd - f) <= max_rel * np.abs(f))
    return np.where(agree, pd, f).astype(np.float32)


def static_planes(fused: list, *, rel_threshold: float = 0.01, **options) -> list[Plane]:
    """:func:`fit_planes` on the static stereo points of every camera's
    :class:`~engine.geometry.stereo.FusedDepth` (threshold ``rel_threshold`` x their median
    depth)."""
    pts, depths, eyes = [], [], []
    for f in fused:
        eyes.append(np.linalg.inv(np.asarray(f.view.viewmat, np.float64))[:3, 3])
        ok = np.isfinite(f.static_depth)
        if ok.any():
            v, u = np.nonzero(ok)
            o, d = _rays(f.view, u + 0.5, v + 0.5)
            pts.append(o + d * f.static_depth[ok][:, None].astype(np.float64))
            depths.append(f.static_depth[ok])
    if not pts:
        return []
    options.setdefault("eyes", np.stack(eyes))
    return fit_planes(np.concatenate(pts), rel_threshold * float(np.median(np.concatenate(depths))), **options)


def nearest_known_on_plane(view, depth: np.ndarray, ok: np.ndarray, planes: list[Plane], *,
                           rel_tol: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """(plane depth [H, W], mask [H, W]): the pixels without stereo (``~ok``) whose nearest pixel
    with stereo lies on the planes (its depth within ``rel_tol`` of the plane depth there) -- a
    gap in a matched floor, not a hole in an object in front of it. Unlike :func:`plane_fill`,
    nothing is interpolated: a slanted floor's depth changes by several % per row near the
    camera, which an interpolation across a gap does not follow."""
    k = view.intrinsics
    v, u = np.mgrid[0:k.height, 0:k.width].astype(np.float64)
    pd = ray_plane_depth(view, planes, u + 0.5, v + 0.5)
    if not planes or ok.all() or not ok.any():
        return pd, np.zeros_like(ok)
    with np.errstate(invalid="ignore"):
        inlier = ok & np.isfinite(pd) & (np.abs(depth - pd) <= rel_tol * pd)
    # nearest known pixel of every pixel: labels of cv2's distance transform index the zero
    # (known) pixels in row-major order
    _, labels = cv2.distanceTransformWithLabels((~ok).astype(np.uint8), cv2.DIST_L2, 5,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    flat = np.flatnonzero(ok.ravel())
    nearest = flat[np.clip(labels.ravel() - 1, 0, len(flat) - 1)].reshape(ok.shape)
    mask = ~ok & np.isfinite(pd) & inlier.ravel()[nearest]
    return pd, mask
