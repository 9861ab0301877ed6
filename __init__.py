"""BulletTime4D Blender extension (id ``bullettime4d``).

Blender loads this package as ``bl_ext.<repository>.bullettime4d``; everything below it is
imported relatively so the same files work from any extension repository.
``engine/`` (torch + numpy, no ``bpy``) ships inside the package and is imported lazily by
the operators.
"""
from __future__ import annotations

import os

# Before anything imports torch: keep torch's and numba's OpenMP pools from busy-waiting
# against each other (see engine/__init__.py).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from . import bt4d_addon, operators  # noqa: E402


def register():
    bt4d_addon.register()
    operators.register()


def unregister():
    operators.unregister()
    bt4d_addon.unregister()
