"""tools/orbit_strip.py (issue 14's +-30 degree orbit): the arc around the stereo pair's
centre of interest, and bpy.ops.bt4d.render_path driven along it on the shared tiny run of
the demo capture -- frames from the keyed viewpoints, different images, no black where
nothing covers the opaque PNG, the strip and the coverage table."""
from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest
from blender_util import NEEDS_BPY
from roundtrip_util import reconstructed, rt_scene, run_tmp  # noqa: F401  (fixtures)

from engine.cameras import look_at_c2w

_spec = importlib.util.spec_from_file_location("orbit_strip",
                                               __file__.rsplit("/tests/", 1)[0] + "/tools/orbit_strip.py")
orbit_strip = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(orbit_strip)


def test_centre_of_interest_of_a_converging_pair():
    target = np.array([0.2, 3.0, 0.5])
    a, b = look_at_c2w([-0.3, -2.0, 0.8], target), look_at_c2w([0.3, -2.0, 0.8], target)
    np.testing.assert_allclose(orbit_strip.pair_centre_of_interest(a, b), target, atol=1e-9)
    # parallel axes: the fallback depth along the mean axis, else a clear error
    p, q = look_at_c2w([-0.3, 0, 0], [-0.3, 5, 0]), look_at_c2w([0.3, 0, 0], [0.3, 5, 0])
    np.testing.assert_allclose(orbit_strip.pair_centre_of_interest(p, q, fallback_depth=2.0), [0, 2, 0], atol=1e-9)
    with pytest.raises(ValueError, match="parallel"):
        orbit_strip.pair_centre_of_interest(p, q)
    # axes that meet behind the cameras (a diverging pair) do not count as a meeting point
    d0, d1 = look_at_c2w([-0.3, 0, 0], [-1.0, 5, 0]), look_at_c2w([0.3, 0, 0], [1.0, 5, 0])
    assert orbit_strip.closest_point_of_axes(d0[:3, 3], -d0[:3, 2], d1[:3, 3], -d1[:3, 2]) is None


def test_arc_poses_keep_distance_height_and_look_at_the_centre():
    centre, eye0 = np.array([0.0, 0.0, 0.3]), np.array([0.0, -5.0, 1.4])
    poses = orbit_strip.arc_poses(centre, eye0, 30.0, 7)
    assert [round(az) for az, _ in poses] == [-30, -20, -10, 0, 10, 20, 30]
    for az, c2w in poses:
        eye = c2w[:3, 3]
        assert np.linalg.norm(eye - centre) == pytest.approx(np.linalg.norm(eye0 - centre))
        assert eye[2] == pytest.approx(eye0[2])
        fwd = -c2w[:3, 2]
        np.testing.assert_allclose(fwd, (centre - eye) / np.linalg.norm(centre - eye), atol=1e-12)
        # azimuth about +Z from the start direction; positive = to the camera's right (+X here)
        ang = math.degrees(math.atan2(eye[0], -eye[1]))
        assert ang == pytest.approx(az, abs=1e-9)
    assert poses[-1][1][0, 3] > 0 > poses[0][1][0, 3]
    assert orbit_strip.pick_labelled([az for az, _ in orbit_strip.arc_poses(centre, eye0, 30.0, 13)], 10.0) == \
        [0, 2, 4, 6, 8, 10, 12]


@NEEDS_BPY
@pytest.mark.slow  # ~5 s: 4 path renders of 7 frames (plus the shared tiny reconstruction)
def test_render_path_along_keyed_orbit(rt_scene, reconstructed, demo_capture, tmp_path):
    """The keyed arc through bpy.ops.bt4d.render_path (EXR + opaque PNG) on a tiny run."""
    import bpy

    from engine.cameras import View
    from engine.io.images import read_exr_channels, read_image_rgba
    from engine.scene.model import load_run

    scene = bpy.context.scene
    # +-60 deg: the arc's ends look past the tiny run's backdrop, so the hole check below has holes
    # to test (at +-30 deg the 10-step run with opacity decay covered every pixel: min alpha 0.07)
    obj, cam, poses, times, centre = orbit_strip.setup_orbit(
        scene, reconstructed["run_dir"], str(demo_capture), degrees=60.0, frames=7, time_mode="sweep", samples=4)
    assert scene.camera == cam and (scene.frame_start, scene.frame_end) == (1, 7)
    pair = orbit_strip.train_rgb_cameras(scene)
    assert [o.name for o in pair] == ["rgb0", "rgb1"]
    # the centre is where the pair's optical axes meet (within a few mm on the demo rig)
    for o in pair:
        m = np.array(o.matrix_world)
        d = -m[:3, 2] / np.linalg.norm(m[:3, 2])
        off = centre - m[:3, 3]
        assert np.linalg.norm(off - (off @ d) * d) < 0.05 * np.linalg.norm(off)
    t0, t1 = obj["bt4d_time_range"]
    assert times[0] == pytest.approx(t0) and times[-1] == pytest.approx(t1) and np.all(np.diff(times) > 0)
    # the camera sits where it was keyed at every frame: same distance, 20 degree steps
    bc = orbit_strip.addon_module("bt4d_addon.blender_cameras")
    keyed = []
    for i, (az, c2w) in enumerate(poses):
        scene.frame_set(1 + i)
        view = bc.camera_to_view(cam, scene, time=times[i])
        np.testing.assert_allclose(view.c2w, c2w, atol=1e-4)
        keyed.append(view)
    dist = [np.linalg.norm(v.center - centre) for v in keyed]
    assert max(dist) - min(dist) < 1e-4 * dist[0]

    exr, png = orbit_strip.render_both(scene, tmp_path / "frames", resolution_percentage=20)  # 32x24
    chans = [read_exr_channels(p) for p in exr]
    rgba = [np.stack([c[k] for k in "RGBA"], -1) for c in chans]
    assert rgba[0].shape == (24, 32, 4)
    for a, b in zip(rgba, rgba[1:]):
        assert np.abs(a - b).max() > 1e-3  # every frame a different viewpoint (and instant)
    # a frame is the engine's render of the keyed pose at the keyed time (alpha: exact)
    model = load_run(reconstructed["run_dir"])
    k = bc.camera_intrinsics(cam, scene)
    assert (k.width, k.height) == (32, 24)
    for i in (0, 3, 6):
        ref = model.render([View(k, poses[i][1], times[i])], background=(0, 0, 0))[0]
        np.testing.assert_allclose(rgba[i][..., 3], ref["alpha"], atol=1e-4)
    # opaque PNG: where the raw render is (nearly) empty the viewer sees the fill, not black
    low_total = 0
    for c, e, p in zip(chans, exr, png):
        img = read_image_rgba(p)
        assert img.shape == (24, 32, 4) and np.all(img[..., 3] == 1.0)
        low = c["A"] < 0.05
        low_total += int(low.sum())
        if low.any():
            raw = np.stack([c[k] for k in "RGB"], -1)[low]
            assert raw.max() < 0.06                                # the raw render is dark there...
            assert np.all(img[..., :3][low].max(axis=-1) > orbit_strip.BLACK)  # ...the PNG is not
        stats = orbit_strip.frame_stats(e, p)
        assert stats["black_in_holes"] == 0.0
        assert stats["coverage"] == pytest.approx(float(np.mean(c["A"] > 0.5)))
    assert low_total > 0, "the tiny run covers every pixel: the hole check would not test anything"
    # "Drop Unobserved Gaussians": the engine's pruned scene (against the run's capture)
    from engine.scene.observed import prune_unobserved

    exr_p, _ = orbit_strip.render_both(scene, tmp_path / "frames", resolution_percentage=20,
                                       prune_unobserved=True, tag="_pruned")
    pruned = load_run(reconstructed["run_dir"])
    prune_unobserved(pruned)
    ref = pruned.render([View(k, poses[3][1], times[3])], background=(0, 0, 0))[0]
    np.testing.assert_allclose(read_exr_channels(exr_p[3])["A"], ref["alpha"], atol=1e-4)


def test_strip_and_table(tmp_path):
    """The montage and the Markdown table from EXR / PNG frames written by the engine's own
    writers (no Blender needed)."""
    from PIL import Image

    from engine.io.images import read_image_rgba, write_exr, write_png

    exr, png = [], []
    for i in range(3):
        a = np.zeros((12, 16), np.float32)
        a[:, : 4 + 4 * i] = 1.0
        rgb = np.full((12, 16, 3), 0.25, np.float32) * a[..., None]
        exr.append(write_exr(tmp_path / f"f{i}.exr", {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "A": a}))
        img = np.where(a[..., None] > 0, 0.5, 0.0).astype(np.float32).repeat(3, -1)
        png.append(write_png(tmp_path / f"f{i}.png", img))
    rows = [{"frame": i + 1, "azimuth": -30 + 30 * i, "time": 0.1 * i, **orbit_strip.frame_stats(e, p)}
            for i, (e, p) in enumerate(zip(exr, png))]
    assert [r["coverage"] for r in rows] == pytest.approx([4 / 16, 8 / 16, 12 / 16])
    assert [r["black_in_holes"] for r in rows] == [1.0, 1.0, 1.0]  # that PNG left its holes black
    table = orbit_strip.coverage_table(rows)
    assert "| 1 | -30° | 0.000 s | 25.0 % | 75.0 % | 75.00 % |" in table
    both = orbit_strip.coverage_table([{**r, **{k + "_pruned": v for k, v in r.items()}} for r in rows],
                                      ("", "_pruned"))
    assert "| 3 | +30° | 0.200 s | 75.0 % | 25.0 % | 25.00 % | 75.0 % | 25.0 % | 25.00 % |" in both
    raw = orbit_strip.raw_over(exr[0])
    np.testing.assert_allclose(raw[0, -1], [1.0, 0.0, 1.0], atol=1e-6)  # uncovered: magenta
    out = orbit_strip.montage([[read_image_rgba(p)[..., :3] for p in png], [orbit_strip.raw_over(e) for e in exr]],
                              ["a", "b", "c"], "caption", tmp_path / "strip.png")
    im = Image.open(out)
    assert im.size == (3 * 16 + 2 * 2, 14 + 14 + 2 * 12 + 2)
    strip = np.asarray(im.convert("RGB"))
    assert (strip[28 + 12 + 2:, 16 + 2 + 12:16 + 2 + 16] == [255, 0, 255]).all()  # 2nd column, raw row: magenta
