"""Stress suite, part 1: results, tiny scenes and the optimisation cases (Adam on raw
Gaussian parameters through the fast CPU rasterizer, every step checked for non-finite
values). The suite and its command line are :mod:`tools.stress`."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from engine.raster import rasterization
from engine.scene.deformation import DeformationField

IMAGE_SIZE = 24
NUM_GAUSSIANS = 24
PARAM_ORDER = ("means", "log_scales", "quats", "opacity_logits", "colors")


# ----------------------------------------------------------------------------- results

@dataclass
class CaseResult:
    name: str
    steps: int = 0
    nonfinite_params: int = 0     # non-finite parameter elements, summed over steps
    nonfinite_grads: int = 0      # non-finite gradient elements, summed over steps
    nonfinite_other: int = 0      # non-finite loss / image / output values, or let-through inputs
    max_grad: float = 0.0         # max |grad| over all steps (finite entries)
    final_loss: float = float("nan")
    first_bad_step: int | None = None
    seconds: float = 0.0
    failures: list = field(default_factory=list)   # failed checks (strings)
    notes: list = field(default_factory=list)      # measured facts worth printing

    @property
    def nonfinite(self) -> int:
        return self.nonfinite_params + self.nonfinite_grads + self.nonfinite_other

    def tally_grad(self, grad: torch.Tensor) -> int:
        """Count ``grad``'s non-finite entries (returned and added to ``nonfinite_grads``)
        and track its largest finite magnitude in ``max_grad``."""
        bad = count_nonfinite(grad)
        self.nonfinite_grads += bad
        finite = grad.detach().abs()
        finite = finite[torch.isfinite(finite)]
        if finite.numel():
            self.max_grad = max(self.max_grad, float(finite.max()))
        return bad

    @property
    def ok(self) -> bool:
        return self.nonfinite == 0 and not self.failures

    def to_dict(self) -> dict:
        return {"name": self.name, "steps": self.steps, "nonfinite_params": self.nonfinite_params,
                "nonfinite_grads": self.nonfinite_grads, "nonfinite_other": self.nonfinite_other,
                "max_grad": self.max_grad, "final_loss": self.final_loss,
                "first_bad_step": self.first_bad_step, "seconds": round(self.seconds, 3),
                "failures": list(self.failures), "notes": list(self.notes), "ok": self.ok}


def count_nonfinite(t: torch.Tensor | np.ndarray | float | None) -> int:
    if t is None:
        return 0
    if isinstance(t, float):
        return 0 if math.isfinite(t) else 1
    if isinstance(t, np.ndarray):
        return int(t.size - np.isfinite(t).sum()) if np.issubdtype(t.dtype, np.floating) else 0
    t = t.detach()
    if not t.is_floating_point():
        return 0
    return int(t.numel() - torch.isfinite(t).sum())


# ----------------------------------------------------------------------------- scenes

@dataclass
class Camera:
    viewmat: torch.Tensor   # [1,4,4] OpenCV world-to-camera
    K: torch.Tensor         # [1,3,3]
    width: int
    height: int
    near: float = 0.01


def make_camera(distance: float, size: int = IMAGE_SIZE, near: float = 0.01, dtype=torch.float32) -> Camera:
    """A camera on the -z axis at ``distance`` looking at the origin (+z forward, OpenCV)."""
    vm = torch.eye(4, dtype=dtype)
    vm[2, 3] = float(distance)
    f = float(size)  # ~53 degree field of view
    K = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    return Camera(vm[None], K[None], size, size, near)


def random_params(n: int, extent: float = 1.0, *, seed: int = 0, log_scale: float | None = None,
                  opacity_logit: float = 0.0, dtype=torch.float32) -> dict:
    """Raw parameters of ``n`` Gaussians in a cube of side ``extent`` around the origin."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * extent
    if log_scale is None:
        log_scale = math.log(0.08 * extent)
    log_scales = torch.full((n, 3), float(log_scale), dtype=torch.float64) \
        + 0.3 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opac = (torch.full((n,), float(opacity_logit), dtype=torch.float64)
            + 0.5 * torch.randn(n, generator=g, dtype=torch.float64))
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return {k: v.to(dtype) for k, v in zip(PARAM_ORDER, (means, log_scales, quats, opac, colors))}


def render_raw(p: dict, cam: Camera, *, backend: str = "cpu", means=None, quats=None, log_scales=None):
    """Render raw parameters (scales = exp(log), opacities = sigmoid(logit)) -> rgb, alpha, meta."""

    m = p["means"] if means is None else means
    q = p["quats"] if quats is None else quats
    ls = p["log_scales"] if log_scales is None else log_scales
    rgb, alpha, meta = rasterization(m, q, torch.exp(ls), torch.sigmoid(p["opacity_logits"]), p["colors"],
                                     cam.viewmat.to(m.dtype), cam.K.to(m.dtype), cam.width, cam.height,
                                     near_plane=cam.near, backend=backend, render_depth=True)
    return rgb[0], alpha[0], meta


def target_image(cam: Camera, extent: float, seed: int) -> torch.Tensor:
    """A reachable target: a render of another random scene of the same size (plus a ramp
    so that the target is never all background)."""
    with torch.no_grad():
        p = random_params(NUM_GAUSSIANS, extent, seed=seed + 1000)
        rgb, _, _ = render_raw(p, make_camera(3.0 * extent, cam.width, cam.near))
    ramp = torch.linspace(0.0, 0.2, cam.width)[None, :, None].expand(cam.height, cam.width, 3)
    return (rgb + ramp).clamp(0, 1).detach()


# ----------------------------------------------------------------------------- optimisation

def optimise(result: CaseResult, params: dict, loss_fn: Callable[[dict, int], torch.Tensor], steps: int,
             lrs: dict, tick: Callable[[int], None] | None = None, extra_params: list | None = None) -> CaseResult:
    """Adam on ``params`` (+ ``extra_params``: list of (name, tensor, lr)) for ``steps`` steps,
    counting non-finite values after every step (never skipping one)."""
    leaves = {k: v.detach().clone().requires_grad_(True) for k, v in params.items()}
    groups = [{"params": [leaves[k]], "lr": lrs.get(k, 1e-2)} for k in leaves]
    named = dict(leaves)
    for name, t, lr in extra_params or []:
        groups.append({"params": [t], "lr": lr})
        named[name] = t
    opt = torch.optim.Adam(groups, lr=1e-2, eps=1e-15)
    t0 = time.perf_counter()
    loss_val = float("nan")
    for step in range(steps):
        opt.zero_grad(set_to_none=True)
        loss = loss_fn(leaves, step)
        loss_val = float(loss.detach())
        bad = count_nonfinite(loss)
        loss.backward()
        for name, t in named.items():
            if t.grad is None:
                continue
            bad += result.tally_grad(t.grad)
        result.nonfinite_other += count_nonfinite(loss)
        opt.step()
        for t in named.values():
            pb = count_nonfinite(t)
            bad += pb
            result.nonfinite_params += pb
        if bad and result.first_bad_step is None:
            result.first_bad_step = step
        result.steps += 1
        if tick is not None:
            tick(1)
    result.final_loss = loss_val
    result.seconds += time.perf_counter() - t0
    params.update({k: v.detach() for k, v in leaves.items()})
    return result


def image_loss(rgb: torch.Tensor, alpha: torch.Tensor, meta: dict, target: torch.Tensor, extent: float) -> torch.Tensor:
    """L1 + MSE on the colour, plus a small expected-depth term (exercises the depth path)."""
    loss = (rgb - target).abs().mean() + ((rgb - target) ** 2).mean()
    depth = meta.get("depths")
    if depth is not None:
        loss = loss + 1e-3 * (depth[0] / extent).mean()
    return loss


def _gaussian_case(name: str, steps: int, tick, *, params: dict, cam: Camera, target: torch.Tensor,
                   extent: float = 1.0, lr_scale: float = 1.0) -> CaseResult:
    res = CaseResult(name)

    def loss_fn(p, step):
        rgb, alpha, meta = render_raw(p, cam)
        res.nonfinite_other += count_nonfinite(rgb) + count_nonfinite(alpha)
        return image_loss(rgb, alpha, meta, target, extent)

    lrs = {"means": 1e-2 * extent * lr_scale, "log_scales": 5e-2, "quats": 1e-2, "opacity_logits": 5e-2,
           "colors": 2e-2}
    optimise(res, params, loss_fn, steps, lrs, tick)
    with torch.no_grad():
        _, alpha, meta = render_raw(params, cam)
        res.notes.append(f"visible {int((meta['radii'] > 0).sum())}/{params['means'].shape[0]}, "
                         f"coverage {float((alpha > 1e-3).float().mean()):.2f}")
    return res


# ----------------------------------------------------------------------------- cases

def case_scale_tiny(steps, tick, seed=0):
    p = random_params(NUM_GAUSSIANS, seed=seed, log_scale=math.log(1e-6))
    cam = make_camera(3.0)
    return _gaussian_case("scale_tiny", steps, tick, params=p, cam=cam, target=target_image(cam, 1.0, seed))


def case_scale_huge(steps, tick, seed=0):
    p = random_params(NUM_GAUSSIANS, seed=seed, log_scale=math.log(1e3))
    cam = make_camera(3.0)
    return _gaussian_case("scale_huge", steps, tick, params=p, cam=cam, target=target_image(cam, 1.0, seed))


def case_scale_range(steps, tick, seed=0):
    p = random_params(NUM_GAUSSIANS, seed=seed)
    g = torch.Generator().manual_seed(seed + 7)
    p["log_scales"] = (torch.rand(NUM_GAUSSIANS, 3, generator=g) * (math.log(1e3) - math.log(1e-6))
                       + math.log(1e-6))
    cam = make_camera(3.0)
    return _gaussian_case("scale_range", steps, tick, params=p, cam=cam, target=target_image(cam, 1.0, seed))


def case_opacity_zero(steps, tick, seed=0):
    p = random_params(NUM_GAUSSIANS, seed=seed, opacity_logit=-30.0)
    cam = make_camera(3.0)
    return _gaussian_case("opacity_zero", steps, tick, params=p, cam=cam, target=target_image(cam, 1.0, seed))


def case_opacity_threshold(steps, tick, seed=0):
    p = random_params(NUM_GAUSSIANS, seed=seed)
    a = torch.linspace(0.5 / 255, 2.0 / 255, NUM_GAUSSIANS)
    p["opacity_logits"] = torch.log(a / (1 - a))
    cam = make_camera(3.0)
    return _gaussian_case("opacity_threshold", steps, tick, params=p, cam=cam, target=target_image(cam, 1.0, seed))


def case_opacity_saturated(steps, tick, seed=0):
    p = random_params(NUM_GAUSSIANS, seed=seed, opacity_logit=30.0)
    cam = make_camera(3.0)
    return _gaussian_case("opacity_saturated", steps, tick, params=p, cam=cam, target=target_image(cam, 1.0, seed))


def case_near_plane(steps, tick, seed=0):
    p = random_params(NUM_GAUSSIANS, seed=seed)
    cam = make_camera(3.0)
    near = cam.near
    # camera-space z = world z + 3 (identity rotation): place Gaussians around the near plane
    zs = torch.tensor([-2.0, -1e-3, 0.0, 1e-7, 1e-4, near * 0.5, near - 1e-6, near, near + 1e-6, near * 1.5,
                       0.02, 0.05, 0.1, 0.5, 1.0, 2.0, 3.0, -1e-7, near * (1 - 1e-7), 0.2, 4.0, 5.0, 1e-3, 0.3])
    p["means"][:, 2] = zs[:NUM_GAUSSIANS] - 3.0
    p["means"][:, :2] *= 0.2
    return _gaussian_case("near_plane", steps, tick, params=p, cam=cam, target=target_image(cam, 1.0, seed))


def case_degenerate_cov(steps, tick, seed=0):
    p = random_params(NUM_GAUSSIANS, seed=seed)
    p["log_scales"][:, 0] = math.log(1e-8)          # needles / discs with one 1e-8 axis
    p["log_scales"][::3, 1] = math.log(1e-8)        # every third: two axes 1e-8 (a line)
    p["quats"][::4] = torch.tensor([1.0, 0.0, 0.0, 0.0])  # axis-aligned: seen exactly edge-on
    p["quats"][1::4] *= 1e-12                       # near-zero quaternion norms
    cam = make_camera(3.0)
    return _gaussian_case("degenerate_cov", steps, tick, params=p, cam=cam, target=target_image(cam, 1.0, seed))


def _extent_case(name, extent, steps, tick, seed):
    p = random_params(NUM_GAUSSIANS, extent, seed=seed)
    cam = make_camera(3.0 * extent, near=0.01 * min(1.0, extent))
    unit_cam = make_camera(3.0)
    target = target_image(unit_cam, 1.0, seed)  # scale-free: the same picture at any extent
    res = _gaussian_case(name, steps, tick, params=p, cam=cam, target=target, extent=extent)
    if extent < 1.0:
        # what the trainer's default near plane (0.01) does to this scene
        with torch.no_grad():
            _, alpha, _ = render_raw(p, make_camera(3.0 * extent, near=0.01))
        res.notes.append(f"default near_plane=0.01 renders coverage {float((alpha > 1e-3).float().mean()):.2f}")
    return res


def case_extent_tiny(steps, tick, seed=0):
    return _extent_case("extent_tiny", 1e-3, steps, tick, seed)


def case_extent_huge(steps, tick, seed=0):
    return _extent_case("extent_huge", 1e4, steps, tick, seed)


def case_empty_view(steps, tick, seed=0):
    p = random_params(NUM_GAUSSIANS, seed=seed)
    p["means"][:, 0] += 50.0   # far off to the side: every Gaussian is culled
    cam = make_camera(3.0)
    res = _gaussian_case("empty_view", steps, tick, params=p, cam=cam, target=target_image(cam, 1.0, seed))
    return res


def case_long_time(steps, tick, seed=0):
    """Deformation field over a 1e4 s range, queried at t in [0, 1e4] and beyond."""
    res = CaseResult("long_time")
    field_ = DeformationField([-0.6] * 3, [0.6] * 3, (0.0, 1e4), features=8, resolution=8, multires=(1,),
                              time_resolution=16, width=32, seed=seed)
    # instants: inside, on the ends, slightly and far outside the range
    probes = [0.0, 1e-6, 1.0 / 30, 5e3, 1e4 - 1e-3, 1e4, 1e4 + 1.0, -1e4, 2e4, 1e6]
    with torch.no_grad():
        for t in probes:
            tn = field_.normalize_time(t)
            if not math.isfinite(tn):
                res.nonfinite_other += 1
                res.failures.append(f"normalize_time({t}) = {tn}")
    # a 1/30 s range queried 1e4 s away, and a degenerate (zero-length) range
    for tr in ((0.0, 1.0 / 30), (5.0, 5.0), (1.7e9, 1.7e9 + 1.0)):
        f2 = DeformationField([-0.6] * 3, [0.6] * 3, tr, features=4, resolution=4, multires=(1,),
                              time_resolution=4, width=8, seed=seed)
        with torch.no_grad():
            out = f2(torch.zeros(3, 3), torch.tensor([[1.0, 0, 0, 0]] * 3), torch.zeros(3, 3), torch.zeros(3),
                     tr[0] + 1e4)
        n = sum(count_nonfinite(v) for v in out.values() if v is not None)
        res.nonfinite_other += n
        if n:
            res.failures.append(f"time_range {tr} queried at t0+1e4 gives {n} non-finite values")

    p = random_params(NUM_GAUSSIANS, seed=seed)
    cam = make_camera(3.0)
    target = target_image(cam, 1.0, seed)
    rng = np.random.default_rng(seed)
    ts = np.concatenate([np.array(probes), rng.uniform(0.0, 1e4, max(1, steps))])  # probes first

    def loss_fn(pp, step):
        t = float(ts[step % len(ts)])
        d = field_(pp["means"], pp["quats"], pp["log_scales"], pp["opacity_logits"], t)
        rgb, alpha, meta = render_raw(pp, cam, means=d["means"], quats=d["quats"], log_scales=d["log_scales"])
        res.nonfinite_other += count_nonfinite(rgb)
        return image_loss(rgb, alpha, meta, target, 1.0) + field_.regularization(2e-4, 1e-3, 1e-4)

    extra = [(f"field.{n}", t, 1e-2 if "grid" in n else 1e-3) for n, t in field_.named_parameters()]
    optimise(res, p, loss_fn, steps, {"means": 1e-2, "log_scales": 5e-2, "quats": 1e-2,
                                      "opacity_logits": 5e-2, "colors": 2e-2}, tick, extra)
    res.notes.append(f"normalised time at t=1e6: {field_.normalize_time(1e6):.3g} (clamped by grid_sample)")
    return res
