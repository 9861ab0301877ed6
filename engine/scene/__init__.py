"""The model: canonical Gaussians, the deformation field (coarse HexPlane + spike fine
branch) and the trained ``Model4D`` / ``Scene4D`` (``load_run``).

May import: foundations, ``engine.io``, ``engine.raster``, ``engine.spike``. Never training.
"""
