"""When a settling run has converged: its train frames' error stops falling.

A run with more steps than its schedule (``schedule.iterations``) settles after it
(engine.train.loop.schedule: the clock holds its end values; engine.train.loop.trainer: every lr
but the positions' at ``SETTLE_LR`` x its value, ``SETTLE_DECAY``-fold less every schedule's length;
at full value the two fixed train views collapsed the new view, 154 at 1000 + 3000 steps 22.04 ->
16.89 dB). Settling holds the new view where the schedule left it (fast preset, 4x its steps: -0.03
... +0.08 dB on five scenes; 8x on a 2.2 m set +0.14: docs/experiments/settle-after-the-schedule.md)
but does not raise it, so a ``--seconds`` run ends there once its train frames say so, and run.json
says it converged instead of burning the rest of the budget.

The test reads the steps' own renders (no extra render, no frame held back from training, which
cost 1.4-2.1 dB: docs/experiments/more-steps-random-scenes.md): a settling run shows every train
frame once per epoch (engine.train.loop.trainer.Trainer.frame_index), so the mean squared error
over a window of whole epochs compares like with like; the run has converged when one window's
error falls by less than ``MIN_GAIN`` of the window before it.
"""
from __future__ import annotations

import math

__all__ = ["MIN_GAIN", "MIN_WINDOW_STEPS", "SETTLE_DECAY", "SETTLE_LR", "SettleMonitor", "settle_lr"]

SETTLE_LR = 0.1  # x every lr but the positions' (already at their final value) when the schedule ends,
SETTLE_DECAY = 0.1  # ... falling this much over every schedule's length of settling steps


def settle_lr(step: int, schedule) -> float:
    """The lr factor at real ``step`` of a settling run: ``SETTLE_LR`` at the schedule's end, ``SETTLE_DECAY``-fold
    less every ``schedule.span`` steps after it. Its sum over any number of steps is bounded (~4 % of the schedule's
    steps at full lr), so no step count can refit the two train views; at a constant tenth 3000 more steps cost
    0.14-0.24 dB and 7000 cost 0.64 (docs/experiments/settle-after-the-schedule.md)."""
    done = max(0, int(step) - schedule.settle_from())
    return SETTLE_LR * SETTLE_DECAY ** (done / max(1, schedule.span or schedule.nominal))
MIN_GAIN = 0.01  # relative fall of the windowed train MSE (0.04 dB) below which a settling run has converged
MIN_WINDOW_STEPS = 50  # a window is the fewest whole epochs of at least this many steps


class SettleMonitor:
    """Windows of whole epochs of a settling run's train MSE; :meth:`update` says when it converged.

    ``n_frames``: the train frames (an epoch's steps); ``from_step``: the first settling step (the
    first window starts at the next epoch boundary, so each window sees every frame equally often)."""

    def __init__(self, n_frames: int, from_step: int):
        self.n_frames = max(1, int(n_frames))
        self.window = self.n_frames * max(1, math.ceil(MIN_WINDOW_STEPS / self.n_frames))
        self.from_step = int(from_step)
        self.start = self.n_frames * math.ceil(self.from_step / self.n_frames)
        self.means: list[float] = []
        self.converged_at: int | None = None
        self._sum = 0.0
        self._count = 0

    def update(self, step: int, mse: float) -> bool:
        """Record real ``step``'s train MSE; True once the run has converged (stays True)."""
        if self.converged_at is not None:
            return True
        if step < self.start:
            return False
        self._sum += float(mse)
        self._count += 1
        if self._count < self.window:
            return False
        self.means.append(self._sum / self._count)
        self._sum, self._count = 0.0, 0
        if len(self.means) >= 2 and self.means[-1] > self.means[-2] * (1.0 - MIN_GAIN):
            self.converged_at = int(step) + 1
            return True
        return False

    def summary(self) -> dict:
        """run.json's ``settle`` record."""
        return {"from_step": self.from_step, "window_steps": self.window, "min_gain": MIN_GAIN,
                "train_mse": [round(m, 7) for m in self.means], "converged_at": self.converged_at}
