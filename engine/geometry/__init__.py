"""Geometry from the calibrated RGB pair: initial points, stereo, scene flow."""
