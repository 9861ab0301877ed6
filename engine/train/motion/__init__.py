"""Motion between RGB instants: the curves carried to a newly admitted instant by stereo and
optical flow (``scene_flow``), an exact grid nearest-neighbour search (``nearest``), and births of
Gaussians with a temporal opacity (``births``).

May import: ``engine.train.config``, ``frames``, ``losses`` and the packages below training."""
