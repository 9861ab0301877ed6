"""The ablation command: variants, equal budgets, table, CSV and bar chart (trainer faked)."""
from __future__ import annotations

import csv
import json

import pytest

from tools import ablate
from tools.__main__ import COMMANDS


def _fakes(calls):
    def train_fn(capture, run_dir, *, preset, seconds, rgb_only, resume, device, seed, overrides):
        calls.append({"run_dir": str(run_dir), "seconds": seconds, "rgb_only": rgb_only, "overrides": overrides,
                      "resume": resume})
        run_dir.mkdir(parents=True, exist_ok=True)
        return {"train_seconds": seconds, "step": 100}

    def eval_fn(run_dir, capture, device="cpu"):
        bonus = 3.0 if "full" in str(run_dir) else 0.0
        m = {"psnr": 20.0 + bonus, "ssim": 0.8, "lpips": 0.25 - bonus / 100, "psnr_interframe": 19.0 + bonus,
             "ssim_interframe": 0.79, "psnr_dynamic": 15.0 + bonus, "num_gaussians": 1000}
        (run_dir / "metrics.json").write_text(json.dumps(m))
        (run_dir / "eval_frames.csv").write_text("index,time,camera,interframe,psnr,ssim,psnr_dynamic\n"
                                                 "0,0.0,eval0,0,21.0,0.8,\n1,0.01,eval0,1,19.0,0.8,\n"
                                                 "2,0.0333,eval0,0,23.0,0.8,\n")
        return m
    return train_fn, eval_fn


def test_registered_and_variants_cover_tables():
    assert COMMANDS["ablate"] == "ablate"
    assert list(ablate.VARIANTS)[:4] == ["rgb-only", "+fine", "+spike", "full"]
    assert ablate.VARIANTS["rgb-only"][0] is True and ablate.VARIANTS["full"][0] is False
    assert {ablate.VARIANTS[v][1].get("baseline") for v in ("rgb+repeat", "rgb+interp", "rgb+spike2img")} == \
        {"repeat", "interp-flow", "spike2img"}
    fi_rgb, fi = ablate.VARIANTS["full+interp"][:2]
    assert not fi_rgb and fi["baseline"] == "interp-flow" and fi["baseline_instants"] == "real"
    assert ablate.VARIANTS["rgb+interp-real"][0] and ablate.VARIANTS["rgb+interp"][1].get("baseline_instants") is None
    assert ablate.parse_variants("full, rgb-only") == ["full", "rgb-only"]
    with pytest.raises(SystemExit):
        ablate.parse_variants("full,bogus")


def test_run_ablation_equal_budget_table_csv_png(tmp_path):
    calls = []
    train_fn, eval_fn = _fakes(calls)
    rows = ablate.run_ablation("cap", tmp_path, 12.0, ["rgb-only", "+spike", "full", "rgb+interp"],
                               overrides={"iterations": 50}, train_fn=train_fn, eval_fn=eval_fn, log=lambda s: None)
    assert [c["seconds"] for c in calls] == [12.0] * 4  # same wall time for every variant
    assert [c["rgb_only"] for c in calls] == [True, False, False, True]
    assert calls[1]["overrides"]["block_loss_weight"] == 0.0 and calls[1]["overrides"]["iterations"] == 50
    assert calls[3]["overrides"]["baseline"] == "interp-flow"
    assert all(c["resume"] is False for c in calls)
    table = ablate.format_table(rows)
    assert "full" in table and "+3.00" in table and "PSNR inter" in table
    assert "LPIPS" in table and "0.220" in table and "0.250" in table
    ablate.write_csv(rows, tmp_path / "a.csv")
    got = list(csv.DictReader(open(tmp_path / "a.csv")))
    assert [r["variant"] for r in got] == ["rgb-only", "+spike", "full", "rgb+interp"]
    assert float(got[2]["psnr_interframe"]) == 22.0 and float(got[2]["lpips"]) == pytest.approx(0.22)
    assert rows[0]["psnr_keyframe"] == 22.0  # mean over the RGB instants of eval_frames.csv
    png = ablate.plot(rows, tmp_path / "a.png", title="t")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # --resume reuses finished variants without training again
    calls.clear()
    again = ablate.run_ablation("cap", tmp_path, 12.0, ["full"], resume=True, train_fn=train_fn, eval_fn=eval_fn,
                                log=lambda s: None)
    assert calls == [] and again[0]["psnr_interframe"] == 22.0


def test_table_handles_missing_values():
    rows = [{"variant": "full", "psnr": None, "ssim": None, "psnr_interframe": None, "ssim_interframe": None,
             "psnr_dynamic": float("nan")}]
    assert "-" in ablate.format_table(rows)


def test_equal_steps_sets_iterations_and_no_time_budget(tmp_path):
    calls = []
    train_fn, eval_fn = _fakes(calls)
    rows = ablate.run_ablation("cap", tmp_path, None, ["rgb-only", "full", "full-pg"], steps=300,
                               overrides={"iterations": 50}, train_fn=train_fn, eval_fn=eval_fn, log=lambda s: None)
    assert [c["seconds"] for c in calls] == [None] * 3  # no wall-clock budget: the schedule is the steps
    assert [c["overrides"]["iterations"] for c in calls] == [300] * 3  # --steps wins over --set iterations
    assert calls[2]["overrides"]["fine_per_gaussian"] and "fine_per_gaussian" not in calls[1]["overrides"]
    assert all(r["steps"] == 100 for r in rows)  # what the run reports
    with pytest.raises(ValueError, match="exactly one"):
        ablate.run_ablation("cap", tmp_path, 10.0, ["full"], steps=10, train_fn=train_fn, eval_fn=eval_fn)
    with pytest.raises(ValueError, match="exactly one"):
        ablate.run_ablation("cap", tmp_path, None, ["full"], train_fn=train_fn, eval_fn=eval_fn)


def test_cli_budget_flags_are_exclusive_and_required():
    import argparse

    p = argparse.ArgumentParser()
    ablate.add_arguments(p)
    assert p.parse_args(["cap", "--out", "o", "--steps", "40", "--seed", "1"]).steps == 40
    assert p.parse_args(["cap", "--out", "o", "--seconds", "9"]).steps is None
    for bad in (["cap", "--out", "o"], ["cap", "--out", "o", "--steps", "4", "--seconds", "9"]):
        with pytest.raises(SystemExit):
            p.parse_args(bad)
