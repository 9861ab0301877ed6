"""Scene representation: Gaussians, motion (deformation field, trajectories), the 4D model."""
