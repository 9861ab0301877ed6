"""scripts/capture_random.py: a scene, rig and sensor drawn from the seed alone, and a capture
rendered from one (``make_capture.py --preset random``) that loads and records its draw."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from blender_util import HAS_BPY

if not HAS_BPY:  # the generators import bpy
    pytest.skip("needs the bpy module (Blender 5.0 as a module, Python 3.11)", allow_module_level=True)

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT / "scripts"))
import capture_random  # noqa: E402
import make_capture  # noqa: E402


def test_the_seed_alone_draws_the_scene_within_its_ranges():
    a = capture_random.configure(11)
    pa = json.dumps(capture_random.PARAMS, sort_keys=True)
    capture_random.configure(12)
    assert json.dumps(capture_random.PARAMS, sort_keys=True) != pa
    assert capture_random.configure(11) == a and json.dumps(capture_random.PARAMS, sort_keys=True) == pa
    dists, weak, counts = [], 0, set()
    for seed in range(200):
        got = capture_random.configure(seed)
        p = capture_random.PARAMS
        d = p["distance"]
        dists.append(d)
        assert 0.8 <= d <= 3.0 and 0.08 - 1e-9 <= p["baseline"] <= min(0.35, d / 3) + 1e-9
        assert 15 <= abs(p["eval0_angles"][0]) <= 28 and 3 <= p["eval0_angles"][1] <= 15
        w, h = got["rgb_size"]
        sw, sh = got["spike_size"]
        assert (w, h) in capture_random.RGB_SIZES and sw * sh % 8 == 0 and w // sw in (2, 4) and h // sh == w // sw
        assert 0.02 <= got["gain_std"] <= 0.05 and 200 <= got["photons_per_threshold"] <= 1000
        poses = capture_random.object_poses(0.1)
        assert set(poses) == set(capture_random.MOVING) and 1 <= len(poses) <= 4
        for o in p["objects"]:
            assert 0.05 * d <= o["size"] <= 0.15 * d and o["sweep"] * o["omega"] <= 0.35 * d * 13 + 1e-9
        weak += p["floor"]["kind"] == "weak"
        counts.add(len(poses))
    assert min(dists) < 1.1 and max(dists) > 2.7 and 60 < weak < 160 and counts == {1, 2, 3, 4}


def test_objects_move_between_rgb_instants():
    capture_random.configure(3)
    a, b = capture_random.object_poses(0.0), capture_random.object_poses(1 / 60)
    moved = [np.linalg.norm(np.subtract(a[n][0], b[n][0])) for n in a]
    assert max(moved) > 0.0 and make_capture.SCENES["random"] is capture_random


@pytest.mark.slow
def test_a_random_capture_renders_loads_and_records_its_draw(tmp_path):
    from engine.io.capture import load_capture

    out = tmp_path / "cap"
    cmd = [sys.executable, str(REPO_ROOT / "scripts" / "make_capture.py"), "--out", str(out), "--preset", "random",
           "--seed", "5", "--seconds", "0.04", "--rgb-size", "48x36", "--spike-size", "24x18", "--eval-fps", "60",
           "--extra-eval-fps", "30", "--samples", "2", "--light-hz", "250", "--no-depth"]
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-4000:]
    cap = load_capture(out)
    tj = json.loads((out / "transforms.json").read_text())
    drawn = capture_random.configure(5)
    assert tj["generator"]["random"]["distance"] == pytest.approx(capture_random.PARAMS["distance"])
    sim = tj["spike_streams"][0]["sim"]
    assert sim["gain_std"] == pytest.approx(drawn["gain_std"]) and sim["dark_current"] == pytest.approx(
        drawn["dark_current"])
    assert {f.camera for f in cap.eval_frames} == {"eval0", "eval_side20", "eval_up20"}
    first = {f.camera: f for f in cap.frames}
    base = np.linalg.norm(np.asarray(first["rgb0"].c2w)[:3, 3] - np.asarray(first["rgb1"].c2w)[:3, 3])
    assert base == pytest.approx(capture_random.PARAMS["baseline"], rel=1e-6)
    img = np.asarray(first["rgb0"].load_rgb())
    assert img.shape[:2] == (36, 48) and img.std() > 0.02  # a lit, textured set
