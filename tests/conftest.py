"""Shared test fixtures. The repo root is put on sys.path so `import engine` works."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

DEMO_CAPTURE = REPO_ROOT / "demo_capture"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture(scope="session")
def demo_capture() -> Path:
    if not (DEMO_CAPTURE / "transforms.json").exists():
        pytest.fail(f"demo capture missing at {DEMO_CAPTURE}; run scripts/make_capture.py")
    return DEMO_CAPTURE
