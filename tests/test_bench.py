"""engine.bench plumbing with a stub trainer (no real training): curve sampling from
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

from engine import bench


def _tiny_capture(root: Path) -> Path:
    """Two train frames and four eval frames of a static 16x12 camera (ours layout)."""
    from engine.cameras import look_at_c2w
    from engine.images import write_png

    root.mkdir(parents=True)
    c2w = look_at_c2w((0.0, -4.0, 0.0), (0.0, 0.0, 0.0)).tolist()
    rng = np.random.default_rng(0)
    base = rng.random((12, 16, 3)).astype(np.float32)
    frames, evals = [], []
    for i in range(2):
        write_png(root / f"t{i}.png", base)
        frames.append({"file_path": f"t{i}.png", "camera": "cam", "time": i * 0.1, "transform_matrix": c2w})
    for i in range(4):
        img = base.copy()
        img[:, 4 * i:4 * i + 2] = 1.0  # a moving bar; the rest is static
        write_png(root / f"e{i}.png", img)
        evals.append({"file_path": f"e{i}.png", "camera": "ev", "time": i * 0.05, "transform_matrix": c2w})
    intr = {"w": 16, "h": 12, "fl_x": 14.0, "fl_y": 14.0, "cx": 8.0, "cy": 6.0}
    data = {"cameras": {"cam": dict(intr), "ev": dict(intr, role="eval")}, "frames": frames, "eval_frames": evals}
    (root / "transforms.json").write_text(json.dumps(data))
    return root


def stub_train(capture, out_dir, *, preset="fast", seconds=None, rgb_only=False, resume=True, device=None, seed=0,
               progress=None, cancel=None, overrides=None):
    """Writes a checkpoint every ``checkpoint_every_s`` (here: every 3 steps) like the trainer."""
    from engine.checkpoint import save_checkpoint, update_run_json
    from engine.gaussians import GaussianModel
    from engine.model import Model4D

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
    from engine.capture import load_capture

    return load_capture(_tiny_capture(tmp_path / "cap"))


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


def test_micro_decode_ratio():
    r = bench.micro_decode(quick=True)
    assert r["identical"] and r["speedup_vs_community"] > 1 and r["speedup_vs_python_loop"] > 10


def test_cli_rejects_unknown_variant(tmp_path, capsys):
    from engine.__main__ import main

    rc = main(["bench", str(tmp_path), "--out", str(tmp_path / "o"), "--variants", "bogus"])
    assert rc == 2 and "unknown variant" in capsys.readouterr().out


def test_early_stopper_cancels_after_patience(monkeypatch):
    import threading
    from types import SimpleNamespace

    scores = iter([10.0, 12.0, 12.5, 12.52, 12.4, 12.51, 12.3, 20.0])
    monkeypatch.setattr(bench, "score_model", lambda *a, **k: {"psnr": next(scores)})
    stopper = bench.EarlyStopper(capture=None, frames=[], every_fraction=0.1, patience=3, min_delta=0.05,
                                 min_deform_fraction=0.0)
    tr = SimpleNamespace(model=object(), static_steps=0)
    cancel = threading.Event()
    for step in range(1, 101):
        stopper({"step": step, "total_steps": 100, "stage": "deform", "elapsed_s": step * 0.1}, tr, cancel)
        if cancel.is_set():
            break
    # evaluations at steps 1, 11, 21, ...: 10, 12, 12.5 improve; 12.52, 12.4, 12.51 do not (< +0.05)
    assert cancel.is_set() and stopper.stopped_at["step"] == 51
    assert stopper.stopped_at["best_proxy_psnr"] == 12.5 and len(stopper.history) == 6


def test_micro_freeze_step_on_a_run_with_a_frozen_mask(tmp_path, capture):
    from engine.checkpoint import save_checkpoint
    from engine.deformation import DeformationField
    from engine.gaussians import GaussianModel
    from engine.model import Model4D

    rng = np.random.default_rng(0)
    g = GaussianModel(rng.uniform(-0.5, 0.5, (200, 3)), rng.random((200, 3)), init_opacity=0.5)
    field = DeformationField([-1] * 3, [1] * 3, (0.0, 0.2), features=4, resolution=8, multires=(1,),
                             time_resolution=4, width=16)
    mask = torch.zeros(200, dtype=torch.bool)
    mask[:150] = True
    model = Model4D(g, field, static_mask=mask)
    save_checkpoint(tmp_path / "run", {"model": model.state(), "step": 1, "total_steps": 1,
                                       "time_range": [0.0, 0.2], "gaussians": 200})
    r = bench.micro_freeze_step(tmp_path / "run", capture, repeats=2)
    assert r["frozen_fraction"] == 0.75 and r["gaussians"] == 200
    assert r["step_ms_frozen"] > 0 and r["step_ms_unfrozen"] > 0 and r["speedup"] > 0
