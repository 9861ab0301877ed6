"""scripts/headless_example.py end to end in a subprocess (its own bpy process): import ->
reconstruct -> load result -> orbit with frozen capture time -> path render -> .blend.

To stay inside the test-time budget the run folder of the shared tiny reconstruction is
copied in first: the script's reconstruct step then resumes a finished checkpoint with the
same settings (no training steps), but still evaluates, brings back and renders.
Training itself is covered by tests/test_reconstruct.py."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys

import blender_util
import numpy as np
import pytest
import roundtrip_util
from roundtrip_util import reconstructed, run_tmp  # noqa: F401  (fixtures)

pytest.importorskip("bpy")


@pytest.mark.slow
def test_headless_example_script(reconstructed, demo_capture, tmp_path):
    from engine.io.images import read_exr_channels

    out = tmp_path / "example"
    shutil.copytree(reconstructed["run_dir"], out / "runs" / demo_capture.name)
    cmd = [sys.executable, str(blender_util.REPO_ROOT / "scripts" / "headless_example.py"),
           "--capture", str(demo_capture), "--out", str(out), "--iterations", str(roundtrip_util.TRAIN_ITERATIONS),
           "--frames", "3", "--turns", "0.5", "--resolution-percentage", "20"]
    proc = subprocess.run(cmd, env=blender_util.isolated_env(), capture_output=True, text=True, timeout=600,
                          cwd=str(blender_util.REPO_ROOT))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    line = next(ln for ln in proc.stdout.splitlines()[::-1] if ln.startswith("RESULT "))
    res = json.loads(line[len("RESULT "):])
    assert res["status"] == "FINISHED" and res["camera"].startswith("BT4D Orbit")
    meta = json.loads((out / "runs" / demo_capture.name / "run.json").read_text())
    assert meta["status"] == "finished"
    assert len(res["frames"]) == 3
    imgs = [read_exr_channels(p) for p in res["frames"]]
    assert imgs[0]["R"].shape == (24, 32) and "Z" in imgs[0]
    assert np.abs(imgs[1]["R"] - imgs[0]["R"]).max() > 1e-4  # the camera orbits
    assert (out / "bullet_time.blend").exists()
    assert res["frozen_capture_time"] == pytest.approx(0.5 * sum(json.loads(json.dumps(meta["time_range"]))))
