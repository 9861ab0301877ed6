"""Training, in parts that name the method (lowest first; docs/architecture.md):
``config`` < ``frames`` < ``losses`` < ``motion`` < ``guidance`` < ``skipping`` < ``loop``.

May import: every package below it (foundations, io, raster, spike, scene, geometry,
evaluate). Nothing below imports training.
"""
from .config import TrainConfig, get_preset
from .loop.run import train

__all__ = ["TrainConfig", "get_preset", "train"]
