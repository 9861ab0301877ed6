"""The ``novel`` scene of scripts/make_capture.py: what two train views get wrong.

Table-top scale, Z up, metres; the stereo pair is 0.2 m apart about 1 m from the subject
(the rig of issue 14). In view:

* a large **weakly-textured floor** (light grey with a faint, low-frequency noise) — where
  stereo matching and a two-view photometric loss have nothing to hold on to;
* a **textured wall** behind (noisy checker), partly hidden from the pair by the objects;
* **thin parts**: a static pole about 2 px wide and the letters ``BT4D`` standing on a
  turntable;
* moving objects: ``ball`` (textured, 0.1 m across, swinging across the view at up to
  3 m/s: about its own diameter per 30 FPS frame), ``turntable`` (a textured disc carrying
  the letters, spinning at 6 rad/s), ``cube`` (a checker cube tumbling in the air).

Materials are built with the generator's ``material(name, build)`` / ``mix`` helpers,
passed in so this module does not import the script.
"""
from __future__ import annotations

import math

import bpy

TARGET = (0.0, 0.05, 0.2)
CAMERA_EYES = {
    "rgb0": (-0.1, -1.0, 0.45),
    "rgb1": (0.1, -1.0, 0.45),
}
MOVING = ("ball", "turntable", "cube")
EVAL0_ANGLES = (-15.0, 10.0)  # held out, 15 deg to the right (+X) and 10 deg above the pair


def object_poses(t: float, speed: float = 1.0):
    """World location and XYZ Euler rotation (radians) of each moving object at time t (s)."""
    t = t * speed
    ball_x = 0.35 * math.sin(8.6 * t - 0.9)  # peak 3 m/s: ~0.1 m (its diameter) per RGB frame
    return {
        "ball": ((ball_x, -0.2, 0.2 + 0.05 * math.cos(12.0 * t)), (0.0, 15.0 * t, 0.0)),
        "turntable": ((-0.24, 0.12, 0.0), (0.0, 0.0, 0.4 + 6.0 * t)),
        "cube": ((0.22, 0.18, 0.2 + 0.03 * math.sin(9.0 * t)), (0.4 + 7.0 * t, 0.3, 0.5 + 5.0 * t)),
    }


def _object_coords(nt, scale: float):
    """Texture vector: object-space coordinates times ``scale`` (square texels on any mesh)."""
    coord = nt.nodes.new("ShaderNodeTexCoord")
    mul = nt.nodes.new("ShaderNodeVectorMath")
    mul.operation = "SCALE"
    mul.inputs["Scale"].default_value = scale
    nt.links.new(coord.outputs["Object"], mul.inputs[0])
    return mul.outputs["Vector"]


def build_objects(scene, material, mix) -> dict:
    """Static set and moving objects; returns name -> moving Blender object."""

    def floor(nt):  # weak texture: +-3 % brightness, low frequency
        noise = nt.nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = 3.0
        noise.inputs["Detail"].default_value = 2.0
        nt.links.new(_object_coords(nt, 1.0), noise.inputs["Vector"])
        base = nt.nodes.new("ShaderNodeRGB")
        base.outputs[0].default_value = (0.55, 0.53, 0.5, 1)
        return mix(nt, base.outputs[0], noise.outputs["Color"], 0.06, "OVERLAY")

    def wall(nt):
        tex = nt.nodes.new("ShaderNodeTexChecker")
        tex.inputs["Color1"].default_value = (0.85, 0.82, 0.75, 1)
        tex.inputs["Color2"].default_value = (0.15, 0.25, 0.45, 1)
        tex.inputs["Scale"].default_value = 1.0
        nt.links.new(_object_coords(nt, 8.0), tex.inputs["Vector"])  # 12.5 cm squares
        noise = nt.nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = 1.0
        noise.inputs["Detail"].default_value = 6.0
        nt.links.new(_object_coords(nt, 12.0), noise.inputs["Vector"])
        return mix(nt, tex.outputs["Color"], noise.outputs["Color"], 0.4, "OVERLAY")

    def pole(nt):
        rgb = nt.nodes.new("ShaderNodeRGB")
        rgb.outputs[0].default_value = (0.08, 0.08, 0.1, 1)
        return rgb.outputs[0]

    def ball(nt):
        tex = nt.nodes.new("ShaderNodeTexWave")
        tex.wave_type = "BANDS"
        tex.inputs["Scale"].default_value = 1.0
        tex.inputs["Distortion"].default_value = 3.0
        nt.links.new(_object_coords(nt, 20.0), tex.inputs["Vector"])
        ramp = nt.nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = (0.9, 0.35, 0.05, 1)
        ramp.color_ramp.elements[1].color = (0.1, 0.1, 0.6, 1)
        nt.links.new(tex.outputs["Fac"], ramp.inputs["Fac"])
        return ramp.outputs["Color"]

    def turntable(nt):
        tex = nt.nodes.new("ShaderNodeTexVoronoi")
        tex.inputs["Scale"].default_value = 1.0
        nt.links.new(_object_coords(nt, 25.0), tex.inputs["Vector"])
        ramp = nt.nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = (0.05, 0.4, 0.12, 1)
        ramp.color_ramp.elements[1].color = (0.9, 0.9, 0.55, 1)
        nt.links.new(tex.outputs["Distance"], ramp.inputs["Fac"])
        return ramp.outputs["Color"]

    def letters(nt):
        rgb = nt.nodes.new("ShaderNodeRGB")
        rgb.outputs[0].default_value = (0.85, 0.1, 0.1, 1)
        return rgb.outputs[0]

    def cube(nt):
        tex = nt.nodes.new("ShaderNodeTexChecker")
        tex.inputs["Color1"].default_value = (0.95, 0.85, 0.2, 1)
        tex.inputs["Color2"].default_value = (0.1, 0.1, 0.1, 1)
        tex.inputs["Scale"].default_value = 1.0
        nt.links.new(_object_coords(nt, 25.0), tex.inputs["Vector"])
        return tex.outputs["Color"]

    bpy.ops.mesh.primitive_plane_add(size=6.0)
    bpy.context.object.name = "floor"
    bpy.context.object.data.materials.append(material("floor", floor))
    bpy.ops.mesh.primitive_plane_add(size=1.0)
    w = bpy.context.object
    w.name = "wall"
    w.scale = (4.0, 2.0, 1.0)
    w.rotation_euler = (math.radians(90), 0, 0)
    w.location = (0.0, 0.5, 1.0)
    w.data.materials.append(material("wall", wall))
    bpy.ops.mesh.primitive_cylinder_add(radius=0.006, depth=0.55, vertices=12, location=(0.06, 0.3, 0.275))
    bpy.context.object.name = "pole"
    bpy.context.object.data.materials.append(material("pole", pole))

    objs = {}
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.05, segments=32, ring_count=16)
    objs["ball"] = bpy.context.object
    bpy.ops.object.shade_smooth()
    objs["ball"].data.materials.append(material("ball", ball))

    # turntable: a textured disc with the letters BT4D standing on it, one mesh (one rigid body)
    bpy.ops.object.text_add(location=(0.0, 0.0, 0.01), rotation=(math.radians(90), 0.0, 0.0))
    text = bpy.context.object
    text.data.body = "BT4D"
    text.data.size = 0.09
    text.data.extrude = 0.006
    text.data.align_x = "CENTER"
    text.data.materials.append(material("letters", letters))
    bpy.ops.object.convert(target="MESH")
    bpy.ops.object.transform_apply(location=True, rotation=True, scale=True)
    bpy.ops.mesh.primitive_cylinder_add(radius=0.17, depth=0.02, vertices=48, location=(0.0, 0.0, 0.0))
    disc = bpy.context.object
    disc.data.materials.append(material("turntable", turntable))
    bpy.ops.object.select_all(action="DESELECT")
    text.select_set(True)
    disc.select_set(True)
    bpy.context.view_layer.objects.active = disc
    bpy.ops.object.join()
    objs["turntable"] = disc

    bpy.ops.mesh.primitive_cube_add(size=0.12)
    objs["cube"] = bpy.context.object
    objs["cube"].data.materials.append(material("cube", cube))
    for name, obj in objs.items():
        obj.name = name
        obj.rotation_mode = "XYZ"
    return objs
