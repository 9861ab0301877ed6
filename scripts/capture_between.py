"""The ``between`` scene of scripts/make_capture.py: motion that 30 FPS cannot sample.

The ``novel`` scene's table-top set and objects (``capture_novel.build_objects``: weakly
textured floor, textured wall, pole, ball, turntable with letters, checker cube), moved so
that **every RGB instant shows nearly the same pose while the objects move a lot between
them** (issue 11: what only the spike camera sees):

* ``ball`` bounces on the floor every 2 RGB frames (66.7 ms), the impacts half-way between
  two RGB instants, while it drifts sideways at 0.6 m/s: at every RGB instant its centre is
  0.135 m high (on the arc's symmetric points), between them it touches the floor (z =
  0.05) or peaks (0.17 m): up to 0.085 m (about 13 px) off the height the RGB frames show;
* ``cube`` vibrates sideways at 15 Hz, ±4 cm (half a period per RGB interval: at every RGB
  instant it is back at the centre) while tumbling slowly;
* ``turntable`` swings ±0.6 rad at 15 Hz about its axis (back at rest at every RGB instant;
  the letters' tips move up to 0.1 m between two frames).

A reconstruction from the RGB frames alone sees a still cube and turntable and a ball
sliding at constant height; the spike stream (20 kHz) sees the real motion. Same rig as
``novel`` (the eval cameras too).
"""
from __future__ import annotations

import math

# the novel scene's rig, eval0 and set (re-exported: the scene API of make_capture.SCENES)
from capture_novel import CAMERA_EYES, EVAL0_ANGLES, TARGET, build_objects  # noqa: F401

MOVING = ("ball", "turntable", "cube")
BOUNCE_PERIOD = 2.0 / 30.0    # s: one bounce per two RGB frames
FIRST_IMPACT = 0.5 / 30.0     # s: impacts half-way between RGB instants
VIBRATION_HZ = 15.0           # half a period per RGB interval: zero at every RGB instant


def object_poses(t: float, speed: float = 1.0):
    """World location and XYZ Euler rotation (radians) of each moving object at time t (s)."""
    t = t * speed
    bounce = abs(math.sin(math.pi * (t - FIRST_IMPACT) / BOUNCE_PERIOD))
    vib = math.sin(2.0 * math.pi * VIBRATION_HZ * t)
    return {
        "ball": ((-0.1 + 0.6 * t, -0.2, 0.05 + 0.12 * bounce), (0.0, 15.0 * t, 0.0)),
        "turntable": ((-0.24, 0.12, 0.0), (0.0, 0.0, 0.4 + 0.6 * vib)),
        "cube": ((0.22 + 0.04 * vib, 0.18, 0.2), (0.4 + 2.0 * t, 0.3, 0.5 + 1.5 * t)),
    }
