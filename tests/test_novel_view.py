"""engine.evaluate.novel_view: coverage, depth error, observed mask and the per-camera table, on cases
with a known answer."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from test_ground_truth import make_capture

from engine.cameras import GL_TO_CV, Intrinsics, View
from engine.evaluate.novel_view import (
    coverage,
    depth_error,
    error_heatmap,
    evaluate_novel_views,
    format_table,
    observed_mask,
    relative_depth_error,
    visible_in,
)
from engine.io.capture import load_capture
from engine.io.images import read_image
from engine.raster import rasterization

K = Intrinsics(64, 48, 40.0, 40.0, 32.0, 24.0)
TILT = 0.3  # plane z = 2 + TILT * x (camera frame)


def cv_view(x: float = 0.0, k: Intrinsics = K) -> View:
    """A camera at (x, 0, 0) looking along +z of the OpenCV frame (= world here)."""
    c2w_cv = np.eye(4)
    c2w_cv[0, 3] = x
    return View(k, c2w_cv @ GL_TO_CV)  # OpenGL camera-to-world


def plane_depth(view: View, x_max: float = 0.6, y_max: float = 0.45) -> np.ndarray:
    """Analytic planar depth of the patch |x| <= x_max, |y| <= y_max of z = 2 + TILT x."""
    k = view.intrinsics
    a = (np.arange(k.width) + 0.5 - k.cx) / k.fx
    b = (np.arange(k.height) + 0.5 - k.cy) / k.fy
    aa, bb = np.meshgrid(a, b)
    z = 2.0 / (1.0 - TILT * aa)
    inside = (np.abs(aa * z) <= x_max) & (np.abs(bb * z) <= y_max)
    return np.where(inside, z, np.inf).astype(np.float32)


def render_plane(keep=lambda x, y: np.ones_like(x, bool)):
    """Rasterize a dense grid of small opaque Gaussians on the plane patch."""
    s = 0.02
    xs, ys = np.meshgrid(np.arange(-0.6 + s / 2, 0.6, s), np.arange(-0.45 + s / 2, 0.45, s))
    m = keep(xs, ys)
    xs, ys = xs[m], ys[m]
    means = torch.tensor(np.stack([xs, ys, 2.0 + TILT * xs], 1), dtype=torch.float32)
    n = len(means)
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)
    scales = torch.full((n, 3), 0.7 * s)
    rgb, alpha, meta = rasterization(means, quats, scales, torch.full((n,), 0.99), torch.full((n, 3), 0.5),
                                     torch.eye(4)[None], torch.tensor(K.K, dtype=torch.float32)[None],
                                     K.width, K.height, backend="torch")
    return alpha[0, ..., 0].numpy(), meta["depths"][0, ..., 0].numpy()


def test_plane_of_gaussians_matches_analytic_depth_and_full_coverage():
    gt = plane_depth(cv_view())
    alpha, depth = render_plane()
    assert coverage(alpha, gt) > 0.97
    med, p90 = depth_error(depth, alpha, gt)
    assert med < 0.015 and p90 < 0.03  # measured 0.75 %: front Gaussians of a tilted plane weigh more
    # depth is normalised by alpha: a half-transparent plane has the same expected depth
    err = relative_depth_error(depth, alpha, gt)
    assert np.nanmax(err[8:40, 20:44]) < 0.01


def test_coverage_and_depth_error_catch_a_hole_and_a_shifted_half():
    gt = plane_depth(cv_view())
    alpha, depth = render_plane(lambda x, y: x < 0.0)  # right half missing
    inside = np.isfinite(gt)
    right = inside & (np.arange(K.width)[None, :] + 0.5 > K.cx)
    assert coverage(alpha, gt) == pytest.approx(1.0 - right.sum() / inside.sum(), abs=0.05)
    # a 5 % deeper render: median relative error 5 %
    alpha, depth = render_plane()
    med, p90 = depth_error(depth * 1.05, alpha, gt)
    assert med == pytest.approx(0.05, abs=0.012)  # 5 % less the render's own ~0.75 % bias
    heat = error_heatmap(relative_depth_error(depth, alpha, gt), gt, np.zeros_like(alpha))
    assert np.all(heat[inside] == (1.0, 0.0, 1.0))  # every GT pixel a hole: magenta


def test_depth_error_exact_values():
    gt = np.array([[1.0, 2.0, np.inf, 4.0]], np.float32)
    depth = np.array([[1.1, 2.0, 5.0, 3.0]], np.float32)
    alpha = np.array([[1.0, 1.0, 1.0, 0.2]], np.float32)
    med, p90 = depth_error(depth, alpha, gt)  # pixels 0 and 1 count: errors 0.1 and 0
    assert med == pytest.approx(0.05) and p90 == pytest.approx(0.09)
    assert coverage(alpha, gt) == pytest.approx(2 / 3)
    assert np.isnan(coverage(alpha, np.full_like(gt, np.inf)))


def test_observed_mask_frustum_and_occlusion():
    wall = np.full((K.height, K.width), 5.0, np.float32)
    # same pose: everything observed, except behind an occluder in the train view
    train_depth = wall.copy()
    train_depth[10:20, 30:50] = 2.0
    seen = observed_mask(cv_view(), wall, [(cv_view(), train_depth)])
    assert not seen[11:19, 31:49].any()
    outside = np.ones_like(seen)
    outside[9:21, 29:51] = False
    assert seen[outside].all()
    # train camera 2 m to the right: eval pixels left of its frustum edge are unseen
    seen = observed_mask(cv_view(), wall, [(cv_view(2.0), wall)])
    u = np.arange(K.width) + 0.5
    x_world = (u - K.cx) / K.fx * 5.0
    u_train = K.fx * (x_world - 2.0) / 5.0 + K.cx
    expect = np.broadcast_to(u_train >= 0, seen.shape)
    assert (seen == expect).mean() > 0.98 and seen.any() and not seen.all()
    # union over views; no GT surface -> never observed
    wall[0, 0] = np.inf
    seen = observed_mask(cv_view(), wall, [(cv_view(2.0), wall), (cv_view(), wall)])
    assert seen.sum() == seen.size - 1 and not seen[0, 0]
    pts = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 5.0]])  # behind the camera / on the wall
    assert visible_in(cv_view(), np.full((K.height, K.width), 5.0), pts).tolist() == [False, True]


class _PerfectScene:
    """Renders exactly the capture's ground truth: the table must read perfect."""

    def __init__(self, cap):
        self.by_time = {(f.camera, round(f.time, 6)): f for f in cap.eval_frames}

    def render(self, views):
        out = []
        for v in views:
            f = self.by_time[(v.extra["camera"], round(v.time, 6))]
            z = f.load_depth()
            out.append({"rgb": read_image(f.path), "alpha": np.isfinite(z).astype(np.float32),
                        "depth": np.where(np.isfinite(z), z, 0.0).astype(np.float32)})
        return out


def test_table_on_a_perfect_render(tmp_path):
    cap = load_capture(make_capture(tmp_path / "c"))
    res = evaluate_novel_views(_PerfectScene(cap), cap, tmp_path / "img")
    row = res["cameras"]["eval0"]
    assert row["n"] == 2 and row["coverage"] == 1.0 and row["depth_med"] == 0.0 and row["psnr_rgb"] > 100
    assert row["psnr_between"] is None  # both eval instants are RGB instants
    assert row["psnr_moving"] > 100  # the patch that changes between the two instants
    assert 0.0 < row["observed"] <= 1.0
    strips = sorted((tmp_path / "img").glob("eval0_*.png"))
    assert strips and read_image(strips[0]).shape == (6, 3 * 8 + 4, 3)
    assert (tmp_path / "img/novel_view.json").is_file()
    text = format_table(res["cameras"], {"eval0": "0° side"})
    assert "| eval0 (0° side) |" in text and "100.0%" in text


@pytest.mark.slow  # a 4-step training run: ~13 s under load
def test_eval_per_camera_command(tmp_path, capsys, demo_capture):
    from engine.__main__ import main

    cap = make_capture(tmp_path / "c")
    run = tmp_path / "run"
    assert main(["train", str(cap), "--out", str(run), "--quiet", "--set", "iterations=4",
                 "--set", "init=random", "--set", "init_random_points=200"]) == 0
    capsys.readouterr()
    assert main(["eval", str(run), "--per-camera"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].startswith("| camera | PSNR@rgb |") and "| eval0 (" in out
    assert sorted(p.name for p in (run / "novel_view").iterdir()) == [
        "eval0_0000.0ms.png", "novel_view.json", "novel_view.md"]
    # a capture without ground-truth depth: a clear message, exit 1
    assert main(["eval", str(run), str(demo_capture), "--per-camera"]) == 1
    assert "no eval frame carries ground-truth depth" in capsys.readouterr().err
