"""The training schedule's clock: a *virtual step* that stays continuous when a budget run re-plans.

Every schedule of a run is a function of its progress: the static stage's end, the densify
window and cadence, the time curriculum's admissions, the position / trajectory / field lr
decays, the SH bands, the freezer's motion checks, early stopping's deformation share. They
all read it here, as a virtual step ``v`` on a nominal total ``N`` (:class:`Schedule`), never
as ``step / total_steps``.

Without a re-plan ``v == step`` (bit-for-bit: one segment of rate 1.0) and ``N`` is the
run's total, so a plain ``iterations`` run is unchanged. A ``--seconds`` run re-plans its real
total several times (engine.train.loop.budget: after ~5% of the run, then every 10% of the
deformation stage). Scaling every schedule by the new total made them jump (between scene,
120 s: 1246 -> 1458 -> 1941 steps in one step; the curriculum un-admitted frames, the lrs jumped
back up, the densify window moved; cube trajectory error 20.2 mm in the spike image plane
against 11.7 mm with 1000 plain steps). A re-plan here keeps ``v`` where it is and spreads the
rest, ``N - v``, evenly over the new remaining real steps: piecewise linear, continuous and
monotone in the real step.

The schedule never spans more real steps than its ``span`` (the preset's ``schedule.iterations``):
a budget or a ``schedule.steps`` count that buys more steps runs the schedule at its own length and
then *settles* (the clock holds its end value ``N - 1``; the trainer lowers every lr but the
positions', engine.train.loop.trainer). Stretching the schedule to the budget overfit the two train
views (fast preset, 4000 steps: 172 22.61 -> 21.88 dB, 154 22.04 -> 21.53 against 1000;
docs/experiments/settle-after-the-schedule.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

__all__ = ["Schedule"]


@dataclass
class Schedule:
    """Maps real steps to virtual steps.

    ``nominal``: N, the total every fraction refers to (the first plan, at most ``span``);
    ``total``: the real step count now planned; ``segments``: ``(first real step, virtual step
    there, virtual steps per real step)``, in order, the first starting at real step 0; ``span``:
    the most real steps the schedule may take (None: the whole run, as before settling existed)."""

    nominal: int
    total: int
    segments: list[tuple[int, float, float]] = field(default_factory=lambda: [(0, 0.0, 1.0)])
    span: int | None = None

    @classmethod
    def plan(cls, total: int, span: int | None = None) -> "Schedule":
        """A fresh plan of ``total`` steps: ``v == step``; past ``span`` steps the clock holds (settle)."""
        total = max(1, int(total))
        span = None if span is None else max(1, int(span))
        return cls(total if span is None else min(total, span), total, [(0, 0.0, 1.0)], span)

    # ------------------------------------------------------------------ the clock
    def virtual(self, step: int) -> float:
        """The virtual step at real ``step`` (the schedules' clock); with a ``span``, at most ``N - 1`` (the
        schedule's end values, which a settling run keeps)."""
        a, va, rate = self.segments[0]
        for seg in self.segments[1:]:
            if seg[0] > step:
                break
            a, va, rate = seg
        v = va + (step - a) * rate
        return v if self.span is None else min(v, float(self.nominal - 1))

    def replan(self, step: int, total: int) -> None:
        """From real ``step`` on, the run has ``total`` real steps: keep the virtual step at
        ``step`` and spread the rest of the nominal schedule over ``total - step`` steps, or over
        the steps up to ``span`` when the run is longer (the rest settles)."""
        step, total = int(step), int(total)
        if total == self.total:
            return
        if total <= step:
            raise ValueError(f"a re-plan at step {step} needs a total after it, got {total}")
        v = self.virtual(step)
        end = total if self.span is None else min(total, max(self.span, step + 1))
        rate = max(0.0, self.nominal - v) / (end - step)
        self.segments = [s for s in self.segments if s[0] < step] + [(step, v, rate)]
        self.total = total

    def settle_from(self) -> int:
        """The first real step after the schedule's last one (``total`` or later when none settles):
        from it the clock holds its end value and the run settles."""
        return self.first_step_at(self.nominal - 1) + 1

    def settling(self, step: int) -> bool:
        """``step`` comes after the schedule's last step (engine.train.loop.trainer lowers the lrs)."""
        return step >= self.settle_from()

    def first_step_at(self, v_target: float) -> int:
        """The first real step whose virtual step is >= ``v_target`` (``total`` or later when
        the plan never gets there)."""
        if self.span is not None and v_target > self.nominal - 1:  # past the clock's end value: never reached
            return max(self.total, self.segments[-1][0])
        for i, (a, va, rate) in enumerate(self.segments):
            end = self.segments[i + 1][0] if i + 1 < len(self.segments) else None
            if va >= v_target:
                return a
            if rate <= 0:
                continue
            s = a + max(0, int(math.ceil((v_target - va) / rate)))
            while s > a and self.virtual(s - 1) >= v_target:  # float round-off of the ceil
                s -= 1
            while self.virtual(s) < v_target:
                s += 1
            if end is None or s < end:
                return s
        return max(self.total, self.segments[-1][0])

    def mark_at(self, step: int, start: float, every: float) -> float | None:
        """The latest mark ``start + k * every`` (k >= 0) that the clock passes at ``step``,
        i.e. in ``(virtual(step - 1), virtual(step)]``, or None. Without a re-plan: ``step``
        itself when ``step >= start`` and ``(step - start) % every == 0``."""
        v1 = self.virtual(step)
        if v1 < start or every <= 0:
            return None
        k = math.floor((v1 - start) / every)
        m = start + k * every
        return m if m > self.virtual(step - 1) else None

    # ------------------------------------------------------------------ the schedules
    def static_end(self, static_fraction: float) -> int:
        """Virtual step where the deformation stage starts."""
        return int(round(static_fraction * self.nominal))

    def static_steps(self, static_fraction: float) -> int:
        """Real step where the deformation stage starts (its first deformation step)."""
        return self.first_step_at(self.static_end(static_fraction))

    def run_progress(self, step: int) -> float:
        """Share of the run done at ``step`` (the means' lr decay), 1 at the last step."""
        return self.virtual(step) / max(1, self.nominal - 1)

    def deform_progress(self, step: int, static_fraction: float, last: int = 0) -> float:
        """Share of the deformation stage done at ``step`` (negative in the static stage):
        ``last=1`` reaches 1 at the last step (lr decays), ``last=0`` at the end (curriculum)."""
        s0 = self.static_end(static_fraction)
        return (self.virtual(step) - s0) / max(1, self.nominal - s0 - last)

    def densify_window(self, cfg) -> tuple[int, int]:
        """(first, end) of densification in virtual steps (fractions of the run)."""
        return int(cfg.densify.start * self.nominal), int(cfg.densify.stop * self.nominal)

    def densify_due(self, step: int, cfg) -> bool:
        """Densify after ``step``: inside the window, every ``densify_every`` *real* steps from
        its first step (at least 3 times in it). The window is a share of the run, the cadence is
        not: the gradient statistics gather per real step (3DGS: every 100 iterations), and a
        cadence on the clock densified a run planned at 501 steps that ran 1080 only 3 times (between,
        120 s, load ~8: 17.1k Gaussians; the old schedule: 5 times, 21.5k; this cadence: 5)."""
        lo, hi = self.densify_window(cfg)
        lo_s, hi_s = self.first_step_at(lo), self.first_step_at(hi)
        every = max(1, min(cfg.densify.every, max(1, (hi_s - lo_s) // 3)))
        return lo_s < step and self.virtual(step) < hi and (step - lo_s) % every == 0

    def in_densify_window(self, step: int, cfg) -> bool:
        """Gather densification statistics at ``step`` (before the window's end)."""
        return self.virtual(step) < self.densify_window(cfg)[1]

    def in_fraction_window(self, step: int, start: float, end: float) -> bool:
        """``start <= v / N < end`` at ``step``: a window given as fractions of the run (the
        opacity decay's ``opacity_decay_from`` / ``opacity_decay_until``)."""
        v = self.virtual(step)
        return start * self.nominal <= v < end * self.nominal

    def sh_degree(self, step: int, cfg) -> int:
        """SH bands active at ``step``: one more every ``sh_step_fraction`` of the run."""
        g = cfg.gaussians
        return min(g.sh_degree, int(self.virtual(step) / max(1, g.sh_step_fraction * self.nominal)))

    # ------------------------------------------------------------------ checkpoint
    def state_dict(self) -> dict:
        return {"nominal": int(self.nominal), "total": int(self.total), "span": self.span,
                "segments": [[int(a), float(v), float(r)] for a, v, r in self.segments]}

    @classmethod
    def from_state(cls, state: dict | None, total: int) -> "Schedule":
        """The checkpoint's schedule; a checkpoint from before this module: a plan of ``total``."""
        if not state:
            return cls.plan(total)
        segs = [(int(a), float(v), float(r)) for a, v, r in state["segments"]]
        span = state.get("span")
        return cls(int(state["nominal"]), int(state["total"]), segs, None if span is None else int(span))
