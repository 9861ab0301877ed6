"""The spike camera: simulator (integrate-and-fire), differentiable spike rendering,
spike-window features and change maps.

May import: foundations, ``engine.io``.
"""
