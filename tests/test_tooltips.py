"""Tooltips speak to artists (issue 45): no config field names, paper equations, method names of
other papers or documentation titles in what the sidebar, the operators and the preferences show."""
from __future__ import annotations

import re

import blender_util
import pytest

bpy = pytest.importorskip("bpy")

# what an artist cannot act on: "Eq. 17", paper / method names, config names (a.b or snake_case),
# documentation paths and issue numbers
JARGON = re.compile(r"\bEq\.|\bpaper\b|E-NeMF|CPOStream|DynTCG|BulletTime4D's|README|docs/|issue \d|"
                    r"\b[a-z]+_[a-z_]+\b|\b[a-z]+\.(?!(json|ply|exr|png|bt4c|zip)\b)[a-z_]+\b")


def _rnas():
    blender_util.enable_addon()
    for name in dir(bpy.types):
        if name.startswith("BT4D_OT_"):
            yield name, getattr(bpy.types, name).bl_rna
    scene = bpy.context.scene
    yield "scene.bt4d", scene.bt4d.bl_rna
    yield "scene.bt4d_run", scene.bt4d_run.bl_rna
    yield "preferences", bpy.context.preferences.addons[blender_util.ADDON_MODULE].preferences.bl_rna


def _texts():
    out = []
    for name, rna in _rnas():
        out.append((name, getattr(rna, "description", "") or ""))
        for prop in rna.properties:
            if prop.identifier == "rna_type" or prop.identifier.startswith("bl_"):  # Blender's own
                continue
            out.append((f"{name}.{prop.identifier}", prop.description or ""))
            for item in getattr(prop, "enum_items", []) or []:
                out.append((f"{name}.{prop.identifier}[{item.identifier}]", item.description or ""))
    return out


def test_tooltips_are_plain_language():
    texts = _texts()
    assert len(texts) > 50  # the operators, panels and settings were found
    bad = [(where, text) for where, text in texts if JARGON.search(text)]
    assert not bad, "\n".join(f"{w}: {t}" for w, t in bad)


def test_the_metrics_say_what_a_good_value_is():
    blender_util.enable_addon()
    rna = bpy.context.scene.bt4d_run.bl_rna.properties
    for name in ("metric_psnr", "metric_ssim", "metric_lpips", "metric_psnr_interframe", "metric_psnr_dynamic"):
        text = rna[name].description
        assert "better" in text and re.search(r"\d", text), (name, text)
