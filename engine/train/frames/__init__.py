"""Training frames: frame interpolation between RGB instants (``interpolation``) and the paper's
Table 1 training-data baselines (``baselines``: repeat, interpolate, spike2img).

May import: ``engine.train.config`` and every engine package below training."""
