"""Blender side of the export issue, through the real operators: bpy.ops.bt4d.export_ply
(Result panel + File > Export) and bpy.ops.bt4d.load_result on a compact cache (.bt4c)."""
from __future__ import annotations

import blender_util
import numpy as np
import pytest
from export_util import TIME_RANGE, write_run

bpy = pytest.importorskip("bpy")


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return write_run(tmp_path_factory.mktemp("bt4d_export") / "run", n=120)


@pytest.fixture()
def scene():
    blender_util.enable_addon()
    return blender_util.reset_scene()


def test_export_ply_operator_writes_a_sequence(scene, run_dir, tmp_path):
    from engine.export import ply
    from engine.export.splats import splats_at
    from engine.scene.model import load_run

    out = tmp_path / "plys"
    assert bpy.ops.bt4d.export_ply(directory=str(out), source=str(run_dir), fps=20.0) == {"FINISHED"}
    index = ply.read_index(out)
    assert index["num_frames"] == 5 and index["fps"] == 20.0  # 0.0, 0.05 .. 0.2
    assert [f["time"] for f in index["frames"]] == pytest.approx([0.0, 0.05, 0.1, 0.15, 0.2])
    got = ply.read_sequence_frame(out, 3)
    want = splats_at(load_run(run_dir).model, 0.15)
    for k in want:
        np.testing.assert_allclose(got[k], want[k], atol=1e-5)


def test_export_ply_defaults_to_the_scene_run_and_fps(scene, run_dir, tmp_path):
    from engine.export import ply

    scene.bt4d_run.run_dir = str(run_dir)
    scene.render.fps, scene.render.fps_base = 10, 1.0
    assert bpy.ops.bt4d.export_ply(directory=str(tmp_path / "p")) == {"FINISHED"}
    assert ply.read_index(tmp_path / "p")["num_frames"] == 3  # 0.0, 0.1, 0.2 at 10 fps


def test_export_ply_errors(scene, tmp_path):
    with pytest.raises(RuntimeError, match="No result to export"):
        bpy.ops.bt4d.export_ply(directory=str(tmp_path / "x"))
    with pytest.raises(RuntimeError, match="nowhere.*run directory does not exist"):
        bpy.ops.bt4d.export_ply(directory=str(tmp_path / "x"), source=str(tmp_path / "nowhere"))
    assert not (tmp_path / "x" / "index.json").exists()


def test_export_ply_is_in_file_export_menu_and_result_panel(scene):
    import inspect

    mod = blender_util.enable_addon()
    menu_funcs = bpy.types.TOPBAR_MT_file_export._dyn_ui_initialize()
    assert any(getattr(f, "__module__", "").endswith("operators.export_ply") for f in menu_funcs)
    panel_run = __import__(f"{blender_util.ADDON_MODULE}.bt4d_addon.panel_run", fromlist=["draw_result"])
    assert '"bt4d.export_ply"' in inspect.getsource(panel_run.draw_result)
    assert mod is not None


def test_load_result_accepts_a_compact_cache(scene, run_dir, tmp_path):
    from engine.export import compact
    from engine.export.cached import load_result, run_meta, sample_splats

    gn = __import__(f"{blender_util.ADDON_MODULE}.bt4d_addon.gaussian_nodes", fromlist=["find_result_objects"])
    run = load_result(run_dir)
    cache = compact.write_compact(tmp_path / "scene.bt4c", np.linspace(*TIME_RANGE, 6), sample_splats(run),
                                  meta=run_meta(run))
    assert bpy.ops.bt4d.load_result(filepath=str(cache), directory=str(tmp_path), num_samples=3) == {"FINISHED"}
    objs = gn.find_result_objects(bpy.context.scene)
    assert len(objs) == 1
    mesh = objs[0].data
    n, k = mesh["bt4d_num_gaussians"], mesh["bt4d_num_samples"]
    assert (n, k) == (120, 3) and len(mesh.vertices) == n * k
    assert bpy.context.scene.bt4d_run.run_dir == str(cache)
    co = np.empty(n * k * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    want = load_result(cache).gaussians_at(TIME_RANGE[1])["means"]
    np.testing.assert_allclose(co.reshape(k, n, 3)[2], want, atol=1e-6)
    # ... and within the cache's error bound of the run's own Gaussians
    np.testing.assert_allclose(want, run.gaussians_at(TIME_RANGE[1])["means"], atol=1e-3)
    # the same cache exports to PLY too
    assert bpy.ops.bt4d.export_ply(directory=str(tmp_path / "fromcache"), source=str(cache), fps=10.0) == {"FINISHED"}


def test_load_result_rejects_a_foreign_file(scene, tmp_path):
    bad = tmp_path / "notacache.bt4c"
    bad.write_bytes(b"hello")
    with pytest.raises(RuntimeError, match="notacache.bt4c: neither a run directory nor"):
        bpy.ops.bt4d.load_result(filepath=str(bad))


def test_result_box_shows_lpips(scene):
    import inspect

    blender_util.enable_addon()
    rec = __import__(f"{blender_util.ADDON_MODULE}.operators.reconstruct", fromlist=["apply_metrics"])
    panel_run = __import__(f"{blender_util.ADDON_MODULE}.bt4d_addon.panel_run", fromlist=["draw_result"])
    rec.apply_metrics(scene, {"psnr": 21.5, "ssim": 0.7, "lpips": 0.1234, "n_frames": 3}, {})
    assert scene.bt4d_run.metric_lpips == pytest.approx(0.1234)
    rec.apply_metrics(scene, {"psnr": 21.5}, {})  # an older metrics.json without lpips
    assert scene.bt4d_run.metric_lpips == -1.0  # shown as "LPIPS n/a", not as a perfect 0
    assert "LPIPS {r.metric_lpips" in inspect.getsource(panel_run.draw_result)
