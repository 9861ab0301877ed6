"""Results out of a trained run: rendered views (PNG / EXR) and the compact ``.npz`` cache.

May import: foundations, ``engine.io``, ``engine.raster``, ``engine.scene``.
"""
