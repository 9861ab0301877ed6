"""Blender side of BulletTime4D: properties, preferences, sidebar panel, scene building.

Registration order: preferences (they put the Python packages path on ``sys.path``),
properties (``Scene.bt4d``, ``Scene.bt4d_run``), panels. Operators live in ``operators/``
and register themselves from the package root. The engine is reached through
``engine_bridge.py`` only.
"""
from __future__ import annotations

import bpy

from . import panel, preferences, properties, worker

# The add-on's own module name ("bl_ext.<repo>.bullettime4d"): the AddonPreferences idname
# and the key for bpy.utils.extension_path_user().
ADDON_PACKAGE = __package__.rpartition(".")[0]

classes = (
    *preferences.classes,
    *properties.classes,
    *panel.classes,
)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    properties.register()
    preferences.register()


def unregister():
    worker.cancel_all()  # background jobs stop at their next step (checkpoints are kept)
    preferences.unregister()
    properties.unregister()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
