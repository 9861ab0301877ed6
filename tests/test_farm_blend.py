"""A .blend saved after Reconstruct or after Load Result is render-farm-ready (issue 44): a fresh
`bpy` process with a stock user folder (the add-on not installed) and torch not importable opens
it and renders the same frame as the add-on's own process, in Cycles and in EEVEE, from a copy of
the .blend alone in another folder; every file the .blend points to is referenced by a path
relative to it."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
import textwrap

import blender_util
import numpy as np
import pytest
import roundtrip_util
from roundtrip_util import reconstructed, rt_scene, run_tmp  # noqa: F401  (fixtures)

bpy = pytest.importorskip("bpy")

FRAME = 4
ENGINES = ("CYCLES", "BLENDER_EEVEE")
# what a stock Flamenco worker runs: open the file, render its frame; torch absent, no add-on
FARM_WORKER = textwrap.dedent("""
    import json, sys
    class NoTorch:  # torch is not on this render node
        def find_spec(self, name, path=None, target=None):
            if name == "torch" or name.startswith("torch."):
                raise ModuleNotFoundError("No module named 'torch'")
    sys.meta_path.insert(0, NoTorch())
    import bpy
    report = {}
    for blend, out in json.loads(sys.argv[1]):
        bpy.ops.wm.open_mainfile(filepath=blend)
        s = bpy.context.scene
        s.render.filepath = out
        bpy.ops.render.render(write_still=True)
        report[blend] = {"paths": bpy.utils.blend_paths(absolute=False), "engine": s.render.engine,
                         "frame": s.frame_current}
    report["addons"] = [a.module for a in bpy.context.preferences.addons]
    report["ours"] = sorted(m for m in sys.modules if "bullettime4d" in m or m.startswith("bt4d"))
    report["torch"] = "torch" in sys.modules
    print("RESULT", json.dumps(report))
""")


def _render_settings(scene, cam, engine: str) -> None:
    scene.camera = cam
    r = scene.render
    r.engine = engine
    r.resolution_percentage = 40  # 64x48 of the demo's 160x120 eval camera
    r.film_transparent = True
    r.image_settings.file_format = "OPEN_EXR"
    if engine == "CYCLES":
        scene.cycles.samples = 8
        scene.cycles.device = "CPU"
        scene.cycles.use_denoising = False
    else:
        scene.eevee.taa_render_samples = 4
    if scene.world is None:
        scene.world = bpy.data.worlds.new("black")
    scene.frame_set(FRAME)


def _scene_after(source: str, reconstructed, demo_capture):  # noqa: F811
    if source == "reconstruct":
        bpy.ops.wm.open_mainfile(filepath=str(reconstructed["blend_after_reconstruct"]))
    else:
        assert bpy.ops.bt4d.import_capture(directory=str(demo_capture)) == {"FINISHED"}
        assert bpy.ops.bt4d.load_result(directory=str(reconstructed["run_dir"])) == {"FINISHED"}
    gn = roundtrip_util.addon_module("bt4d_addon.gaussian_nodes")
    assert len(gn.find_result_objects(bpy.context.scene)) == 1
    return bpy.context.scene


@pytest.mark.slow
@pytest.mark.parametrize("source", ["reconstruct", "load_result"])
def test_saved_blend_renders_on_a_stock_farm_worker(source, rt_scene, reconstructed, demo_capture,  # noqa: F811
                                                    tmp_path):
    from engine.io.images import read_image_rgba

    scene = _scene_after(source, reconstructed, demo_capture)
    jobs, refs = [], {}
    for engine in ENGINES:
        _render_settings(scene, bpy.data.objects["eval0"], engine)
        blend = tmp_path / "farm" / f"{source}_{engine.lower()}.blend"
        blend.parent.mkdir(exist_ok=True)
        bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)  # relative_remap: Blender's default
        scene.render.filepath = str(tmp_path / f"addon_{engine}.exr")
        bpy.ops.render.render(write_still=True)  # the add-on's own process renders the same file
        # the farm gets the .blend alone, somewhere else: what it points to (the capture's frames as
        # camera backgrounds, viewport only) is not there, and nothing rendered may need it
        farm_copy = tmp_path / "farm_storage" / "shots" / "take_1" / blend.name
        farm_copy.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(blend, farm_copy)
        refs[str(farm_copy)] = read_image_rgba(tmp_path / f"addon_{engine}.exr")
        jobs.append([str(farm_copy), str(tmp_path / f"farm_{engine}.exr")])
    stock_user = tempfile.mkdtemp(prefix="bt4d_stock_blender_")  # a render node's Blender: no add-on installed
    proc = subprocess.run([sys.executable, "-c", FARM_WORKER, json.dumps(jobs)],
                          env=blender_util.isolated_env(user=stock_user), capture_output=True, text=True,
                          timeout=900, cwd=tempfile.gettempdir())
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    report = json.loads(next(ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT "))[7:])
    assert report["ours"] == [] and not report["torch"], report
    assert not any("bullettime4d" in a for a in report["addons"])
    for blend, out in jobs:
        info = report[blend]
        assert info["frame"] == FRAME
        assert all(p.startswith("//") for p in info["paths"]), info["paths"]  # relative to the .blend
        img = read_image_rgba(out)
        ref = refs[blend]
        assert img.shape == ref.shape == (48, 64, 4)
        assert float(ref[..., 3].mean()) > 0.05, f"{info['engine']}: the result is not in the picture"
        p = roundtrip_util.psnr(img, ref)
        print(f"\n{source} {info['engine']}: farm worker vs add-on: {p:.1f} dB; files: {info['paths']}")
        assert p >= 40.0, (info["engine"], p)
        assert np.isfinite(img).all()
