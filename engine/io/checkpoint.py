"""Atomic checkpoints and the run directory's ``run.json``.

A checkpoint is written to a temporary file in the same directory and moved over the old
one with ``os.replace`` (atomic on POSIX and Windows), so a crash or a kill at any moment
leaves either the previous good checkpoint or the new one, never a torn file. The previous
good checkpoint is kept as ``checkpoint.prev.pt`` and used if the newest one is unreadable.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch

from ..errors import RunError
from .fileio import atomic_write

CHECKPOINT = "checkpoint.pt"
PREVIOUS = "checkpoint.prev.pt"
RUN_JSON = "run.json"
FORMAT_VERSION = 1


def save_checkpoint(run_dir: str | Path, state: dict) -> Path:
    """Write ``state`` atomically to RUN/checkpoint.pt, keeping the last good one as .prev."""
    run_dir = Path(run_dir)
    path = run_dir / CHECKPOINT
    state = {"format_version": FORMAT_VERSION, **state}
    if path.exists():
        # keep the last good checkpoint: hard link (cheap) or copy before replacing
        prev = run_dir / PREVIOUS
        try:
            tmp_prev = run_dir / f".{PREVIOUS}.link"
            if tmp_prev.exists():
                tmp_prev.unlink()
            os.link(path, tmp_prev)
            os.replace(tmp_prev, prev)
        except OSError:
            pass
    atomic_write(path, lambda fh: torch.save(state, fh))
    return path


def load_checkpoint(run_dir: str | Path, map_location="cpu") -> dict:
    """Load RUN/checkpoint.pt (falling back to the previous good one); RunError if none."""
    run_dir = Path(run_dir)
    errors = []
    for name in (CHECKPOINT, PREVIOUS):
        path = run_dir / name
        if not path.exists():
            continue
        try:
            state = torch.load(path, map_location=map_location, weights_only=False)
        except Exception as exc:  # torn / corrupt file
            errors.append(f"{name}: {exc.__class__.__name__}: {exc}")
            continue
        if not isinstance(state, dict) or "gaussians" not in state:
            errors.append(f"{name}: not a BulletTime4D checkpoint")
            continue
        return state
    if not run_dir.exists():
        raise RunError(run_dir, "run directory does not exist")
    if errors:
        raise RunError(run_dir / CHECKPOINT, "checkpoint unreadable (" + "; ".join(errors) + ")")
    raise RunError(run_dir / CHECKPOINT, "no checkpoint in this run directory (train it first)")


def write_json(path: str | Path, data: dict) -> None:
    path = Path(path)
    text = json.dumps(data, indent=2, sort_keys=False, default=_json_default)
    atomic_write(path, lambda fh: fh.write(text.encode("utf-8")))


def _json_default(o):
    try:

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:
        pass
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def read_run_json(run_dir: str | Path) -> dict:
    path = Path(run_dir) / RUN_JSON
    if not path.exists():
        raise RunError(path, "missing run.json (is this a run directory?)")
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise RunError(path, f"unreadable run.json: {exc}") from exc


def update_run_json(run_dir: str | Path, **fields) -> dict:
    path = Path(run_dir) / RUN_JSON
    data = {}
    if path.exists():
        try:
            data = json.loads(path.read_text())
        except ValueError:
            data = {}
    data.update(fields)
    write_json(path, data)
    return data
