"""Training terms that keep geometry consistent across the two train views (issue 14, item 3).

Each is a switch of the training configuration's ``losses`` group (binocular consistency,
depth smoothness and a random background were measured and dropped:
docs/experiments/two-view-geometry.md):

* ``opacity_decay`` -- each step, the opacity of the Gaussians the step's view sees is
  multiplied by this factor (Binocular-guided 3DGS, Sec. 3.3, 0.995): Gaussians that the
  photometric loss keeps needing recover, floaters that only one view supports fade and are
  pruned by the usual ``prune_opacity`` rule. Gaussians outside the rendered view are left
  alone (so the backdrop beyond every train frustum keeps its opacity).
* ``losses.cover`` -- no cracks at a nearby new viewpoint: every ``COVER_EVERY`` steps the
  step's frame is rendered again (``COVER_SCALE`` x its resolution, same instant) from a
  virtual camera turned by ``COVER_ANGLE_DEG`` x U(0.5, 1) about the point the view looks at
  (its median rendered depth on the optical axis), about a random axis in the image plane;
  the mean of ``1 - alpha`` over the pixels inside the render's covered region (a
  morphological closing of ``alpha > 0.5`` with a box ``COVER_KERNEL_FRAC`` x the render's
  shorter side wide: the cracks between splats, not the empty space around the scene),
  restricted to the pixels the step's own view sees (``seen_from``, at the orbit's pivot
  depth), is the loss; only the Gaussians the step's own render draws get its gradient
  (``Model4D.render(grad_rows=...)``), and only their ``cover_grad`` attributes. A floor seen at a grazing angle
  by both train cameras is made of blobs that leave gaps 20 deg above it (docs/experiments/overfit-more-steps.md);
  the photometric loss never sees those gaps.
* ``losses.flat`` -- Gaussians on the stereo surface lie flat in it (:func:`lie_flat`): a
  horizontal baseline leaves horizontal edges free to be fins or stacked discs, which smear seen
  from above.
Functions take and return tensors with documented shapes; the run calls
:func:`geometry_loss_terms` (loss list) and :func:`geometry_post_step_hooks`.
"""
from __future__ import annotations

import functools
import math

import numpy as np
import torch
import torch.nn.functional as F

from ...geometry.depth_priors import world_planes
from ...raster.projection import pinhole_project
from ...scene.model import scaled_view
from ..config import opacity_decay_window


def pixel_grid(height: int, width: int, device=None) -> torch.Tensor:
    """[H, W, 2] pixel-centre coordinates (u + 0.5, v + 0.5) of the engine's convention."""
    v, u = torch.meshgrid(torch.arange(height, device=device, dtype=torch.float32) + 0.5,
                          torch.arange(width, device=device, dtype=torch.float32) + 0.5, indexing="ij")
    return torch.stack([u, v], -1)


def project_into(depth_a: torch.Tensor, K_a: torch.Tensor, viewmat_a: torch.Tensor, K_b: torch.Tensor,
                 viewmat_b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where view a's pixels land in view b: (u_b, v_b, z_b), each [H,W], for the planar
    depth ``depth_a`` [H,W] of view a (K [3,3], viewmat [4,4] OpenCV world-to-camera, all in
    ``depth_a``'s dtype). ``z_b`` is the depth in b; u/v divide by it clamped to 1e-6."""
    H, W = depth_a.shape
    uv = pixel_grid(H, W, depth_a.device).to(depth_a.dtype)
    x = (uv[..., 0] - K_a[0, 2]) / K_a[0, 0] * depth_a
    y = (uv[..., 1] - K_a[1, 2]) / K_a[1, 1] * depth_a
    cam = torch.stack([x, y, depth_a], -1)                          # [H,W,3] camera a
    rel = viewmat_b @ torch.linalg.inv(viewmat_a)                   # a -> b
    q = cam @ rel[:3, :3].T + rel[:3, 3]
    z = q[..., 2]
    zs = torch.where(z > 1e-6, z, torch.full_like(z, 1e-6))
    return K_b[0, 0] * q[..., 0] / zs + K_b[0, 2], K_b[1, 1] * q[..., 1] / zs + K_b[1, 2], z


def decay_visible_opacity(opacity_logits: torch.Tensor, visible: torch.Tensor, factor: float) -> None:
    """In place: opacity <- factor * opacity for the ``visible`` [N] Gaussians (logits [N] or [N,1])."""
    o = torch.sigmoid(opacity_logits[visible]) * factor
    opacity_logits[visible] = torch.logit(o.clamp(1e-6, 1 - 1e-6))


# ---------------------------------------------------------------------------------- run glue
def orbit_view(vt: dict, pivot_depth: float, axis_angle: float, angle_rad: float, scale: float = 1.0) -> dict:
    """A view dict (``view_tensors`` keys; viewmat world->camera [1,4,4], OpenCV axes) whose
    camera is turned by ``angle_rad`` about the point ``pivot_depth`` ahead on its optical
    axis, about the axis ``cos(axis_angle) x_cam + sin(axis_angle) y_cam``, at ``scale`` x the
    resolution (same field of view, :func:`engine.scene.model.scaled_view`). The image is not copied."""
    out = dict(vt)
    vm = vt["viewmat"][0].detach().to("cpu", torch.float64)  # 4x4 arithmetic: on the CPU whatever the device
    R_wc, t_wc = vm[:3, :3], vm[:3, 3]
    R_cw = R_wc.T                              # columns: camera axes in world
    c = -R_cw @ t_wc                           # camera centre
    p = c + float(pivot_depth) * R_cw[:, 2]    # the point the view looks at
    a = math.cos(axis_angle) * R_cw[:, 0] + math.sin(axis_angle) * R_cw[:, 1]
    ax = torch.tensor([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]], dtype=torch.float64)
    rot = torch.eye(3, dtype=torch.float64) + math.sin(angle_rad) * ax + (1 - math.cos(angle_rad)) * (ax @ ax)
    R_cw2, c2 = rot @ R_cw, p + rot @ (c - p)
    vm2 = torch.eye(4, dtype=torch.float64)
    vm2[:3, :3], vm2[:3, 3] = R_cw2.T, -R_cw2.T @ c2
    out["viewmat"] = vm2.to(vt["viewmat"].device, vt["viewmat"].dtype)[None]
    out["campos"] = c2.to(vt["campos"].device, vt["campos"].dtype)
    return scaled_view(out, scale)


def cover_kernel_px(fraction: float, height: int, width: int) -> int:
    """Side (odd, >= 3 px) of :func:`crack_mask`'s closing box for a ``height`` x ``width``
    render: ``fraction`` of its shorter side, so the box spans the same part of the view at any
    resolution (a 1080x720 capture renders 540x360 at ``COVER_SCALE`` 0.5, where the 9 px of the
    test scenes' 80x60 renders would close only cracks a fifth as wide). 0.125 keeps the 9 px
    measured on those scenes (80x60 and 96x72 renders); at 320x240 (160x120 renders) 9, 15 and
    19 px scored within 0.3 dB of each other, without a trend (docs/experiments/cover-loss.md)."""
    return max(3, int(float(fraction) * min(int(height), int(width)) + 0.5) | 1)


def crack_mask(alpha: torch.Tensor, kernel: int, covered: float = 0.5) -> torch.Tensor:
    """bool [H,W]: the pixels inside the covered region of ``alpha`` [H,W] -- a closing
    (dilate, then erode, ``kernel`` x ``kernel`` box) of ``alpha > covered`` -- so a crack
    between splats is inside and the empty space around the scene's outline is not. A box's
    max is a row max of column maxes: two 1-D pools per pass, O(kernel) per pixel rather than
    O(kernel^2) (a 45 px box at 540x360 stays cheap)."""
    k = max(1, int(kernel) | 1)
    r = k // 2
    # outside the image counts as empty: a band along the border is the view looking past the
    # scene's edge, not a crack (read as covered, it asked Gaussians at the edge to grow outward
    # every step, where no train view holds them: fog in RGB-only runs of ~3000 steps on the demo)
    m = F.pad((alpha.detach() > covered).float()[None, None], (r, r, r, r))

    def box_max(x):
        x = F.max_pool2d(x, (k, 1), stride=1, padding=(r, 0))
        return F.max_pool2d(x, (1, k), stride=1, padding=(0, r))

    closed = -box_max(-box_max(m))
    return closed[0, 0, r:r + alpha.shape[0], r:r + alpha.shape[1]] > 0.5


def seen_from(vt: dict, source: dict, depth: float) -> torch.Tensor:
    """bool [H,W] of view ``vt``: the pixels whose ray, at ``depth`` along ``vt``'s optical
    axis (the plane through the point it orbits), lands inside ``source``'s image, in front of
    it. Pixels beyond the train view's frustum show what no train camera saw: asking them to be
    covered grows Gaussians there that no photometric loss holds (fog in front of the demo's
    wall at the eval camera, above the train cameras' frustum, in RGB-only runs of ~3000 steps)."""
    H, W = int(vt["height"]), int(vt["width"])
    f64 = torch.float64
    u, v, z = project_into(torch.full((H, W), float(depth), dtype=f64, device=vt["K"].device),
                           vt["K"][0].to(f64), vt["viewmat"][0].to(f64),
                           source["K"][0].to(f64), source["viewmat"][0].to(f64))
    return (z > 1e-6) & (u >= 0) & (u < int(source["width"])) & (v >= 0) & (v < int(source["height"]))


def cover_loss(alpha: torch.Tensor, kernel: int, eligible: torch.Tensor | None = None) -> torch.Tensor | None:
    """Mean of ``1 - alpha`` over :func:`crack_mask`'s pixels of ``alpha`` [H,W] (and of the
    bool [H,W] ``eligible`` ones, when given), divided by the whole image's pixel count (a few
    cracks give a small loss); None when there is none."""
    inside = crack_mask(alpha, kernel)
    if eligible is not None:
        inside = inside & eligible
    if not bool(inside.any()):
        return None
    return ((1.0 - alpha) * inside).sum() / alpha.numel()


# the cover term: a virtual render every COVER_EVERY steps (4 against 2: a cheaper step, no loss),
# COVER_ANGLE_DEG x U(0.5, 1) off the step's frame at COVER_SCALE x its resolution; the closing box
# that tells cracks from the outline is COVER_KERNEL_FRAC x the render's shorter side
# (docs/experiments/cover-loss.md)
COVER_EVERY = 4
COVER_ANGLE_DEG = 20.0
COVER_SCALE = 0.5
COVER_KERNEL_FRAC = 0.125
# the init.backdrop Gaussians' opacity at step 0 (no train view sees them; docs/experiments/two-view-geometry.md)
BACKDROP_OPACITY = 0.9


def _cover(ctx, grad_attrs: tuple | None = None):
    every = max(1, int(COVER_EVERY))
    depth = ctx.meta.get("depths")
    if ctx.step % every or depth is None:
        return None
    d, a = depth[0, ..., 0].detach(), ctx.alpha[0, ..., 0].detach()
    hit = d[a > 0.5]
    if hit.numel() < 16:
        return None
    pivot = float(hit.median())
    rng = np.random.default_rng([int(getattr(ctx.run, "seed", 0)), int(ctx.step), 11])
    angle = math.radians(float(COVER_ANGLE_DEG)) * float(rng.uniform(0.5, 1.0))
    vt = orbit_view(ctx.item, pivot, float(rng.uniform(0, 2 * math.pi)), angle, float(COVER_SCALE))
    # only the Gaussians the step's own view draws may change for it: one outside every train
    # frustum is held by no photometric loss, and grown by this term alone it became fog
    radii = ctx.meta.get("radii")  # [C, N] on every backend (engine.raster)
    drawn = None if radii is None else radii[0] > 0
    _, alpha, _, _ = ctx.run.model.render(vt, float(ctx.item["time"]), render_depth=False, grad_rows=drawn,
                                              grad_attrs=grad_attrs)
    kernel = cover_kernel_px(float(COVER_KERNEL_FRAC), int(vt["height"]), int(vt["width"]))
    return cover_loss(alpha[0, ..., 0], kernel,
                      seen_from(vt, ctx.item, pivot).to(alpha.device))


COVER_GRAD_ATTRS = ("means", "quats", "scales", "size", "opacities", "colors")


def cover_grad_attrs(text: str) -> tuple | None:
    """``cover_grad`` ("all", or "+"-joined names of :data:`COVER_GRAD_ATTRS`) -> the
    ``grad_attrs`` of the term's render (None: all); ValueError names a wrong one."""
    text = str(text).strip()
    if text == "all":
        return None
    names = tuple(n.strip() for n in text.split("+") if n.strip())
    bad = [n for n in names if n not in COVER_GRAD_ATTRS]
    if bad or not names:
        raise ValueError(f"cover_grad={text!r}: expected 'all' or '+'-joined names of {', '.join(COVER_GRAD_ATTRS)}"
                         + (f" (unknown: {', '.join(bad)})" if bad else ""))
    return names


FLAT_BAND = 0.03  # a Gaussian lies on the stereo surface when its depth is within this share of it


def in_gaussian_frame(quats: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
    """R(q)^T v for wxyz quaternions [N,4] (any norm) and vectors [N,3]: v's components along each
    Gaussian's axes, ``quat_to_rotmat(q).transpose(1, 2) @ v`` without the matrices (a fifth of the
    autograd nodes): R^T v = v - 2w (u x v) + 2 u x (u x v), q = (w, u) unit."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, u = q[:, :1], q[:, 1:]
    c = torch.linalg.cross(u, vectors, dim=-1)
    return vectors - 2.0 * w * c + 2.0 * torch.linalg.cross(u, c, dim=-1)


def lie_flat(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, item: dict,
             band: float = FLAT_BAND) -> torch.Tensor | None:
    """Mean over the Gaussians on the item's stereo surface of their second moment about its local
    plane along the plane's normal, as a share of their whole spread:
    (sigma_n^2 + delta^2) / (trace(Sigma) + delta^2), delta the centre's distance to the plane.
    0 for a disc lying in the plane, 1/3 for a ball centred on it, 1/2 for a fin standing out of it.

    The planes are ``item["stereo_normal"]`` (world [h,w,3], zero where unknown) and
    ``stereo_offset`` ([h,w]: the plane is n . x = offset), fitted to ``stereo_depth`` [h,w] by
    :func:`engine.geometry.depth_priors.depth_normals`; "on the surface": the centre projects onto
    a pixel with a plane and its depth is within ``band`` of the stereo depth there.
    Two cameras on a horizontal baseline cannot place what runs along their epipolar lines: a
    horizontal edge is the same in both views whether its Gaussians are discs on the wall, fins
    standing out of it or discs in front of and behind it, and from above all but the first smear
    it (docs/experiments/lie-flat.md)."""
    normal, depth, offset = item.get("stereo_normal"), item.get("stereo_depth"), item.get("stereo_offset")
    if normal is None or depth is None or offset is None or normal.shape[:2] != depth.shape:
        return None
    vm, K = item["viewmat"][0].to(means.dtype), item["K"][0].to(means.dtype)
    h, w = depth.shape
    with torch.no_grad():
        uv, z = pinhole_project(means.detach(), vm, K)
        u = (uv[:, 0] * (w / float(item["width"]))).floor().long()
        v = (uv[:, 1] * (h / float(item["height"]))).floor().long()
        inside = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        pix = (v.clamp(0, h - 1) * w + u.clamp(0, w - 1))
        d = depth.reshape(-1)[pix]
        n = normal.reshape(-1, 3)[pix]
        on = inside & (n.abs().sum(-1) > 0.5) & ((z - d).abs() <= band * d)
        rows = on.nonzero(as_tuple=True)[0]
    if rows.numel() == 0:
        return None
    nr = n[rows]
    s2 = scales[rows] ** 2
    along = in_gaussian_frame(quats[rows], nr) ** 2  # (axis_k . n)^2
    delta2 = ((means[rows] * nr).sum(-1) - offset.reshape(-1)[pix[rows]]) ** 2
    return (((s2 * along).sum(-1) + delta2) / (s2.sum(-1) + delta2).clamp_min(1e-20)).mean()


# planes only where the pair's disparity is at least this many pixels: there one pixel of matching
# error moves the depth by at most 1/8, four times FLAT_BAND (a 0.08 m baseline 2.7 m away at 160x120
# has 4 px, and its stereo planes were 47 % off: docs/experiments/lie-flat.md)
PLANE_MIN_DISPARITY = 8.0


def _partner_baseline(same_instant: list[dict], it: dict) -> float:
    """Distance (m) from the item's camera to the nearest other camera among ``same_instant``
    (the train items at its instant; 0: none)."""
    others = [float((o["campos"] - it["campos"]).norm()) for o in same_instant if o.get("camera") != it.get("camera")]
    return min(others) if others else 0.0


def attach_stereo(items: list[dict], priors: list, *, planes: bool, min_pixels: int = 16) -> None:
    """In place: each train item gets its fused stereo depth (``stereo_depth`` [H,W], ``stereo_mask``)
    from ``priors`` (per item: (depth, mask) numpy or None; kept with at least ``min_pixels`` known),
    and with ``planes`` the local planes :func:`lie_flat` reads (``stereo_normal``, ``stereo_offset``),
    fitted where the pair's disparity is at least :data:`PLANE_MIN_DISPARITY` pixels."""
    at: dict[float, list[dict]] = {}
    for it in items:
        at.setdefault(round(float(it["time"]), 6), []).append(it)
    for it, prior in zip(items, priors):
        if prior is None or int(prior[1].sum()) < min_pixels:
            continue
        d, ok = prior
        dev = it["viewmat"].device
        it["stereo_depth"], it["stereo_mask"] = torch.from_numpy(d).to(dev), torch.from_numpy(ok).to(dev)
        if planes:
            K = it["K"][0].cpu().numpy()
            baseline = _partner_baseline(at[round(float(it["time"]), 6)], it)
            near = ok & (d <= float(K[0, 0]) * baseline / PLANE_MIN_DISPARITY)
            n, off = world_planes(d, near, K, it["viewmat"][0].cpu().numpy())
            it["stereo_normal"], it["stereo_offset"] = torch.from_numpy(n).to(dev), torch.from_numpy(off).to(dev)


def _flat(ctx):
    a = ctx.attrs
    return lie_flat(a["means"], a["quats"], a["scales"], ctx.item)


def geometry_loss_terms(cfg, LossTerm) -> list:
    """The enabled geometry terms as ``LossTerm`` (the run's class, passed in to keep
    this module free of the run)."""
    terms = []
    if cfg.losses.cover > 0:
        # parsed once per run; a wrong name fails here, before the first step
        attrs = cover_grad_attrs(cfg.losses.cover_grad)
        terms.append(LossTerm("cover", cfg.losses.cover, functools.partial(_cover, grad_attrs=attrs)))
    if cfg.losses.flat > 0:
        terms.append(LossTerm("flat", cfg.losses.flat, _flat))
    return terms


def _opacity_decay_hook(factor: float, start_fraction: float = 0.0, end_fraction: float = 1.0):
    def hook(run, step: int, item: dict, meta: dict) -> None:
        if not run.schedule.in_fraction_window(step, start_fraction, end_fraction):
            return
        radii = meta.get("radii")
        g = run.model.gaussians
        if radii is None or radii.shape[1] != g.num_gaussians:
            return
        decay_visible_opacity(g.opacity_logits.data, radii[0] > 0, factor)
    return hook


def set_tail_opacity(opacity_logits: torch.Tensor, count: int, opacity: float) -> None:
    """In place: the last ``count`` Gaussians (logits [N] or [N,1]) get ``opacity``."""
    if count > 0:
        with torch.no_grad():
            opacity_logits[-count:] = float(torch.logit(torch.tensor(min(max(opacity, 1e-4), 1 - 1e-4))))


def _backdrop_opacity_hook(opacity: float):
    """The ``init.backdrop`` Gaussians (appended last to the initial cloud, run.json
    ``init.backdrop``) lie beyond every train camera's image, so no step trains their opacity;
    at ``init_opacity`` (0.1) a viewer 20-30 deg off sees through them (alpha < 0.5). Set once,
    after the first step (before any densification reorders the Gaussians)."""
    def hook(run, step: int, item: dict, meta: dict) -> None:
        info = run.info.get("init") or {}
        g = run.model.gaussians
        if step == 0 and info.get("backdrop") and g.num_gaussians == info.get("num_points"):
            set_tail_opacity(g.opacity_logits.data, int(info["backdrop"]), opacity)
    return hook


def geometry_post_step_hooks(cfg) -> list:
    """Hooks ``(run, step, item, meta)`` run after each optimiser step."""
    hooks = []
    if cfg.init.backdrop > 0 and BACKDROP_OPACITY > 0:
        hooks.append(_backdrop_opacity_hook(BACKDROP_OPACITY))
    if 0.0 < cfg.losses.opacity_decay < 1.0:
        hooks.append(_opacity_decay_hook(cfg.losses.opacity_decay, *opacity_decay_window(cfg)))
    return hooks
