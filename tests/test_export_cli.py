"""``python -m engine export --format ply|compact`` and opening a compact cache like a run."""
from __future__ import annotations

import numpy as np
import pytest
from export_util import TIME_RANGE, camera, write_run

from engine.__main__ import main
from engine.evaluate.metrics import psnr
from engine.export import ply
from engine.export.cached import CachedScene, load_result
from engine.export.splats import render_splats, splats_at
from engine.scene.model import load_run, view_tensors


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return write_run(tmp_path_factory.mktemp("export_cli") / "run", n=200)


def test_export_ply_at_fps(run_dir, tmp_path, capsys):
    out = tmp_path / "seq"
    assert main(["export", str(run_dir), "--format", "ply", "--fps", "50", "--out", str(out)]) == 0
    assert "11 instants" in capsys.readouterr().out
    index = ply.read_index(out)
    times = [f["time"] for f in index["frames"]]
    assert times == pytest.approx(np.arange(11) / 50.0) and index["fps"] == 50.0
    assert index["background"] == pytest.approx([0.1, 0.2, 0.3])
    scene = load_run(run_dir)
    view = camera(times[7])
    got = render_splats(ply.read_ply(out / "frame_000007.ply"), view_tensors(view, "cpu"), scene.background,
                        scene.model.near_plane)["rgb"]
    assert psnr(got, scene.render([view])[0]["rgb"]) >= 50.0


def test_export_compact_and_load_it_back(run_dir, tmp_path, capsys):
    out = tmp_path / "scene.bt4c"
    assert main(["export", str(run_dir), "--fps", "100", "--out", str(out)]) == 0  # format from the suffix
    assert "compact, 21 instants" in capsys.readouterr().out
    run, cached = load_run(run_dir), load_result(out)
    assert isinstance(cached, CachedScene)
    assert cached.time_range == pytest.approx(TIME_RANGE) and cached.num_gaussians == 200
    assert cached.background == run.background and cached.info["source"] == str(run_dir)
    # on a stored instant and between two (interpolated), the cache renders like the run
    for t in (0.07, 0.075):
        view = camera(t)
        assert psnr(cached.render([view])[0]["rgb"], run.render([view])[0]["rgb"]) > 38.0
    g, want = cached.gaussians_at(0.1), run.gaussians_at(0.1)
    for k in ("means", "scales", "opacities", "colors"):
        np.testing.assert_allclose(g[k], want[k], atol=2e-2)
    # a cache re-exports to PLY (and not to npz: it holds no model)
    assert main(["export", str(out), "--format", "ply", "--times", "0", "0.2", "3", "--out", str(tmp_path / "p")]) == 0
    np.testing.assert_allclose(ply.read_sequence_frame(tmp_path / "p", 1)["means"], cached.splats_at(0.1)["means"])
    assert main(["export", str(out), "--format", "npz", "--out", str(tmp_path / "x.npz")]) == 1
    assert "npz export needs a run directory" in capsys.readouterr().err


def test_compact_is_much_smaller_than_the_raw_arrays(run_dir, tmp_path):
    assert main(["export", str(run_dir), "--format", "npz", "--fps", "100", "--out", str(tmp_path / "a.npz")]) == 0
    assert main(["export", str(run_dir), "--format", "compact", "--fps", "100", "--out", str(tmp_path / "a.bt4c")]) == 0
    raw = 21 * sum(v.nbytes for v in splats_at(load_run(run_dir).model, 0.0).values())
    # every Gaussian of this stand-in moves, turns and recolours at random: a hard case
    # (on the trained demo run the ratios are 100x and 16x, docs/experiments/export-and-lpips.md "Export")
    size = (tmp_path / "a.bt4c").stat().st_size
    assert size * 10 < raw and size * 3 < (tmp_path / "a.npz").stat().st_size


def test_export_errors(run_dir, tmp_path, capsys):
    assert main(["export", str(tmp_path / "norun"), "--format", "ply", "--out", str(tmp_path / "o")]) == 1
    assert "norun: run directory does not exist" in capsys.readouterr().err
    (tmp_path / "torn.bt4c").write_bytes((b"BT4DC\x00\r\n" + b"\x01\x00\x00\x00\xff\x00\x00\x00"))
    assert main(["export", str(tmp_path / "torn.bt4c"), "--format", "ply", "--out", str(tmp_path / "o")]) == 1
    assert "torn.bt4c: truncated inside the header" in capsys.readouterr().err
    assert main(["export", str(run_dir), "--fps", "-3", "--format", "ply", "--out", str(tmp_path / "o")]) == 1
    assert "--fps must be positive" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.fixture()
def small_capture(demo_capture, tmp_path):
    """The demo capture with 4 of its 61 eval frames (files linked, not copied)."""
    import json

    root = tmp_path / "cap"
    root.mkdir()
    for p in demo_capture.iterdir():
        if p.name != "transforms.json":
            (root / p.name).symlink_to(p.resolve(), target_is_directory=p.is_dir())
    meta = json.loads((demo_capture / "transforms.json").read_text())
    meta["eval_frames"] = meta["eval_frames"][10:14]
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


@pytest.mark.slow  # 30 s under load: two evals with LPIPS
def test_eval_scores_a_compact_cache_like_its_run(run_dir, small_capture, tmp_path, capsys):
    import json

    cache = tmp_path / "s.bt4c"
    assert main(["export", str(run_dir), "--format", "compact", "--fps", "300", "--out", str(cache)]) == 0
    capsys.readouterr()
    assert main(["eval", str(run_dir), str(small_capture)]) == 0
    by_run = json.loads(capsys.readouterr().out)
    assert main(["eval", str(cache), str(small_capture)]) == 0
    by_cache = json.loads(capsys.readouterr().out)
    assert by_run["n_frames"] == by_cache["n_frames"] == 4
    assert 0 < by_run["lpips"] < 1 and abs(by_cache["lpips"] - by_run["lpips"]) < 0.01
    assert abs(by_cache["psnr"] - by_run["psnr"]) < 0.2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "s.bt4c"]  # nothing written beside the cache
    # a cache whose run recorded no capture needs one on the command line
    assert main(["eval", str(cache)]) == 1
    assert "s.bt4c: no capture recorded" in capsys.readouterr().err


@pytest.mark.slow  # ~10 s under load
def test_compact_steps_tool_prints_the_table(run_dir, small_capture, capsys):
    from tools.__main__ import main as tools_main

    assert tools_main(["compact-steps", str(run_dir), str(small_capture), "--fps", "100", "--scales", "1", "8"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith(("| 1 |", "| 8 |"))]
    assert len(rows) == 2
    size = [float(r.split("|")[2]) for r in rows]
    fidelity = [float(r.split("|")[7]) for r in rows]
    assert size[1] < size[0] and fidelity[1] < fidelity[0] and fidelity[0] > 35.0
