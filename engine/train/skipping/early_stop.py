"""Early stop: end a run when the PSNR on a few train frames held back from training stops
improving (the ``early_stop`` switch of :class:`engine.train.config.TrainConfig`); never
the eval frames, which are the test views every reported metric is computed on."""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from ...evaluate.metrics import psnr_from_mse
from ...scene.model import Model4D, view_tensors

__all__ = ["EarlyStop", "hold_back_frames"]


# the early-stopping proxy: how many train frames are held back, how often it is scored, what counts
# as a gain and how early it may stop (docs/experiments/stress-and-skipping.md)
PROXY_FRAMES = 4
EVERY_FRACTION = 0.05            # a proxy evaluation every this share of the steps
MIN_DELTA_DB = 0.05              # a smaller gain is no gain
MIN_DEFORM_FRACTION = 0.25       # never stop before this share of the deformation stage


def hold_back_frames(frames: list, n: int | None = None) -> tuple[list, list]:
    """(kept, held): up to ``n`` train frames held back from training as the early-stopping
    proxy. Only an instant that two or more train cameras see gives up one frame (the other
    cameras still train that instant, so no motion goes unseen and the proxy measures a
    view no camera trained on at that instant); the first instant is spared when another
    one is eligible (the static stage fits the canonical scene to it). The chosen instants
    are spread evenly over the eligible ones and take the cameras in turn. ``n``: PROXY_FRAMES."""
    n = PROXY_FRAMES if n is None else n
    by_t: dict[float, list] = {}
    for f in frames:
        by_t.setdefault(round(float(f.time), 9), []).append(f)
    multi = sorted(t for t, fs in by_t.items() if len({f.camera for f in fs}) >= 2)
    if len(multi) > 1:
        multi = multi[1:]
    if n <= 0 or not multi:
        return list(frames), []
    idx = sorted(set(np.linspace(0, len(multi) - 1, min(int(n), len(multi))).round().astype(int).tolist()))
    held = []
    for j, i in enumerate(idx):
        fs = sorted(by_t[multi[i]], key=lambda f: str(f.camera))
        held.append(fs[j % len(fs)])
    ids = {id(f) for f in held}
    return [f for f in frames if id(f) not in ids], held


class EarlyStop:
    """Stop when the PSNR on a few held-back train frames (the *proxy*) stops improving.

    The proxy is ``PROXY_FRAMES`` train frames that the run holds back from
    training (:func:`hold_back_frames`: one camera's frame at instants that another train
    camera also sees), never the capture's eval frames, which are the test views every
    reported metric is computed on (``source == "held_back_train"``, named in run.json's
    ``early_stop_proxy``). A capture with no such instant (a single train camera) has no
    proxy: early stopping is off and run.json says why. The proxy is scored every
    ``early_stop_every_fraction`` of the steps (its cost counts in the run's wall time);
    training stops after ``early_stop_patience`` evaluations without a gain of
    ``early_stop_min_delta`` dB, once the deformation stage has run for
    ``early_stop_min_deform_fraction`` of its steps (before that only the best is tracked).
    """

    SOURCE = "held_back_train"

    def __init__(self, frames: list[dict], names: list[str], source: str = SOURCE, *, patience: int = 3,
                 min_delta: float = 0.05, every_fraction: float = 0.05, min_deform_fraction: float = 0.25):
        self.frames = frames          # view tensors with "image" [1,H,W,3]
        self.names = names
        self.source = source
        self.patience = max(1, int(patience))
        self.min_delta = float(min_delta)
        self.every_fraction = float(every_fraction)
        self.min_deform_fraction = float(min_deform_fraction)
        self.history: list[dict] = []
        self.stopped_at: dict | None = None
        self.eval_seconds = 0.0
        self._next = 0
        self._best = -math.inf
        self._bad = 0

    @classmethod
    def for_run(cls, run, held_back: list) -> "EarlyStop | None":
        """The proxy of the train frames ``held_back`` from ``run`` (None when nothing could be held back)."""
        cfg, cap = run.cfg, run.capture
        frames, names = [], []
        for f in held_back:
            vt = view_tensors(cap.view(f), run.device)
            img = np.asarray(f.load_rgb(), dtype=np.float32)[..., :3]
            vt["image"] = torch.from_numpy(np.ascontiguousarray(img)).to(run.device)[None]
            frames.append(vt)
            names.append(f"train:{f.camera}@{float(f.time):.6f}")
        if not frames:
            return None
        return cls(frames, names, cls.SOURCE, patience=cfg.skip.early_stop_patience, min_delta=MIN_DELTA_DB,
                   every_fraction=EVERY_FRACTION, min_deform_fraction=MIN_DEFORM_FRACTION)

    def every(self, total_steps: int) -> int:
        return max(1, int(self.every_fraction * total_steps))

    @torch.no_grad()
    def score(self, model: Model4D) -> float:
        was = model.training
        model.eval()
        ps = []
        for vt in self.frames:
            rgb = model.render(vt, render_depth=False)[0]
            ps.append(psnr_from_mse(float(((rgb.clamp(0, 1) - vt["image"]) ** 2).mean())))
        model.train(was)
        return float(np.mean(ps)) if ps else float("nan")

    def update(self, run, done: int) -> bool:
        """After ``done`` completed steps: evaluate when due; True when training should stop."""
        if self.stopped_at is not None:
            return True
        if done < self._next:
            return False
        total = run.total_steps
        self._next = done + self.every(total)
        deform_done = run.schedule.deform_progress(done, run.cfg.schedule.static_fraction)
        t0 = time.perf_counter()
        score = self.score(run.model)
        self.eval_seconds += time.perf_counter() - t0
        self.history.append({"step": done, "proxy_psnr": round(score, 4)})
        if run.stage_of(done - 1) != "deform" or deform_done < self.min_deform_fraction:
            self._best = max(self._best, score)
            return False
        if score > self._best + self.min_delta:
            self._best, self._bad = score, 0
            return False
        self._bad += 1
        if self._bad < self.patience:
            return False
        self.stopped_at = {"step": done, "total_steps": total, "proxy_psnr": round(score, 4),
                           "best_proxy_psnr": round(self._best, 4), "proxy": self.source}
        return True

    def state_dict(self) -> dict:
        return {"history": list(self.history), "stopped_at": self.stopped_at, "eval_seconds": self.eval_seconds,
                "next": self._next, "best": self._best, "bad": self._bad}

    def load_state_dict(self, state: dict) -> None:
        self.history = list(state.get("history", []))
        self.stopped_at = state.get("stopped_at")
        self.eval_seconds = float(state.get("eval_seconds", 0.0))
        self._next = int(state.get("next", 0))
        self._best = float(state.get("best", -math.inf))
        self._bad = int(state.get("bad", 0))

    def summary(self) -> dict:
        return {"proxy": self.source, "frames": list(self.names), "evaluations": len(self.history),
                "eval_seconds": round(self.eval_seconds, 3), "stopped_at": self.stopped_at,
                "history": list(self.history)}
