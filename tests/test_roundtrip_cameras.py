"""Blender camera <-> engine View: intrinsics match Blender's own projection, and a capture
camera survives the round trip View -> Blender camera -> View within 0.5 px."""
from __future__ import annotations

import json

import blender_util
import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from bt4d_addon import blender_cameras as bc  # noqa: E402
from engine.cameras import Intrinsics, View, look_at_c2w, project_points  # noqa: E402


@pytest.fixture()
def empty_scene():
    return blender_util.reset_scene()


def _blender_project(obj, scene, pts):
    """Project with Blender's own camera matrix (calc_matrix_camera) -> pixels from top-left."""

    W, H = bc.render_size(scene)
    r = scene.render
    dg = bpy.context.evaluated_depsgraph_get()
    P = np.array(obj.calc_matrix_camera(dg, x=W, y=H, scale_x=r.pixel_aspect_x, scale_y=r.pixel_aspect_y))
    V = np.array(obj.matrix_world.inverted())
    out = []
    for p in pts:
        c = P @ V @ np.array([*p, 1.0])
        ndc = c[:3] / c[3]
        out.append(((ndc[0] + 1) * 0.5 * W, (1 - ndc[1]) * 0.5 * H))
    return np.array(out)


def _points():
    rng = np.random.default_rng(0)
    return rng.uniform(-1.0, 1.0, size=(50, 3))


CASES = [
    # res_x, res_y, pct, lens, sensor_w, sensor_h, fit, shift_x, shift_y, aspx, aspy
    (64, 48, 100, 50.0, 36.0, 24.0, "AUTO", 0.0, 0.0, 1.0, 1.0),
    (48, 64, 100, 35.0, 36.0, 24.0, "AUTO", 0.1, -0.05, 1.0, 1.0),
    (80, 40, 50, 28.0, 32.0, 18.0, "HORIZONTAL", -0.2, 0.15, 1.0, 1.0),
    (80, 40, 100, 28.0, 32.0, 18.0, "VERTICAL", 0.05, 0.3, 1.0, 1.0),
    (60, 50, 100, 40.0, 36.0, 24.0, "AUTO", 0.1, 0.1, 2.0, 1.0),
    (60, 50, 100, 40.0, 36.0, 24.0, "VERTICAL", -0.1, 0.2, 1.0, 1.5),
]


@pytest.mark.parametrize("case", CASES)
def test_intrinsics_match_blender_projection(empty_scene, case):
    rx, ry, pct, lens, sw, sh, fit, shx, shy, ax, ay = case
    scene = empty_scene
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = rx, ry, pct
    r.pixel_aspect_x, r.pixel_aspect_y = ax, ay
    data = bpy.data.cameras.new("c")
    data.lens, data.sensor_width, data.sensor_height, data.sensor_fit = lens, sw, sh, fit
    data.shift_x, data.shift_y = shx, shy
    obj = bpy.data.objects.new("c", data)
    scene.collection.objects.link(obj)
    from mathutils import Matrix

    obj.matrix_world = Matrix(look_at_c2w([4.0, -3.0, 2.0], [0, 0, 0]).tolist())
    bpy.context.view_layer.update()
    view = bc.camera_to_view(obj, scene)
    assert (view.intrinsics.width, view.intrinsics.height) == bc.render_size(scene)
    pts = _points()
    ours, z = project_points(view, pts)
    theirs = _blender_project(obj, scene, pts)
    assert np.all(z > 0)
    np.testing.assert_allclose(ours, theirs, atol=1e-3)


def _capture_view():
    """A camera from the demo capture when present, else an off-centre synthetic one."""
    from conftest import DEMO_CAPTURE

    tj = DEMO_CAPTURE / "transforms.json"
    if tj.exists():
        meta = json.loads(tj.read_text())
        fr = meta["frames"][0]
        c = meta["cameras"][fr["camera"]]
        intr = Intrinsics(int(c["w"]), int(c["h"]), float(c["fl_x"]), float(c.get("fl_y", c["fl_x"])),
                          float(c.get("cx", c["w"] / 2)), float(c.get("cy", c["h"] / 2)))
        return View(intr, np.array(fr["transform_matrix"], dtype=np.float64), 0.0, fr["camera"])
    intr = Intrinsics(160, 120, 150.0, 153.0, 83.2, 57.9)
    return View(intr, look_at_c2w([3.0, -2.0, 1.0], [0, 0, 0.2]), 0.0, "synthetic")


@pytest.mark.parametrize("source", ["capture", "anisotropic"])
def test_capture_camera_round_trip(empty_scene, source):
    view = _capture_view()
    if source == "anisotropic":
        view = View(Intrinsics(160, 120, 150.0, 141.0, 76.5, 64.25), view.c2w, 0.0, "aniso")
    obj = bc.view_to_camera(view, scene=empty_scene, set_scene_resolution=True)
    bpy.context.view_layer.update()
    back = bc.camera_to_view(obj, empty_scene)
    # points in front of the camera
    c2w = view.c2w
    rng = np.random.default_rng(1)
    cam_pts = np.stack([rng.uniform(-1, 1, 40), rng.uniform(-0.7, 0.7, 40), -rng.uniform(1, 5, 40)], 1)
    world = (c2w[:3, :3] @ cam_pts.T).T + c2w[:3, 3]
    a, _ = project_points(view, world)
    b, _ = project_points(back, world)
    assert np.abs(a - b).max() < 0.5
    assert back.intrinsics.width == view.intrinsics.width and back.intrinsics.height == view.intrinsics.height
    for k in ("fx", "fy", "cx", "cy"):
        assert abs(getattr(back.intrinsics, k) - getattr(view.intrinsics, k)) < 1e-3
    # and Blender itself projects the same way
    theirs = _blender_project(obj, empty_scene, world)
    assert np.abs(a - theirs).max() < 0.5


def test_imported_capture_camera_round_trip(demo_capture):
    """A camera made by bpy.ops.bt4d.import_capture converts back to the capture's View
    within 0.5 px (and every imported camera of the capture does)."""
    import blender_util
    import roundtrip_util

    from engine.io.capture import load_capture

    roundtrip_util.enable()
    blender_util.reset_scene()
    assert bpy.ops.bt4d.import_capture(directory=str(demo_capture)) == {"FINISHED"}
    scene = bpy.context.scene
    cap = load_capture(demo_capture)
    abc = roundtrip_util.addon_module("bt4d_addon.blender_cameras")
    checked = 0
    for frame in [*cap.frames[:2], *cap.eval_frames[:1]]:
        ref = cap.view(frame)
        obj = bpy.data.objects[frame.camera]
        k = ref.intrinsics
        back = abc.camera_to_view(obj, scene, width=k.width, height=k.height)
        c2w = ref.c2w
        rng = np.random.default_rng(2)
        cam_pts = np.stack([rng.uniform(-1, 1, 30), rng.uniform(-0.7, 0.7, 30), -rng.uniform(1, 6, 30)], 1)
        world = (c2w[:3, :3] @ cam_pts.T).T + c2w[:3, 3]
        a, _ = project_points(ref, world)
        b, _ = project_points(back, world)
        assert np.abs(a - b).max() < 0.5, frame.camera
        checked += 1
    assert checked == 3
