"""Skipping what a scene does not need: CPOStream freezing of still Gaussians (``freezing``),
early stopping on train frames held back from training (``early_stop``), frustum culling
(``culling``). Each is a switch of the configuration's ``skip`` group, off by default.

May import: every part of training below the loop, and the packages below training."""
