"""BulletTime4D spike guidance wired into the run (paper Eq. 4-23).

* :class:`SpikeFineEncoder` is the deformation field's ``fine_encoder`` hook (Eq. 10):
  ``(xyz_normalised [N, 3], t) -> f_fine [N, feature_dim]`` from the spike window around
  ``t`` (:mod:`engine.scene.fine_deformation`). Its spec is JSON-able and stored in the field's
  config, so a checkpoint rebuilds it; the spike windows are re-read lazily from the
  capture recorded in the spec (zeros when the capture or the window is unavailable, e.g.
  outside the stream).
* :class:`SpikeGuidance` adds, at between-frame instants ``t in (T1, T2)``:
  - the spike loss (Eq. 17) at the spike camera's co-located RGB view: the render at ``t``
    through the spike camera model (:mod:`engine.spike.render`) vs the captured spike
    counts in ``m`` frames centred on ``t`` (expected-count renderer by default, or the
    m-step integrate-and-fire with a surrogate gradient, ``spike_loss_mode='if'``); the
    rate difference is divided by the photometric scale, i.e. measured in linear luminance;
  - the block colour loss (Eq. 20): 4x4 average-pooled render vs the frame interpolated
    (flow or linear) from the camera's RGB frames at T1 and T2.
  The frame loss at RGB instants (Eq. 22) is the run's own L1 + D-SSIM term.
* :func:`guidance_factory` is listed in :data:`engine.train.loop.trainer.LOSS_FACTORIES`;
  with ``rgb_only`` the run never calls it; without a spike stream it returns nothing
  (no flag needed): such captures train exactly as the RGB-only model.

Every option is a :class:`engine.train.config.TrainConfig` field (older run configs get
the defaults of newer fields through ``TrainConfig.from_dict``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ...scene.fine_deformation import SpikeFineEncoder, project_to_grid
from ...scene.model import scaled_view
from ...spike.features import SpikeWindowCache, bracket
from ...spike.render import SpikeRenderer, cumulative_spike_loss, estimate_sensor, spike_count_loss
from ..config import block_weight
from ..frames.interpolation import avg_pool_blocks, block_colour_loss, flow_consistency, flow_interpolate, linear_blend
from ..losses.terms import BLOCK_SIZE, LossTerm
from .instants import InstantSampler

__all__ = ["SpikeGuidance", "admitted_time", "guidance_factory", "make_fine_encoder", "spike_stream_info",
           "spike_view_guidance"]

# No term reads the between-frame render's depth: without it the rasterizer composites 3
# feature channels instead of 4, with the same colours and gradients bit for bit (issue 13;
# tests/test_between_render.py). tools/bench-step's ``guided-main`` variant sets it back.
BETWEEN_DEPTH = False
# What a between-frame render trains (Model4D.render's grad_attrs): a Gaussian's size, not its shape (the
# ratios of its scales). One greyscale view between RGB frames cannot tell a splat's extent along its own
# ray; with the ratios trained, flat surface splats stood up in front of the static world at the eval
# cameras; with no scale gradient at all a far set's floor kept its holes (issue 47;
# docs/experiments/unsampled-motion-random-scenes.md, "Static pixels lost in front of the surface").
BETWEEN_GRAD_ATTRS = ("means", "quats", "colors", "opacities", "size")

LR_FINE = 1e-3           # learning rate of the fine branch
CHANGE_BLOCK = 4         # block size (spike pixels) of the change maps
# the spike windows' conv encoder output kept (EncodedWindows): 1 = one pass per window and weights
# (the renders of a step share it; exact), k > 1 = a window's encoder runs at most every k steps, its
# tokens reused detached in between; 0 = no reuse
FINE_ENCODER_EVERY = 1


def spike_stream_info(capture):
    """The first spike stream co-located with a training RGB camera (or None)."""
    for info in getattr(capture, "spike_streams", []) or []:
        if info.co_located_with and any(f.camera == info.co_located_with for f in capture.frames):
            return info
    return None


# ----------------------------------------------------------------------------- fine encoder

def make_fine_encoder(run, field, cache: SpikeWindowCache | None = None) -> SpikeFineEncoder | None:
    """Build the fine encoder for ``field`` from the run's capture (None without spikes).
    ``cache``: reuse already computed spike windows (same stream and RGB times)."""
    cfg = run.cfg
    info = spike_stream_info(run.capture)
    if info is None or not cfg.spike.fine_deformation:
        return None
    stream = info.open()
    cam = info.co_located_with
    rgb_times = sorted({float(f.time) for f in run.capture.frames if f.camera == cam
                        and not getattr(f, "extra", {}).get("synthetic")})
    if len(rgb_times) < 2:
        return None
    view = {"viewmat": (stream.view(0.0).viewmat if stream.c2w is not None and stream.intrinsics is not None
                        else np.eye(4)).tolist(),
            "K": (stream.intrinsics.K if stream.intrinsics is not None else np.eye(3)).tolist(),
            "width": int(stream.width), "height": int(stream.height)}
    spec = {"capture": str(Path(run.capture.root).resolve()), "stream_camera": info.camera,
            "rgb_times": rgb_times, "coverage": [float(stream.t0), float(stream.t_end)],
            "k_sub": int(cfg.spike.fine_k_sub), "d_model": int(cfg.spike.fine_d_model),
            "channels": int(cfg.spike.fine_channels), "per_gaussian": bool(cfg.spike.fine_per_gaussian),
            "frozen_encoder": bool(cfg.spike.fine_frozen_encoder), "encoder_every": int(FINE_ENCODER_EVERY),
            "change_gate": bool(cfg.spike.fine_change_gate), "change_block": int(CHANGE_BLOCK),
            "bounds_min": field.bounds_min.tolist(), "bounds_max": field.bounds_max.tolist(), "view": view}
    enc = SpikeFineEncoder(field.feature_dim, spec).to(field.bounds_min.device)
    if cache is None or cache.k_sub != spec["k_sub"] or list(cache.rgb_times) != rgb_times:
        cache = SpikeWindowCache(stream, rgb_times, k_sub=spec["k_sub"]).precompute()
    enc.attach(cache)
    return enc


# ----------------------------------------------------------------------------- losses

class SpikeGuidance:
    """Per-run state of the between-frame supervision (see module doc)."""

    def __init__(self, run):
        self.run = run
        cfg = run.cfg
        self.cfg = cfg
        cap = run.capture
        self.real_frames = [f for f in cap.frames if not getattr(f, "extra", {}).get("synthetic")]
        self.by_cam: dict[str, list[int]] = {}
        for i, it in enumerate(run.items):
            self.by_cam.setdefault(it["camera"], []).append(i)
        for cam in self.by_cam:
            self.by_cam[cam].sort(key=lambda i: run.items[i]["time"])
        self.info = spike_stream_info(cap)
        self.stream = self.info.open() if self.info is not None else None
        self.colocated = self.info.co_located_with if self.info is not None else None
        times = sorted({float(it["time"]) for it in run.items})
        cov = (self.stream.t0, self.stream.t_end) if self.stream is not None else None
        self.sampler = InstantSampler(times, p_between=1.0, seed=run.seed,
                                      snap_hz=self.stream.rate_hz if self.stream is not None else None,
                                      snap_t0=self.stream.t0 if self.stream is not None else 0.0)
        self.spike_sampler = None
        if self.stream is not None:
            self.spike_sampler = InstantSampler(times, p_between=1.0, coverage=cov, seed=run.seed + 1,
                                                snap_hz=self.stream.rate_hz, snap_t0=self.stream.t0)
        self.renderer = None
        self.sensor = None
        self._spikes = None
        if self.stream is not None and cfg.spike.loss_weight > 0:
            self.sensor = estimate_sensor(cap, self.stream)
            self.renderer = SpikeRenderer(self.sensor)
            if self.stream.num_frames * self.stream.width * self.stream.height <= 256 * 2 ** 20:
                self._spikes = self.stream.read(0, self.stream.num_frames)
        self._flows: dict = {}
        self._consistency: dict = {}  # occlusion maps of each flow pair (flow_consistency)
        if block_weight(cfg) > 0 and cfg.spike.block_interp == "flow":
            self.precompute_flows()
        self.rng = np.random.default_rng(run.seed + 17)
        self._window_cache: SpikeWindowCache | None = None
        self.change = None
        self.skipped_intervals = 0
        if self.stream is not None and cfg.spike.skip_static:
            self.skip_static_windows()

    # --- skipping spike windows without change (engine.spike.change) --------------------------
    def window_cache(self) -> SpikeWindowCache | None:
        """Spike windows of the co-located camera's RGB intervals (shared with the fine branch)."""
        if self._window_cache is None and self.stream is not None:
            rgb_times = sorted({float(f.time) for f in self.real_frames if f.camera == self.colocated})
            if len(rgb_times) >= 2:
                self._window_cache = SpikeWindowCache(self.stream, rgb_times, k_sub=int(self.cfg.spike.fine_k_sub))
        return self._window_cache

    def skip_static_windows(self) -> None:
        """Drop the between-frame intervals whose spike window shows no change: their
        in-between instants hold nothing the RGB frames at both ends do not already say."""
        cache = self.window_cache()
        if cache is None:
            return
        self.change = cache.change(int(CHANGE_BLOCK))
        active = set(self.change.active_intervals.tolist())
        def keep(sampler):
            ks = [k for k in sampler.intervals.tolist()
                  if bracket(cache.rgb_times, 0.5 * (sampler.rgb_times[k] + sampler.rgb_times[k + 1]))[0] in active]
            return sampler.restrict(ks)

        self.skipped_intervals = keep(self.sampler)
        if self.spike_sampler is not None:
            keep(self.spike_sampler)

    # --- fine branch -----------------------------------------------------------------------
    def ensure_fine(self, tr) -> None:
        """Attach the fine encoder to ``tr``'s deformation field and optimiser (idempotent;
        ``tr`` is the run of the step, which may be the budget probe's copy)."""
        field = tr.model.deformation if tr.model is not None else None
        if field is None or not tr.model.use_deformation or tr.deform_opt is None:
            return
        if self.cfg.spike.static_prior and tr.model.static_prior is None:
            tr.model.static_prior = self.static_prior()
        if field.fine_encoder is None and getattr(field, "fine_spec", None) is not None:
            field.restore_fine_encoder()  # resumed checkpoint: spec + pending weights
        if field.fine_encoder is None:
            if getattr(field, "_bt4d_no_fine", False):
                return
            enc = make_fine_encoder(tr, field, self._window_cache)
            if enc is None:
                field._bt4d_no_fine = True
                return
            self._window_cache = enc.source()
            field.fine_encoder = enc
        if any(g.get("name") == "fine" for g in tr.deform_opt.param_groups):
            return
        params = [p for p in field.fine_encoder.parameters() if p.requires_grad]
        if params:
            tr.add_deformation_parameters(params, LR_FINE, name="fine")

    def static_prior(self):
        """``(canonical means [N,3]) -> bool [N]`` for ``Model4D.static_prior``: Gaussians in
        front of the spike camera, inside its view, whose projection is two blocks or more
        from any change in any spike window. They skip the deformation field: the spike loss
        watches one viewpoint, and a field free to move the static background along that
        camera's rays explains in-between changes with motion the other views never saw."""
        cache = self.window_cache()
        if cache is None or self.stream is None or self.stream.c2w is None or self.stream.intrinsics is None:
            return None
        change = cache.change(int(CHANGE_BLOCK))
        view = self.stream.view(0.0)
        vm = torch.as_tensor(view.viewmat, dtype=torch.float32)
        K = torch.as_tensor(self.stream.intrinsics.K, dtype=torch.float32)
        w, h = int(self.stream.width), int(self.stream.height)

        def prior(means: torch.Tensor) -> torch.Tensor:
            grid, vis = project_to_grid(means.float(), vm.to(means.device), K.to(means.device), w, h)
            return vis & (change.gate(None, grid, dilate=2) <= 0)

        return prior

    # --- observations ------------------------------------------------------------------------
    def observed(self, t: float, m: int):
        """(counts [h, w] float32, spike frames [n, h, w] uint8, n) in m frames centred on t."""
        s = self.stream
        half = m / 2.0 / s.rate_hz
        a, b = s.index_range(t - half, t + half)
        frames = self._spikes[a:b] if self._spikes is not None else s.read(a, b - a)
        return frames.sum(0, dtype=np.float32), frames, b - a

    def _real_pairs(self):
        items = self.run.items
        for cam, idx in self.by_cam.items():
            real = [i for i in idx if not items[i].get("synthetic")]
            for ia, ib in zip(real[:-1], real[1:]):
                yield ia, ib

    def precompute_flows(self) -> None:
        """Both-way flows of every consecutive RGB pair of each camera (once per run)."""
        items = self.run.items
        for ia, ib in self._real_pairs():
            if (ia, ib) not in self._flows:
                _, self._flows[(ia, ib)] = flow_interpolate(items[ia]["image"][0], items[ib]["image"][0], 0.5,
                                                            return_flows=True)

    def bracket(self, cam: str, t: float) -> tuple[int, int, float, float] | None:
        """(ia, ib, t1, t2): the run items of camera ``cam``'s real RGB frames with
        ``t1 <= t < t2``, or None outside them."""
        items = self.run.items
        real = [i for i in self.by_cam.get(cam, []) if not items[i].get("synthetic")]
        times = [items[i]["time"] for i in real]
        if len(times) < 2:
            return None
        k = int(np.searchsorted(times, t, side="right")) - 1
        if k < 0 or k >= len(times) - 1:
            return None
        return real[k], real[k + 1], times[k], times[k + 1]

    def interpolated(self, cam: str, t: float) -> torch.Tensor | None:
        """Interpolated frame [1, H, W, 3] of camera ``cam`` at ``t`` from its RGB frames."""
        br = self.bracket(cam, t)
        if br is None:
            return None
        ia, ib, t1, t2 = br
        items = self.run.items
        a, b = items[ia]["image"][0], items[ib]["image"][0]
        eps = (t - t1) / (t2 - t1)
        if self.cfg.spike.block_interp == "linear":
            return linear_blend(a, b, eps)[None]
        key = (ia, ib)
        if key not in self._flows:
            _, flows = flow_interpolate(a, b, 0.5, return_flows=True)
            self._flows[key] = flows
        if key not in self._consistency:  # occlusion maps of the pair: the same at every instant
            self._consistency[key] = flow_consistency(*self._flows[key])
        return flow_interpolate(a, b, eps, flows=self._flows[key],
                                consistency=self._consistency[key]).clamp(0, 1)[None]

    TARGET_STEPS = 64  # block-colour targets are interpolated at 1/64-interval steps (cached)
    TARGET_CACHE_BYTES = 256 * 2 ** 20

    def pooled_target(self, cam: str, t: float, k: int) -> torch.Tensor | None:
        """``AvgPool_k`` of the frame interpolated at ``t`` [1, H/k, W/k, 3], cached.

        The interpolation time is rounded to 1/64 of the RGB interval (at 30 FPS, 0.5 ms:
        a sub-pixel shift after 4x4 pooling even for fast motion), so the flow warp runs
        once per (camera, instant) instead of every step; the cache keeps the pooled blocks
        only and is bounded (least recently used out)."""
        br = self.bracket(cam, t)
        if br is None:
            return None
        ia, _, t1, t2 = br
        q = int(round((t - t1) / (t2 - t1) * self.TARGET_STEPS))
        key = (cam, ia, q, int(k))
        cache = self.__dict__.setdefault("_targets", {})
        hit = cache.pop(key, None)
        if hit is None:
            full = self.interpolated(cam, min(max(t1 + (t2 - t1) * q / self.TARGET_STEPS, t1), t2))
            if full is None:
                return None
            hit = avg_pool_blocks(full, k)
            size = hit.numel() * hit.element_size()
            while cache and (len(cache) + 1) * size > self.TARGET_CACHE_BYTES:
                cache.pop(next(iter(cache)))
        cache[key] = hit  # most recently used last
        return hit

    # --- the between-frame render (once per step) ------------------------------------------
    def between(self, ctx) -> dict | None:
        cache = ctx.__dict__.get("_between", "unset")
        if cache != "unset":
            return cache
        ctx.__dict__["_between"] = None
        every = int(self.cfg.spike.between_every)
        if ctx.stage != "deform" or every <= 0 or ctx.step % every != 0:
            return None
        self.ensure_fine(ctx.run)
        use_spike = self.renderer is not None and self.spike_sampler is not None and self.spike_sampler.has_between
        window = getattr(ctx.run, "time_window", None)
        max_time = window(ctx.step) if callable(window) and self.cfg.spike.between_curriculum else None
        if use_spike and self.colocated in self.by_cam and self.rng.random() < self.cfg.spike.between_colocated_p:
            cam = self.colocated
            inst = self.spike_sampler.between_instant(max_time=max_time)
        else:
            if not self.sampler.has_between or block_weight(self.cfg) <= 0:
                return None
            cams = [c for c in self.by_cam if c != self.colocated] or list(self.by_cam)
            cam = cams[int(self.rng.integers(len(cams)))]
            inst = self.sampler.between_instant(max_time=max_time)
        if inst is None:  # the time curriculum has not opened any interval yet
            return None
        item = ctx.run.items[self.by_cam[cam][0]]
        vt = scaled_view(item, float(self.cfg.spike.between_scale))
        vt["time"] = inst.time
        scale = vt["width"] / item["width"]
        rgb, alpha, meta, attrs = ctx.run.model.render(vt, inst.time, render_depth=BETWEEN_DEPTH,
                                                       grad_rows=self.trainable_between(ctx, inst.time),
                                                       grad_attrs=BETWEEN_GRAD_ATTRS)
        out = {"rgb": rgb, "camera": cam, "instant": inst, "scale": scale, "meta": meta}
        ctx.__dict__["_between"] = out
        return out

    @staticmethod
    def trainable_between(ctx, t: float) -> torch.Tensor | None:
        """bool [N]: the Gaussians a between-frame render at ``t`` may train; None: all. Not those the
        spike view saw still over the interval holding ``t`` (their curves are quiet,
        :meth:`QuietCurves.still_at`): the RGB frames place and colour what does not move, and the
        spike loss's noise and sensor mismatch at one greyscale viewpoint repainted it
        (docs/experiments/still-gaussians-between-frames.md)."""
        quiet = ctx.run.part("quiet_curves")
        still = quiet.still_at(ctx.run.model, t) if quiet is not None else None
        return None if still is None else ~still

    def colocated_between(self, ctx) -> dict | None:
        """This step's between-frame render (:meth:`between`) when it was made at the spike
        camera's viewpoint -- what every spike-view term needs -- else None."""
        b = self.between(ctx)
        return b if b is not None and b["camera"] == self.colocated else None

    def deforming_spike_view(self, ctx) -> tuple[dict, object] | None:
        """(:meth:`colocated_between`, the run's model) when there is such a render and the
        model deforms (the terms that move motion at the spike view need both), else None."""
        b = self.colocated_between(ctx)
        model = ctx.run.model
        if b is None or model is None or not model.use_deformation:
            return None
        return b, model


def _spike_term(guid: SpikeGuidance):
    def fn(ctx):
        b = guid.colocated_between(ctx)
        if b is None or guid.renderer is None:
            return None
        m = int(guid.cfg.spike.window)
        counts, frames, n = guid.observed(b["instant"].time, m)
        if n == 0:
            return None
        img = b["rgb"][0].clamp(0, 1)
        scale = max(guid.sensor.scale, 1e-6)
        # spike pixels outside the rendered RGB view (a spike camera with its own field of view) say nothing
        valid = guid.sensor.valid
        mask = None if valid is None else torch.as_tensor(valid, dtype=img.dtype, device=img.device)
        if guid.cfg.spike.loss_mode == "if":
            spikes = guid.renderer.render_spikes(img, n)
            obs_spikes = torch.as_tensor(np.ascontiguousarray(frames), device=img.device)
            if mask is not None:
                spikes, obs_spikes = spikes * mask, obs_spikes * mask.to(obs_spikes.dtype)
            return cumulative_spike_loss(spikes, obs_spikes) / scale
        pred = guid.renderer.render_counts(img, n)
        obs = torch.as_tensor(np.ascontiguousarray(counts), device=img.device)
        return spike_count_loss(pred, obs, n, mask) / scale
    return fn


def _block_term(guid: SpikeGuidance):
    def fn(ctx):
        b = guid.between(ctx)
        if b is None:
            return None
        k = int(BLOCK_SIZE)
        target = guid.pooled_target(b["camera"], b["instant"].time, k)
        if target is None:
            return None
        kp = max(1, int(round(k * b["scale"])))
        return block_colour_loss(b["rgb"], target.to(b["rgb"].device), kp, k_target=1)
    return fn


def _fine_term(guid: SpikeGuidance):
    """Attaches the fine branch as soon as the deformation stage starts (no loss of its own)."""
    def fn(ctx):
        if ctx.stage == "deform":
            guid.ensure_fine(ctx.run)
        return None
    return fn


def _tick_fine(tr, step, item, meta) -> None:
    """Post-step hook: one step done for the fine encoder's kept windows (``FINE_ENCODER_EVERY``)."""
    field = tr.model.deformation if tr.model is not None else None
    enc = getattr(field, "fine_encoder", None)
    if isinstance(enc, SpikeFineEncoder):
        enc.encoded.tick()


def admitted_time(ctx, last: float) -> float:
    """The latest capture time the time curriculum has admitted at ``ctx.step`` (the run's
    ``time_window``), or ``last`` for a run without one (the terms that ride on the
    between-frame renders use only intervals whose ends are both admitted)."""
    window = getattr(ctx.run, "time_window", None)
    return window(ctx.step) if callable(window) else last


def spike_view_guidance(run) -> SpikeGuidance | None:
    """The run's spike guidance when its spike loss renders at the spike camera (a renderer
    and ``spike_loss_weight > 0``): what the terms riding on those renders (the along-ray
    prior, the spike-view flow) need; None otherwise."""
    guid = run.part("spike_guidance")
    if guid is None or guid.renderer is None or run.cfg.spike.loss_weight <= 0:
        return None
    return guid


def guidance_factory(run) -> list:
    """Loss terms of the spike guidance for a (non rgb_only) run."""
    cfg = run.cfg
    if spike_stream_info(run.capture) is None:  # no spike stream: the whole branch is skipped
        return []
    guid = SpikeGuidance(run)
    run.parts["spike_guidance"] = guid
    hooks_after = getattr(run, "post_step_hooks", None)
    if hooks_after is not None:
        hooks_after.append(_tick_fine)
    hooks = getattr(run, "deformation_hooks", None)
    if hooks is not None:  # the run calls it when the field is created or restored
        hooks.append(guid.ensure_fine)
        terms = []
    else:
        terms = [LossTerm("fine_attach", 1.0, _fine_term(guid), stages=("deform",))]
    if guid.renderer is not None and cfg.spike.loss_weight > 0:
        terms.append(LossTerm("spike", float(cfg.spike.loss_weight), _spike_term(guid), stages=("deform",)))
    if block_weight(cfg) > 0:
        terms.append(LossTerm("block_colour", block_weight(cfg), _block_term(guid),
                              stages=("deform",)))
    return terms

