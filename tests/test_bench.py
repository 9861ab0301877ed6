"""tools.bench plumbing with a stub trainer (no real training): curve sampling from
periodic checkpoints, CSV / PNG / markdown / JSON outputs, peak RSS, the CLI, and the
micro-benchmark ratios."""
from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from tools import bench, micro


def _tiny_capture(root: Path, stereo: bool = False) -> Path:
    """Two train frames and four eval frames of a static 16x12 camera (ours layout);
    ``stereo``: a second train camera beside it (early stopping holds one of its frames back)."""
    from engine.cameras import look_at_c2w
    from engine.io.images import write_png

    root.mkdir(parents=True)
    c2w = look_at_c2w((0.0, -4.0, 0.0), (0.0, 0.0, 0.0)).tolist()
    c2w2 = look_at_c2w((0.2, -4.0, 0.0), (0.0, 0.0, 0.0)).tolist()
    rng = np.random.default_rng(0)
    base = rng.random((12, 16, 3)).astype(np.float32)
    frames, evals = [], []
    for i in range(2):
        write_png(root / f"t{i}.png", base)
        frames.append({"file_path": f"t{i}.png", "camera": "cam", "time": i * 0.1, "transform_matrix": c2w})
        if stereo:
            frames.append({"file_path": f"t{i}.png", "camera": "cam2", "time": i * 0.1, "transform_matrix": c2w2})
    for i in range(4):
        img = base.copy()
        img[:, 4 * i:4 * i + 2] = 1.0  # a moving bar; the rest is static
        write_png(root / f"e{i}.png", img)
        evals.append({"file_path": f"e{i}.png", "camera": "ev", "time": i * 0.05, "transform_matrix": c2w})
    intr = {"w": 16, "h": 12, "fl_x": 14.0, "fl_y": 14.0, "cx": 8.0, "cy": 6.0}
    cams = {"cam": dict(intr), "ev": dict(intr, role="eval")}
    if stereo:
        cams["cam2"] = dict(intr)
    data = {"cameras": cams, "frames": frames, "eval_frames": evals}
    (root / "transforms.json").write_text(json.dumps(data))
    return root


def stub_train(capture, out_dir, *, preset="fast", seconds=None, rgb_only=False, resume=True, device=None, seed=0,
               progress=None, cancel=None, overrides=None):
    """Writes a checkpoint every ``checkpoint_every_s`` (here: every 3 steps) like the trainer."""
    from engine.io.checkpoint import save_checkpoint, update_run_json
    from engine.scene.gaussians import GaussianModel
    from engine.scene.model import Model4D

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    g = GaussianModel(rng.uniform(-0.5, 0.5, (30, 3)), rng.random((30, 3)), init_opacity=0.5)
    model = Model4D(g, None)
    total = 9
    t0 = time.perf_counter()
    update_run_json(out_dir, capture=str(capture.root), preset=preset, status="running")

    def save(step):
        save_checkpoint(out_dir, {"model": model.state(), "step": step, "total_steps": total,
                                  "time_range": [0.0, 0.2], "gaussians": g.num_gaussians})

    for step in range(1, total + 1):
        with torch.no_grad():
            g.opacity_logits += 0.3
        if step % 3 == 0 and step < total:
            save(step)
        if progress:
            progress({"step": step, "total_steps": total, "stage": "static", "loss": 0.1, "psnr": 20.0,
                      "elapsed_s": time.perf_counter() - t0, "eta_s": 0.0, "num_gaussians": g.num_gaussians})
        if cancel is not None and cancel.is_set():
            break
    save(total)
    secs = time.perf_counter() - t0
    update_run_json(out_dir, status="finished", train_seconds=secs, step=total)
    return {"status": "finished", "step": total, "total_steps": total, "train_seconds": secs,
            "num_gaussians": g.num_gaussians, "rgb_only": rgb_only}


@pytest.fixture()
def capture(tmp_path):
    from engine.io.capture import load_capture

    return load_capture(_tiny_capture(tmp_path / "cap"))


@pytest.mark.slow
def test_bench_with_stub_trainer_writes_all_outputs(tmp_path, capture):
    out = tmp_path / "bench"
    res = bench.run_bench(capture, out, presets=("fast",), variants=("full", "rgb_only"), seconds=5,
                          eval_every_s=1.0, micro=False, progress=False, train_fn=stub_train, log=None)
    for name in ("bench.csv", "bench.png", "bench.md", "bench.json"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    rows = list(csv.DictReader((out / "bench.csv").open()))
    for variant in ("full", "rgb_only"):
        steps = [int(r["step"]) for r in rows if r["variant"] == variant]
        assert steps == [3, 6, 9], steps          # every checkpoint became a curve sample
        walls = [float(r["wall_s"]) for r in rows if r["variant"] == variant]
        assert walls == sorted(walls) and all(w >= 0 for w in walls)
        assert all(np.isfinite(float(r["psnr"])) and -1 <= float(r["ssim"]) <= 1 for r in rows)
    r0 = res["results"][0]
    assert r0.final["psnr"] is not None and r0.final["n_frames"] == 4
    assert r0.peak_rss_mb > 10
    assert np.isfinite(r0.final["flicker"]["flicker"])
    assert r0.final["flicker"]["flicker"] == pytest.approx(0.0, abs=1e-6)   # a static model does not flicker
    assert not (Path(r0.run_dir) / "snapshots").exists()
    md = (out / "bench.md").read_text()
    assert "| fast | full |" in md and "| fast | rgb_only |" in md
    data = json.loads((out / "bench.json").read_text())
    assert [r["variant"] for r in data["runs"]] == ["full", "rgb_only"]
    assert data["runs"][1]["summary"]["rgb_only"] is True


@pytest.mark.slow
def test_curve_improves_when_the_model_does(tmp_path, capture):
    res = bench.run_bench(capture, tmp_path / "b", presets=("fast",), variants=("full",), seconds=5, eval_every_s=1,
                          micro=False, progress=False, train_fn=stub_train, flicker=False, log=None)
    curve = res["results"][0].curve
    assert len(curve) == 3 and len({round(c["psnr"], 6) for c in curve}) > 1


def test_peak_rss_reset_and_read():
    big = np.ones(20_000_000)  # 160 MB
    p1, src = bench.peak_rss_mb()
    del big
    if bench.reset_peak_rss():
        p2, _ = bench.peak_rss_mb()
        assert p2 < p1 - 100
    assert p1 > 150 and src


def test_time_to_within():
    curve = [{"wall_s": 1.0, "psnr": 10.0}, {"wall_s": 2.0, "psnr": 19.7}, {"wall_s": 3.0, "psnr": 20.0}]
    assert bench.time_to_within(curve, 20.0, 0.5) == 2.0


def test_unknown_variant_rejected(tmp_path, capture):
    with pytest.raises(KeyError):
        bench.run_one(capture, tmp_path, "fast", "nope", seconds=1, eval_every_s=1, train_fn=stub_train)


def test_micro_decode_decodes_identically_and_reports_speedups():
    # the speed-up figures belong in the benchmark's output (python -m tools bench), not here
    r = micro.micro_decode(quick=True)
    assert r["identical"]
    assert r["speedup_vs_community"] > 0 and r["speedup_vs_python_loop"] > 0


def test_cli_rejects_unknown_variant(tmp_path, capsys):
    from tools.__main__ import main

    rc = main(["bench", str(tmp_path), "--out", str(tmp_path / "o"), "--variants", "bogus"])
    assert rc == 2 and "unknown variant" in capsys.readouterr().out


@pytest.mark.slow
def test_skip_variants_are_trainer_switches(tmp_path, capture):
    """freeze / early_stop / cull reach the trainer as its config switches (overrides), and
    what the trainer reports about them (summary["skips"]) lands in the bench results."""
    seen = {}

    def recording_train(capture, out_dir, **kw):
        seen[Path(out_dir).name] = (dict(kw["overrides"]), kw["rgb_only"])
        s = stub_train(capture, out_dir, **kw)
        ov = kw["overrides"]
        s["skips"] = {}
        if ov.get("skip.early_stop"):
            s["skips"]["early_stop"] = {"proxy": "held_back_train", "frames": ["train:rgb0@0.033333"],
                                        "stopped_at": {"step": 6, "total_steps": 9}, "history": []}
        if ov.get("skip.cull_frustum"):
            s["skips"]["cull"] = {"pruned": 7, "events": []}
        if ov.get("skip.freeze_static"):
            s["skips"]["freeze"] = {"fraction_frozen": 0.5, "woken": 2, "checks": 3}
        return s

    res = bench.run_bench(capture, tmp_path / "b", presets=("fast",), variants=bench.VARIANTS, seconds=5,
                          eval_every_s=1, overrides={"max_gaussians": 500}, micro=False, progress=False,
                          train_fn=recording_train, flicker=False, log=None)
    assert seen["fast-freeze"][0]["skip.freeze_static"] is True and seen["fast-cull"][0]["skip.cull_frustum"] is True
    assert seen["fast-early_stop"][0]["skip.early_stop"] is True
    assert not any(k.startswith("skip.") for k in seen["fast-full"][0])
    assert seen["fast-rgb_only"][1] is True and all(ov["max_gaussians"] == 500 for ov, _ in seen.values())
    by = {r.variant: r for r in res["results"]}
    assert by["cull"].extra["cull"]["pruned"] == 7 and by["freeze"].extra["freeze"]["woken"] == 2
    assert by["early_stop"].extra["early_stop"]["proxy"] == "held_back_train"
    md = res["markdown"]
    assert "stopped at 6/9" in md and "culled 7" in md and "frozen 50% at end, woken 2" in md


@pytest.mark.slow
def test_skip_variants_with_the_real_trainer(tmp_path, monkeypatch):
    from engine.io.capture import load_capture
    from engine.train.skipping import early_stop, freezing

    monkeypatch.setattr(freezing, "START_FRACTION", 0.0)
    monkeypatch.setattr(freezing, "CHECKS_PER_STAGE", 6)
    monkeypatch.setattr(early_stop, "MIN_DEFORM_FRACTION", 0.0)
    monkeypatch.setattr(early_stop, "MIN_DELTA_DB", 100.0)
    capture = load_capture(_tiny_capture(tmp_path / "cap", stereo=True))
    ov = {"iterations": 10, "init": "random", "init_random_points": 300, "static_fraction": 0.4,
          "freeze_k_checks": 1, "freeze_motion_eps_px": 100.0, "early_stop_patience": 1,
          "motion": "hexplane"}  # freezing skips the HexPlane field
    for variant in ("freeze", "early_stop", "cull"):
        r = bench.run_one(capture, tmp_path, "fast", variant, seconds=None, eval_every_s=100.0, overrides=ov,
                          flicker=False, evaluate_fn=lambda run, cap: {"psnr": 0.0})
        assert r.summary["status"] == "finished", r.summary
        if variant == "freeze":
            assert r.extra["freeze"]["checks"] > 0 and r.extra["freeze"]["fraction_frozen"] > 0
        elif variant == "early_stop":  # a gain of 100 dB never comes: stops at the first deformation evaluation
            assert r.summary["stopped_early"] and r.summary["step"] < 10
            assert r.extra["early_stop"]["proxy"] == "held_back_train"  # never the eval frames
        else:
            assert "pruned" in r.extra["cull"]


def test_micro_freeze_step_on_a_run_with_a_frozen_mask(tmp_path, capture):
    from engine.io.checkpoint import save_checkpoint
    from engine.scene.deformation import DeformationField
    from engine.scene.gaussians import GaussianModel
    from engine.scene.model import Model4D

    rng = np.random.default_rng(0)
    g = GaussianModel(rng.uniform(-0.5, 0.5, (200, 3)), rng.random((200, 3)), init_opacity=0.5)
    field = DeformationField([-1] * 3, [1] * 3, (0.0, 0.2), features=4, resolution=8, multires=(1,),
                             time_resolution=4, width=16)
    mask = torch.zeros(200, dtype=torch.bool)
    mask[:150] = True
    model = Model4D(g, field, static_mask=mask)
    save_checkpoint(tmp_path / "run", {"model": model.state(), "step": 1, "total_steps": 1,
                                       "time_range": [0.0, 0.2], "gaussians": 200})
    r = micro.micro_freeze_step(tmp_path / "run", capture, repeats=2)
    assert r["frozen_fraction"] == 0.75 and r["gaussians"] == 200
    assert r["step_ms_frozen"] > 0 and r["step_ms_unfrozen"] > 0 and r["speedup"] > 0


def test_markdown_table_has_lpips():
    final = {"psnr": 20.0, "ssim": 0.8, "lpips": 0.1234, "psnr_interframe": 19.0, "psnr_dynamic": 15.0,
             "num_gaussians": 10}
    r = bench.RunResult("fast", "full", "run", {"step": 5, "total_steps": 5, "status": "finished"}, [], final,
                        100.0, "test", 1.0)
    md = bench.markdown([r], {}, {"seconds": 1, "eval_stride": 1, "eval_every_s": 1})
    header = next(line for line in md.splitlines() if line.startswith("| preset"))
    row = next(line for line in md.splitlines() if line.startswith("| fast | full"))
    cells = [c.strip() for c in header.strip("|").split("|")]
    values = [c.strip() for c in row.strip("|").split("|")]
    assert len(values) == len(cells) and values[cells.index("LPIPS")] == "0.1234"
