"""Animated Gaussians in Blender without any Python at render time.

Storage ("sample cache")
    The model is sampled at K capture times ``t_k = t0 + k (t1 - t0) / (K - 1)`` and all
    samples (``Scene4D.sample``, the engine) are stored in ONE mesh of ``N * K`` vertices
    (vertex ``gid + k*N`` is Gaussian ``gid`` at ``t_k``), packed in the .blend like any
    mesh. Point attributes (names in ``attributes.py``):

    ============== ============ =====================================================
    position       FLOAT_VECTOR centre (world units)
    bt4d_rot       QUATERNION   orientation (w, x, y, z), normalised
    bt4d_scale     FLOAT_VECTOR standard deviations along the local axes (linear)
    bt4d_opacity   FLOAT        peak opacity in [0, 1]
    bt4d_color     FLOAT_COLOR  colour, LINEAR (the engine's sRGB-encoded colours are
                                decoded with ``engine.colour.srgb_to_linear`` on load)
    ============== ============ =====================================================

Geometry nodes ("BT4D Gaussians" group, one modifier per result object)
    Inputs: ``Capture Time`` (seconds, keyframable), ``Gaussians`` (N), ``Samples`` (K),
    ``Start Time`` / ``End Time`` (t0, t1), ``Size`` (multiplier on the ellipsoids) and
    ``Use Scene Time`` (when on, Capture Time is ignored and the GN Scene Time seconds are
    used: real-time playback with no keyframes at all).
    ``u = clamp((T - t0) / (t1 - t0), 0, 1) * (K - 1)``, ``k = min(floor(u), K - 2)``,
    ``frac = u - k``; a Points node makes N points and Sample Index fetches vertex
    ``Index + k*N`` and ``Index + (k+1)*N``: positions, scales, opacities and colours are
    interpolated linearly, rotations with the Mix node's rotation mode (slerp). Then Instance
    on Points puts an ico sphere of radius ``ELLIPSOID_RADIUS`` (the 3-sigma surface) on
    every point, rotated by the quaternion and scaled by the sigmas, with the Gaussian
    material (``gaussian_material.py``), which reads ``bt4d_color`` / ``bt4d_opacity`` as
    instancer attributes.

Holding Capture Time while the camera moves is bullet time; keying it slower than real
time is slow motion.
"""
from __future__ import annotations

import bpy
import numpy as np
from bpy_extras import anim_utils

from . import attributes as A
from . import gaussian_material
from .engine_bridge import srgb_to_linear

GROUP_NAME = "BT4D Gaussians"
MODIFIER_NAME = "BT4D Gaussians"
CAPTURE_TIME = "Capture Time"
ICO_SUBDIVISIONS = 2
VIEWPORT_SUBDIVISIONS = 1
# An ico sphere with 2 subdivisions has its faces at >= 0.94 of its radius: put the faces
# (not only the vertices) at ~3 sigma.
SIGMA_CUTOFF = 3.0
ELLIPSOID_RADIUS = SIGMA_CUTOFF / 0.94

# interface: (name, socket type, default, min, max, description); the times show in seconds
TIME_INPUTS = (CAPTURE_TIME, "Start Time", "End Time")
_INPUTS = [
    (CAPTURE_TIME, "NodeSocketFloat", 0.0, None, None,
     "Capture time in seconds that the Gaussians show; hold it while the camera moves for bullet time"),
    ("Gaussians", "NodeSocketInt", 1, 1, None, "Number of Gaussians N (set on load; do not change)"),
    ("Samples", "NodeSocketInt", 2, 2, None, "Number of stored time samples K (set on load; do not change)"),
    ("Start Time", "NodeSocketFloat", 0.0, None, None, "Capture time of the first stored sample (s)"),
    ("End Time", "NodeSocketFloat", 1.0, None, None, "Capture time of the last stored sample (s)"),
    ("Size", "NodeSocketFloat", 1.0, 0.0, None, "Multiplier on every Gaussian's extent"),
    ("Use Scene Time", "NodeSocketBool", False, None, None,
     "Ignore Capture Time and follow the scene's playback time (seconds, frame / fps)"),
]


# ----------------------------------------------------------------------------- mesh cache

def build_sample_mesh(name: str, samples: dict):
    """Mesh of N*K vertices with the attributes listed in the module docstring, from the
    engine's sample arrays (``Scene4D.sample``)."""
    means = np.asarray(samples["means"], dtype=np.float32)
    K, N = means.shape[:2]
    quats = np.asarray(samples[A.ROT.sample_key], dtype=np.float32).reshape(K * N, 4)
    norm = np.linalg.norm(quats, axis=1, keepdims=True)
    quats = np.where(norm > 0, quats / np.maximum(norm, 1e-12), np.array([1, 0, 0, 0], np.float32))
    # keep consecutive samples of one Gaussian in the same hemisphere (short-way slerp)
    q = quats.reshape(K, N, 4)
    for k in range(1, K):
        flip = np.sum(q[k] * q[k - 1], axis=1) < 0
        q[k, flip] *= -1
    scales = np.asarray(samples[A.SCALE.sample_key], dtype=np.float32).reshape(K * N, 3)
    opac = np.clip(np.asarray(samples[A.OPACITY.sample_key], dtype=np.float32).reshape(K * N), 0.0, 1.0)
    col = np.asarray(samples[A.COLOUR.sample_key], dtype=np.float32).reshape(K * N, 3)
    lin = np.clip(srgb_to_linear(np.clip(col, 0.0, None)), 0.0, None).astype(np.float32)
    rgba = np.concatenate([lin, np.ones((K * N, 1), np.float32)], axis=1)

    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(K * N)
    mesh.vertices.foreach_set("co", means.reshape(-1))
    values = {A.ROT: q, A.SCALE: scales, A.OPACITY: opac, A.COLOUR: rgba}
    for attr in A.POINT_ATTRIBUTES:
        a = mesh.attributes.new(attr.name, attr.data_type, "POINT")
        a.data.foreach_set(attr.value_key, values[attr].reshape(-1))
    mesh.update()
    mesh[A.NUM_GAUSSIANS] = int(N)
    mesh[A.NUM_SAMPLES] = int(K)
    mesh[A.SAMPLE_TIMES] = [float(t) for t in samples["times"]]
    return mesh


# ----------------------------------------------------------------------------- node group

class _Builder:
    def __init__(self, tree):
        self.tree = tree
        self.x = 0

    def node(self, idname, location=(0, 0), **props):
        n = self.tree.nodes.new(idname)
        n.location = location
        for k, v in props.items():
            setattr(n, k, v)
        return n

    def link(self, out_socket, in_socket):
        self.tree.links.new(out_socket, in_socket)

    def math(self, op, a, b=None, loc=(0, 0), clamp=False):
        n = self.node("ShaderNodeMath", loc, operation=op, use_clamp=clamp)
        self._feed(n.inputs[0], a)
        if b is not None:
            self._feed(n.inputs[1], b)
        return n.outputs[0]

    def _feed(self, sock, v):
        if hasattr(v, "is_output") or hasattr(v, "links"):
            self.link(v, sock)
        else:
            sock.default_value = v


def _sock(node, name, data_type=None, is_output=False):
    """Socket by name among the enabled ones (Mix/Sample Index have one per data type)."""
    coll = node.outputs if is_output else node.inputs
    for s in coll:
        if s.name == name and s.enabled:
            return s
    raise KeyError(f"{node.bl_idname} has no enabled {'output' if is_output else 'input'} {name!r}")


def ensure_node_group(material=None):
    """The shared "BT4D Gaussians" node group (created on first use)."""
    tree = bpy.data.node_groups.get(GROUP_NAME)
    if tree is not None and tree.bl_idname == "GeometryNodeTree" and tree.get("bt4d_version") == 1:
        if material is not None:
            for n in tree.nodes:
                if n.bl_idname == "GeometryNodeSetMaterial":
                    n.inputs["Material"].default_value = material
        return tree
    tree = bpy.data.node_groups.new(GROUP_NAME, "GeometryNodeTree")
    tree["bt4d_version"] = 1
    iface = tree.interface
    iface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    for name, stype, default, lo, hi, desc in _INPUTS:
        s = iface.new_socket(name, in_out="INPUT", socket_type=stype)
        s.default_value = default
        s.description = desc
        if name in TIME_INPUTS:
            s.subtype = "TIME_ABSOLUTE"  # shown with its unit (s), as Blender shows times
        if lo is not None:
            s.min_value = lo
        if hi is not None:
            s.max_value = hi
    iface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")

    b = _Builder(tree)
    gi = b.node("NodeGroupInput", (-1600, 0))
    go = b.node("NodeGroupOutput", (1400, 0))
    out = lambda name: gi.outputs[name]  # noqa: E731

    # time -> (k, frac)
    scene_time = b.node("GeometryNodeInputSceneTime", (-1600, 300))
    sw = b.node("GeometryNodeSwitch", (-1400, 300), input_type="FLOAT")
    b.link(out("Use Scene Time"), sw.inputs["Switch"])
    b.link(out(CAPTURE_TIME), sw.inputs["False"])
    b.link(scene_time.outputs["Seconds"], sw.inputs["True"])
    T = sw.outputs[0]
    span = b.math("SUBTRACT", out("End Time"), out("Start Time"), (-1200, 200))
    span = b.math("MAXIMUM", span, 1e-9, (-1000, 200))
    rel = b.math("SUBTRACT", T, out("Start Time"), (-1200, 350))
    u01 = b.math("DIVIDE", rel, span, (-900, 300), clamp=True)
    km1 = b.math("SUBTRACT", out("Samples"), 1.0, (-1000, 450))
    u = b.math("MULTIPLY", u01, km1, (-800, 300))
    km2 = b.math("SUBTRACT", out("Samples"), 2.0, (-800, 450))
    k = b.math("MINIMUM", b.math("FLOOR", u, None, (-650, 300)), km2, (-500, 300))
    k = b.math("MAXIMUM", k, 0.0, (-350, 300))
    frac = b.math("SUBTRACT", u, k, (-200, 350))
    base = b.math("MULTIPLY", k, out("Gaussians"), (-200, 200))

    index = b.node("GeometryNodeInputIndex", (-350, 50))
    idx0 = b.math("ADD", index.outputs[0], base, (0, 150))
    idx1 = b.math("ADD", idx0, out("Gaussians"), (150, 150))

    def sampled(data_type, value_socket_fn, mix_type, y):
        """Interpolated field of one attribute: Sample Index at idx0/idx1 + Mix by frac."""
        vals = []
        for j, idx in enumerate((idx0, idx1)):
            si = b.node("GeometryNodeSampleIndex", (300 + 200 * j, y), data_type=data_type, domain="POINT")
            b.link(out("Geometry"), si.inputs["Geometry"])
            b.link(value_socket_fn(), _sock(si, "Value"))
            b.link(idx, si.inputs["Index"])
            vals.append(_sock(si, "Value", is_output=True))
        mix = b.node("ShaderNodeMix", (750, y), data_type=mix_type)
        if mix_type == "VECTOR":
            mix.factor_mode = "UNIFORM"
        b.link(frac, _sock(mix, "Factor"))
        b.link(vals[0], _sock(mix, "A"))
        b.link(vals[1], _sock(mix, "B"))
        return _sock(mix, "Result", is_output=True)

    def named(name, data_type):
        def make():
            n = b.node("GeometryNodeInputNamedAttribute", (100, 0), data_type=data_type)
            n.inputs["Name"].default_value = name
            return _sock(n, "Attribute", is_output=True)
        return make

    def position():
        return b.node("GeometryNodeInputPosition", (100, 0)).outputs[0]

    pos = sampled("FLOAT_VECTOR", position, "VECTOR", -100)
    rot = sampled(A.ROT.data_type, named(A.ROT.name, A.ROT.data_type), "ROTATION", -300)
    scl = sampled(A.SCALE.data_type, named(A.SCALE.name, A.SCALE.data_type), "VECTOR", -500)
    opa = sampled(A.OPACITY.data_type, named(A.OPACITY.name, A.OPACITY.data_type), "FLOAT", -700)
    col = sampled(A.COLOUR.data_type, named(A.COLOUR.name, A.COLOUR.data_type), "RGBA", -900)

    pts = b.node("GeometryNodePoints", (300, 300))
    b.link(out("Gaussians"), pts.inputs["Count"])
    b.link(pos, pts.inputs["Position"])
    pts.inputs["Radius"].default_value = 0.01
    geo = pts.outputs[0]
    # stored on the points: the material reads them as instancer attributes
    for attr, field, x in ((A.OPACITY, opa, 950), (A.COLOUR, col, 1050)):
        st = b.node("GeometryNodeStoreNamedAttribute", (x, 300), data_type=attr.data_type, domain="POINT")
        st.inputs["Name"].default_value = attr.name
        b.link(geo, st.inputs["Geometry"])
        b.link(field, _sock(st, "Value"))
        geo = st.outputs[0]

    ico = b.node("GeometryNodeMeshIcoSphere", (800, 600))
    ico.inputs["Radius"].default_value = ELLIPSOID_RADIUS
    # lighter ellipsoids in the viewport (42 instead of 162 vertices each) for playback
    is_vp = b.node("GeometryNodeIsViewport", (400, 700))
    detail = b.node("GeometryNodeSwitch", (600, 700), input_type="INT")
    b.link(is_vp.outputs[0], detail.inputs["Switch"])
    detail.inputs["False"].default_value = ICO_SUBDIVISIONS
    detail.inputs["True"].default_value = VIEWPORT_SUBDIVISIONS
    b.link(detail.outputs[0], ico.inputs["Subdivisions"])
    setmat = b.node("GeometryNodeSetMaterial", (1000, 600))
    b.link(ico.outputs["Mesh"], setmat.inputs["Geometry"])
    if material is not None:
        setmat.inputs["Material"].default_value = material

    size = b.node("ShaderNodeVectorMath", (1000, -500), operation="SCALE")
    b.link(scl, size.inputs[0])
    b.link(out("Size"), size.inputs["Scale"])

    iop = b.node("GeometryNodeInstanceOnPoints", (1200, 300))
    b.link(geo, iop.inputs["Points"])
    b.link(setmat.outputs[0], iop.inputs["Instance"])
    b.link(rot, iop.inputs["Rotation"])
    b.link(size.outputs[0], iop.inputs["Scale"])
    b.link(iop.outputs[0], go.inputs[0])
    return tree


def input_identifier(tree, name: str) -> str:
    for item in tree.interface.items_tree:
        if getattr(item, "in_out", None) == "INPUT" and item.name == name:
            return item.identifier
    raise KeyError(name)


def set_modifier_input(obj, name: str, value) -> None:
    mod = obj.modifiers[MODIFIER_NAME]
    mod[input_identifier(mod.node_group, name)] = value


def get_modifier_input(obj, name: str):
    mod = obj.modifiers[MODIFIER_NAME]
    return mod[input_identifier(mod.node_group, name)]


def capture_time_data_path(obj) -> str:
    mod = obj.modifiers[MODIFIER_NAME]
    return f'modifiers["{MODIFIER_NAME}"]["{input_identifier(mod.node_group, CAPTURE_TIME)}"]'


def build_result_object(name: str, samples: dict, collection=None, material=None):
    """Mesh cache + object + GN modifier. Returns the object (Capture Time not keyed)."""
    mesh = build_sample_mesh(name, samples)
    obj = bpy.data.objects.new(name, mesh)
    (collection or bpy.context.scene.collection).objects.link(obj)
    material = material or gaussian_material.ensure_material()
    tree = ensure_node_group(material)
    mod = obj.modifiers.new(MODIFIER_NAME, "NODES")
    mod.node_group = tree
    K, N = np.asarray(samples["means"]).shape[:2]
    times = samples["times"]
    set_modifier_input(obj, "Gaussians", int(N))
    set_modifier_input(obj, "Samples", int(K))
    set_modifier_input(obj, "Start Time", float(times[0]))
    set_modifier_input(obj, "End Time", float(times[-1]))
    set_modifier_input(obj, CAPTURE_TIME, float(times[0]))
    obj[A.IS_RESULT] = True
    obj[A.TIME_RANGE] = [float(times[0]), float(times[-1])]
    return obj


# ----------------------------------------------------------------------------- animation

def _channelbag(obj):
    """The object's action channelbag (Blender 4.4+ layered actions; 5.0 has no Action.fcurves)."""
    ad = obj.animation_data or obj.animation_data_create()
    if ad.action is None:
        ad.action = bpy.data.actions.new(f"{obj.name} Action")
    action = ad.action
    if ad.action_slot is None:
        slot = action.slots.new(id_type="OBJECT", name=obj.name)
        ad.action_slot = slot
    return anim_utils.action_ensure_channelbag_for_slot(action, ad.action_slot)


def capture_time_fcurve(obj, create: bool = False):
    ad = obj.animation_data
    path = capture_time_data_path(obj)
    if ad is None or ad.action is None or ad.action_slot is None:
        if not create:
            return None
    if create:
        cb = _channelbag(obj)
    else:
        cb = anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot)
        if cb is None:
            return None
    fc = cb.fcurves.find(path)
    if fc is None and create:
        fc = cb.fcurves.new(path)
    return fc


def key_capture_time(obj, keys, interpolation: str = "LINEAR", replace: bool = True):
    """Key Capture Time: ``keys`` is [(frame, seconds), ...]. Linear interpolation and
    constant extrapolation (the value holds before the first and after the last key)."""
    fc = capture_time_fcurve(obj, create=True)
    if replace:
        fc.keyframe_points.clear()
    for frame, value in keys:
        kp = fc.keyframe_points.insert(float(frame), float(value), options={"FAST"})
        kp.interpolation = interpolation
    for kp in fc.keyframe_points:
        kp.interpolation = interpolation
    fc.extrapolation = "CONSTANT"
    fc.update()
    return fc


def key_realtime(obj, scene, t0: float, t1: float, frame_start: int | None = None):
    """Default animation: Capture Time follows frame / fps (real time) from ``frame_start``;
    returns the last frame covered."""
    fps = scene.render.fps / scene.render.fps_base
    fs = scene.frame_start if frame_start is None else frame_start
    fe = fs + (t1 - t0) * fps
    key_capture_time(obj, [(fs, t0), (fe, t1)])
    return fe


def capture_time_at(obj, frame: float) -> float:
    """Capture Time the object shows at ``frame`` (F-curve when keyed, else the value)."""
    fc = capture_time_fcurve(obj)
    if fc is not None and len(fc.keyframe_points):
        return float(fc.evaluate(frame))
    if bool(get_modifier_input(obj, "Use Scene Time")):
        scene = bpy.context.scene
        return float(frame) * scene.render.fps_base / scene.render.fps
    return float(get_modifier_input(obj, CAPTURE_TIME))


def find_result_objects(scene):
    return [o for o in scene.objects if o.get(A.IS_RESULT) and MODIFIER_NAME in o.modifiers]


def pick_result_object(context):
    """The active reconstruction object, else the scene's first one, else None."""
    results = find_result_objects(context.scene)
    if not results:
        return None
    obj = context.active_object
    return obj if obj in results else results[0]
