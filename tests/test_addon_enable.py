"""The extension as Blender sees it: manifest, zip build, install from disk, enable/disable.

Everything that changes Blender's preferences runs in a subprocess with a throw-away user
folder (tests/blender_util.run_python), so it cannot leak into the other bpy tests.
"""
from __future__ import annotations

import subprocess
import sys
import textwrap
import tomllib
import zipfile

import blender_util
import pytest
from blender_util import NEEDS_BPY, REPO_ROOT


def _manifest() -> dict:
    with open(REPO_ROOT / "blender_manifest.toml", "rb") as fh:
        return tomllib.load(fh)


def test_manifest_fields():
    m = _manifest()
    assert m["schema_version"] == "1.0.0"
    assert m["id"] == "bullettime4d" and m["version"] == "0.1.0" and m["name"] == "BulletTime4D"
    assert m["type"] == "add-on"
    assert m["blender_version_min"] == "5.0.0"
    assert m["license"] == ["SPDX:GPL-3.0-or-later"]
    assert "files" in m["permissions"]
    excluded = m["build"]["paths_exclude_pattern"]
    for pattern in ("__pycache__/", ".*", "/tests/", "/scripts/", "/runs/"):
        assert pattern in excluded


@NEEDS_BPY
def test_manifest_passes_blenders_validation():
    sys.path.insert(0, str(REPO_ROOT / "scripts"))
    try:
        import build_extension
    finally:
        sys.path.pop(0)
    cli = build_extension.blender_ext_cli()
    proc = subprocess.run([sys.executable, str(cli), "validate", str(REPO_ROOT)],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout
    assert "Success" in proc.stdout


@pytest.fixture(scope="module")
def built_zip(tmp_path_factory):
    out = tmp_path_factory.mktemp("dist")
    proc = subprocess.run([sys.executable, str(REPO_ROOT / "scripts" / "build_extension.py"),
                           "--output-dir", str(out)],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout
    zips = list(out.glob("bullettime4d-*.zip"))
    assert len(zips) == 1, proc.stdout
    return zips[0]


@NEEDS_BPY
def test_zip_holds_the_extension_and_nothing_else(built_zip):
    names = zipfile.ZipFile(built_zip).namelist()
    for required in ("blender_manifest.toml", "__init__.py", "bt4d_addon/__init__.py", "bt4d_addon/panel.py",
                     "operators/__init__.py", "operators/import_capture.py", "engine/__init__.py",
                     "engine/io/capture.py", "engine/train/loop/trainer.py", "demo_capture/transforms.json"):
        assert required in names, required
    for n in names:
        assert not n.startswith(("tests/", "scripts/", "tools/", ".venv/", ".git", ".ci/", "runs/", "dist/",
                                 "build/")), n
        assert not any(w in n for w in ("bench", "stress", "ablate", "synthetic")), n  # development tools
        assert "__pycache__" not in n and not n.endswith(".pyc"), n
        assert not n.split("/")[-1].startswith("."), n
    assert built_zip.stat().st_size < 20e6


ENABLE_SCRIPT = textwrap.dedent("""
    import json, sys, tempfile
    from pathlib import Path
    sys.path.insert(0, "tests")
    import blender_util
    import bpy
    import addon_utils

    out = {}
    parent = Path(tempfile.mkdtemp())
    blender_util.make_extension_dir(parent, copy=COPY)
    repo = bpy.context.preferences.extensions.repos.new(
        name="BT4D Test", module="bt4d_test", custom_directory=str(parent), source="USER")
    bpy.ops.extensions.repo_refresh_all()
    errors = []
    mod = addon_utils.enable("bl_ext.bt4d_test.bullettime4d", default_set=True, handle_error=errors.append)
    out["module"] = getattr(mod, "__name__", None)
    out["errors"] = [repr(e) for e in errors]
    out["torch_at_enable"] = "torch" in sys.modules  # Blender ships without torch
    out["op"] = hasattr(bpy.ops.bt4d, "import_capture") and "import_capture" in dir(bpy.ops.bt4d)
    out["panels"] = [n for n in ("BT4D_PT_capture", "BT4D_PT_reconstruction", "BT4D_PT_result",
                                 "BT4D_PT_bullet_time") if getattr(bpy.types, n, None) is not None]
    out["prefs"] = type(bpy.context.preferences.addons["bl_ext.bt4d_test.bullettime4d"].preferences).__name__
    out["scene_prop"] = bpy.context.scene.bt4d.preset
    out["menu"] = any(getattr(f, "__name__", "") == "menu_func_import"
                      for f in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize())
    out["import"] = sorted(bpy.ops.bt4d.import_capture(directory=str(Path("demo_capture").resolve())))
    out["cameras"] = sorted(o.name for o in bpy.data.collections["demo_capture"].objects)
    addon_utils.disable("bl_ext.bt4d_test.bullettime4d", default_set=True, handle_error=errors.append)
    out["after_disable"] = {
        "op": "import_capture" in dir(bpy.ops.bt4d),
        "panel": getattr(bpy.types, "BT4D_PT_capture", None) is not None,
        "scene_prop": hasattr(bpy.types.Scene, "bt4d"),
        "enabled": "bl_ext.bt4d_test.bullettime4d" in bpy.context.preferences.addons,
        "errors": [repr(e) for e in errors],
    }
    print("RESULT " + json.dumps(out))
""")


@NEEDS_BPY
@pytest.mark.parametrize("copy", [False, True], ids=["symlink", "copy"])
def test_enable_and_disable_through_extension_repository(demo_capture, copy):
    res, log = blender_util.run_python(ENABLE_SCRIPT.replace("COPY", str(copy)))
    assert res is not None, log
    assert res["module"] == "bl_ext.bt4d_test.bullettime4d" and not res["errors"], log
    assert res["torch_at_enable"] is False, log  # the engine's torch modules load on first use
    assert res["op"], log
    assert res["panels"] == ["BT4D_PT_capture", "BT4D_PT_reconstruction", "BT4D_PT_result", "BT4D_PT_bullet_time"]
    assert res["prefs"] == "BT4D_AddonPreferences"
    assert res["scene_prop"] == "fast"  # engine.train.config.DEFAULT_PRESET (the engine is not imported here)
    assert res["menu"]
    assert res["import"] == ["FINISHED"]
    assert res["cameras"] == ["eval0", "rgb0", "rgb1", "spike0"]
    assert res["after_disable"] == {"op": False, "panel": False, "scene_prop": False, "enabled": False,
                                    "errors": []}, log


INSTALL_ZIP_SCRIPT = textwrap.dedent("""
    import json, os, sys
    import bpy
    prefs = bpy.context.preferences
    repo = next(r for r in prefs.extensions.repos if r.module == "user_default")
    res = bpy.ops.extensions.package_install_files(filepath=ZIP, repo="user_default", enable_on_install=True)
    out = {"result": sorted(res), "enabled": "bl_ext.user_default.bullettime4d" in prefs.addons,
           "op": "import_capture" in dir(bpy.ops.bt4d),
           "demo": os.path.isfile(os.path.join(repo.directory, "bullettime4d", "demo_capture", "transforms.json"))}
    demo = os.path.join(repo.directory, "bullettime4d", "demo_capture")
    out["import"] = sorted(bpy.ops.bt4d.import_capture(directory=demo))
    print("RESULT " + json.dumps(out))
""")


@NEEDS_BPY
def test_built_zip_installs_from_disk_and_imports_its_demo(built_zip):
    """The zip goes through Blender's own "Install from Disk" and its bundled demo imports."""
    res, log = blender_util.run_python(INSTALL_ZIP_SCRIPT.replace("ZIP", repr(str(built_zip))))
    assert res == {"result": ["FINISHED"], "enabled": True, "op": True, "demo": True, "import": ["FINISHED"]}, log
