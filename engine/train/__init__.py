"""Training: the trainer loop, its loss terms, presets (``TrainConfig``), budget probe,
spike guidance, freezing, early stop, culling and the two-stage baselines.

May import: every package below it (foundations, io, raster, spike, scene, geometry,
evaluate). Nothing below imports training.
"""
from .config import TrainConfig, get_preset
from .run import train

__all__ = ["TrainConfig", "get_preset", "train"]
