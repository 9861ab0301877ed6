#!/usr/bin/env python
"""Ground-truth 2D motion at the spike view, for the spike-flow term (diagnostic, issue 11).

The flow term (``spike_flow_weight``, engine/train/spike_flow.py) supervises the visible
Gaussians' projected displacement at the spike camera with optical flow between grey
images reconstructed from the spikes. This script answers two questions on a capture with
ground truth (``ground_truth.objects`` and per-frame depth at the spike camera's co-located
RGB camera, e.g. /work/coord/scenes/between):

* how good is the estimated flow? ``--flow``: end-point error (spike px) of the estimated
  flow against the true 2D motion, on the pixels that move (> 0.5 px) and are kept by the
  forward-backward check, and how many of them it keeps;
* what would a perfect flow buy? ``--train RUN``: train with the term fed the true motion
  instead of the estimate (an upper bound; not a feature)::

      .venv/bin/python scripts/spike_flow_oracle.py CAPTURE --flow
      nice -n 10 .venv/bin/python scripts/spike_flow_oracle.py CAPTURE --train RUN [--seed S] \\
          [--set key=value ...]     # init=stereo and spike_flow_weight=1 unless given

True motion at a spike pixel at ``T``: the ground-truth depth of the co-located RGB camera at
``T`` back-projects each RGB pixel; the point belongs to the moving object with a surface
sample within ``--radius`` (else it is static), moves with that object's transform to ``t``
and is projected through the spike camera; the RGB pixels' displacements are averaged over
each spike pixel, which is valid where all of them agree on the object.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from engine.cameras import project_points  # noqa: E402
from engine.io.ground_truth import pose_at  # noqa: E402
from engine.train.scene_flow import backproject_pixels  # noqa: E402


class TrueMotion:
    """True 2D motion at the spike view between RGB instants and any ``t`` (cached depth)."""

    def __init__(self, cap, radius: float = 0.01):
        from engine.train.spike_guidance import spike_stream_info

        info = spike_stream_info(cap)
        self.stream = info.open()
        self.sview = self.stream.view(0.0)
        self.frames = {round(float(f.time), 9): f for f in cap.frames if f.camera == info.co_located_with}
        self.cap = cap
        self.truth = cap.ground_truth.objects.load()
        self.names = list(cap.ground_truth.objects.names)
        self.radius = float(radius)
        self._ref: dict = {}

    def pose(self, name: str, t: float) -> np.ndarray:
        return pose_at(self.truth["times"], self.truth[name], float(t))

    def reference(self, T: float):
        """(world points [H*W, 3] of the RGB camera's pixels at ``T``, object id [H*W] (-1
        static, -2 no surface), RGB size)."""
        key = round(float(T), 9)
        if key not in self._ref:
            f = self.frames[key]
            depth = f.load_depth()
            h, w = depth.shape
            gx, gy = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
            uv = np.stack([gx.ravel(), gy.ravel()], 1)
            z = depth.ravel().astype(np.float64)
            fin = np.isfinite(z)
            X = backproject_pixels(self.cap.view(f), uv, np.where(fin, z, 1.0))
            owner = np.where(fin, -1, -2)
            best = np.full(len(X), np.inf)
            for k, name in enumerate(self.names):
                M = self.pose(name, T)
                pts = self.truth[f"{name}_points"].astype(np.float64) @ M[:3, :3].T + M[:3, 3]
                import torch

                d = torch.cdist(torch.from_numpy(X), torch.from_numpy(pts)).min(1).values.numpy()
                take = fin & (d < self.radius) & (d < best)
                owner[take], best[take] = k, d[take]
            self._ref[key] = (X, owner, (h, w))
        return self._ref[key]

    def flow(self, T: float, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(true flow T -> t [h, w, 2] in spike px, valid bool [h, w]) at the spike resolution."""
        X, owner, (H, W) = self.reference(T)
        Xt = X.copy()
        for k, name in enumerate(self.names):
            sel = owner == k
            if sel.any():
                A = self.pose(name, t) @ np.linalg.inv(self.pose(name, T))
                Xt[sel] = X[sel] @ A[:3, :3].T + A[:3, 3]
        uv0, _ = project_points(self.sview, X)
        uv1, _ = project_points(self.sview, Xt)
        d = (uv1 - uv0).reshape(H, W, 2)
        h, w = int(self.stream.height), int(self.stream.width)
        sy, sx = H // h, W // w
        blocks = d[: h * sy, : w * sx].reshape(h, sy, w, sx, 2)
        own = owner.reshape(H, W)[: h * sy, : w * sx].reshape(h, sy, w, sx)
        valid = (own.min(axis=(1, 3)) == own.max(axis=(1, 3))) & (own.min(axis=(1, 3)) >= -1)
        return blocks.mean(axis=(1, 3)).astype(np.float32), valid


def flow_report(cap, per_interval: int = 3, window: int = 128) -> None:
    from engine.spike.render import estimate_sensor
    from engine.train.baselines import spike_to_gray
    from engine.train.spike_flow import flow_pair

    tm = TrueMotion(cap)
    sensor = estimate_sensor(cap, tm.stream)
    times = sorted(tm.frames)
    rows = []
    for a, b in zip(times, times[1:]):
        for i in range(per_interval):
            t = a + (b - a) * (i + 1) / (per_interval + 1)
            T = a if t - a <= b - t else b
            gt, ok = tm.flow(T, t)
            fl, val = flow_pair(spike_to_gray(tm.stream, T, sensor, window=window),
                                spike_to_gray(tm.stream, t, sensor, window=window))
            moving = ok & (np.linalg.norm(gt, axis=-1) > 0.5)
            use = moving & val
            epe = np.linalg.norm(fl - gt, axis=-1)
            zero = np.linalg.norm(gt, axis=-1)
            rows.append((t, T, int(moving.sum()), float(use.sum()) / max(1, moving.sum()),
                         float(epe[use].mean()) if use.any() else np.nan,
                         float(zero[use].mean()) if use.any() else np.nan, float(epe[ok & val & ~moving].mean())))
            print(f"t={t:.4f} ref={T:.4f}: moving px {rows[-1][2]}, kept {rows[-1][3]:.2f}, EPE {rows[-1][4]:.2f} px "
                  f"(zero flow {rows[-1][5]:.2f}), static EPE {rows[-1][6]:.2f}")
    r = np.array([x[2:] for x in rows], float)
    print(f"mean over {len(rows)} instants: moving px {r[:, 0].mean():.0f}, kept {np.nanmean(r[:, 1]):.2f}, "
          f"EPE {np.nanmean(r[:, 2]):.2f} px against zero flow {np.nanmean(r[:, 3]):.2f} px, static EPE "
          f"{np.nanmean(r[:, 4]):.2f}")


def train_oracle(cap_path, out, seed: int, overrides: dict, oracle: bool = True) -> dict:
    """Train ``out`` with the flow term fed the true motion (``oracle``) or its own estimate;
    the term's per-step diagnostics (surface Gaussians, mean residual px) go to
    ``out/spike_flow_trace.json``."""
    import json

    from engine.io.capture import load_capture
    from engine.train import spike_flow
    from engine.train.run import train

    cap = load_capture(cap_path)
    cls = spike_flow.SpikeFlowSupervision
    if oracle:
        tm = TrueMotion(cap)
        cls.estimate = lambda self, T, t, init=None: (*tm.flow(T, t), None)
    trace, fits = [], {}
    call = cls.__call__

    def traced(self, ctx):
        out = call(self, ctx)
        fits.update(self.fitted)
        if out is not None:
            trace.append({"step": ctx.step, **self.last})
        return out

    cls.__call__ = traced
    ov = {"init": "stereo", "spike_flow_weight": 1.0, **overrides}
    res = train(cap_path, out, preset="fast", resume=False, seed=seed, overrides=ov)
    Path(out, "spike_flow_trace.json").write_text(json.dumps({"steps": trace, "fits": fits}))
    return res


def main(argv=None) -> int:
    from engine.cli.train import parse_overrides
    from engine.io.capture import load_capture

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("--flow", action="store_true", help="end-point error of the estimated flow")
    ap.add_argument("--window", type=int, default=128)
    ap.add_argument("--train", type=Path, help="train RUN with the true motion as the flow")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--estimated", action="store_true", help="with --train: the estimated flow (trace only)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    if args.flow:
        flow_report(load_capture(args.capture), window=args.window)
    if args.train:
        res = train_oracle(args.capture, args.train, args.seed, parse_overrides(args.set), oracle=not args.estimated)
        print({k: res.get(k) for k in ("status", "step", "train_seconds", "num_gaussians")})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
