"""Camera records and the two pose conventions the project meets.

* Captures and Blender store **camera-to-world** matrices in the OpenGL / Blender
  convention: the camera looks down its -Z axis, +Y is up, +X is right.
* The rasterizer (like gsplat) takes **world-to-camera** "view matrices" in the OpenCV
  convention: +Z forward, +Y down, +X right, and pixel centres at (u + 0.5, v + 0.5)
  with ``u = fx * x / z + cx`` measured from the top-left corner.

``View`` is the one record that crosses every boundary: capture frames, eval frames,
the render CLI's camera files and Blender's camera path are all turned into Views.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Flips the Y and Z camera axes: OpenGL camera frame <-> OpenCV camera frame.
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels; (cx, cy) from the image's top-left corner."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix, float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same field of view at another resolution (e.g. the spike sensor's)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy)


@dataclass
class View:
    """One camera at one instant: intrinsics, camera-to-world pose (OpenGL), time (s)."""

    intrinsics: Intrinsics
    c2w: np.ndarray  # (4, 4) float64, OpenGL / Blender convention
    time: float = 0.0
    name: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def viewmat(self) -> np.ndarray:
        """(4, 4) world-to-camera matrix in the OpenCV convention (what rasterization takes)."""
        return viewmat_from_c2w_gl(self.c2w)

    @property
    def K(self) -> np.ndarray:
        return self.intrinsics.K

    @property
    def center(self) -> np.ndarray:
        return np.asarray(self.c2w, dtype=np.float64)[:3, 3].copy()


def viewmat_from_c2w_gl(c2w: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world (4x4) -> OpenCV world-to-camera (4x4)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    return GL_TO_CV @ np.linalg.inv(c2w)


def c2w_gl_from_viewmat(viewmat: np.ndarray) -> np.ndarray:
    """Inverse of :func:`viewmat_from_c2w_gl`."""
    viewmat = np.asarray(viewmat, dtype=np.float64)
    return np.linalg.inv(GL_TO_CV @ viewmat)


def project_points(view: View, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of world points (N, 3) -> pixel coords (N, 2) and depth (N,).

    Pixel coordinates are continuous with the top-left corner of the image at (0, 0), so
    the centre of pixel (i, j) is (j + 0.5, i + 0.5).
    """
    pts = np.asarray(points, dtype=np.float64)
    cam = (view.viewmat @ np.concatenate([pts, np.ones((len(pts), 1))], axis=1).T).T[:, :3]
    z = cam[:, 2]
    k = view.intrinsics
    uv = np.stack([k.fx * cam[:, 0] / z + k.cx, k.fy * cam[:, 1] / z + k.cy], axis=1)
    return uv, z


def look_at_c2w(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL camera-to-world matrix for a camera at ``eye`` looking at ``target`` (Z-up world)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    if np.linalg.norm(right) < 1e-9:  # looking straight along `up`
        right = np.cross(np.array([0.0, 1.0, 0.0]), back)
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, back, eye
    return c2w
