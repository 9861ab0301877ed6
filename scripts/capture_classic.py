"""The classic scene of scripts/make_capture.py (presets demo, large, fast).

Z up, metres: a brick back wall and a checker/noise floor (static texture to reconstruct), a
spinning checker cube, a striped ball swinging across the view in front of it (about 10-20
px per 30 FPS frame at 160 px wide) and a noise-textured torus spinning and bobbing. The
stereo pair stands ~5 m away, 0.6 m apart; ``eval0`` above and between them.

Materials are built with the generator's ``material(name, build)`` / ``mix`` helpers,
passed in so this module does not import the script.
"""
from __future__ import annotations

import math

import bpy

TARGET = (0.0, 0.3, 0.9)
CAMERA_EYES = {
    "rgb0": (-0.3, -5.0, 1.4),
    "rgb1": (0.3, -5.0, 1.4),
    "eval0": (0.0, -4.7, 2.2),
}
MOVING = ("cube", "ball", "torus")
Vec3 = tuple[float, float, float]


def object_poses(t: float, speed: float = 1.0) -> dict[str, tuple[Vec3, Vec3]]:
    """World location and XYZ Euler rotation (radians) of each moving object at time t (s);
    ``speed`` scales every motion (the paths stay the same, traversed ``speed`` times faster)."""
    t = t * speed
    ball_x = 1.6 * math.sin(10.0 * t - 1.1)  # peak 16 m/s ~ 16 px per 30 FPS frame at 160 px
    return {
        "cube": ((-0.75, 0.5, 0.95 + 0.15 * math.sin(9.0 * t)), (0.35, 25.0 * t, 0.6 + 18.0 * t)),
        "ball": ((ball_x, -0.6, 1.25 + 0.25 * math.cos(12.0 * t)), (0.0, 20.0 * t, 0.0)),
        "torus": ((1.05, 0.6, 0.75 + 0.35 * math.sin(14.0 * t + 0.5)), (1.1, 0.0, 20.0 * t)),
    }


def _bricks(nt, mix):
    tex = nt.nodes.new("ShaderNodeTexBrick")
    tex.inputs["Color1"].default_value = (0.55, 0.18, 0.09, 1)
    tex.inputs["Color2"].default_value = (0.75, 0.45, 0.25, 1)
    tex.inputs["Mortar"].default_value = (0.85, 0.85, 0.8, 1)
    tex.inputs["Scale"].default_value = 6.0
    noise = nt.nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = 25.0
    return mix(nt, tex.outputs["Color"], noise.outputs["Color"], 0.15, "MULTIPLY")


def _floor(nt, mix):
    tex = nt.nodes.new("ShaderNodeTexChecker")
    tex.inputs["Color1"].default_value = (0.8, 0.8, 0.75, 1)
    tex.inputs["Color2"].default_value = (0.12, 0.2, 0.35, 1)
    tex.inputs["Scale"].default_value = 8.0
    noise = nt.nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = 12.0
    noise.inputs["Detail"].default_value = 6.0
    return mix(nt, tex.outputs["Color"], noise.outputs["Color"], 0.35, "OVERLAY")


def _cube(nt):
    tex = nt.nodes.new("ShaderNodeTexChecker")
    tex.inputs["Color1"].default_value = (0.9, 0.15, 0.1, 1)
    tex.inputs["Color2"].default_value = (0.95, 0.85, 0.2, 1)
    tex.inputs["Scale"].default_value = 4.0
    return tex.outputs["Color"]


def _ball(nt):
    tex = nt.nodes.new("ShaderNodeTexWave")
    tex.wave_type = "BANDS"
    tex.inputs["Scale"].default_value = 3.0
    tex.inputs["Distortion"].default_value = 2.0
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (0.05, 0.15, 0.8, 1)
    ramp.color_ramp.elements[1].color = (0.95, 0.95, 0.95, 1)
    nt.links.new(tex.outputs["Fac"], ramp.inputs["Fac"])
    return ramp.outputs["Color"]


def _torus(nt):
    tex = nt.nodes.new("ShaderNodeTexVoronoi")
    tex.inputs["Scale"].default_value = 6.0
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (0.05, 0.45, 0.1, 1)
    ramp.color_ramp.elements[1].color = (0.85, 0.95, 0.5, 1)
    nt.links.new(tex.outputs["Distance"], ramp.inputs["Fac"])
    return ramp.outputs["Color"]


def build_objects(scene, material, mix) -> dict:
    """Static set and moving objects; returns name -> moving Blender object."""
    objs = {}
    bpy.ops.mesh.primitive_plane_add(size=1.0)
    wall = bpy.context.object
    wall.name = "wall"
    wall.scale = (10.0, 5.0, 1.0)
    wall.rotation_euler = (math.radians(90), 0, 0)
    wall.location = (0.0, 2.5, 2.5)
    wall.data.materials.append(material("bricks", lambda nt: _bricks(nt, mix)))
    bpy.ops.mesh.primitive_plane_add(size=10.0)
    floor = bpy.context.object
    floor.name = "floor"
    floor.data.materials.append(material("floor", lambda nt: _floor(nt, mix)))

    bpy.ops.mesh.primitive_cube_add(size=0.7)
    objs["cube"] = bpy.context.object
    objs["cube"].data.materials.append(material("cube", _cube))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.33, segments=32, ring_count=16)
    objs["ball"] = bpy.context.object
    bpy.ops.object.shade_smooth()
    objs["ball"].data.materials.append(material("ball", _ball))
    bpy.ops.mesh.primitive_torus_add(major_radius=0.32, minor_radius=0.11)
    objs["torus"] = bpy.context.object
    bpy.ops.object.shade_smooth()
    objs["torus"].data.materials.append(material("torus", _torus))
    for name, obj in objs.items():
        obj.name = name
        obj.rotation_mode = "XYZ"
    return objs
