"""The trajectory-error diagnostic (tools/trajectory_error.py, issue 11) on synthetic truth."""
from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

from engine.cameras import Intrinsics, View, look_at_c2w
from engine.errors import CaptureError

_spec = importlib.util.spec_from_file_location("trajectory_error", __file__.rsplit("/tests/", 1)[0]
                                               + "/tools/trajectory_error.py")
te = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(te)


def _truth(tmp_path):
    times = np.linspace(0.0, 0.2, 201)
    mats = np.repeat(np.eye(4)[None], len(times), 0)
    mats[:, 0, 3] = 5.0 * times  # 5 m/s along x
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(400, 3))
    pts = 0.1 * pts / np.linalg.norm(pts, axis=1, keepdims=True)
    np.savez(tmp_path / "objects.npz", times=times, ball=mats, ball_points=pts)
    (tmp_path / "transforms.json").write_text(json.dumps({"ground_truth": {"objects": {
        "file_path": "objects.npz", "rate_hz": 1000.0, "t0": 0.0, "names": ["ball"]}}}))
    return te.load_object_truth(tmp_path), pts


def test_errors_split_along_the_ray_and_across(tmp_path):
    truth, pts = _truth(tmp_path)
    view = View(intrinsics=Intrinsics(80, 60, 70.0, 70.0, 40.0, 30.0),
                c2w=look_at_c2w((0.0, -5.0, 0.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)), time=0.0)
    rgb = [0.0, 0.1, 0.2]
    x0 = pts * 0.9  # Gaussians just inside the surface samples
    stray = np.array([[3.0, 3.0, 3.0]])  # on no object
    opac = np.ones(len(x0) + 1)

    def exact(t):
        return np.concatenate([x0 + [5.0 * t, 0, 0], stray])

    r = te.trajectory_errors(exact, opac, truth, rgb, view, per_interval=3)["ball"]
    assert r["gaussians"] == len(x0) and r["instants"] == 6
    assert r["ray_mm"] < 1e-6 and r["plane_mm"] < 1e-6 and r["plane_px"] < 1e-6

    def along_y(t):  # 2 cm off along +y (~the spike camera's viewing direction) between frames
        return exact(t) + (0.0 if t in rgb else 1.0) * np.array([0.0, 0.02, 0.0])

    r = te.trajectory_errors(along_y, opac, truth, rgb, view, per_interval=3)["ball"]
    assert 18.0 < r["ray_mm"] < 20.5 and r["plane_mm"] < 3.0
    # by place in the interval: exact at the RGB instants, 2 cm off at each of the three between them
    assert len(r["phase_mm"]) == 4 and r["phase_mm"][0] < 1e-6
    assert all(abs(mm - 20.0) < 1e-6 for mm in r["phase_mm"][1:])

    def growing(t):  # off along x by 4 cm x the place in the interval (0 at the RGB instants)
        u = (t % 0.1) / 0.1
        return exact(t) + np.array([0.04 * u, 0.0, 0.0])

    r = te.trajectory_errors(growing, opac, truth, rgb, view, per_interval=3)["ball"]
    assert np.allclose(r["phase_mm"], [0.0, 10.0, 20.0, 30.0], atol=1e-3)

    def across_z(t):  # 2 cm off along z: in the image plane, ~0.28 px at 5 m with f = 70
        return exact(t) + (0.0 if t in rgb else 1.0) * np.array([0.0, 0.0, 0.02])

    r = te.trajectory_errors(across_z, opac, truth, rgb, view, per_interval=3)["ball"]
    assert 18.0 < r["plane_mm"] < 20.5 and r["ray_mm"] < 3.0 and 0.2 < r["plane_px"] < 0.35


def test_missing_truth_is_a_clear_error(tmp_path):
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": []}))
    with pytest.raises(CaptureError, match="ground_truth"):
        te.load_object_truth(tmp_path)


def test_wobble_measures_along_ray_departure_from_the_rgb_curve(tmp_path):
    """``wobble_mm``: distance from the spike camera off the Hermite curve through the RGB
    instants -- zero for the exact (linear) motion and for a between-frame move across the ray,
    the offset for a between-frame move along it."""
    truth, pts = _truth(tmp_path)
    view = View(intrinsics=Intrinsics(80, 60, 70.0, 70.0, 40.0, 30.0),
                c2w=look_at_c2w((0.0, -5.0, 0.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)), time=0.0)
    rgb = [0.0, 0.1, 0.2]
    x0 = pts * 0.9
    opac = np.ones(len(x0))

    def exact(t):
        return x0 + [5.0 * t, 0, 0]

    r = te.trajectory_errors(exact, opac, truth, rgb, view, per_interval=3)["ball"]
    # a straight line 5 m away: rho is nearly a quadratic (one-sided end tangents: ~2.5 mm)
    assert r["gt_wobble_mm"] < 4.0 and abs(r["wobble_mm"] - r["gt_wobble_mm"]) < 1e-6
    r = te.trajectory_errors(lambda t: exact(t) + (0.0 if t in rgb else 1.0) * np.array([0.0, 0.02, 0.0]), opac,
                             truth, rgb, view, per_interval=3)["ball"]
    assert 16.0 < r["wobble_mm"] < 23.0 and r["gt_wobble_mm"] < 4.0
    r = te.trajectory_errors(lambda t: exact(t) + (0.0 if t in rgb else 1.0) * np.array([0.0, 0.0, 0.02]), opac,
                             truth, rgb, view, per_interval=3)["ball"]
    assert r["wobble_mm"] < 4.0


def test_visible_weights_see_the_front_gaussian_not_the_hidden_one():
    """--visible: the blending weight of a Gaussian hidden behind an opaque one is ~0, the
    front one's is its footprint in pixels, one outside the view gets nothing."""
    view = View(intrinsics=Intrinsics(40, 30, 35.0, 35.0, 20.0, 15.0),
                c2w=look_at_c2w((0.0, -2.0, 0.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)), time=0.0)
    g = {"means": np.array([[0.0, 0.0, 0.0], [0.0, 0.5, 0.0], [5.0, 0.0, 0.0]], np.float32),
         "quats": np.tile(np.array([1.0, 0, 0, 0], np.float32), (3, 1)),
         "scales": np.array([[0.3] * 3, [0.04] * 3, [0.15] * 3], np.float32),  # the hidden one inside the core
         "opacities": np.array([0.99, 0.99, 0.99], np.float32),
         "colors": np.full((3, 3), 0.5, np.float32)}
    w = te.visible_weights(g, view)
    assert w.shape == (3,) and w[0] > 10.0 and w[1] < 0.05 * w[0] and w[2] == 0.0
