"""The Gaussian splat material (Cycles and EEVEE).

Every Gaussian is an ico-sphere instance whose object space is the Gaussian's
sigma-normalised space (the instance is rotated by the Gaussian's quaternion and scaled by
its sigmas, so the Gaussian is the unit isotropic one there, and the sphere's surface sits
at 3 sigma). For the ray through a shading point ``o`` (object space) with direction ``d``
(the world incoming vector brought to object space, not normalised), the squared
sigma-distance of the ray's closest approach to the centre is

    d2 = |o|^2 - (o . d)^2 / |d|^2

and the peak Gaussian response along the ray gives the splat's alpha:

    alpha = opacity * exp(-0.5 * d2)      (0 on back faces, so each Gaussian counts once)

The surface is ``mix(Transparent, Emission(colour), alpha)``: emission, not diffuse, so it
matches the engine's unlit splats under the Standard view transform. Colours are stored
linear (decoded from the engine's sRGB-encoded colours on load) and read from the
instancer attributes ``bt4d_color`` / ``bt4d_opacity``.
"""
from __future__ import annotations

import bpy

from .attributes import COLOUR, OPACITY

MATERIAL_NAME = "BT4D Gaussian"
ALPHA_MAX = 0.99  # the engine's (3DGS) alpha cap


def ensure_material():
    mat = bpy.data.materials.get(MATERIAL_NAME)
    if mat is not None and mat.get("bt4d_version") == 1:
        return mat
    mat = bpy.data.materials.new(MATERIAL_NAME)
    mat["bt4d_version"] = 1
    if mat.node_tree is None:  # Blender < 5: node trees are opt-in
        mat.use_nodes = True
    tree = mat.node_tree
    tree.nodes.clear()
    N, L = tree.nodes, tree.links

    def node(idname, loc, **props):
        n = N.new(idname)
        n.location = loc
        for k, v in props.items():
            setattr(n, k, v)
        return n

    def math(op, a, b=None, loc=(0, 0), clamp=False):
        n = node("ShaderNodeMath", loc, operation=op, use_clamp=clamp)
        for sock, v in zip(n.inputs, (a, b)):
            if v is None:
                continue
            if hasattr(v, "is_output"):
                L.new(v, sock)
            else:
                sock.default_value = v
        return n.outputs[0]

    geom = node("ShaderNodeNewGeometry", (-1200, 0))
    to_obj_p = node("ShaderNodeVectorTransform", (-1000, 100), vector_type="POINT",
                    convert_from="WORLD", convert_to="OBJECT")
    to_obj_d = node("ShaderNodeVectorTransform", (-1000, -100), vector_type="VECTOR",
                    convert_from="WORLD", convert_to="OBJECT")
    L.new(geom.outputs["Position"], to_obj_p.inputs[0])
    L.new(geom.outputs["Incoming"], to_obj_d.inputs[0])
    o, d = to_obj_p.outputs[0], to_obj_d.outputs[0]

    def dot(a, b, loc):
        n = node("ShaderNodeVectorMath", loc, operation="DOT_PRODUCT")
        L.new(a, n.inputs[0])
        L.new(b, n.inputs[1])
        return n.outputs["Value"]

    oo = dot(o, o, (-800, 200))
    od = dot(o, d, (-800, 0))
    dd = dot(d, d, (-800, -200))
    od2 = math("MULTIPLY", od, od, (-600, 0))
    q = math("DIVIDE", od2, math("MAXIMUM", dd, 1e-20, (-600, -200)), (-450, 0))
    d2 = math("MAXIMUM", math("SUBTRACT", oo, q, (-300, 100)), 0.0, (-150, 100))
    g = math("EXPONENT", math("MULTIPLY", d2, -0.5, (0, 100)), None, (150, 100))

    opac = node("ShaderNodeAttribute", (-150, -150), attribute_type="INSTANCER", attribute_name=OPACITY.name)
    color = node("ShaderNodeAttribute", (-150, -400), attribute_type="INSTANCER", attribute_name=COLOUR.name)
    a = math("MULTIPLY", g, opac.outputs["Fac"], (300, 50))
    a = math("MINIMUM", a, ALPHA_MAX, (450, 50))
    front = math("SUBTRACT", 1.0, geom.outputs["Backfacing"], (450, -100))
    alpha = math("MULTIPLY", a, front, (600, 50))

    transp = node("ShaderNodeBsdfTransparent", (600, -150))
    emit = node("ShaderNodeEmission", (600, -300))
    L.new(color.outputs["Color"], emit.inputs["Color"])
    emit.inputs["Strength"].default_value = 1.0
    mix = node("ShaderNodeMixShader", (850, 0))
    L.new(alpha, mix.inputs["Fac"])
    L.new(transp.outputs[0], mix.inputs[1])
    L.new(emit.outputs[0], mix.inputs[2])
    out = node("ShaderNodeOutputMaterial", (1050, 0))
    L.new(mix.outputs[0], out.inputs["Surface"])

    # EEVEE: stochastic (dithered) transparency is order independent, which thousands of
    # overlapping splats need; back faces are masked in the shader itself.
    for attr, value in (("surface_render_method", "DITHERED"), ("use_backface_culling", False),
                        ("use_transparency_overlap", True)):
        if hasattr(mat, attr):
            try:
                setattr(mat, attr, value)
            except (TypeError, AttributeError):
                pass
    mat.diffuse_color = (0.8, 0.8, 0.8, 1.0)
    return mat


def configure_scene_for_splats(scene, min_transparent_bounces: int = 256) -> None:
    """Render settings the splats need: enough transparent bounces in Cycles and EEVEE
    settings for many layers of transparency; Standard view transform (the engine's
    colours are display values)."""
    cy = getattr(scene, "cycles", None)
    if cy is not None:
        try:
            cy.transparent_max_bounces = max(int(cy.transparent_max_bounces), min_transparent_bounces)
        except AttributeError:
            pass
    ee = getattr(scene, "eevee", None)
    if ee is not None:
        for attr, value in (("use_shadows", False),):
            if hasattr(ee, attr):
                try:
                    setattr(ee, attr, value)
                except (TypeError, AttributeError):
                    pass
    try:
        scene.view_settings.view_transform = "Standard"
        scene.view_settings.look = "None"
    except TypeError:
        pass
