"""Scoring: image metrics, held-out evaluation of a run, flicker of static regions.

May import: foundations, ``engine.io``, ``engine.raster``, ``engine.scene``.
"""
from .heldout import evaluate

__all__ = ["evaluate"]
