"""python -m tools time-to-result (issue 43): every stage from train to a scored, exported run with
its seconds and peak memory, and the new-view PSNR curve, on a tiny run of the demo capture."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_time_to_result_reports_every_stage_and_a_curve(demo_capture, tmp_path):
    out = tmp_path / "ttr"
    r = subprocess.run([sys.executable, "-m", "tools", "time-to-result", str(demo_capture), "--out", str(out),
                        "--set", "schedule.iterations=30", "--set", "schedule.checkpoint_every_s=0.5",
                        "--eval-every", "0.5", "--eval-stride", "8"],
                       cwd=REPO, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    rep = json.loads((out / "time_to_result.json").read_text())
    stages = " | ".join(s["stage"] for s in rep["stages"])
    for name in ("loading the capture", "stereo", "initial Gaussians", "static stage", "deformation stage",
                 "evaluation", "export"):
        assert name in stages, stages
    assert all(s["seconds"] >= 0 for s in rep["stages"])
    assert rep["steps"] == 30 and rep["peak_rss_mb"] > 0
    assert rep["curve"] and rep["curve"][-1]["step"] == 30 and 5 < rep["curve"][-1]["psnr"] < 60
    assert rep["final"]["psnr"] > 5 and rep["final"]["lpips"] is not None
    assert (out / "result.bt4c").exists()
    assert "| stage | seconds | peak memory MB |" in (out / "time_to_result.md").read_text()
