"""The engine's command line on the demo capture: train -> eval -> render -> export (+ demo)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from engine.__main__ import main

TINY = ["--set", "iterations=12", "--set", "init_max_points=1500", "--set", "static_fraction=0.5"]


@pytest.fixture(scope="module")
def run_dir(demo_capture, tmp_path_factory):
    run = tmp_path_factory.mktemp("cli") / "run"
    assert main(["train", str(demo_capture), "--out", str(run), "--quiet", "--seed", "1", *TINY]) == 0
    return run


@pytest.mark.slow
def test_train_writes_a_run(run_dir, demo_capture, capsys):
    info = json.loads((run_dir / "run.json").read_text())
    assert info["status"] == "finished" and info["step"] == 12 and info["seed"] == 1
    assert info["capture"] == str(demo_capture.resolve()) and info["preset"] == "fast"
    assert (run_dir / "checkpoint.pt").exists()
    # resuming a finished run is a no-op that still prints the summary
    assert main(["train", str(demo_capture), "--out", str(run_dir), "--quiet", "--seed", "1", *TINY]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["resumed_from"] == 12 and summary["status"] == "finished"


@pytest.mark.slow
def test_eval_prints_metrics_json(run_dir, demo_capture, capsys):
    assert main(["eval", str(run_dir)]) == 0
    out = json.loads(capsys.readouterr().out)
    for k in ("psnr", "ssim", "psnr_interframe", "ssim_interframe", "psnr_dynamic", "n_frames", "train_seconds",
              "num_gaussians"):
        assert k in out
    assert out["n_frames"] == 61 and out["n_interframe"] > 40 and 5 < out["psnr"] < 60
    assert 0.0 < out["lpips"] < 1.0
    rows = (run_dir / "eval_frames.csv").read_text().splitlines()
    assert rows[0].split(",")[:4] == ["index", "time", "camera", "interframe"] and len(rows) == 62
    assert rows[0].split(",")[-2:] == ["lpips", "psnr_static"]
    assert all(0 < float(r.split(",")[-2]) < 1 and 5 < float(r.split(",")[-1]) < 60 for r in rows[1:])
    assert 5 < out["psnr_static_instants"] < 60 and 5 < out["psnr_static_interframe"] < 60
    assert 0.0 <= out["static_colour_shift"] < 0.5 and 0.0 < out["static_fraction"] < 1.0
    assert json.loads((run_dir / "metrics.json").read_text())["psnr"] == out["psnr"]
    # what was scored, to look at: ground truth | render for every frame (issue 45)
    from engine.io.images import read_image_rgba

    shots = sorted((run_dir / "eval_images").glob("*.png"))
    assert len(shots) == 61
    side = read_image_rgba(shots[0])
    assert side.shape[:2] == (120, 320)
    from engine.io.capture import load_capture

    first = sorted(load_capture(demo_capture).eval_frames, key=lambda f: (f.camera, f.time))[0]
    gt = first.load_rgb()
    assert np.abs(side[:, :160, :3] - gt[..., :3]).max() < 1.5 / 255


@pytest.mark.slow
def test_render_exr_and_png(run_dir, demo_capture, tmp_path, capsys):
    from engine.io.images import read_exr_channels, read_image_rgba

    data = json.loads((demo_capture / "transforms.json").read_text())
    cams = {"cameras": data["cameras"], "frames": data["eval_frames"][:2]}
    (tmp_path / "cams.json").write_text(json.dumps(cams))
    assert main(["render", str(run_dir), "--cameras", str(tmp_path / "cams.json"), "--out", str(tmp_path / "exr")]) == 0
    exrs = sorted((tmp_path / "exr").glob("*.exr"))
    assert [p.stem for p in exrs] == ["000000", "000001"]
    ch = read_exr_channels(exrs[0])
    assert set("RGBAZ") <= set(ch) and ch["R"].shape == (120, 160)
    assert np.all(np.isfinite(ch["Z"])) and ch["A"].max() <= 1.0
    assert main(["render", str(run_dir), "--cameras", str(tmp_path / "cams.json"), "--out", str(tmp_path / "png"),
                 "--format", "png", "--time", "0.1"]) == 0
    png = read_image_rgba(sorted((tmp_path / "png").glob("*.png"))[0])
    assert png.shape == (120, 160, 4)
    # a missing camera file is an error message, not a traceback
    assert main(["render", str(run_dir), "--cameras", str(tmp_path / "none.json"), "--out", str(tmp_path)]) == 1
    assert "none.json" in capsys.readouterr().err


@pytest.mark.slow
def test_render_names_never_collide(run_dir, demo_capture, tmp_path, capsys):
    """rgb0/000000.png and rgb1/000000.png of the capture both have the stem 000000: every
    view still gets its own file (camera-prefixed), and the count printed is the count on disk."""
    data = json.loads((demo_capture / "transforms.json").read_text())
    n = len(data["frames"])
    stems = [p.rsplit("/", 1)[-1] for p in (f["file_path"] for f in data["frames"])]
    assert len(set(stems)) < n  # the capture really has colliding file names
    out = tmp_path / "all"
    assert main(["render", str(run_dir), "--cameras", str(demo_capture / "transforms.json"), "--out", str(out),
                 "--format", "png"]) == 0
    files = sorted(p.name for p in out.glob("*.png"))
    assert len(files) == n and f"wrote {n} PNG file(s)" in capsys.readouterr().out
    assert "rgb0_000000.png" in files and "rgb1_000000.png" in files


@pytest.mark.slow
def test_render_orbit_with_times_and_a_gif(run_dir, tmp_path, capsys):
    """Issue 45: a bullet-time orbit from the command line, without Blender: N views on an arc
    through the first train camera, capture time spread over them, progress, and a GIF."""
    from PIL import Image

    from engine.io.capture import load_capture
    from engine.io.images import read_image_rgba
    from engine.scene.model import load_run

    out, gif = tmp_path / "orbit", tmp_path / "orbit.gif"
    assert main(["render", str(run_dir), "--orbit", "40", "--views", "3", "--times", "0.0", "0.2", "--format", "png",
                 "--out", str(out), "--video", str(gif), "--device", "auto"]) == 0
    cap = capsys.readouterr()
    assert "render 3/3 t=0.20000 s" in cap.err and "wrote 3 PNG file(s)" in cap.out
    files = sorted(out.glob("*.png"))
    assert [p.name for p in files] == ["000000.png", "000001.png", "000002.png"]
    imgs = [read_image_rgba(p) for p in files]
    assert imgs[0].shape == (120, 160, 4) and np.abs(imgs[2] - imgs[0]).max() > 0.05  # the camera moved
    with Image.open(gif) as im:
        assert im.n_frames == 3 and im.size == (160, 120)
    # the middle view of a 40 degree arc through the first train camera is that camera itself
    scene = load_run(run_dir)
    capture = load_capture(scene.info["capture"])
    first = sorted(capture.train_frames(), key=lambda f: (f.time, f.camera))[0]
    ref = scene.render([capture.view(first)], time=0.1)[0]
    mid = imgs[1]
    assert np.abs(mid[..., 3] - ref["alpha"]).max() < 1e-2
    # bad input is a message
    assert main(["render", str(run_dir), "--orbit", "0", "--out", str(out)]) == 1
    assert "--orbit must be" in capsys.readouterr().err
    assert main(["render", str(run_dir), "--orbit", "90", "--out", str(out), "--video", str(tmp_path / "x.avi")]) == 1
    assert "x.avi" in capsys.readouterr().err


@pytest.mark.slow
def test_render_path_file_is_camera_records(run_dir, demo_capture, tmp_path):
    from engine.io.images import read_exr_channels

    data = json.loads((demo_capture / "transforms.json").read_text())
    (tmp_path / "path.json").write_text(json.dumps({"cameras": data["cameras"], "frames": data["eval_frames"][:2]}))
    assert main(["render", str(run_dir), "--path", str(tmp_path / "path.json"), "--out", str(tmp_path / "a"),
                 "--quiet"]) == 0
    assert main(["render", str(run_dir), "--cameras", str(tmp_path / "path.json"), "--out", str(tmp_path / "b"),
                 "--quiet"]) == 0
    for name in ("000000.exr", "000001.exr"):
        a, b = read_exr_channels(tmp_path / "a" / name), read_exr_channels(tmp_path / "b" / name)
        assert np.array_equal(a["R"], b["R"])


def test_output_names_disambiguate_or_refuse():
    from engine.cameras import Intrinsics, View
    from engine.export.render_views import output_names

    k = Intrinsics(4, 4, 4.0, 4.0, 2.0, 2.0)
    c2w = np.eye(4)
    a = View(k, c2w, 0.0, "000000", {"camera": "rgb0"})
    b = View(k, c2w, 0.0, "000000", {"camera": "rgb1"})
    c = View(k, c2w, 0.0, "000001", {"camera": "rgb1"})
    assert output_names([a, c]) == ["000000", "000001"]           # no collision: names as given
    assert output_names([a, b, c]) == ["rgb0_000000", "rgb1_000000", "rgb1_000001"]
    d = View(k, c2w, 0.0, "x", {"file_path": "left/x.png"})
    e = View(k, c2w, 0.0, "x", {"file_path": "right/x.png"})
    assert output_names([d, e]) == ["left_x", "right_x"]           # no camera: the file's folder
    with pytest.raises(ValueError, match="written twice: rgb0_000000"):
        output_names([a, a])


@pytest.mark.slow
def test_export_npz(run_dir, tmp_path):
    from engine.export.npz import read_export
    from engine.scene.model import load_run

    out = tmp_path / "cache.npz"
    assert main(["export", str(run_dir), "--times", "0", "0.2", "5", "--out", str(out)]) == 0
    data = read_export(out)
    assert data["times"].tolist() == pytest.approx([0, 0.05, 0.1, 0.15, 0.2])
    scene = load_run(run_dir)
    frame = read_export(out, 2)
    np.testing.assert_allclose(frame["means"], scene.gaussians_at(0.1)["means"], atol=5e-3)


def test_cli_errors_are_messages(tmp_path, capsys):
    assert main(["eval", str(tmp_path / "no_run")]) == 1
    assert "does not exist" in capsys.readouterr().err
    assert main(["train", str(tmp_path / "no_capture"), "--out", str(tmp_path / "r"), "--quiet"]) == 1
    assert "no_capture" in capsys.readouterr().err


@pytest.mark.slow
def test_demo_command(demo_capture, tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--views", "4", *TINY]) == 0
    text = capsys.readouterr().out
    metrics = json.loads(text[: text.index("\n}") + 2])
    assert metrics["n_frames"] == 61
    orbit = sorted((out / "orbit").glob("*.png"))
    assert len(orbit) == 4 and "orbit" in text


@pytest.mark.slow
def test_eval_prune_unobserved(run_dir, tmp_path, capsys):
    """``eval --prune-unobserved``: scored without the Gaussians no train camera saw (issue 14),
    recorded in the output; a compact cache is refused with a clear message."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    assert main(["eval", str(run), "--fill-holes", "--prune-unobserved", "2"]) == 0
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    pr = out["pruned_unobserved"]
    assert pr["inset_px"] == 2.0 and pr["min_cameras"] == 1 and out["fill_holes"] is True
    assert out["num_gaussians"] == pr["left"] and f"pruned {pr['pruned']} unobserved" in captured.err
    assert main(["export", str(run), "--format", "compact", "--fps", "100", "--out", str(tmp_path / "c.bt4c")]) == 0
    capsys.readouterr()
    assert main(["eval", str(tmp_path / "c.bt4c"), "--prune-unobserved"]) == 1
    assert "needs a run folder" in capsys.readouterr().err
