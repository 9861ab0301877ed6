"""Whole runs of one config field's values alternated in one process (scripts/config_ab.py, issue 13)."""
from __future__ import annotations

import importlib.util
import re
import threading

import pytest

_spec = importlib.util.spec_from_file_location("config_ab", __file__.rsplit("/tests/", 1)[0] + "/scripts/config_ab.py")
config_ab = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(config_ab)

_SMALL = ["static_fraction=0.25", "init_max_points=300", "init_random_points=100", "densify_from=2.0",
          "densify_until=2.0", "time_curriculum=0.0"]


@pytest.mark.slow
def test_one_line_per_value_in_order_with_both_stages_timed(demo_capture, capsys):
    config_ab.main([str(demo_capture), "spike_flow_prefetch", "0,2,0", "--steps", "8",
                    *[a for kv in _SMALL for a in ("--set", kv)]])
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("spike_flow_prefetch=")]
    assert [ln.split(":")[0] for ln in lines] == ["spike_flow_prefetch=0", "spike_flow_prefetch=2",
                                                  "spike_flow_prefetch=0"]
    for ln in lines:
        ms = [float(x) for x in re.findall(r"(?:static|deform) ([0-9.]+) ms", ln)]
        assert len(ms) == 2 and all(m > 0 for m in ms) and re.search(r"run [0-9.]+ s$", ln)
    assert not [t for t in threading.enumerate() if t.name == "bt4d-flow-prefetch"]  # each run closed its worker
