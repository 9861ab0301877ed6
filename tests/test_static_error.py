"""tools/static_error.py: a run's static-pixel loss split into in front of the true surface / on it."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from engine.io.capture import load_capture
from engine.io.images import write_exr, write_png

W, H, DEPTH = 12, 8, 2.0
GREY = 0.5


def _script(repo_root):
    spec = importlib.util.spec_from_file_location("static_error", repo_root / "tools" / "static_error.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _c2w(x: float) -> list:
    m = np.eye(4)
    m[0, 3], m[2, 3] = x, 3.0
    return m.tolist()


def _frame(root: Path, cam: str, i: int, t: float, x: float, depth: bool) -> dict:
    rel = f"rgb/{cam}/{i:06d}.png"
    (root / rel).parent.mkdir(parents=True, exist_ok=True)
    img = np.full((H, W, 3), GREY, np.float32)
    img[0:2, 0:2] = 0.1 + 0.4 * i  # a corner that changes: not static
    write_png(root / rel, img)
    rec = {"file_path": rel, "camera": cam, "time": t, "transform_matrix": _c2w(x)}
    if depth:
        drel = f"depth/{cam}/{i:06d}.exr"
        (root / drel).parent.mkdir(parents=True, exist_ok=True)
        write_exr(root / drel, {"Z": np.full((H, W), DEPTH, np.float32)})
        rec["depth_file_path"] = drel
    return rec


def make_capture(root: Path, depth: bool = True) -> Path:
    """Two train cameras at RGB instants 0 and 0.1; one eval camera at 0, 0.05 (between) and 0.1."""
    cams = {n: {"w": W, "h": H, "fl_x": 10.0, "fl_y": 10.0, "cx": W / 2, "cy": H / 2,
                "role": "eval" if n == "eval0" else "train"} for n in ("rgb0", "rgb1", "eval0")}
    pair = (("rgb0", -0.1), ("rgb1", 0.1))
    frames = [_frame(root, n, i, t, x, depth) for i, t in enumerate((0.0, 0.1)) for n, x in pair]
    evals = [_frame(root, "eval0", i, t, 0.0, depth) for i, t in enumerate((0.0, 0.05, 0.1))]
    (root / "transforms.json").write_text(json.dumps({"version": 1, "cameras": cams, "frames": frames,
                                                      "eval_frames": evals}))
    return root


class Fake:
    """Renders the truth, with a floater (colour ``floater`` at half the depth) over ``front`` and a
    repainted colour at the true depth over ``repaint``."""

    def __init__(self, cap, floater=None, repaint=None):
        self.cap, self.floater, self.repaint = cap, floater, repaint

    def render(self, views, **_):
        frame = min(self.cap.eval_frames, key=lambda f: abs(f.time - views[0].time))
        rgb, depth = frame.load_rgb().astype(np.float32), np.full((H, W), DEPTH, np.float32)
        if self.floater is not None:
            rgb[4:8, 0:4], depth[4:8, 0:4] = self.floater, DEPTH / 2
        if self.repaint is not None:
            rgb[4:8, 8:12] = self.repaint
        return [{"rgb": rgb, "depth": depth, "alpha": np.ones((H, W), np.float32)}]


def test_depth_classes_partition_the_pixels_with_a_true_depth(repo_root):
    mod = _script(repo_root)
    true = np.array([[2.0, 2.0, 2.0, np.inf]])
    cls = mod.depth_classes(np.array([[1.0, 2.05, 3.0, 1.0]]), true, 0.05)
    assert cls["front"].tolist() == [[True, False, False, False]]
    assert cls["surface"].tolist() == [[False, True, False, False]]
    assert cls["behind"].tolist() == [[False, False, True, False]]


def test_extra_error_splits_into_the_floater_and_the_repaint(repo_root, tmp_path, monkeypatch, capsys):
    mod = _script(repo_root)
    cap = load_capture(make_capture(tmp_path / "cap"))
    floater, repaint = 0.8, 0.3  # squared errors 0.09 and 0.04 per channel, 16 pixels each
    runs = {"truth": Fake(cap), "both": Fake(cap, floater=floater, repaint=repaint)}
    monkeypatch.setattr(mod, "load_run", lambda run, device="cpu": runs[run])
    mod.main([str(tmp_path / "cap"), "truth", "both"])
    out = capsys.readouterr().out
    rows = [ln for ln in out.splitlines() if ln.startswith("| eval0")]
    assert [r.split("|")[2].strip() for r in rows] == ["inst", "between"]
    for r in rows:
        cells = [c.strip() for c in r.split("|")]
        shares = [float(x) for x in cells[6].split("/")]
        e_front, e_surface = (floater - GREY) ** 2, (repaint - GREY) ** 2
        assert shares == pytest.approx([e_front / (e_front + e_surface), e_surface / (e_front + e_surface), 0.0],
                                       abs=0.01)
        static = H * W - 4
        assert float(cells[5].rstrip("%")) == pytest.approx(100 * 16 / static, abs=0.1)  # B's static px in front
        bias_b = [float(v) for v in cells[7].split()]
        assert bias_b == pytest.approx([16 * (repaint - GREY) / (static - 16)] * 3, abs=2e-3)  # PNG rounding
        assert float(cells[3]) > 60 > float(cells[4])  # the truth scores near-perfectly, B does not


def test_a_capture_without_depth_is_refused_with_the_file_named(repo_root, tmp_path):
    mod = _script(repo_root)
    make_capture(tmp_path / "cap", depth=False)
    with pytest.raises(SystemExit, match=r"000000\.png: static-error needs eval frames with ground-truth depth"):
        mod.main([str(tmp_path / "cap"), "a", "b"])
