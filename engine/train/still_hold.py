"""Still hold: the RGB frames' still background held between the RGB instants (issue 11).

Each RGB instant fits a Gaussian's place on its own; a Gaussian of a still wall may sit a few
centimetres apart at consecutive instants (a median 4 cm on the demo) and both places explain
their frame. Half-way between the instants its curve runs between the two places and the
wall's texture is misaligned at a new viewpoint. On the demo at the eval cameras (1000 fast
steps, seed 0; the complement of the motion mask) still pixels scored 25.94 dB at the RGB
instants and 25.63 half-way between them with RGB-only, 26.00 / 25.32 with the full model,
while the Interpolate baseline, which trains on interpolated frames in between, kept 26.03 /
25.97 (README "Still frames held between the RGB instants"). An interpolated frame is only sure
where nothing moved: where a camera's two neighbouring frames agree and nothing passed between.

Every ``still_every``-th deformation step the term (``engine.train.losses``, ``still_weight``)
renders one train camera at a random instant inside one of its admitted RGB intervals and
takes the frame loss against the two frames' linear blend on that pair's *still* pixels
(:func:`still_mask`), the render itself elsewhere:

* changed: the two frames' 3 x 3 box means differ by more than ``still_colour_tol``;
* swept: each changed pixel's optical flow (:func:`sweep_flow`, both ways) draws the segment
  its content travelled between the frames (an object moving farther than its own size passes
  over pixels that show the background at both ends);
* changed and swept pixels, dilated by ``still_margin_px``, are not still;
* with a spike view (the full model), neither is a pixel whose rendered surface projects onto a
  spike block that changed during the interval (dilated by ``still_spike_dilate`` blocks,
  :meth:`StillHold.spike_still`): the spike stream saw something there that the two frames,
  1/30 s apart, did not (the ``between`` scene's ball vibrates at 15 Hz).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from .geometry_losses import project_into
from .scene_flow import image_flow

__all__ = ["sweep_flow", "still_mask", "StillPair", "StillHold"]


def _box3(img: np.ndarray) -> np.ndarray:
    return cv2.blur(np.asarray(img, np.float32)[..., :3], (3, 3), borderType=cv2.BORDER_REPLICATE)


FLOW_SIDE = 320  # the sweep's flow runs on frames scaled down to at most this many pixels a side


def sweep_flow(img_a: np.ndarray, img_b: np.ndarray) -> np.ndarray:
    """Flow a -> b [H, W, 2] in full-resolution pixels, for the sweep only: our block
    matching + Lucas-Kanade pyramid (:func:`engine.train.scene_flow.image_flow` "lk", the scene-flow
    carry's default) on frames scaled to at most :data:`FLOW_SIDE` a side. On a textured 24 px
    square moved 10 px in a 160 x 120 frame it reads 9.7 px where OpenCV's DIS reads 3 px the
    wrong way (tests/test_still_hold.py); at 1080 x 720, scaled, a pair's two flows and mask
    take 0.28 s CPU."""
    h, w = img_a.shape[:2]
    scale = min(1.0, FLOW_SIDE / max(h, w))
    if scale < 1.0:
        size = (max(8, round(w * scale)), max(8, round(h * scale)))
        img_a, img_b = (cv2.resize(np.asarray(x, np.float32)[..., :3], size, interpolation=cv2.INTER_AREA)
                        for x in (img_a, img_b))
    flow = image_flow(img_a, img_b, "lk")
    if scale < 1.0:
        flow = cv2.resize(flow, (w, h), interpolation=cv2.INTER_LINEAR) / scale
    return flow


def _sweep(changed: np.ndarray, flow: np.ndarray, max_len: float = 256.0) -> np.ndarray:
    """bool [H, W]: the pixels on the segments ``p + s * flow(p)``, s in [0, 1], of the changed pixels."""
    h, w = changed.shape
    ys, xs = np.nonzero(changed)
    f = np.clip(flow[ys, xs].astype(np.float32), -max_len, max_len)
    n = int(math.ceil(float(np.abs(f).max(initial=0.0)))) + 1
    out = np.zeros((h, w), bool)
    for s in np.linspace(0.0, 1.0, n, dtype=np.float32):
        out[np.clip(np.rint(ys + s * f[:, 1]).astype(np.int64), 0, h - 1),
            np.clip(np.rint(xs + s * f[:, 0]).astype(np.int64), 0, w - 1)] = True
    return out


def still_mask(img_a: np.ndarray, img_b: np.ndarray, *, colour_tol: float = 0.015, margin_px: int = 2,
               flows: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, float]:
    """(bool [H, W] still pixels, the longest sweep in pixels) of two frames [H, W, >=3] of one camera.

    Changed: a 3 x 3 box mean differs by more than ``colour_tol`` in any channel. Each changed
    pixel sweeps the segment its flow draws (a -> b from a's changed pixels, b -> a from b's:
    what moves passes over those pixels between the frames, :func:`_sweep`); the changed and
    swept pixels, dilated by ``margin_px`` (a disc), are not still. ``flows``: (a -> b, b -> a)
    [H, W, 2] each; default :func:`sweep_flow` both ways."""
    if colour_tol <= 0:
        raise ValueError(f"still colour_tol must be > 0 (got {colour_tol})")
    changed = (np.abs(_box3(img_a) - _box3(img_b)).max(-1) > colour_tol)
    if not changed.any():
        return np.ones(changed.shape, bool), 0.0
    if flows is None:
        flows = (sweep_flow(img_a, img_b), sweep_flow(img_b, img_a))
    moved = changed | _sweep(changed, flows[0]) | _sweep(changed, flows[1])
    longest = max(float(np.hypot(f[..., 0], f[..., 1])[changed].max()) for f in flows)
    if margin_px > 0:
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin_px + 1, 2 * margin_px + 1))
        moved = cv2.dilate(moved.astype(np.uint8), disc) > 0
    return ~moved, longest


@dataclass
class StillPair:
    """Two consecutive RGB frames of one train camera (indices into ``Trainer.items``) and,
    once drawn (:meth:`StillHold.still_of`), their still pixels (bool [1, H, W, 1]) and
    longest flow in pixels."""

    a: int
    b: int
    still: torch.Tensor | None = None
    sweep_px: float = 0.0


class StillHold:
    """The still pairs of a trainer's frames (listed on first use; a pair's mask is made from
    the frames in memory when it is first drawn, so a run pays the flows of the intervals
    its curriculum reaches, spread over its steps) and, per step, one draw."""

    def __init__(self, cfg):
        self.colour_tol = float(cfg.still_colour_tol)
        self.margin_px = int(cfg.still_margin_px)
        self.every = max(1, int(cfg.still_every))
        self.spike_dilate = int(cfg.still_spike_dilate)
        self.pairs: list[StillPair] | None = None
        self._spike = None  # False: no spike view; else (change, viewmat [4,4], K [3,3], (w, h), rgb_times)

    @staticmethod
    def build(items: list[dict]) -> list[StillPair]:
        """Consecutive real frames of each camera (a held-back frame between two splits
        their interval: pairs over 1.5 x the camera's median spacing are skipped)."""
        by_cam: dict[str, list[int]] = {}
        for i, it in enumerate(items):
            if it.get("knot", True) and not it.get("synthetic", False):
                by_cam.setdefault(str(it["camera"]), []).append(i)
        pairs = []
        for idx in by_cam.values():
            idx.sort(key=lambda i: float(items[i]["time"]))
            gaps = np.diff([float(items[i]["time"]) for i in idx])
            if len(gaps):
                limit = 1.5 * float(np.median(gaps))
                pairs += [StillPair(ia, ib) for ia, ib, gap in zip(idx[:-1], idx[1:], gaps) if 0 < gap <= limit]
        return pairs

    def still_of(self, pair: StillPair, items: list[dict]) -> torch.Tensor:
        """The pair's still mask (made on first call, :func:`still_mask`)."""
        if pair.still is None:
            a, b = (items[i]["image"][0].detach().cpu().numpy() for i in (pair.a, pair.b))
            still, pair.sweep_px = still_mask(a, b, colour_tol=self.colour_tol, margin_px=self.margin_px)
            pair.still = torch.from_numpy(still)[None, ..., None].to(items[pair.a]["image"].device)
        return pair.still

    def sample(self, trainer, step: int):
        """(view tensors, instant, target [1, H, W, 3], still [1, H, W, 1]) for this step, or
        None: not an ``every``-th step, no pair admitted yet (both frames within the time
        curriculum's window) or no still pixel in the one drawn. The instant is uniform inside
        the interval; the target is the two frames' linear blend there."""
        if step % self.every:
            return None
        items = trainer.items
        if self.pairs is None:
            self.pairs = self.build(items)
        t_max = trainer.time_window(step) + 1e-9
        pool = [p for p in self.pairs if float(items[p.b]["time"]) <= t_max]
        if not pool:
            return None
        rng = np.random.default_rng([int(trainer.seed), int(step), 13])
        pair = pool[int(rng.integers(len(pool)))]
        eps = float(rng.uniform(0.0, 1.0))
        still = self.still_of(pair, items)
        if not bool(still.any()):
            return None
        a, b = items[pair.a], items[pair.b]
        t = float(a["time"]) + eps * (float(b["time"]) - float(a["time"]))
        return a, t, a["image"] * (1.0 - eps) + b["image"] * eps, still

    def spike_view(self, trainer):
        """(change maps, viewmat, K, (width, height), rgb times) of the run's spike view, or None
        (RGB-only, no calibrated co-located stream). Looked up once, at the first call."""
        if self._spike is None:
            self._spike = False
            guid = getattr(trainer, "spike_guidance", None)
            stream = None if guid is None else guid.stream
            if stream is not None and stream.c2w is not None and stream.intrinsics is not None:
                cache = guid.window_cache()
                if cache is not None:
                    self._spike = (cache.change(int(trainer.cfg.spike_change_block)),
                                   torch.as_tensor(stream.view(0.0).viewmat, dtype=torch.float32),
                                   torch.as_tensor(stream.intrinsics.K, dtype=torch.float32),
                                   (int(stream.width), int(stream.height)), [float(t) for t in cache.rgb_times])
        return self._spike or None

    def spike_still(self, trainer, vt: dict, t_a: float, depth: torch.Tensor, alpha: torch.Tensor):
        """bool [1, H, W, 1]: False where the render's surface (``depth`` [H, W] planar, where
        ``alpha`` [H, W] > 0.5) projects into the spike view onto a block that changed during
        the interval starting at ``t_a`` (dilated by ``still_spike_dilate`` blocks): the spike
        stream saw something there between the two RGB frames, though they agree. None: no
        spike view, or its maps do not cover the interval."""
        spike = self.spike_view(trainer)
        if spike is None:
            return None
        change, viewmat, K, (w, h), rgb_times = spike
        k = int(np.searchsorted(np.asarray(rgb_times), t_a + 1e-6)) - 1
        if not 0 <= k < change.num_intervals:
            return None
        dev = depth.device
        ub, vb, z = project_into(depth, vt["K"][0], vt["viewmat"][0], K.to(dev), viewmat.to(dev))
        grid = torch.stack([ub / w * 2 - 1, vb / h * 2 - 1], -1).reshape(-1, 2)
        gate = change.gate(k, grid, dilate=self.spike_dilate).reshape(depth.shape).to(dev)
        return ~((gate > 0) & (alpha > 0.5) & (z > 1e-6))[None, ..., None]

