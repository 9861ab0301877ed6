"""What the parts of training see of a run: :class:`RunContext`.

The trainer (``engine.train.loop.trainer``) owns one and hands it -- never itself -- to the loss
factories, the loss terms (through ``StepContext.run``), the post-step and deformation hooks, the
carries and births, and the skipping parts, as gsplat's densification ``Strategy`` gets the
parameters, optimisers and its state rather than the trainer. A part reads the run's data, model
and clock here, registers its hooks and parts here, and keeps its per-run caches in ``memo``;
the trainer's own machinery (the step, the optimisers' schedules, densification, checkpoints)
stays out of its reach.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

from .config import TrainConfig

__all__ = ["RunContext"]


@dataclass(eq=False)
class RunContext:
    cfg: TrainConfig
    capture: Any                       # engine.io.capture.Capture
    device: Any                        # torch.device
    seed: int
    items: list                        # the train frames as view dicts (image, time, camera, ...)
    frame_times: list                  # the RGB instants (trajectory knots), sorted
    time_range: tuple                  # (first, last) capture time
    fusion_cache: Any                  # engine.geometry.depth_priors.FusionCache: one stereo fusion a run
    rgb_only: bool = False
    schedule: Any = None               # engine.train.loop.schedule.Schedule: the one clock (re-planned by budgets)
    model: Any = None                  # engine.scene.model.Model4D once initialised (replaced on resume)
    extent: float = 1.0                # the scene's radius (learning rates, thresholds)
    deform_opt: Any = None             # the deformation field's optimiser, when there is a field
    guided: bool = False               # the spike guidance supervises instants between RGB frames
    # registries the parts add to: hooks (run, step, item, meta) after each optimiser step; hooks
    # (run) once the deformation field exists; the fine feature of a step's render (item -> tensor)
    post_step_hooks: list = field(default_factory=list)
    deformation_hooks: list = field(default_factory=list)
    fine_provider: Callable | None = None
    parts: dict = field(default_factory=dict)   # name -> a part a factory built (spike_guidance, spike_flow, ...)
    memo: dict = field(default_factory=dict)    # per-run caches of the parts (stereo priors, item images, ...)
    info: dict = field(default_factory=dict)    # what the parts report to run.json (births, carries)
    # the trainer's answers: the stage of a step, the latest admitted capture time, and a way to
    # train more deformation parameters (the spike fine branch)
    stage_of: Callable[[int], str] | None = None
    time_window: Callable[[int], float] | None = None
    add_deformation_parameters: Callable | None = None

    def part(self, name: str):
        """The part registered as ``name`` (None when the run has none)."""
        return self.parts.get(name)

    @property
    def total_steps(self) -> int:
        return self.schedule.total
