"""tools/spike_view_psnr.py: scores runs at the spike camera against the generator's light."""
from __future__ import annotations

import importlib.util
import json
import re
import types

import numpy as np
import torch

from engine.colour import linear_to_srgb


def _script(repo_root):
    spec = importlib.util.spec_from_file_location("spike_view_psnr", repo_root / "tools" / "spike_view_psnr.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


class _Grey:
    """A 'model' rendering a uniform sRGB grey at every view and time."""

    def __init__(self, level):
        self.level = level

    def render(self, vt, t=None, **_):
        return (torch.full((1, vt["height"], vt["width"], 3), self.level),)


def test_spike_view_psnr_scores_the_spike_view_between_and_at_rgb_instants(repo_root, demo_capture, tmp_path,
                                                                        monkeypatch, capsys):
    mod = _script(repo_root)
    lin = 0.2
    light = np.full((201, 60, 80), lin, np.float32)
    light[:, :, :40] = lin * 1.5  # the left half brighter: a uniform render cannot match it
    npz = tmp_path / "light.npz"
    np.savez(npz, light=light, key=np.array(json.dumps({"light_hz": 1000.0})))
    grey = float(linear_to_srgb(np.float32(lin)))
    runs = {"right": _Grey(grey), "wrong": _Grey(0.9)}
    monkeypatch.setattr(mod, "load_run", lambda run: types.SimpleNamespace(model=runs[run]))
    assert mod.main([str(demo_capture), str(npz), "right", "wrong", "--stride", "5"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    vals = [[float(v) for v in re.findall(r"(?:instants|them) ([0-9.]+)", line)] for line in out]
    (r_key, r_between), (w_key, w_between) = vals
    assert r_key > w_key + 6 and r_between > w_between + 6
    assert 10 < r_key < 40 and abs(r_key - r_between) < 0.5  # the same error at every instant
