"""The ``random`` scene of scripts/make_capture.py: a new set, rig and sensor for every seed.

Judging a change on scenes nobody tuned on needs scenes nobody built by hand. ``--preset random
--seed N`` draws, from N alone:

* the rig: the stereo pair 0.8-3 m from the subject, 0.08-0.35 m apart (at most a third of the
  distance), looking 4-22 deg down; the held-out ``eval0`` 15-28 deg to one side and 3-15 deg up;
* the set: a floor and a back wall 0.3-1.2 x the distance behind the subject, each with a texture
  from strong (bricks, checker) to weak (faint low-frequency noise: where two views struggle);
* 1-4 moving objects (ball, cube, torus) 5-15 % of the distance across, each sweeping 5-35 % of
  the distance at 3-13 rad/s and spinning, with its own texture and colours; 0-2 static props;
* the light: sun direction and strength, sky strength;
* the cameras: RGB 160x120, 240x180 or 320x240 and a spike sensor at half or a quarter of it;
* the sensor's noise, as a real Vidar camera shows it: gain non-uniformity 2-5 %, dark current
  0.001-0.01 and shot noise of 200-1000 photons per threshold.

Those sweeps are smooth: a 30 FPS camera samples them well enough that a model of the RGB frames
alone interpolates them (issue 47: RGB-only lost 0-1.5 dB on moving pixels half-way between RGB
instants). ``configure(seed, motion="between")`` (``--preset random_between``) keeps the same draw
and adds, from a stream of its own, motion that 30 FPS cannot sample -- what a spike camera is
for: each object bounces on the floor (impacts 1.5-3 RGB intervals apart, anywhere in an interval,
arcs 6-15 % of the distance high), vibrates along its heading at 10-25 Hz (3-6 % of the distance),
or keeps its smooth sweep; at least one object does not.

:func:`configure` must be called first (make_capture does it); it returns the capture settings
the seed chose (sizes, sensor noise) and records the whole draw in ``PARAMS``.
"""
from __future__ import annotations

import math

import bpy
import numpy as np
from capture_novel import _object_coords  # object-space coordinates times a scale: the texture vector

TARGET = (0.0, 0.0, 0.3)
CAMERA_EYES: dict = {}
EVAL0_ANGLES = (-20.0, 8.0)
MOVING: tuple = ()
PARAMS: dict = {}

RGB_SIZES = ((160, 120), (240, 180), (320, 240))
TEXTURES = ("bricks", "checker", "noise", "weak")
MOTIONS = ("smooth", "between")  # configure's motion: the sweeps alone, or bounces and vibrations added


def configure(seed: int, motion: str = "smooth") -> dict:
    """Draw the scene of ``seed`` into this module (``TARGET``, ``CAMERA_EYES``, ``EVAL0_ANGLES``,
    ``MOVING``, ``PARAMS``; ``motion``: one of ``MOTIONS``) and return its capture settings
    (``rgb_size``, ``spike_size`` and the sensor's ``gain_std``, ``dark_current``, ``photons_per_threshold``)."""
    global TARGET, CAMERA_EYES, EVAL0_ANGLES, MOVING, PARAMS
    if motion not in MOTIONS:  # before any of the module's scene is replaced
        raise ValueError(f"motion must be one of {MOTIONS}, not {motion!r}")
    rng = np.random.default_rng([int(seed), 48])
    d = float(rng.uniform(0.8, 3.0))
    base = float(min(rng.uniform(0.08, 0.35), d / 3.0))
    down = math.radians(rng.uniform(4.0, 22.0))
    h = float(rng.uniform(0.15, 0.35)) * d
    TARGET = (0.0, 0.0, h)
    eye_y, eye_z = -d * math.cos(down), h + d * math.sin(down)
    CAMERA_EYES = {"rgb0": (-base / 2, eye_y, eye_z), "rgb1": (base / 2, eye_y, eye_z)}
    side = float(rng.uniform(15.0, 28.0)) * (1 if rng.random() < 0.5 else -1)
    EVAL0_ANGLES = (side, float(rng.uniform(3.0, 15.0)))
    objects = []
    for i in range(int(rng.integers(1, 5))):
        size = float(rng.uniform(0.05, 0.15)) * d
        heading = float(rng.uniform(0, math.pi))
        objects.append({
            "name": f"obj{i}", "kind": str(rng.choice(("ball", "cube", "torus"))), "size": size,
            "centre": (float(rng.uniform(-0.35, 0.35)) * d, float(rng.uniform(-0.25, 0.3)) * d,
                       size + float(rng.uniform(0.0, 0.35)) * d),
            "sweep": float(rng.uniform(0.05, 0.35)) * d, "heading": (math.cos(heading), math.sin(heading)),
            "omega": float(rng.uniform(3.0, 13.0)), "phase": float(rng.uniform(0, 2 * math.pi)),
            "bob": float(rng.uniform(0.0, 0.08)) * d, "spin": tuple(float(x) for x in rng.uniform(-9, 9, 3)),
            "texture": _texture_draw(rng, strong=True)})
    props = [{"name": f"prop{i}", "kind": str(rng.choice(("cube", "ball"))), "size": float(rng.uniform(0.06, 0.2)) * d,
              "at": (float(rng.uniform(-0.6, 0.6)) * d, float(rng.uniform(0.1, 0.4)) * d),
              "texture": _texture_draw(rng, strong=True)} for i in range(int(rng.integers(0, 3)))]
    if motion == "between":
        _draw_unsampled_motion(np.random.default_rng([int(seed), 49]), objects, d)
    MOVING = tuple(o["name"] for o in objects)
    w, hh = RGB_SIZES[int(rng.integers(len(RGB_SIZES)))]
    # the spike sensor at half or a quarter of the RGB size, whole bytes per frame (Vidar's layout)
    div = int(rng.choice([k for k in (2, 4) if (w // k) * (hh // k) % 8 == 0]))
    PARAMS = {
        "distance": d, "baseline": base, "down_deg": math.degrees(down), "eval0_angles": EVAL0_ANGLES,
        "wall_behind": float(rng.uniform(0.3, 1.2)) * d, "floor": _texture_draw(rng, strong=rng.random() < 0.4),
        "wall": _texture_draw(rng, strong=rng.random() < 0.7), "objects": objects, "props": props,
        "sun": {"elevation_deg": float(rng.uniform(25, 70)), "azimuth_deg": float(rng.uniform(-60, 60)),
                "energy": float(rng.uniform(1.5, 4.0))}, "sky": float(rng.uniform(0.25, 0.7)),
    }
    return {"rgb_size": (w, hh), "spike_size": (w // div, hh // div),
            "gain_std": float(rng.uniform(0.02, 0.05)), "dark_current": float(rng.uniform(0.001, 0.01)),
            "photons_per_threshold": float(rng.uniform(200.0, 1000.0))}


def _draw_unsampled_motion(rng, objects: list, d: float) -> None:
    """Give each object a motion 30 FPS cannot sample (``motion`` and its parameters), from its own
    random stream so the rest of the seed's draw stays as ``motion="smooth"`` draws it."""
    kinds = [str(rng.choice(("bounce", "vibrate", "smooth"), p=(0.4, 0.4, 0.2))) for _ in objects]
    if all(k == "smooth" for k in kinds):
        kinds[int(rng.integers(len(kinds)))] = str(rng.choice(("bounce", "vibrate")))
    for o, kind in zip(objects, kinds):
        o["motion"] = kind
        if kind == "bounce":  # impacts period_s apart, the first at first_impact_s: |sin| arcs on the floor
            o["period_s"] = float(rng.uniform(1.5, 3.0)) / 30.0
            o["first_impact_s"] = float(rng.uniform(0.0, 1.0)) / 30.0
            o["height"] = float(rng.uniform(0.06, 0.15)) * d
        elif kind == "vibrate":
            o["vibration_hz"] = float(rng.uniform(10.0, 25.0))
            o["vibration_amp"] = float(rng.uniform(0.03, 0.06)) * d


def _texture_draw(rng, strong: bool) -> dict:
    kind = str(rng.choice(TEXTURES[:3])) if strong else "weak"
    return {"kind": kind, "scale": float(rng.uniform(3.0, 12.0)),
            "colours": [tuple(float(c) for c in rng.uniform(0.05, 0.95, 3)) for _ in range(2)]}


def object_poses(t: float, speed: float = 1.0) -> dict:
    """World location and XYZ Euler rotation (radians) of each moving object at time t (s)."""
    t = t * speed
    out = {}
    for o in PARAMS.get("objects", ()):
        s = o["sweep"] * math.sin(o["omega"] * t + o["phase"])
        cx, cy, cz = o["centre"]
        z = cz + o["bob"] * math.cos(1.3 * o["omega"] * t)
        kind = o.get("motion", "smooth")
        if kind == "vibrate":
            s += o["vibration_amp"] * math.sin(2.0 * math.pi * o["vibration_hz"] * t)
        elif kind == "bounce":  # resting on the floor at each impact (the object's half size above it)
            z = 0.5 * o["size"] + o["height"] * abs(math.sin(math.pi * (t - o["first_impact_s"]) / o["period_s"]))
        loc = (cx + s * o["heading"][0], cy + s * o["heading"][1], z)
        out[o["name"]] = (loc, tuple(w * t for w in o["spin"]))
    return out


def _colour(nt, mix, tex: dict, length: float):
    """The colour output of a texture draw (``_texture_draw``): ``tex["scale"]`` texels across
    ``length`` metres (the set's distance, or an object's size)."""
    a, b = (tuple(c) + (1.0,) for c in tex["colours"])
    vec = _object_coords(nt, tex["scale"] / max(length, 1e-6))  # square texels of a size in metres
    if tex["kind"] == "weak":  # faint, low frequency: +-3 % around one colour
        noise = nt.nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = 0.3
        noise.inputs["Detail"].default_value = 2.0
        nt.links.new(vec, noise.inputs["Vector"])
        ramp = nt.nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = tuple(c * 0.97 for c in a[:3]) + (1.0,)
        ramp.color_ramp.elements[1].color = tuple(min(1.0, c * 1.03) for c in a[:3]) + (1.0,)
        nt.links.new(noise.outputs["Fac"], ramp.inputs["Fac"])
        return ramp.outputs["Color"]
    if tex["kind"] in ("bricks", "checker"):
        node = nt.nodes.new("ShaderNodeTexBrick" if tex["kind"] == "bricks" else "ShaderNodeTexChecker")
        node.inputs["Color1"].default_value = a
        node.inputs["Color2"].default_value = b
        node.inputs["Scale"].default_value = 1.0
        nt.links.new(vec, node.inputs["Vector"])
        if tex["kind"] == "bricks":
            return node.outputs["Color"]
        noise = nt.nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = 2.0
        nt.links.new(vec, noise.inputs["Vector"])
        return mix(nt, node.outputs["Color"], noise.outputs["Color"], 0.2, "OVERLAY")
    node = nt.nodes.new("ShaderNodeTexNoise")
    node.inputs["Scale"].default_value = 1.0
    node.inputs["Detail"].default_value = 6.0
    nt.links.new(vec, node.inputs["Vector"])
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = a
    ramp.color_ramp.elements[1].color = b
    nt.links.new(node.outputs["Fac"], ramp.inputs["Fac"])
    return ramp.outputs["Color"]


def _add(kind: str, size: float):
    if kind == "ball":
        bpy.ops.mesh.primitive_uv_sphere_add(radius=size / 2, segments=32, ring_count=16)
        bpy.ops.object.shade_smooth()
    elif kind == "torus":
        bpy.ops.mesh.primitive_torus_add(major_radius=size / 2, minor_radius=size / 6)
        bpy.ops.object.shade_smooth()
    else:
        bpy.ops.mesh.primitive_cube_add(size=size)
    return bpy.context.object


def build_objects(scene, material, mix) -> dict:
    """The drawn set, props, moving objects and light; returns name -> moving Blender object."""
    if not PARAMS:
        raise RuntimeError("capture_random.configure(seed) must be called before build_objects")
    d = PARAMS["distance"]
    bpy.ops.mesh.primitive_plane_add(size=8.0 * d)
    floor = bpy.context.object
    floor.name = "floor"
    floor.data.materials.append(material("floor", lambda nt: _colour(nt, mix, PARAMS["floor"], d)))
    bpy.ops.mesh.primitive_plane_add(size=1.0)
    wall = bpy.context.object
    wall.name = "wall"
    wall.scale = (8.0 * d, 3.0 * d, 1.0)
    bpy.ops.object.transform_apply(location=False, rotation=False, scale=True)  # mesh in metres: square texels
    wall.rotation_euler = (math.radians(90), 0, 0)
    wall.location = (0.0, PARAMS["wall_behind"], 1.5 * d)
    wall.data.materials.append(material("wall", lambda nt: _colour(nt, mix, PARAMS["wall"], d)))
    for p in PARAMS["props"]:
        obj = _add(p["kind"], p["size"])
        obj.name = p["name"]
        obj.location = (p["at"][0], p["at"][1], p["size"] / 2)
        obj.data.materials.append(material(p["name"], lambda nt, t=p["texture"], n=p["size"]: _colour(nt, mix, t, n)))
    objs = {}
    for o in PARAMS["objects"]:
        obj = _add(o["kind"], o["size"])
        obj.name = o["name"]
        obj.rotation_mode = "XYZ"
        obj.data.materials.append(material(o["name"], lambda nt, t=o["texture"], n=o["size"]: _colour(nt, mix, t, n)))
        objs[o["name"]] = obj
    sun = bpy.data.objects.get("sun")
    if sun is not None:
        s = PARAMS["sun"]
        sun.data.energy = s["energy"]
        sun.rotation_euler = (math.radians(90 - s["elevation_deg"]), 0.0, math.radians(s["azimuth_deg"]))
    if scene.world is not None:
        scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value = PARAMS["sky"]
    return objs
