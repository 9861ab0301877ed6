"""Files in and out: captures, images, spike streams, point clouds, checkpoints.

May import: the foundations (``engine.errors``, ``engine.cameras``, ``engine.colour``).
"""
