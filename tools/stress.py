"""Numerical-stability stress suite (``python -m engine stress``).

Each *optimisation case* runs Adam on raw parameters -- means, log-scales, quaternions
(raw, normalised inside the renderer), opacity logits, colours -- through the fast CPU
rasterizer (``backend="cpu"``) against a target image, and checks after **every** step that
the loss, every gradient and every parameter is finite. No step is ever skipped: a NaN, once
produced, propagates and is counted, exactly as it would in training.

Optimisation cases (a tiny scene: ``N`` Gaussians, a 24x24 image, one camera):

* ``scale_tiny`` / ``scale_huge`` / ``scale_range``: linear scales 1e-6, 1e3 and log-uniform
  in [1e-6, 1e3];
* ``opacity_zero`` (logits -30: everything below 1/255, culled), ``opacity_threshold``
  (opacities just around 1/255) and ``opacity_saturated`` (logits +30: sigmoid == 1 in
  float32, alpha clamped at ``alpha_max``);
* ``near_plane``: Gaussians behind the camera, exactly at / just around the near plane and
  straddling z = 0;
* ``degenerate_cov``: one axis 1e-8 (needle / flat discs seen edge-on), plus quaternions of
  norm 1e-12;
* ``extent_tiny`` / ``extent_huge``: the whole scene (and camera, near plane, learning rate)
  scaled by 1e-3 and 1e4;
* ``long_time``: a HexPlane deformation field (``engine.deformation``) over a 1e4 s time
  range, queried at t in [0, 1e4] and beyond (normalised time must stay finite);
* ``empty_view``: every Gaussian outside the view (all culled): zero gradients, no NaN.

Check cases (no optimiser, fixed work):

* ``spikes_extreme``: all-zero and all-one spike streams through ``spike_sim`` (simulate,
  ``tfp``, ``tfi``), ``spikes.write_spikes/read_spikes`` and ``spike_render`` (expected
  counts, m-step integrate-and-fire with surrogate gradients, both losses, sensor fit);
* ``fp32_vs_fp64``: the float64 dense reference path against the float32 fast path on
  random scenes: image / alpha / depth difference and gradient relative error;
* ``bad_inputs``: NaN / inf in poses, intrinsics, times and image pixels of a capture must
  raise :class:`engine.errors.CaptureError` naming the file; a non-finite value that gets
  through is counted;
* ``trainer``: the real ``engine.train.train`` (both stages, densification) for up to 150
  steps on a tiny synthetic capture at scene scale 1 and 40 steps at 1e-3, every parameter
  and gradient of the Gaussians and the deformation field checked after each step.

``run_suite`` returns one :class:`CaseResult` per case; ``format_table`` prints them, and
the last line of ``python -m engine stress`` is ``non-finite values: <count>``.
"""
from __future__ import annotations

import json
import math
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

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
        bad = _count_nonfinite(grad)
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


def _count_nonfinite(t: torch.Tensor | np.ndarray | float | None) -> int:
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
    opac = torch.full((n,), float(opacity_logit), dtype=torch.float64) + 0.5 * torch.randn(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return {k: v.to(dtype) for k, v in zip(PARAM_ORDER, (means, log_scales, quats, opac, colors))}


def render_raw(p: dict, cam: Camera, *, backend: str = "cpu", means=None, quats=None, log_scales=None):
    """Render raw parameters (scales = exp(log), opacities = sigmoid(logit)) -> rgb, alpha, meta."""
    from .raster import rasterization

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
        bad = _count_nonfinite(loss)
        loss.backward()
        for name, t in named.items():
            if t.grad is None:
                continue
            bad += result.tally_grad(t.grad)
        result.nonfinite_other += _count_nonfinite(loss)
        opt.step()
        for t in named.values():
            pb = _count_nonfinite(t)
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
        res.nonfinite_other += _count_nonfinite(rgb) + _count_nonfinite(alpha)
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
    try:
        from .deformation import DeformationField
    except Exception as exc:  # pragma: no cover - module missing in a partial checkout
        res.notes.append(f"skipped: engine.deformation unavailable ({exc})")
        return res
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
        n = sum(_count_nonfinite(v) for v in out.values() if v is not None)
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
        res.nonfinite_other += _count_nonfinite(rgb)
        return image_loss(rgb, alpha, meta, target, 1.0) + field_.regularization(2e-4, 1e-3, 1e-4)

    extra = [(f"field.{n}", t, 1e-2 if "grid" in n else 1e-3) for n, t in field_.named_parameters()]
    optimise(res, p, loss_fn, steps, {"means": 1e-2, "log_scales": 5e-2, "quats": 1e-2,
                                      "opacity_logits": 5e-2, "colors": 2e-2}, tick, extra)
    res.notes.append(f"normalised time at t=1e6: {field_.normalize_time(1e6):.3g} (clamped by grid_sample)")
    return res


# ----------------------------------------------------------------------------- check cases

def case_spikes_extreme(steps, tick, seed=0):
    """All-zero and all-one spike streams through the simulator, reconstructions, IO and the
    differentiable spike renderer."""
    from .spike_sim import simulate_spikes, tfi, tfp
    from .spikes import read_spikes, write_spikes

    res = CaseResult("spikes_extreme")
    t0 = time.perf_counter()
    H, W, n = 12, 16, 64
    streams = {
        "zero": simulate_spikes(np.zeros((H, W)), rate_hz=20000.0, num_frames=n, seed=seed),
        "one": simulate_spikes(np.full((H, W), 5.0), rate_hz=20000.0, num_frames=n, seed=seed),
    }
    if streams["zero"].any():
        res.failures.append("zero light produced spikes")
    if not streams["one"].all():
        res.failures.append("saturating light did not fire every frame")
    streams["zero"][:] = 0
    streams["one"][:] = 1
    with tempfile.TemporaryDirectory(prefix="bt4d_stress_") as tmp:
        for kind, s in streams.items():
            rec = [tfp(s), tfp(s, 8, index=0), tfp(s, 8, index=n - 1), tfi(s, 0), tfi(s, n // 2),
                   tfi(s, n - 1), tfi(s, n // 2, max_window=3)]
            res.nonfinite_other += sum(_count_nonfinite(np.asarray(r, dtype=np.float64)) for r in rec)
            want = 0.0 if kind == "zero" else 1.0
            if not all(np.allclose(r, want) for r in rec):
                res.failures.append(f"{kind} stream: tfp/tfi not all {want}")
            path = Path(tmp) / f"{kind}.dat"
            write_spikes(path, s)
            if not np.array_equal(read_spikes(path, H, W), s):
                res.failures.append(f"{kind} stream: write/read round trip differs")
    try:
        from . import spike_render as sr
    except Exception as exc:  # pragma: no cover
        res.notes.append(f"spike_render unavailable ({exc})")
        sr = None
    if sr is not None:
        sensor = sr.SensorModel(width=W, height=H, scale=0.5, dark_current=0.0, threshold=1.0)
        rend = sr.SpikeRenderer(sensor)
        for kind, s in streams.items():
            obs = torch.from_numpy(s.astype(np.float32))
            obs_counts = obs.sum(0)
            # black, grey, saturated renders (sigmoid of a raw image) and an unbounded one
            # (values from -1 to 3: out-of-range renders must not break sRGB decoding)
            for init in (-30.0, 0.0, 30.0, None):
                if init is None:
                    raw = torch.linspace(-1.0, 3.0, 2 * H * 2 * W * 3).reshape(2 * H, 2 * W, 3).requires_grad_(True)
                else:
                    raw = torch.full((2 * H, 2 * W, 3), init, requires_grad=True)
                opt = torch.optim.Adam([raw], lr=0.05)
                for step in range(max(1, steps // 8)):
                    opt.zero_grad()
                    img = raw if init is None else torch.sigmoid(raw)
                    counts = rend.render_counts(img, n)
                    spikes = rend.render_spikes(img, m=16, generator=torch.Generator().manual_seed(step))
                    loss = sr.spike_count_loss(counts, obs_counts, n) \
                        + sr.cumulative_spike_loss(spikes, obs[:16])
                    res.nonfinite_other += _count_nonfinite(loss) + _count_nonfinite(counts)
                    loss.backward()
                    gb = res.tally_grad(raw.grad)
                    opt.step()
                    pb = _count_nonfinite(raw)
                    res.nonfinite_params += pb
                    if (gb or pb) and res.first_bad_step is None:
                        res.first_bad_step = res.steps
                    res.steps += 1
                    res.final_loss = float(loss.detach())
            # sensor fit from all-zero / all-one rates and black / white images
            for luma_v in (0.0, 1.0):
                luma = np.full((3, H, W), luma_v)
                rates = np.broadcast_to(s.mean(0, dtype=np.float64), (3, H, W))
                fit = sr.fit_sensor(luma, rates, width=W, height=H)
                vals = [fit.scale, fit.dark_current, fit.info.get("fit_l1_rate", 0.0)]
                n_bad = sum(0 if math.isfinite(float(v)) else 1 for v in vals)
                n_bad += _count_nonfinite(fit.gain) if fit.gain is not None else 0
                res.nonfinite_other += n_bad
                if n_bad:
                    res.failures.append(f"fit_sensor({kind} stream, luma {luma_v}) is not finite")
    if tick is not None:
        tick(steps)
    res.seconds = time.perf_counter() - t0
    return res


def compare_fp32_fp64(seed: int = 0, n: int = 12, size: int = 16) -> dict:
    """Fast path (float32, ``cpu``) vs dense reference (float64) on one random scene.

    Returns max abs differences of image / alpha / depth and the relative L2 error of each
    parameter's gradient under the same loss."""
    p64 = random_params(n, seed=seed, dtype=torch.float64)
    cam = make_camera(3.0, size)
    g = torch.Generator().manual_seed(seed + 5)
    target = torch.rand(size, size, 3, generator=g, dtype=torch.float64)
    out = {}
    grads = {}
    for name, backend, dtype in (("fast32", "cpu", torch.float32), ("ref64", "reference", torch.float64)):
        leaves = {k: v.to(dtype).clone().requires_grad_(True) for k, v in p64.items()}
        rgb, alpha, meta = render_raw(leaves, cam, backend=backend)
        loss = ((rgb - target.to(dtype)) ** 2).mean() + 1e-2 * meta["depths"].mean()
        loss.backward()
        out[name] = (rgb.detach().double(), alpha.detach().double(), meta["depths"][0].detach().double())
        grads[name] = {k: v.grad.detach().double() for k, v in leaves.items()}
    a, b = out["fast32"], out["ref64"]
    res = {"image": float((a[0] - b[0]).abs().max()), "alpha": float((a[1] - b[1]).abs().max()),
           "depth": float((a[2] - b[2]).abs().max())}
    for k in PARAM_ORDER:
        ga, gb = grads["fast32"][k], grads["ref64"][k]
        res[f"grad_{k}"] = float((ga - gb).norm() / gb.norm().clamp_min(1e-12))
        res[f"nonfinite_{k}"] = _count_nonfinite(ga) + _count_nonfinite(gb)
    return res


# tolerances for fp32_vs_fp64 (float32 compositing vs float64 dense reference)
FP_TOL = {"image": 2e-4, "alpha": 2e-4, "depth": 2e-3, "grad": 2e-3}


def case_fp32_vs_fp64(steps, tick, seed=0):
    res = CaseResult("fp32_vs_fp64")
    t0 = time.perf_counter()
    n_scenes = max(1, min(20, steps // 10))
    worst = {}
    for i in range(n_scenes):
        r = compare_fp32_fp64(seed * 1000 + i)
        for k, v in r.items():
            if k.startswith("nonfinite_"):
                res.nonfinite_grads += int(v)
            else:
                worst[k] = max(worst.get(k, 0.0), v)
        res.steps += 1
    for k, v in worst.items():
        tol = FP_TOL["grad"] if k.startswith("grad_") else FP_TOL[k]
        if not v <= tol:
            res.failures.append(f"{k} differs by {v:.2e} (> {tol:.0e})")
    res.notes.append("max diff: " + ", ".join(f"{k} {v:.1e}" for k, v in worst.items()))
    res.final_loss = float("nan")
    res.seconds = time.perf_counter() - t0
    if tick is not None:
        tick(steps)
    return res


def _write_tiny_capture(root: Path, *, pose=None, fl_x=20.0, time_value=0.0, image: np.ndarray | None = None,
                        exr: bool = False) -> Path:
    """A one-camera, one-frame capture (ours layout); returns transforms.json's path."""
    from .images import write_exr, write_png

    root.mkdir(parents=True, exist_ok=True)
    img = np.full((8, 8, 3), 0.5, np.float32) if image is None else image
    name = "f0.exr" if exr else "f0.png"
    if exr:
        write_exr(root / name, img)
    else:
        write_png(root / name, img)
    c2w = np.eye(4).tolist() if pose is None else pose
    data = {"cameras": {"cam": {"w": 8, "h": 8, "fl_x": fl_x, "fl_y": 20.0, "cx": 4.0, "cy": 4.0}},
            "frames": [{"file_path": name, "camera": "cam", "time": time_value, "transform_matrix": c2w}]}
    (root / "transforms.json").write_text(json.dumps(data, allow_nan=True))
    return root / "transforms.json"


def bad_input_checks(tmp: Path) -> list[dict]:
    """Each bad input -> dict(name, rejected, names_file, message, leaked). ``leaked`` counts
    non-finite values that reached the caller (0 when rejected)."""
    from .capture import load_capture
    from .errors import CaptureError

    nan, inf = float("nan"), float("inf")
    bad_pose = np.eye(4)
    bad_pose[0, 3] = nan
    inf_pose = np.eye(4)
    inf_pose[1, 1] = inf
    nan_img = np.full((8, 8, 3), 0.5, np.float32)
    nan_img[2, 3, 1] = nan
    inf_img = np.full((8, 8, 3), 0.5, np.float32)
    inf_img[4, 4, 0] = inf
    variants = {
        "pose_nan": dict(pose=bad_pose.tolist()),
        "pose_inf": dict(pose=inf_pose.tolist()),
        "intrinsics_nan": dict(fl_x=nan),
        "time_nan": dict(time_value=nan),
        "image_exr_nan": dict(image=nan_img, exr=True),
        "image_exr_inf": dict(image=inf_img, exr=True),
    }
    out = []
    for name, kw in variants.items():
        root = tmp / name
        tpath = _write_tiny_capture(root, **kw)
        rec = {"name": name, "rejected": False, "names_file": False, "message": "", "leaked": 0}
        try:
            cap = load_capture(root)
            views = [cap.view(f) for f in cap.frames]
            imgs = [f.load_rgb() for f in cap.frames]
            rec["leaked"] = sum(_count_nonfinite(v.c2w) + _count_nonfinite(np.asarray(v.K)) +
                                (0 if math.isfinite(v.time) else 1) for v in views)
            rec["leaked"] += sum(_count_nonfinite(np.asarray(i, dtype=np.float32)) for i in imgs)
            if rec["leaked"] == 0 and name.startswith("image_exr_inf"):
                rec["rejected"] = False  # inf clipped to 1 by the sRGB encode: not a leak
                rec["message"] = "accepted (inf clipped to 1.0)"
        except CaptureError as exc:
            rec["rejected"] = True
            rec["message"] = str(exc)
            culprit = (root / "f0.exr") if name.startswith("image") else tpath
            rec["names_file"] = culprit.name in str(exc)
        out.append(rec)
    return out


def case_bad_inputs(steps, tick, seed=0):
    res = CaseResult("bad_inputs")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bt4d_stress_") as tmp:
        for rec in bad_input_checks(Path(tmp)):
            res.steps += 1
            res.nonfinite_other += rec["leaked"]
            if rec["leaked"]:
                res.failures.append(f"{rec['name']}: {rec['leaked']} non-finite values accepted")
            elif rec["rejected"] and not rec["names_file"]:
                res.failures.append(f"{rec['name']}: error does not name the file: {rec['message']}")
            elif not rec["rejected"]:
                res.notes.append(f"{rec['name']}: {rec['message'] or 'accepted'}")
    res.seconds = time.perf_counter() - t0
    if tick is not None:
        tick(steps)
    return res


def _write_moving_capture(root: Path, scale: float = 1.0, seed: int = 0) -> Path:
    """Two 32x24 cameras, three instants of a bright moving block, scene scaled by ``scale``."""
    from .cameras import look_at_c2w
    from .images import write_png

    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    frames = []
    for cam, x in (("a", -0.3), ("b", 0.3)):
        c2w = look_at_c2w((x * scale, -4.0 * scale, 0.0), (0.0, 0.0, 0.0)).tolist()
        for i in range(3):
            img = np.clip(rng.random((24, 32, 3)) * 0.3 + 0.3, 0, 1).astype(np.float32)
            img[8:16, 4 + 4 * i: 12 + 4 * i] = 0.9
            write_png(root / f"{cam}{i}.png", img)
            frames.append({"file_path": f"{cam}{i}.png", "camera": cam, "time": i / 30, "transform_matrix": c2w})
    intr = {"w": 32, "h": 24, "fl_x": 30.0, "fl_y": 30.0, "cx": 16.0, "cy": 12.0}
    (root / "transforms.json").write_text(json.dumps({"cameras": {"a": intr, "b": intr}, "frames": frames}))
    return root


def case_trainer(steps, tick, seed=0):
    """The real trainer (``engine.train.train``, fast preset, both stages, densification) on a
    tiny synthetic capture at scene scale 1 and 1e-3; parameters and gradients of the
    Gaussians and the deformation field are checked after every step."""
    from .train import train

    res = CaseResult("trainer")
    t0 = time.perf_counter()
    state = {"trainer": None}

    def grab(trainer):
        state["trainer"] = trainer
        return []

    from . import train as train_mod

    train_mod.register_loss_factory(grab)
    try:
        with tempfile.TemporaryDirectory(prefix="bt4d_stress_") as tmp:
            for scale, n in ((1.0, min(steps, 150)), (1e-3, min(steps, 40))):
                if n < 2:
                    continue
                cap = _write_moving_capture(Path(tmp) / f"cap{scale:g}", scale, seed)

                def progress(p):
                    tr = state["trainer"]
                    named = dict(tr.model.gaussians.params())
                    if tr.model.deformation is not None:
                        named.update({f"field.{k}": v for k, v in tr.model.deformation.named_parameters()})
                    bad = 0
                    for t in named.values():
                        bad += _count_nonfinite(t)
                        res.nonfinite_params += _count_nonfinite(t)
                        if t.grad is not None:
                            bad += res.tally_grad(t.grad)
                    res.nonfinite_other += _count_nonfinite(float(p["loss"]))
                    if bad and res.first_bad_step is None:
                        res.first_bad_step = res.steps
                    res.steps += 1
                    res.final_loss = float(p["loss"])

                out = train(cap, Path(tmp) / f"run{scale:g}", preset="fast", resume=False, seed=seed,
                            progress=progress, overrides={"iterations": n, "init_max_points": 300,
                                                          "init_random_points": 100, "checkpoint_every_s": 1e9})
                res.notes.append(f"scale {scale:g}: {out['step']} steps, train PSNR {out['psnr']:.2f}, "
                                 f"{out['num_gaussians']} Gaussians, init {out['init'].get('method')}")
    finally:
        if grab in train_mod._LOSS_FACTORIES:
            train_mod._LOSS_FACTORIES.remove(grab)
    res.seconds = time.perf_counter() - t0
    if tick is not None:
        tick(steps)
    return res


# ----------------------------------------------------------------------------- suite

CASES: dict[str, Callable] = {
    "scale_tiny": case_scale_tiny,
    "scale_huge": case_scale_huge,
    "scale_range": case_scale_range,
    "opacity_zero": case_opacity_zero,
    "opacity_threshold": case_opacity_threshold,
    "opacity_saturated": case_opacity_saturated,
    "near_plane": case_near_plane,
    "degenerate_cov": case_degenerate_cov,
    "extent_tiny": case_extent_tiny,
    "extent_huge": case_extent_huge,
    "empty_view": case_empty_view,
    "long_time": case_long_time,
    "spikes_extreme": case_spikes_extreme,
    "fp32_vs_fp64": case_fp32_vs_fp64,
    "bad_inputs": case_bad_inputs,
    "trainer": case_trainer,
}


CASE_HELP = {
    "scale_tiny": "linear scales 1e-6",
    "scale_huge": "linear scales 1e3",
    "scale_range": "scales log-uniform in [1e-6, 1e3]",
    "opacity_zero": "opacity logits -30 (all below 1/255)",
    "opacity_threshold": "opacities around 1/255",
    "opacity_saturated": "opacity logits +30 (sigmoid == 1 in float32)",
    "near_plane": "Gaussians behind, at and around the near plane",
    "degenerate_cov": "one (or two) axes 1e-8, edge-on, quaternion norms 1e-12",
    "extent_tiny": "scene + camera scaled by 1e-3",
    "extent_huge": "scene + camera scaled by 1e4",
    "empty_view": "every Gaussian outside the view",
    "long_time": "deformation field over 1e4 s, queried up to 1e6 s",
    "spikes_extreme": "all-zero / all-one spike streams: sim, tfp/tfi, IO, spike renderer, sensor fit",
    "fp32_vs_fp64": "float32 fast path vs float64 dense reference",
    "bad_inputs": "NaN / inf in poses, intrinsics, times, image pixels -> CaptureError",
    "trainer": "the real trainer on a tiny synthetic capture at scale 1 and 1e-3",
}


def run_case(name: str, steps: int, tick=None, seed: int = 0) -> CaseResult:
    if name not in CASES:
        raise KeyError(f"unknown stress case {name!r}; cases: {', '.join(CASES)}")
    t0 = time.perf_counter()
    try:
        res = CASES[name](int(steps), tick, seed)
    except Exception as exc:  # a crash is a failure of the case, reported, not hidden
        res = CaseResult(name)
        res.failures.append(f"raised {type(exc).__name__}: {exc}")
    res.seconds = time.perf_counter() - t0
    return res


def run_suite(steps: int = 10_000, cases=None, *, seed: int = 0, progress: bool = True) -> list[CaseResult]:
    names = list(CASES) if not cases else list(cases)
    bar = None
    tick = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=steps * len(names), unit="step", desc="stress", dynamic_ncols=True)
        tick = bar.update
    out = []
    try:
        for name in names:
            if bar is not None:
                bar.set_postfix_str(name)
            before = bar.n if bar is not None else 0
            res = run_case(name, steps, tick, seed)
            if bar is not None and bar.n < before + steps:  # cases that stop early
                bar.update(before + steps - bar.n)
            out.append(res)
    finally:
        if bar is not None:
            bar.close()
    return out


def total_nonfinite(results: list[CaseResult]) -> int:
    return int(sum(r.nonfinite for r in results))


def format_table(results: list[CaseResult]) -> str:
    head = f"{'case':<18}{'steps':>7}{'nf params':>10}{'nf grads':>10}{'nf other':>10}{'max |grad|':>12}" \
           f"{'final loss':>12}{'sec':>8}  status"
    lines = [head, "-" * len(head)]
    for r in results:
        fl = "-" if not math.isfinite(r.final_loss) and r.nonfinite == 0 else f"{r.final_loss:.4g}"
        status = "ok" if r.ok else "FAIL"
        lines.append(f"{r.name:<18}{r.steps:>7}{r.nonfinite_params:>10}{r.nonfinite_grads:>10}{r.nonfinite_other:>10}"
                     f"{r.max_grad:>12.3g}{fl:>12}{r.seconds:>8.1f}  {status}")
    details = []
    for r in results:
        for f in r.failures:
            details.append(f"  {r.name}: FAIL {f}")
        if r.first_bad_step is not None:
            details.append(f"  {r.name}: first non-finite value at step {r.first_bad_step}")
        for n in r.notes:
            details.append(f"  {r.name}: {n}")
    return "\n".join(lines + (["", "details:"] + details if details else []))
