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


def _midpoint_miss(poses_at, t0: float, name: str) -> float:
    """How far an object is, half-way between two RGB instants, from the straight line between its
    places at them: what a 30 FPS camera cannot see (metres)."""
    a, m, b = (np.array(poses_at(t)[name][0]) for t in (t0, t0 + 1 / 60, t0 + 1 / 30))
    return float(np.linalg.norm(m - 0.5 * (a + b)))


def test_between_motion_adds_what_30_fps_cannot_sample_to_the_same_draw():
    for seed in range(60):
        smooth = capture_random.configure(seed)
        p_smooth = json.loads(json.dumps(capture_random.PARAMS))
        smooth_miss = {o["name"]: max(_midpoint_miss(capture_random.object_poses, k / 30, o["name"]) for k in range(9))
                       for o in p_smooth["objects"]}
        assert capture_random.configure(seed, "between") == smooth  # sizes and sensor as drawn
        p = capture_random.PARAMS
        d = p["distance"]
        kinds = [o["motion"] for o in p["objects"]]
        assert set(kinds) <= {"bounce", "vibrate", "smooth"} and set(kinds) != {"smooth"}
        added = ("motion", "period_s", "first_impact_s", "height", "vibration_hz", "vibration_amp")
        kept = [{k: v for k, v in o.items() if k not in added} for o in p["objects"]]
        assert json.loads(json.dumps(kept)) == p_smooth["objects"]
        for o in p["objects"]:
            miss = max(_midpoint_miss(capture_random.object_poses, k / 30, o["name"]) for k in range(9))
            if o["motion"] == "bounce":  # on the floor at every impact, never below it
                hit = capture_random.object_poses(o["first_impact_s"] + 2 * o["period_s"])[o["name"]][0]
                assert hit[2] == pytest.approx(0.5 * o["size"], abs=1e-9)
                lowest = min(capture_random.object_poses(k / 600)[o["name"]][0][2] for k in range(180))
                assert lowest >= 0.5 * o["size"] - 1e-9
            if o["motion"] != "smooth":  # far off the RGB frames' straight line at some midpoint
                assert miss > 0.005 * d and miss > 2 * smooth_miss[o["name"]], (seed, o)
    before = json.dumps(capture_random.PARAMS, sort_keys=True), capture_random.CAMERA_EYES
    with pytest.raises(ValueError, match="motion"):
        capture_random.configure(1, "fast")
    assert (json.dumps(capture_random.PARAMS, sort_keys=True), capture_random.CAMERA_EYES) == before


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["random", "random_between"])
def test_a_random_capture_renders_loads_and_records_its_draw(tmp_path, preset):
    from engine.io.capture import load_capture

    out = tmp_path / "cap"
    cmd = [sys.executable, str(REPO_ROOT / "scripts" / "make_capture.py"), "--out", str(out), "--preset", preset,
           "--seed", "5", "--seconds", "0.04", "--rgb-size", "48x36", "--spike-size", "24x18", "--eval-fps", "60",
           "--extra-eval-fps", "30", "--samples", "2", "--light-hz", "250", "--no-depth"]
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-4000:]
    cap = load_capture(out)
    tj = json.loads((out / "transforms.json").read_text())
    drawn = capture_random.configure(5, "between" if preset == "random_between" else "smooth")
    assert tj["generator"]["random"]["distance"] == pytest.approx(capture_random.PARAMS["distance"])
    motions = [o.get("motion", "smooth") for o in tj["generator"]["random"]["objects"]]
    assert motions == [o.get("motion", "smooth") for o in capture_random.PARAMS["objects"]]
    assert (set(motions) == {"smooth"}) == (preset == "random")
    sim = tj["spike_streams"][0]["sim"]
    assert sim["gain_std"] == pytest.approx(drawn["gain_std"]) and sim["dark_current"] == pytest.approx(
        drawn["dark_current"])
    assert {f.camera for f in cap.eval_frames} == {"eval0", "eval_side20", "eval_up20"}
    first = {f.camera: f for f in cap.frames}
    base = np.linalg.norm(np.asarray(first["rgb0"].c2w)[:3, 3] - np.asarray(first["rgb1"].c2w)[:3, 3])
    assert base == pytest.approx(capture_random.PARAMS["baseline"], rel=1e-6)
    img = np.asarray(first["rgb0"].load_rgb())
    assert img.shape[:2] == (36, 48) and img.std() > 0.02  # a lit, textured set
