"""One module per user action (``bpy.ops.bt4d.*``). Each module defines ``classes``.

Add a module by importing it here and listing it in ``MODULES``.
"""
from __future__ import annotations

import bpy

from . import bullet_time, export_path, export_ply, import_capture, load_result, reconstruct, render_path

MODULES = (import_capture, reconstruct, load_result, export_ply, render_path, export_path, bullet_time)


def _classes():
    for mod in MODULES:
        yield from mod.classes


def register():
    for cls in _classes():
        bpy.utils.register_class(cls)
    for mod in MODULES:
        if hasattr(mod, "register"):
            mod.register()


def unregister():
    for mod in reversed(MODULES):
        if hasattr(mod, "unregister"):
            mod.unregister()
    for cls in reversed(list(_classes())):
        bpy.utils.unregister_class(cls)
