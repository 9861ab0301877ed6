"""Spike guidance (BulletTime4D Eq. 4-23): between-frame renders, the spike loss and the fine
branch (``spike_guidance``), the spike view's optical flow on the curves (``spike_flow`` and its
cache, pairs and pinhole helpers), quiet curves, the between-frame instants.

May import: ``engine.train.config``, ``frames``, ``losses``, ``motion`` and the packages below
training."""
