"""The documentation holds: README is for users and short, every documentation path the code
and the docs cite exists, and no file carries an absolute path of a development machine."""
from __future__ import annotations

import re
import subprocess

import pytest

# absolute paths a development machine writes into files (built here so this file has none)
MACHINE_PATHS = re.compile("(?<![\\w.])(" + "|".join(["/" + p + "/" for p in ("work", "root", "home", "Users", "tmp",
                                                                              "mnt", "opt")]) + r")[\w.+-]")
DOC_PATH = re.compile(r"(?<![\w/.-])docs/[\w./-]*\w\.(?:md|png)")


def _tracked_text_files(repo_root):
    names = subprocess.run(["git", "ls-files"], cwd=repo_root, capture_output=True, text=True, check=True).stdout
    for name in names.split():
        path = repo_root / name
        if not path.is_file() or path.suffix in (".png", ".exr", ".dat", ".npz", ".zip", ".blend"):
            continue
        try:
            yield name, path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue


@pytest.fixture(scope="module")
def files(repo_root):
    try:
        return dict(_tracked_text_files(repo_root))
    except (OSError, subprocess.CalledProcessError) as err:
        pytest.skip(f"not a git checkout: {err}")


def test_readme_is_for_users(repo_root):
    text = (repo_root / "README.md").read_text()
    assert len(text.splitlines()) <= 400
    for needed in ("make demo", "make test", "## Install", "## Blender workflow", "## Headless",
                   "## Command line", "## Reading the metrics", "## Troubleshooting"):
        assert needed in text, needed
    assert "docs/capture_format.md" in text and "docs/architecture.md" in text


def test_every_cited_documentation_path_exists(repo_root, files):
    missing = sorted({(name, m) for name, text in files.items() for m in DOC_PATH.findall(text)
                      if not (repo_root / m).exists()})
    assert not missing, missing
    assert any(DOC_PATH.search(t) for n, t in files.items() if n.startswith("engine/"))  # the code cites docs


def test_no_absolute_path_of_a_development_machine(files):
    found = [(name, line) for name, text in files.items() for line in text.splitlines() if MACHINE_PATHS.search(line)]
    assert not found, found[:20]


def test_the_check_would_catch_them():
    assert MACHINE_PATHS.search("see " + "/work" + "/coord/scenes/fast") and MACHINE_PATHS.search("--out /" + "tmp/x")
    assert not MACHINE_PATHS.search("engine/train/loop/run.py and a/tmp/b")
    assert DOC_PATH.findall("(docs/experiments/quiet-curves.md, x)") == ["docs/experiments/quiet-curves.md"]


def test_licence_file_matches_the_manifest(repo_root):
    """Issue 45: a LICENSE file with the licence the manifest declares."""
    text = (repo_root / "LICENSE").read_text()
    manifest = (repo_root / "blender_manifest.toml").read_text()
    assert "SPDX:GPL-3.0-or-later" in manifest
    assert "GNU GENERAL PUBLIC LICENSE" in text and "Version 3, 29 June 2007" in text
