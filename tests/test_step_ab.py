"""The in-run A/B of an exact speed switch (scripts/step_ab.py, issue 13) on a tiny capture."""
from __future__ import annotations

import importlib.util
import re

import pytest

from tools.synthetic import write_synthetic_capture

_spec = importlib.util.spec_from_file_location("step_ab", __file__.rsplit("/tests/", 1)[0] + "/scripts/step_ab.py")
step_ab = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(step_ab)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return str(write_synthetic_capture(tmp_path_factory.mktemp("ab") / "cap", width=32, height=24, n_rgb=4,
                                       with_points=True))


def test_fixed_sides_train_alike_and_print_a_hash(capture, capsys):
    from engine.scene import trajectory

    assert trajectory.SINK
    hashes = []
    for side in ("on", "off"):
        step_ab.main([capture, "engine.scene.trajectory:SINK", "--steps", "8", "--fixed", side, "--rgb-only",
                      "--set", "init=ply"])
        hashes.append(re.search(r"parameters ([0-9a-f]{16})", capsys.readouterr().out).group(1))
    assert hashes[0] == hashes[1] and trajectory.SINK  # the switch is back where it was


def test_drawn_steps_are_timed_on_both_sides(capture, capsys):
    from engine.scene import fused_adam

    step_ab.main([capture, "engine.scene.fused_adam:PARALLEL", "--steps", "24", "--from", "8", "--rgb-only",
                  "--set", "init=ply"])
    out = capsys.readouterr().out
    assert fused_adam.PARALLEL
    counts = {(k, side): int(n) for k, side, n in re.findall(r"(backward|optimizer)\s+(on|off)\s+n\s+(\d+)", out)}
    assert set(counts) == {(k, s) for k in ("backward", "optimizer") for s in ("on", "off")}
    assert counts["backward", "on"] + counts["backward", "off"] == 16
    assert min(counts.values()) > 0 and "wall" in out


def test_a_non_switch_is_refused(capture):
    with pytest.raises(SystemExit, match="not a boolean switch"):
        step_ab.main([capture, "engine.scene.fused_adam:BLOCK", "--steps", "2"])
