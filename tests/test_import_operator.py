"""bpy.ops.bt4d.import_capture on the demo capture and on small hand-made captures.

Runs in-process: the add-on is enabled once through Blender's extension machinery
(tests/blender_util.py) and every test starts from an empty factory scene.
"""
from __future__ import annotations

import json
from pathlib import Path

import blender_util
import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from engine.cameras import Intrinsics, View, look_at_c2w, project_points  # noqa: E402


@pytest.fixture(scope="module")
def addon():
    return blender_util.enable_addon()


@pytest.fixture()
def scene(addon):
    return blender_util.reset_scene()


def import_capture(path, **kw):
    return bpy.ops.bt4d.import_capture(directory=str(path), **kw)


# ----------------------------------------------------------------------------- tiny captures

LEFT = Intrinsics(48, 32, 52.0, 44.0, 21.25, 17.5)    # fx != fy, off-centre principal point
RIGHT = Intrinsics(48, 32, 48.0, 48.0, 24.0, 16.0)
SPIKE = LEFT.scaled(24, 16)                           # LEFT at half resolution
EVAL = Intrinsics(32, 24, 30.0, 30.0, 16.0, 12.0)


def _cam(k: Intrinsics, role="train"):
    return {"w": k.width, "h": k.height, "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "role": role}


def make_capture(root: Path, *, n_rgb=3, rgb_fps=30.0, eval_fps=90.0, moving_left=False,
                 spike_frames=100, seed=0) -> Path:
    """A small capture: left/right (train), spk (spikes, co-located with left), ev (eval)."""
    from engine.io.spikes import write_spikes

    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    left0 = look_at_c2w((-0.2, -4.0, 1.0), (0.0, 0.0, 0.8))
    right = look_at_c2w((0.3, -4.0, 1.1), (0.0, 0.0, 0.8))
    ev = look_at_c2w((0.0, -3.5, 2.0), (0.0, 0.0, 0.8))
    frames, eval_frames = [], []
    for i in range(n_rgb):
        t = i / rgb_fps
        left = look_at_c2w((-0.2 + 0.1 * i, -4.0, 1.0 + 0.05 * i), (0.0, 0.0, 0.8)) if moving_left else left0
        for name, k, c2w in (("left", LEFT, left), ("right", RIGHT, right)):
            rel = f"rgb/{name}/{i:06d}.png"
            blender_util.write_png(root / rel, rng.random((k.height, k.width, 3)).astype(np.float32))
            frames.append({"file_path": rel, "camera": name, "time": t, "transform_matrix": c2w.tolist()})
    n_eval = int(round((n_rgb - 1) / rgb_fps * eval_fps)) + 1
    for i in range(n_eval):
        rel = f"eval/ev/{i:06d}.png"
        blender_util.write_png(root / rel, rng.random((EVAL.height, EVAL.width, 3)).astype(np.float32))
        eval_frames.append({"file_path": rel, "camera": "ev", "time": i / eval_fps, "transform_matrix": ev.tolist()})
    spikes = (rng.random((spike_frames, SPIKE.height, SPIKE.width)) < 0.2).astype(np.uint8)
    write_spikes(root / "spike" / "spk.dat", spikes)
    data = {
        "version": 1,
        "cameras": {"left": _cam(LEFT), "right": _cam(RIGHT), "spk": _cam(SPIKE), "ev": _cam(EVAL, "eval")},
        "frames": frames,
        "eval_frames": eval_frames,
        "spike_streams": [{"file_path": "spike/spk.dat", "camera": "spk", "rate_hz": 1000.0, "t0": 0.0,
                           "num_frames": spike_frames, "w": SPIKE.width, "h": SPIKE.height,
                           "co_located_with": "left", "transform_matrix": left0.tolist()}],
    }
    (root / "transforms.json").write_text(json.dumps(data, indent=1))
    return root


@pytest.fixture()
def tiny(tmp_path):
    return make_capture(tmp_path / "tiny_capture")


def camera_pixels(scene, cam_obj, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (top-left origin) of world points through a Blender camera."""
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    w, h = scene.render.resolution_x, scene.render.resolution_y
    out = []
    for p in points:
        x, y, _ = world_to_camera_view(scene, cam_obj, Vector(p.tolist()))
        out.append((x * w, (1.0 - y) * h))
    return np.array(out)


def points_in_view(k: Intrinsics, c2w: np.ndarray, n=40, seed=1) -> np.ndarray:
    """World points that project inside the image (spread over it, depth 2..8)."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-0.2, 1.2, n) * k.width
    v = rng.uniform(-0.2, 1.2, n) * k.height
    z = rng.uniform(2.0, 8.0, n)
    cam_cv = np.stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z], axis=1)
    cam_gl = cam_cv * np.array([1.0, -1.0, -1.0])
    return (c2w[:3, :3] @ cam_gl.T).T + c2w[:3, 3]


def shown_file(cam_obj, scene_frame: int) -> int:
    """The file number the viewport draws behind ``cam_obj`` at ``scene_frame``.

    The overlay engine calls BKE_image_user_frame_calc on the *evaluated* camera's image
    user: ``n = clamp(frame - frame_start + 1, 0, frame_duration) + frame_offset``.
    (``ImageUser.frame_current`` on the original datablock can lag one frame behind an
    animated offset, so it is not used here.)
    """
    depsgraph = bpy.context.evaluated_depsgraph_get()
    iu = cam_obj.evaluated_get(depsgraph).data.background_images[0].image_user
    n = min(max(scene_frame - iu.frame_start + 1, 0), iu.frame_duration)
    return n + iu.frame_offset


# ----------------------------------------------------------------------------- the demo capture

def test_import_demo_capture(scene, demo_capture):
    from engine.io.capture import load_capture

    cap = load_capture(demo_capture)
    before = blender_util.datablock_counts()
    assert import_capture(demo_capture) == {"FINISHED"}

    coll = bpy.data.collections[demo_capture.name]
    assert coll.name in scene.collection.children
    assert sorted(o.name for o in coll.objects) == sorted(cap.cameras)
    assert {o.type for o in coll.objects} == {"CAMERA"}
    assert blender_util.datablock_counts()["objects"] == before["objects"] + len(cap.cameras)

    main = cap.cameras["rgb0"].intrinsics
    assert (scene.render.resolution_x, scene.render.resolution_y) == (main.width, main.height)
    assert scene.render.fps == 30 and scene.render.fps_base == 1.0
    t0, t1 = cap.time_range
    assert scene.frame_start == 1
    assert scene.frame_end == 1 + int(np.ceil((t1 - t0) * 30 - 1e-6))
    assert scene.camera.name == "rgb0"
    s = scene.bt4d
    assert Path(s.capture_dir) == demo_capture.resolve()
    assert s.num_cameras == len(cap.cameras) and s.num_frames == len(cap.frames)
    assert s.num_eval_frames == len(cap.eval_frames) and s.num_spike_streams == len(cap.spike_streams)
    assert s.capture_collection == coll and s.main_camera == "rgb0"

    stream = cap.spike_streams[0]
    spk = bpy.data.objects[stream.camera]
    assert spk["bt4d_role"] == "train"
    assert Path(spk["bt4d_spike_file"]) == stream.path
    assert spk["bt4d_spike_frames"] == stream.num_frames
    assert spk["bt4d_spike_rate_hz"] == pytest.approx(stream.rate_hz)
    assert spk["bt4d_co_located_with"] == stream.co_located_with == "rgb0"
    assert list(spk["bt4d_spike_size"]) == [stream.width, stream.height]
    np.testing.assert_allclose(np.array(spk.matrix_world), np.array(bpy.data.objects["rgb0"].matrix_world), atol=1e-5)
    assert bpy.data.objects["eval0"]["bt4d_role"] == "eval"
    for name, cam in cap.cameras.items():
        obj = bpy.data.objects[name]
        frames = cap.frames_by_camera().get(name, [])
        if frames:
            np.testing.assert_allclose(np.array(obj.matrix_world), frames[0].c2w, atol=1e-5)
        assert obj.get("bt4d_intrinsics")["w"] == cam.intrinsics.width


def test_demo_background_sequences_follow_capture_time(scene, demo_capture):
    """At scene frame f the eval camera (300 FPS) shows the file nearest (f - 1) / 30 s."""
    assert import_capture(demo_capture) == {"FINISHED"}
    for name, per_scene_frame in (("rgb0", 1), ("eval0", 10)):
        cam = bpy.data.objects[name].data
        assert cam.show_background_images
        bg = cam.background_images[0]
        assert bg.image.source == "SEQUENCE"
        assert Path(bpy.path.abspath(bg.image.filepath)).name == "000000.png"
        for f in range(scene.frame_start, scene.frame_end + 1):
            scene.frame_set(f)
            shown = shown_file(bpy.data.objects[name], f)
            assert shown == (f - 1) * per_scene_frame, (name, f)


# ----------------------------------------------------------------------------- camera model

def addon_module(sub: str):
    import sys

    return sys.modules[f"{blender_util.ADDON_MODULE}.{sub}"]


def test_projection_matches_pinhole_model(scene, tiny):
    """World points land within 0.5 px of engine.cameras.project_points (fx != fy, off-centre)."""
    from engine.io.capture import load_capture

    cap = load_capture(tiny)
    assert import_capture(tiny) == {"FINISHED"}
    assert scene.camera.name == "left"
    # the import set the scene up for the main camera; fx != fy goes into the pixel aspect
    assert scene.render.pixel_aspect_y / scene.render.pixel_aspect_x == pytest.approx(LEFT.fx / LEFT.fy)
    cameras = addon_module("bt4d_addon.blender_cameras")
    checked = 0
    for name, info in cap.cameras.items():
        k = info.intrinsics
        obj = bpy.data.objects[name]
        if name != "left":  # other cameras: set the scene up for them as a renderer would
            cameras.configure_render(scene, k)
        c2w = np.array(obj.matrix_world)
        pts = points_in_view(k, c2w)
        expected, depth = project_points(View(k, c2w), pts)
        assert (depth > 0).all()
        got = camera_pixels(scene, obj, pts)
        err = np.abs(got - expected).max()
        assert err < 0.5, (name, err)
        assert err < 1e-3, (name, err)  # in fact exact up to float32
        checked += 1
    assert checked == 4


@pytest.mark.parametrize("k", [
    Intrinsics(640, 480, 500.0, 500.0, 320.0, 240.0),
    Intrinsics(640, 480, 500.0, 450.0, 300.5, 260.25),
    Intrinsics(300, 500, 410.0, 440.0, 140.0, 270.0),   # portrait, fy > fx
    Intrinsics(64, 48, 40.0, 40.0, 0.0, 48.0),           # principal point at a corner
])
def test_camera_params_round_trip(addon, scene, k):
    """camera_params -> Blender camera -> intrinsics_from_camera gives back the pinhole model."""
    cameras = addon_module("bt4d_addon.blender_cameras")
    data = bpy.data.cameras.new("probe")
    p = cameras.apply_intrinsics(data, k)
    back = cameras.intrinsics_from_camera(data, k.width, k.height, p["pixel_aspect_x"], p["pixel_aspect_y"])
    fx, fy, cx, cy = back.fx, back.fy, back.cx, back.cy
    assert (back.width, back.height) == (k.width, k.height)
    assert (fx, fy, cx, cy) == pytest.approx((k.fx, k.fy, k.cx, k.cy), rel=1e-6, abs=1e-6)
    # and the projection through a real object agrees
    cameras.configure_render(scene, k)
    c2w = look_at_c2w((1.0, -3.0, 2.0), (0.0, 0.5, 0.3))
    obj = bpy.data.objects.new("probe", data)
    scene.collection.objects.link(obj)
    obj.matrix_world = cameras.matrix_from_rows(c2w)
    bpy.context.view_layer.update()
    pts = points_in_view(k, c2w, n=20, seed=3)
    expected, _ = project_points(View(k, c2w), pts)
    np.testing.assert_allclose(camera_pixels(scene, obj, pts), expected, atol=1e-3 * max(k.width, k.height) / 100)


def test_moving_camera_is_keyframed_per_frame_time(scene, tmp_path):
    from engine.io.capture import load_capture

    root = make_capture(tmp_path / "moving", moving_left=True, n_rgb=4)
    cap = load_capture(root)
    assert import_capture(root) == {"FINISHED"}
    left = bpy.data.objects["left"]
    assert left["bt4d_moving"] and left.animation_data and left.animation_data.action
    assert not bpy.data.objects["right"].animation_data
    for fr in cap.frames_by_camera()["left"]:
        frame = 1 + fr.time * scene.render.fps
        scene.frame_set(int(round(frame)))
        np.testing.assert_allclose(np.array(left.matrix_world), fr.c2w, atol=1e-4)


def test_fps_option_and_eval_sequence(scene, tiny):
    """fps=90 puts the 90 FPS eval camera one file per scene frame, the 30 FPS RGB every 3rd."""
    from engine.io.capture import load_capture

    t0, t1 = load_capture(tiny).time_range   # the spike stream (0.1 s) outlasts the RGB frames
    assert import_capture(tiny, fps=90) == {"FINISHED"}
    assert scene.render.fps == 90
    assert (scene.frame_start, scene.frame_end) == (1, 1 + int(np.ceil((t1 - t0) * 90 - 1e-6)))
    for name, files_per_frame, n_files in (("ev", 1.0, 7), ("left", 1 / 3, 3)):
        for f in range(scene.frame_start, scene.frame_end + 1):
            scene.frame_set(f)
            shown = shown_file(bpy.data.objects[name], f)
            # nearest file in time (earlier one on ties), the last one after the camera stops
            want = min(n_files - 1, int(np.floor((f - 1) * files_per_frame + 0.5 - 1e-9)))
            assert shown == want, (name, f)


def test_import_accepts_transforms_json_path(scene, tiny):
    assert bpy.ops.bt4d.import_capture(filepath=str(tiny / "transforms.json")) == {"FINISHED"}
    assert tiny.name in bpy.data.collections


# ----------------------------------------------------------------------------- bad input

def _missing_transforms(root):
    (root / "transforms.json").unlink()
    return "transforms.json"


def _malformed_json(root):
    (root / "transforms.json").write_text('{"version": 1, "cameras": {')
    return "transforms.json"


def _missing_frame(root):
    (root / "rgb" / "right" / "000001.png").unlink()
    return "000001.png"


def _wrong_image_size(root):
    blender_util.write_png(root / "rgb" / "left" / "000002.png", np.zeros((10, 12, 3), np.float32))
    return "000002.png"


def _partial_spike_file(root):
    p = root / "spike" / "spk.dat"
    p.write_bytes(p.read_bytes()[:-7])
    return "spk.dat"


def _stream_unknown_camera(root):
    data = json.loads((root / "transforms.json").read_text())
    data["spike_streams"][0]["camera"] = "nope"
    (root / "transforms.json").write_text(json.dumps(data))
    return "transforms.json"


def _frame_unknown_camera(root):
    data = json.loads((root / "transforms.json").read_text())
    data["frames"][1]["camera"] = "ghost"
    (root / "transforms.json").write_text(json.dumps(data))
    return "transforms.json"


def _damaged_png(root):
    (root / "eval" / "ev" / "000003.png").write_bytes(b"not a png at all")
    return "000003.png"


@pytest.mark.parametrize("break_it", [_missing_transforms, _malformed_json, _missing_frame, _wrong_image_size,
                                      _partial_spike_file, _stream_unknown_camera, _frame_unknown_camera,
                                      _damaged_png], ids=lambda f: f.__name__.strip("_"))
def test_bad_capture_is_reported_and_scene_untouched(scene, tiny, break_it):
    names_file = break_it(tiny)
    before = blender_util.datablock_counts()
    settings = (scene.render.resolution_x, scene.render.fps, scene.frame_end, scene.bt4d.capture_dir)
    # an ERROR report makes bpy.ops raise RuntimeError carrying the message (operator CANCELLED)
    with pytest.raises(RuntimeError) as info:
        import_capture(tiny)
    assert names_file in str(info.value)
    assert blender_util.datablock_counts() == before
    assert (scene.render.resolution_x, scene.render.fps, scene.frame_end, scene.bt4d.capture_dir) == settings


def test_missing_folder_is_reported(scene, tmp_path):
    with pytest.raises(RuntimeError, match="does not exist"):
        import_capture(tmp_path / "no_such_capture")
    assert blender_util.datablock_counts()["collections"] == 0


def test_failure_while_building_rolls_back(scene, tiny, monkeypatch):
    """If building fails half-way (after some cameras exist), nothing is left behind."""
    cameras = addon_module("bt4d_addon.blender_cameras")
    real = cameras.create_camera_object
    calls = []

    def flaky(name, *a, **kw):
        calls.append(name)
        if len(calls) == 3:
            raise RuntimeError("simulated failure")
        return real(name, *a, **kw)

    monkeypatch.setattr(cameras, "create_camera_object", flaky)
    before = blender_util.datablock_counts()
    with pytest.raises(RuntimeError, match="simulated failure"):
        import_capture(tiny)
    assert len(calls) == 3
    assert blender_util.datablock_counts() == before
    assert not scene.bt4d.capture_dir


def test_dnerf_capture_moving_camera_and_single_images(scene, tmp_path):
    """A D-NeRF folder (transforms_train.json, camera_angle_x, no extensions): one moving camera."""
    root = tmp_path / "lego"
    rng = np.random.default_rng(5)
    frames = []
    for i in range(4):
        blender_util.write_png(root / "train" / f"r_{i:03d}.png", rng.random((20, 24, 3)).astype(np.float32))
        c2w = look_at_c2w((np.cos(i), np.sin(i) - 4.0, 1.0), (0.0, 0.0, 0.0))
        frames.append({"file_path": f"./train/r_{i:03d}", "time": i / 3, "transform_matrix": c2w.tolist()})
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
    assert import_capture(root) == {"FINISHED"}
    cam = bpy.data.objects["train"]
    assert cam["bt4d_moving"] and cam["bt4d_num_frames"] == 4
    assert (scene.render.resolution_x, scene.render.resolution_y) == (24, 20)
    assert scene.render.fps == 3  # frames 1/3 s apart
    for i, fr in enumerate(frames):
        scene.frame_set(1 + i)
        np.testing.assert_allclose(np.array(cam.matrix_world), np.array(fr["transform_matrix"]), atol=1e-4)
        assert shown_file(cam, 1 + i) == i
