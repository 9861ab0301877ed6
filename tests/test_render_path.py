"""bpy.ops.bt4d.render_path on a real (tiny) run of the demo capture: headless orbit at a
frozen capture time -> readable EXRs that change with the camera and not with time, the
exact engine image, Blender's frame numbering and resolution percentage for PNG, and the
sequence loaded back."""
from __future__ import annotations

import numpy as np
import pytest
import roundtrip_util
from roundtrip_util import reconstructed, rt_scene, run_tmp  # noqa: F401  (fixtures)

bpy = pytest.importorskip("bpy")


def _setup(run_dir, demo_capture):
    assert bpy.ops.bt4d.import_capture(directory=str(demo_capture)) == {"FINISHED"}
    assert bpy.ops.bt4d.load_result(directory=str(run_dir), num_samples=4) == {"FINISHED"}
    gn = roundtrip_util.addon_module("bt4d_addon.gaussian_nodes")
    scene = bpy.context.scene
    return scene, gn.find_result_objects(scene)[0], gn


def test_orbit_at_frozen_time_exr(rt_scene, reconstructed, demo_capture, tmp_path):
    from engine.colour import srgb_to_linear
    from engine.io.images import read_exr_channels
    from engine.scene.model import load_run

    scene, obj, gn = _setup(reconstructed["run_dir"], demo_capture)
    scene.frame_start, scene.frame_end = 1, 4
    scene.frame_set(3)
    t_frozen = gn.capture_time_at(obj, 3)
    assert bpy.ops.bt4d.add_orbit_camera(turns=0.25) == {"FINISHED"}
    orbit = scene.camera
    assert orbit.name.startswith("BT4D Orbit")
    # frames 1 and 2: the same pose (camera held), frames 3 and 4: moving on
    ad = orbit.animation_data
    from bpy_extras import anim_utils

    cb = anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot)
    for fc in cb.fcurves:
        v1 = fc.evaluate(1)
        for kp in fc.keyframe_points:
            if kp.co[0] == 2:
                kp.co[1] = v1
                kp.handle_left[1] = kp.handle_right[1] = v1
        fc.update()
    for f in range(1, 5):
        assert gn.capture_time_at(obj, f) == pytest.approx(t_frozen)
    scene.render.resolution_percentage = 20  # 160x120 -> 32x24
    scene.render.filepath = str(tmp_path / "orbit_")
    assert bpy.ops.bt4d.render_path(file_format="OPEN_EXR") == {"FINISHED"}
    files = [tmp_path / f"orbit_{f:04d}.exr" for f in range(1, 5)]
    assert all(p.exists() for p in files), sorted(tmp_path.iterdir())
    chans = [read_exr_channels(p) for p in files]
    assert set(chans[0]) == {"R", "G", "B", "A", "Z"}
    assert chans[0]["R"].shape == (24, 32)
    img = [np.stack([c[k] for k in "RGBA"], -1) for c in chans]
    np.testing.assert_array_equal(img[0], img[1])                  # same camera, same frozen time
    assert np.abs(img[2] - img[0]).max() > 1e-3                    # camera moved
    assert np.abs(img[3] - img[2]).max() > 1e-3
    assert np.all(np.isfinite(chans[0]["Z"])) and chans[0]["Z"][chans[0]["A"] > 0.5].max() < 1e3
    # the EXR is the engine's exact render of that camera at that time (linear light,
    # premultiplied: the straight sRGB colour decoded, then multiplied by alpha)
    bc = roundtrip_util.addon_module("bt4d_addon.blender_cameras")
    scene.frame_set(3)
    view = bc.camera_to_view(orbit, scene, time=t_frozen)
    ref = load_run(reconstructed["run_dir"]).render([view], background=(0, 0, 0))[0]
    a = ref["alpha"][..., None]
    straight = np.where(a > 1e-6, ref["rgb"] / np.maximum(a, 1e-6), 0.0).clip(0, 1)
    np.testing.assert_allclose(img[2][..., :3], srgb_to_linear(straight) * a, atol=2e-4)
    np.testing.assert_allclose(img[2][..., 3], ref["alpha"], atol=1e-5)
    # loaded back as an image sequence
    name = scene.get("bt4d_last_render")
    assert name and bpy.data.images[name].source == "SEQUENCE"
    assert bpy.path.abspath(bpy.data.images[name].filepath) == str(files[0])


def test_unfrozen_time_changes_images_and_png_numbering(rt_scene, reconstructed, demo_capture, tmp_path):
    from engine.io.images import read_image_rgba

    scene, obj, gn = _setup(reconstructed["run_dir"], demo_capture)
    scene.camera = bpy.data.objects["eval0"]  # static camera
    t0, t1 = obj["bt4d_time_range"]
    gn.key_capture_time(obj, [(1, t0), (3, t1)])
    scene.frame_start, scene.frame_end = 1, 3
    scene.render.resolution_percentage = 25  # 160x120 -> 40x30
    scene.render.film_transparent = False
    scene.render.filepath = str(tmp_path / "shot_##_x")
    assert bpy.ops.bt4d.render_path(file_format="PNG", load_back=False) == {"FINISHED"}
    files = [tmp_path / f"shot_{f:02d}_x.png" for f in (1, 2, 3)]
    assert all(p.exists() for p in files), sorted(tmp_path.iterdir())
    a, c = read_image_rgba(files[0]), read_image_rgba(files[2])
    assert a.shape == (30, 40, 4)
    model_moves = reconstructed["step"] > 3  # the deformation stage ran
    if model_moves:
        assert np.abs(a - c).max() > 0  # same camera, different capture time


def test_render_path_errors_without_result(rt_scene):
    with pytest.raises(RuntimeError, match="No reconstruction"):
        bpy.ops.bt4d.render_path()


def test_render_job_in_thread_png_alpha_and_cancel(tmp_path):
    """The path-render job in a worker thread (stand-in model): straight-alpha RGBA PNGs,
    EXR Z where something was hit, and cancel keeps the frames written so far."""
    import threading
    import time

    from roundtrip_fakes import FakeScene4D

    from engine.cameras import Intrinsics, View, look_at_c2w
    from engine.io.images import read_exr_channels, read_image_rgba

    worker = roundtrip_util.addon_module("bt4d_addon.worker")
    model = FakeScene4D(n=10, seed=2)
    k = Intrinsics(24, 18, 22.0, 22.0, 12.0, 9.0)
    views = [View(k, look_at_c2w([3 * np.cos(a), 3 * np.sin(a), 1.0], [0, 0, 0]), 0.1) for a in (0.0, 0.5, 1.0)]
    outs = [str(tmp_path / f"f{i}.png") for i in range(3)]
    # pumped as the modal operator's timer does
    progress = []
    job = worker.Job(worker.render_views_job, kind="test_render", scene4d=model, views=views, outputs=outs,
                     file_format="PNG", transparent=True).watch(progress.append).start()
    deadline = time.monotonic() + 60
    while job.pump() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert job.result["status"] == "finished" and job.result["written"] == outs
    assert [(p["step"], p["total_steps"], p["path"]) for p in progress] == [(i + 1, 3, o) for i, o in enumerate(outs)]
    ref = model.render(views[:1])[0]
    img = read_image_rgba(outs[0])
    np.testing.assert_allclose(img[..., 3], ref["alpha"], atol=1 / 255 + 1e-6)
    hit = ref["alpha"] > 0.5
    np.testing.assert_allclose(img[..., :3][hit] * img[..., 3:][hit], ref["rgb"][hit], atol=2 / 255)

    exr = [str(tmp_path / f"e{i}.exr") for i in range(3)]
    gate = threading.Event()

    class Slow(FakeScene4D):
        def render(self, views, background=None, time=None, fill_holes=False):
            gate.wait(10)
            return super().render(views, background, time)

    job = worker.Job(worker.render_views_job, scene4d=Slow(n=10, seed=2), views=views, outputs=exr).start()
    job.cancel()
    gate.set()
    job.join(60)
    job.poll()
    assert job.result["status"] == "cancelled" and len(job.result["written"]) < 3
    job = worker.Job(worker.render_views_job, scene4d=model, views=views[:1], outputs=exr[:1]).run_sync()
    z = read_exr_channels(exr[0])
    assert z["Z"][ref["alpha"] > 0.5].max() < 10 and z["Z"][ref["alpha"] < 1e-6].min() == pytest.approx(1e10)


def test_render_path_of_a_result_loaded_from_a_compact_cache(rt_scene, reconstructed, demo_capture, tmp_path):
    """Issue 45, defect 1: a result delivered as a ``.bt4c`` renders along a path; the frames are
    the run folder's within the cache's quantisation. Drop Unobserved needs the run folder."""

    from engine.io.images import read_image_rgba

    cache = tmp_path / "result.bt4c"
    from engine.__main__ import main

    assert main(["export", str(reconstructed["run_dir"]), "--format", "compact", "--fps", "100",
                 "--out", str(cache)]) == 0
    assert bpy.ops.bt4d.import_capture(directory=str(demo_capture)) == {"FINISHED"}
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 2
    scene.render.resolution_percentage = 25
    images = {}
    # as a user does: load the cache, add an orbit, render the path (the result says where it came from)
    for name, kw in (("cache", {"filepath": str(cache)}), ("run", {"directory": str(reconstructed["run_dir"])})):
        assert bpy.ops.bt4d.load_result(num_samples=4, **kw) == {"FINISHED"}
        if scene.camera is None or not scene.camera.name.startswith("BT4D Orbit"):
            assert bpy.ops.bt4d.add_orbit_camera(turns=0.25) == {"FINISHED"}
        scene.render.filepath = str(tmp_path / name / "f_")
        source = {} if name == "cache" else {"run_dir": str(reconstructed["run_dir"])}
        assert bpy.ops.bt4d.render_path(file_format="PNG", **source) == {"FINISHED"}
        images[name] = [read_image_rgba(tmp_path / name / f"f_{f:04d}.png") for f in (1, 2)]
    for a, b in zip(images["run"], images["cache"]):
        mse = float(np.mean((a[..., :3] - b[..., :3]) ** 2))
        assert 10 * np.log10(1.0 / max(mse, 1e-12)) > 30.0
    with pytest.raises(RuntimeError, match="compact cache"):
        bpy.ops.bt4d.render_path(file_format="PNG", run_dir=str(cache), prune_unobserved=True)


def test_cli_renders_the_exported_path_as_blender_does(rt_scene, reconstructed, demo_capture, tmp_path):
    """Issue 45: Export Camera Path + ``engine render --path`` on a machine without Blender give the
    frames Render Camera Path gives (PSNR >= 40 dB), moving camera and keyed capture time alike."""
    from engine.__main__ import main
    from engine.evaluate.metrics import psnr
    from engine.io.images import read_image_rgba

    scene, obj, gn = _setup(reconstructed["run_dir"], demo_capture)
    t0, t1 = obj["bt4d_time_range"]
    gn.key_capture_time(obj, [(1, t0), (3, t1)])
    scene.frame_start, scene.frame_end = 1, 3
    assert bpy.ops.bt4d.add_orbit_camera(turns=0.25) == {"FINISHED"}
    scene.render.resolution_percentage = 25
    scene.render.film_transparent = True  # straight RGBA, as the CLI writes (opaque PNGs fill holes)
    scene.render.filepath = str(tmp_path / "blender_")
    assert bpy.ops.bt4d.render_path(file_format="PNG", load_back=False) == {"FINISHED"}
    path = tmp_path / "path.json"
    assert bpy.ops.bt4d.export_camera_path(filepath=str(path)) == {"FINISHED"}
    assert main(["render", str(reconstructed["run_dir"]), "--path", str(path), "--out", str(tmp_path / "cli"),
                 "--format", "png", "--quiet"]) == 0
    for f in (1, 2, 3):
        ours = read_image_rgba(tmp_path / "cli" / f"frame_{f:04d}.png")
        theirs = read_image_rgba(tmp_path / f"blender_{f:04d}.png")
        assert ours.shape[:2] == theirs.shape[:2] == (30, 40)
        assert psnr(ours * ours[..., 3:4], theirs * theirs[..., 3:4]) >= 40.0
