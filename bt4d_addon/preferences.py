"""Add-on preferences: where the engine's Python packages (torch, numba, ...) come from.

Blender ships its own Python with numpy but without torch. The add-on finds torch in one
of two folders, both *appended* to ``sys.path`` (so Blender's bundled numpy keeps
precedence) on register and whenever the setting changes:

1. **Python packages path**: the ``site-packages`` folder of an existing environment
   with the same Python minor version as Blender (e.g. a project ``.venv``), or
2. the extension's own user folder ``<extensions user dir>/bullettime4d/site-packages``,
   filled by the *Install Dependencies* button, which runs
   ``<Blender's python> -m pip install --target <that folder> <REQUIREMENTS>``.
"""
from __future__ import annotations

import collections
import importlib
import importlib.util
import shlex
import subprocess
import sys
import threading
from pathlib import Path

import bpy
from bpy.props import StringProperty
from bpy.types import AddonPreferences, Operator

ADDON_PACKAGE = __package__.rpartition(".")[0]

# What the engine needs, pinned exactly as requirements.txt pins it (tests/test_addon_preferences.py
# compares them). numpy is pinned too: under --target pip would otherwise put the newest numpy (2.x,
# which bpy cannot load) beside torch.
REQUIREMENTS = (
    "torch==2.13.0",
    "numpy==1.26.4",
    "numba==0.68.1",
    "llvmlite==0.50.0",
    "OpenEXR==3.5.3",
    "trimesh==5.2.0",
    "pytorch-msssim==1.0.0",
    "pillow==13.0.0",
    "plyfile==1.1.2",
    "zstandard==0.25.0",
    "tqdm==4.70.1",
    "opencv-python-headless==4.11.0.86",  # stereo (engine.geometry.stereo); 4.11 keeps numpy < 2
)
# in requirements.txt but not for the add-on: Blender itself, the tests, the linter, the benchmarks' plots, and
# Ray (optional: engine batch and sharded renders on a cluster)
DEVELOPMENT_ONLY = ("bpy", "pytest", "ruff", "matplotlib", "ray")

_added_paths: list[str] = []  # the sys.path entries this add-on appended


def user_site_packages(create: bool = False) -> str | None:
    """The extension's private site-packages folder, or None outside the extension system."""
    try:
        return bpy.utils.extension_path_user(ADDON_PACKAGE, path="site-packages", create=create)
    except (ValueError, TypeError):  # not loaded as bl_ext.<repo>.bullettime4d
        return None


def get_prefs(context=None):
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon else None


def wanted_paths(python_path: str) -> list[str]:
    """Existing folders that should be on sys.path: the user's path, then our own folder."""
    out = []
    for p in (python_path, user_site_packages()):
        if p:
            p = str(Path(bpy.path.abspath(p)).expanduser().resolve())
            if Path(p).is_dir() and p not in out:
                out.append(p)
    return out


def sync_sys_path(python_path: str | None = None) -> list[str]:
    """Make this add-on's entries on sys.path match the preferences. Returns them."""
    if python_path is None:
        prefs = get_prefs()
        python_path = prefs.python_path if prefs else ""
    for p in _added_paths:
        while p in sys.path:
            sys.path.remove(p)
    _added_paths.clear()
    for p in wanted_paths(python_path):
        if p not in sys.path:
            sys.path.append(p)
            _added_paths.append(p)
    importlib.invalidate_caches()
    return list(_added_paths)


def torch_location() -> str | None:
    """Where ``import torch`` would load from (without importing it), or None."""
    try:
        spec = importlib.util.find_spec("torch")
    except (ImportError, ValueError):
        return None
    return None if spec is None or not spec.origin else str(Path(spec.origin).parent)


def pip_install_command(target: str, packages=REQUIREMENTS, extra_args: str = "") -> list[str]:
    """The pip command the Install Dependencies button runs."""
    return [sys.executable, "-m", "pip", "install", "--upgrade", "--no-input",
            "--target", target, *shlex.split(extra_args), *packages]


class PipRun:
    """A pip process whose output is read as it comes (a thread drains the pipe, so a long torch
    download never blocks on a full pipe); ``latest`` is its last line, ``cancel`` stops it."""

    def __init__(self, cmd: list[str]):
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
        self.lines: collections.deque[str] = collections.deque(maxlen=400)
        self.cancelled = False
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            line = line.rstrip()
            if line:
                self.lines.append(line)
        self.proc.stdout.close()

    @property
    def latest(self) -> str:
        return self.lines[-1] if self.lines else ""

    def poll(self) -> int | None:
        """The exit code once pip has exited and its output is read, else None."""
        code = self.proc.poll()
        if code is None:
            return None
        self._reader.join(timeout=5.0)
        return code

    def cancel(self) -> None:
        self.cancelled = True
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._reader.join(timeout=5.0)

    def output(self) -> str:
        return "\n".join(self.lines)


def _on_path_changed(self, context):
    sync_sys_path(self.python_path)


class BT4D_AddonPreferences(AddonPreferences):
    bl_idname = ADDON_PACKAGE

    python_path: StringProperty(
        name="Python Packages Path", subtype="DIR_PATH", update=_on_path_changed,
        description="The packages folder of a Python environment that has torch (same Python version as "
                    "Blender); Blender then finds torch there")
    pip_args: StringProperty(
        name="Extra pip Arguments", default="",
        description="Added to the pip command. For a CUDA build of torch: --extra-index-url followed by "
                    "the PyTorch wheel index of your CUDA version (the other packages still come from PyPI)")
    last_install_log: StringProperty(name="Last Install", default="")

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "python_path")
        box = layout.box()
        own = user_site_packages()
        box.label(text=f"Add-on packages folder: {own or '(only when installed as an extension)'}")
        box.prop(self, "pip_args")
        box.operator(BT4D_OT_install_dependencies.bl_idname, icon="IMPORT")
        if self.last_install_log:
            box.label(text=self.last_install_log)
        loc = torch_location()
        layout.label(text=f"torch: {loc}" if loc else "torch: not found",
                     icon="CHECKMARK" if loc else "ERROR")


class BT4D_OT_install_dependencies(Operator):
    """Install torch and the engine's other packages into the add-on's own folder with pip"""

    bl_idname = "bt4d.install_dependencies"
    bl_label = "Install Dependencies"
    bl_options = {"REGISTER", "INTERNAL"}

    packages: StringProperty(
        name="Packages", default=" ".join(REQUIREMENTS),
        description="Space-separated pip requirement specifiers")
    extra_args: StringProperty(name="Extra Arguments", default="",
                               description="Added to the preferences' pip arguments")
    target: StringProperty(name="Target", subtype="DIR_PATH", default="",
                           description="Install folder (default: the add-on's site-packages folder)")

    _run: PipRun | None = None
    _timer = None

    def _command(self, context) -> list[str] | None:
        target = self.target or user_site_packages(create=True)
        if not target:
            self.report({"ERROR"}, "BulletTime4D is not installed as an extension: "
                                   "set a Python packages path in the preferences instead")
            return None
        Path(target).mkdir(parents=True, exist_ok=True)
        prefs = get_prefs(context)
        extra = " ".join(a for a in ((prefs.pip_args if prefs else ""), self.extra_args) if a)
        return pip_install_command(target, self.packages.split(), extra)

    def _finish(self, context, returncode: int, output: str) -> set[str]:
        prefs = get_prefs(context)
        tail = (output or "").strip().splitlines()[-1:] or [""]
        msg = ("Installed: " if returncode == 0 else f"pip failed ({returncode}): ") + tail[0][:200]
        if prefs:
            prefs.last_install_log = msg
        sync_sys_path()
        if returncode != 0:
            self.report({"ERROR"}, msg)
            return {"CANCELLED"}
        self.report({"INFO"}, msg)
        return {"FINISHED"}

    def execute(self, context):  # blocking: scripts and tests
        cmd = self._command(context)
        if cmd is None:
            return {"CANCELLED"}
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        return self._finish(context, proc.returncode, proc.stdout)

    def invoke(self, context, event):  # non-blocking: the UI keeps responding while pip runs
        cmd = self._command(context)
        if cmd is None:
            return {"CANCELLED"}
        self._run = PipRun(cmd)
        self._timer = context.window_manager.event_timer_add(0.5, window=context.window)
        context.window_manager.modal_handler_add(self)
        self.report({"INFO"}, "Installing dependencies with pip (Esc cancels)...")
        return {"RUNNING_MODAL"}

    def _status(self, context, text: str | None) -> None:
        prefs = get_prefs(context)
        if prefs and text is not None:
            prefs.last_install_log = text[:200]
        workspace = getattr(context, "workspace", None)
        if workspace is not None:
            workspace.status_text_set(text)
        for area in getattr(context.screen, "areas", []) if getattr(context, "screen", None) else []:
            area.tag_redraw()

    def modal(self, context, event):
        if event.type == "ESC":
            self._run.cancel()
            context.window_manager.event_timer_remove(self._timer)
            self._status(context, None)
            msg = "Install cancelled; the packages folder may hold a partial install (press the button again)"
            prefs = get_prefs(context)
            if prefs:
                prefs.last_install_log = msg
            self.report({"WARNING"}, msg)
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        code = self._run.poll()
        if code is None:
            self._status(context, f"pip: {self._run.latest}" if self._run.latest else "pip: starting...")
            return {"PASS_THROUGH"}
        context.window_manager.event_timer_remove(self._timer)
        self._status(context, None)
        return self._finish(context, code, self._run.output())


classes = (BT4D_AddonPreferences, BT4D_OT_install_dependencies)


def register():
    sync_sys_path()


def unregister():
    for p in _added_paths:
        while p in sys.path:
            sys.path.remove(p)
    _added_paths.clear()
