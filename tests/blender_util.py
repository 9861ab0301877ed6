"""Helpers for tests that drive Blender through the ``bpy`` module.

``bpy`` is one module with global state per process. The tests use it in two ways:

* in-process (fast): :func:`enable_addon` registers a temporary local extension
  repository whose ``bullettime4d`` entry is a symlink to this checkout and enables
  ``bl_ext.bt4d_test.bullettime4d`` once per process; :func:`reset_scene` loads an empty
  factory start-up file between tests (preferences and enabled add-ons survive it);
* in a subprocess (isolation): :func:`run_python` runs a script with the project's
  Python and a throw-away Blender user folder, for tests that enable/disable the add-on
  or install packages.

Blender's user folders are pointed at a temporary directory before ``bpy`` is imported,
so tests never touch the real ``~/.config/blender``.
"""
from __future__ import annotations

import atexit
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
REPO_MODULE = "bt4d_test"
ADDON_MODULE = f"bl_ext.{REPO_MODULE}.bullettime4d"
# what a packaged extension needs (the rest of the checkout is development files)
EXTENSION_FILES = ("blender_manifest.toml", "__init__.py", "bt4d_addon", "operators", "engine")

# bpy 5.0.1 is built for Python 3.11 only: elsewhere (a GPU box's 3.12) its tests skip
HAS_BPY = importlib.util.find_spec("bpy") is not None
NEEDS_BPY = pytest.mark.skipif(not HAS_BPY, reason="needs the bpy module (Blender 5.0 as a module, Python 3.11)")

_USER_DIR = None


def user_dir() -> Path:
    """A per-process temporary Blender user folder (removed at exit)."""
    global _USER_DIR
    if _USER_DIR is None:
        _USER_DIR = Path(tempfile.mkdtemp(prefix="bt4d_blender_user_"))
        atexit.register(shutil.rmtree, _USER_DIR, True)
    return _USER_DIR


def isolated_env(user: Path | None = None) -> dict:
    env = dict(os.environ)
    user = user or user_dir()
    env["BLENDER_USER_RESOURCES"] = str(user)
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


if "bpy" not in sys.modules:  # must happen before Blender reads its folders
    os.environ.setdefault("BLENDER_USER_RESOURCES", str(user_dir()))


def make_extension_dir(parent: Path, *, copy: bool = False) -> Path:
    """``parent/bullettime4d`` -> this checkout (symlink, or a copy of the extension files)."""
    parent = Path(parent)
    parent.mkdir(parents=True, exist_ok=True)
    target = parent / "bullettime4d"
    if copy:
        target.mkdir()
        for name in EXTENSION_FILES:
            src = REPO_ROOT / name
            if src.is_dir():
                shutil.copytree(src, target / name, ignore=shutil.ignore_patterns("__pycache__"))
            else:
                shutil.copy2(src, target / name)
    else:
        target.symlink_to(REPO_ROOT, target_is_directory=True)
    return target


_ENABLED = {}


def enable_addon():
    """Enable the add-on through Blender's extension machinery (once per process)."""
    if "module" in _ENABLED:
        return _ENABLED["module"]
    import addon_utils
    import bpy

    ext_parent = Path(tempfile.mkdtemp(prefix="bt4d_ext_repo_"))
    atexit.register(shutil.rmtree, ext_parent, True)
    make_extension_dir(ext_parent)
    repos = bpy.context.preferences.extensions.repos
    if REPO_MODULE not in [r.module for r in repos]:
        repos.new(name=REPO_MODULE, module=REPO_MODULE, custom_directory=str(ext_parent), source="USER")
    errors = []
    mod = addon_utils.enable(ADDON_MODULE, default_set=True, handle_error=errors.append)
    if errors or mod is None:
        raise RuntimeError(f"enabling {ADDON_MODULE} failed: {errors!r}")
    _ENABLED["module"] = mod
    return mod


def reset_scene():
    """An empty scene; keeps preferences and enabled add-ons."""
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    return bpy.context.scene


def datablock_counts() -> dict:
    import bpy

    return {name: len(getattr(bpy.data, name)) for name in
            ("objects", "cameras", "collections", "images", "actions")}


def run_python(code: str, *, timeout: float = 300, env: dict | None = None, cwd: Path | None = None):
    """Run ``code`` with the project's Python in an isolated Blender user folder.

    The script reports by printing one line ``RESULT <json>``; returns (json or None, output).
    """
    user = Path(tempfile.mkdtemp(prefix="bt4d_blender_user_"))
    try:
        proc = subprocess.run([sys.executable, "-c", code], cwd=str(cwd or REPO_ROOT),
                              env=env or isolated_env(user), stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True, timeout=timeout)
    finally:
        shutil.rmtree(user, ignore_errors=True)
    result = None
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            result = json.loads(line[len("RESULT "):])
    return result, proc.stdout


def write_png(path: Path, img) -> None:
    from engine.io.images import write_png as _write

    _write(path, img)
