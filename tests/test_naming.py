"""Spelling of identifiers: *colour*, except the names listed here (docs/architecture.md, Conventions)."""
from __future__ import annotations

import io
import tokenize
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# `color` identifiers that stay: gsplat's API names (the rasterizer mirrors gsplat), names
# stored in files (checkpoint keys, run.json config, the Blender attribute), and bpy /
# matplotlib / trimesh API names.
ALLOWED = {
    "colors", "eval_colors", "render_colors",            # gsplat: rasterization(..., colors)
    "color_head", "deform_color", "color_delta",         # checkpoint / config keys of the colour head
    "ATTR_COLOR",                                        # names the stored Blender attribute bt4d_color
    "color", "color_ramp", "color_mode", "color_depth", "diffuse_color", "vertex_colors",  # bpy, matplotlib, trimesh
}


def _identifiers(path: Path):
    for tok in tokenize.generate_tokens(io.StringIO(path.read_text(encoding="utf-8")).readline):
        if tok.type == tokenize.NAME:
            yield tok.string, tok.start[0]


def test_identifiers_say_colour():
    bad = []
    for folder in ("engine", "tools", "scripts", "tests", "bt4d_addon", "operators"):
        for path in sorted((REPO / folder).rglob("*.py")):
            for name, line in _identifiers(path):
                if "color" in name.lower() and name not in ALLOWED:
                    bad.append(f"{path.relative_to(REPO)}:{line}: {name}")
    assert not bad, "spell these 'colour' (or add a stored/API name to ALLOWED):\n" + "\n".join(bad)
