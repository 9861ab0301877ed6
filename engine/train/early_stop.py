"""Early stop: end a run when the PSNR on a few held-out frames stops improving
(the ``early_stop`` switch of :class:`engine.train.presets.TrainConfig`)."""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from ..evaluate.metrics import psnr_from_mse
from ..scene.model import Model4D, view_tensors

__all__ = ["EarlyStop"]


class EarlyStop:
    """Stop when the PSNR on a few held-out frames (the *proxy*) stops improving.

    The proxy is ``early_stop_proxy_frames`` eval frames of the capture, evenly spread over
    them (sorted by camera and time); a capture without eval frames falls back to as many
    train frames (``source == "train"``, noted in run.json). It is scored every
    ``early_stop_every_fraction`` of the steps (its cost counts in the run's wall time);
    training stops after ``early_stop_patience`` evaluations without a gain of
    ``early_stop_min_delta`` dB, once the deformation stage has run for
    ``early_stop_min_deform_fraction`` of its steps (before that only the best is tracked).
    """

    def __init__(self, frames: list[dict], names: list[str], source: str, *, patience: int = 3,
                 min_delta: float = 0.05, every_fraction: float = 0.05, min_deform_fraction: float = 0.25):
        self.frames = frames          # view tensors with "image" [1,H,W,3]
        self.names = names
        self.source = source          # "eval" | "train"
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
    def for_trainer(cls, trainer) -> "EarlyStop":
        cfg, cap = trainer.cfg, trainer.capture
        n = max(1, int(cfg.early_stop_proxy_frames))
        evals = sorted(getattr(cap, "eval_frames", None) or [], key=lambda f: (f.camera, f.time))
        frames, names = [], []
        if evals:
            source = "eval"
            idx = np.linspace(0, len(evals) - 1, min(n, len(evals))).round().astype(int)
            for i in sorted(set(idx.tolist())):
                f = evals[i]
                vt = view_tensors(cap.view(f), trainer.device)
                img = np.asarray(f.load_rgb(), dtype=np.float32)[..., :3]
                vt["image"] = torch.from_numpy(np.ascontiguousarray(img)).to(trainer.device)[None]
                frames.append(vt)
                names.append(str(f.path))
        else:
            source = "train"
            order = sorted(range(len(trainer.items)), key=lambda i: (trainer.items[i]["time"], i))
            idx = np.linspace(0, len(order) - 1, min(n, len(order))).round().astype(int)
            for i in sorted(set(idx.tolist())):
                frames.append(trainer.items[order[i]])
                names.append(f"train:{trainer.items[order[i]]['camera']}@{trainer.items[order[i]]['time']:.6f}")
        return cls(frames, names, source, patience=cfg.early_stop_patience, min_delta=cfg.early_stop_min_delta,
                   every_fraction=cfg.early_stop_every_fraction,
                   min_deform_fraction=cfg.early_stop_min_deform_fraction)

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

    def update(self, trainer, done: int) -> bool:
        """After ``done`` completed steps: evaluate when due; True when training should stop."""
        if self.stopped_at is not None:
            return True
        if done < self._next:
            return False
        total = trainer.total_steps
        self._next = done + self.every(total)
        s0 = trainer.static_steps
        deform_done = (done - s0) / max(1, total - s0)
        t0 = time.perf_counter()
        score = self.score(trainer.model)
        self.eval_seconds += time.perf_counter() - t0
        self.history.append({"step": done, "proxy_psnr": round(score, 4)})
        if trainer.stage_of(done - 1) != "deform" or deform_done < self.min_deform_fraction:
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
