"""tools/phase_psnr.py: eval PSNR split by pixel class (far / near / moving) and interval phase."""
from __future__ import annotations

import importlib.util
import re

import numpy as np


def _script(repo_root):
    spec = importlib.util.spec_from_file_location("phase_psnr", repo_root / "tools" / "phase_psnr.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_phases_bin_the_place_in_the_interval(repo_root):
    mod = _script(repo_root)
    ts = [0.0, 0.1, 0.2]
    assert [mod.phase_of(t, ts) for t in (0.0, 0.1, 0.2, 0.25, 0.01, 0.185, 0.03, 0.05, 0.16)] == [
        "inst", "inst", "inst", "inst", "q1", "q1", "q2", "half", "half"]


def test_classes_partition_the_pixels_and_their_error(repo_root):
    mod = _script(repo_root)
    rng = np.random.default_rng(0)
    gt, pred = rng.random((40, 60, 3)), rng.random((40, 60, 3))
    moving = np.zeros((40, 60), bool)
    moving[18:22, 28:32] = True
    out = mod.split_errors(pred, gt, moving, near_px=3)
    assert out["moving"][1] == 16 and out["near"][1] == 10 * 10 - 16 and out["all"][1] == 40 * 60
    assert out["far"][1] + out["near"][1] + out["moving"][1] == out["all"][1]
    assert np.isclose(out["far"][0] + out["near"][0] + out["moving"][0], out["all"][0])
    assert np.isclose(out["all"][0], ((pred - gt) ** 2).mean(-1).sum())


def test_main_prints_a_table_per_run_over_the_demos_eval_frames(repo_root, demo_capture, monkeypatch, capsys):
    mod = _script(repo_root)

    class Grey:
        def __init__(self, level):
            self.level = level

        def render(self, views, **_):
            v = views[0]
            return [{"rgb": np.full((v.intrinsics.height, v.intrinsics.width, 3), self.level, np.float32)}]

    runs = {"mid": Grey(0.45), "white": Grey(1.0)}
    monkeypatch.setattr(mod, "load_run", lambda run, device="cpu": runs[run])
    mod.main([str(demo_capture), "mid", "white"])
    out = capsys.readouterr().out
    tables = out.strip().split("\n\n")
    assert len(tables) == 2
    vals = []
    for t in tables:
        rows = [ln for ln in t.splitlines() if ln.startswith("| ") and not ln.startswith("| phase")]
        assert [r.split("|")[1].strip() for r in rows] == ["inst", "q1", "q2", "half"]
        vals.append([[float(x) for x in re.findall(r"[0-9]+\.[0-9]+", r)] for r in rows])
        assert all(len(r) == 4 for r in vals[-1])
    assert all(a > b for ra, rb in zip(*vals) for a, b in zip(ra, rb))  # mid grey beats white everywhere
