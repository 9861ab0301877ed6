#!/usr/bin/env python
"""Build (and validate) the extension zip without a Blender binary.

``blender --command extension build`` runs Blender's ``bl_pkg`` command line module,
``blender_ext.py``, which is plain Python. The ``bpy`` wheel ships the same file, so this
script runs it directly: same manifest validation, same ``[build]`` rules
(``paths_exclude_pattern``), same zip layout.

    .venv/bin/python scripts/build_extension.py                 # -> dist/bullettime4d-<version>.zip
    .venv/bin/python scripts/build_extension.py --output-dir dist
    .venv/bin/python scripts/build_extension.py --validate-only
"""
from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def blender_ext_cli() -> Path:
    """Path of Blender's ``bl_pkg/cli/blender_ext.py`` inside the installed bpy module."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.origin:
        raise SystemExit("the bpy module is not installed (pip install bpy)")
    found = sorted(Path(spec.origin).parent.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        raise SystemExit(f"no bl_pkg/cli/blender_ext.py under {Path(spec.origin).parent}")
    return found[-1]


def run_cli(*args: str) -> int:
    return subprocess.run([sys.executable, str(blender_ext_cli()), *args], cwd=str(REPO)).returncode


def zip_name() -> str:
    with open(REPO / "blender_manifest.toml", "rb") as fh:
        m = tomllib.load(fh)
    return f"{m['id']}-{m['version']}.zip"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--output-dir", type=Path, default=REPO / "dist")
    ap.add_argument("--validate-only", action="store_true", help="only validate the manifest")
    args = ap.parse_args(argv)
    rc = run_cli("validate", str(REPO))
    if rc or args.validate_only:
        return rc
    args.output_dir.mkdir(parents=True, exist_ok=True)
    rc = run_cli("build", "--source-dir", str(REPO), "--output-dir", str(args.output_dir.resolve()))
    if rc == 0:
        print(f"built {args.output_dir.resolve() / zip_name()}")
    return rc


if __name__ == "__main__":
    sys.exit(main())
