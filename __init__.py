"""BulletTime4D Blender extension (id ``bullettime4d``).

Blender loads this package as ``bl_ext.<repository>.bullettime4d``; everything below it is
imported relatively so the same files work from any extension repository.
``engine/`` (torch + numpy, no ``bpy``) ships inside the package and is imported lazily by
the operators.
"""
from __future__ import annotations

# First, before anything imports torch: engine/__init__.py (numpy only) sets OMP_WAIT_POLICY
# so that torch's and numba's OpenMP pools do not busy-wait against each other.
from . import engine  # noqa: F401

# isort: split
from . import bt4d_addon, operators


def register():
    bt4d_addon.register()
    operators.register()


def unregister():
    operators.unregister()
    bt4d_addon.unregister()
