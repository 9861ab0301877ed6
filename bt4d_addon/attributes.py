"""Names a reconstruction is stored under in a .blend, in one place: the per-point attributes
of the sample mesh (written on load, read by the geometry nodes, the splat material and the
bullet-time operators) and the custom properties of the mesh and the result object.

Each point attribute carries the key of the engine array it is filled from
(``Scene4D.sample``: ``quats``, ``scales``, ``opacities``, ``colors``; ``means`` become the
vertex positions). No bpy here.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PointAttribute:
    name: str          # Blender attribute name
    sample_key: str    # key of the engine's sample arrays it is filled from
    data_type: str     # Blender attribute type
    value_key: str     # foreach_get / foreach_set key of that type
    width: int         # floats per point


ROT = PointAttribute("bt4d_rot", "quats", "QUATERNION", "value", 4)          # (w, x, y, z), normalised
SCALE = PointAttribute("bt4d_scale", "scales", "FLOAT_VECTOR", "vector", 3)  # sigmas along the local axes
OPACITY = PointAttribute("bt4d_opacity", "opacities", "FLOAT", "value", 1)   # peak opacity in [0, 1]
COLOUR = PointAttribute("bt4d_color", "colors", "FLOAT_COLOR", "color", 4)    # LINEAR RGBA (alpha 1)
POINT_ATTRIBUTES = (ROT, SCALE, OPACITY, COLOUR)

# custom properties of the sample mesh
NUM_GAUSSIANS = "bt4d_num_gaussians"   # N
NUM_SAMPLES = "bt4d_num_samples"       # K
SAMPLE_TIMES = "bt4d_times"            # the K capture times (s)
# custom properties of the result object
IS_RESULT = "bt4d_result"
TIME_RANGE = "bt4d_time_range"         # (t0, t1) of the stored samples (s)
RUN_DIR = "bt4d_run_dir"               # the run folder it was loaded from
METRICS = "bt4d_metrics"               # held-out metrics of that run
