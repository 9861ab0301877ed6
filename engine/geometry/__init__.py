"""Scene geometry from the capture: two-view stereo depth and the initial point cloud.

May import: foundations, ``engine.io``.
"""
