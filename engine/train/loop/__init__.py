"""The training loop: ``Trainer`` (one step), ``Schedule`` (the one clock every schedule reads),
the wall-clock budget, and ``train()`` (resume, checkpoints, run.json).

May import: every other part of training and the packages below it."""
