"""Results out of a trained run: rendered views (PNG / EXR), the raw ``.npz`` cache, 3DGS PLY
sequences (``ply``), the compact 4D cache (``compact``) and opening either form (``cached``).

May import: foundations, ``engine.io``, ``engine.raster``, ``engine.scene``.
"""
