"""tools steps-curve: real training at multiples of the preset's steps on a tiny capture, the table,
the collapse verdict and the plot."""
from __future__ import annotations

import json
from types import SimpleNamespace

from tools import steps_curve
from tools.__main__ import COMMANDS
from tools.synthetic import write_synthetic_capture

TINY = dict(width=40, height=32, n_rgb=3, eval_fps=60.0)  # LPIPS needs 31 px or more


def test_collapse_is_marked_against_the_smallest_multiple():
    rows = [{"capture": "a", "multiple": m, "psnr": p, "psnr_interframe": b, "lpips": lp}
            for m, p, b, lp in ((1, 20.0, 19.0, 0.20), (2, 20.3, 19.2, 0.19), (4, 20.0, 18.85, 0.20),
                                (8, 20.5, 19.5, 0.21))]
    rows += [{"capture": "b", "multiple": 1, "psnr": 25.0, "psnr_interframe": None, "lpips": None}]
    out = {(r["capture"], r["multiple"]): r for r in steps_curve.mark_collapse(rows)}
    assert not out["a", 1]["collapse"] and not out["a", 2]["collapse"] and out["a", 2]["d_psnr"] == 0.3
    assert out["a", 4]["collapse"] and out["a", 4]["d_between"] == -0.15  # between frames fell 0.15 dB
    assert out["a", 8]["collapse"] and out["a", 8]["d_lpips"] == 0.01    # PSNR up, LPIPS worse: still a collapse
    assert not out["b", 1]["collapse"] and out["b", 1]["d_between"] is None


def test_steps_curve_trains_each_multiple_and_reports(tmp_path, capsys):
    assert COMMANDS["steps-curve"] == "steps_curve"
    cap = write_synthetic_capture(tmp_path / "cap", with_points=True, **TINY)
    args = SimpleNamespace(captures=[str(cap)], out=str(tmp_path / "sc"), multiples="2,1", preset="fast",
                           rgb_only=True, seed=0, device="cpu", resume=False,
                           overrides=["iterations=8", "init_max_points=300", "static_fraction=0.5"])
    assert steps_curve.main(args) == 0
    report = json.loads((tmp_path / "sc" / "steps_curve.json").read_text())
    assert [r["multiple"] for r in report["rows"]] == [1.0, 2.0] and [r["steps"] for r in report["rows"]] == [8, 16]
    for r in report["rows"]:  # real runs, scored at the eval camera
        run = tmp_path / "sc" / "cap" / f"x{r['multiple']:g}"
        info = json.loads((run / "run.json").read_text())
        assert info["step"] == r["steps"] and info["config"]["schedule"]["iterations"] == 8  # 2x: 8 settle
        assert 5.0 < r["psnr"] < 60.0 and r["lpips"] is not None
    assert report["rows"][0]["d_psnr"] == 0.0 and "collapse" in capsys.readouterr().out
    assert (tmp_path / "sc" / "steps_curve.png").stat().st_size > 10_000
    md = (tmp_path / "sc" / "steps_curve.md").read_text()
    assert "16 (x2)" in md and "static between" in md
    # --resume reuses the scored runs: nothing is trained again
    mtime = (tmp_path / "sc" / "cap" / "x1" / "run.json").stat().st_mtime
    args.resume = True
    assert steps_curve.main(args) == 0
    assert (tmp_path / "sc" / "cap" / "x1" / "run.json").stat().st_mtime == mtime


def test_a_bad_capture_is_one_error_line(tmp_path, capsys):
    args = SimpleNamespace(captures=[str(tmp_path / "nowhere")], out=str(tmp_path / "sc"), multiples="1",
                           preset="fast", rgb_only=True, seed=0, device="cpu", resume=False, overrides=None)
    assert steps_curve.main(args) == 1
    err = capsys.readouterr().err
    assert err.strip().splitlines()[-1].startswith("error: ") and "nowhere" in err
