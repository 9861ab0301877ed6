"""No black holes (issue 14): push-pull fill of what the Gaussians do not cover."""
from __future__ import annotations

import torch

from engine.raster.holes import fill_uncovered


def test_covered_pixels_are_unchanged_and_cracks_take_their_edges_colour():
    rgb = torch.rand(20, 30, 3)
    assert torch.allclose(fill_uncovered(rgb, torch.ones(20, 30), (0, 0, 0)), rgb)
    red = torch.zeros(20, 30, 3)
    red[..., 0] = 0.8
    alpha = torch.ones(20, 30)
    alpha[:, 14:16] = 0.0                       # a crack showing the black background
    shown = red * alpha[..., None]
    out = fill_uncovered(shown, alpha, (0, 0, 0))
    assert torch.allclose(out[:, 14:16, 0], torch.full((20, 2), 0.8), atol=1e-5)
    assert float(out[..., 1:].abs().max()) < 1e-6


def test_wide_border_gets_the_nearest_colour_not_the_background():
    img = torch.zeros(16, 32, 3)
    img[:, :16] = torch.tensor([0.2, 0.4, 0.9])  # left half covered, blue-ish
    alpha = torch.zeros(16, 32)
    alpha[:, :16] = 1.0
    bg = (0.0, 1.0, 0.0)                         # a green background must not appear
    shown = img * alpha[..., None] + (1 - alpha[..., None]) * torch.tensor(bg)
    out = fill_uncovered(shown, alpha, bg)
    assert torch.allclose(out[:, 16:], torch.tensor([0.2, 0.4, 0.9]).expand(16, 16, 3), atol=1e-4)
    # partial coverage keeps the Gaussians' share and fills only the rest
    half = torch.full((16, 32), 0.5)
    out2 = fill_uncovered(torch.full((16, 32, 3), 0.25) + 0.5 * torch.tensor(bg), half, bg)
    assert torch.allclose(out2, torch.full((16, 32, 3), 0.5), atol=1e-5)


def test_nothing_covered_shows_the_background():
    out = fill_uncovered(torch.tensor([0.1, 0.2, 0.3]).expand(8, 8, 3), torch.zeros(8, 8), (0.1, 0.2, 0.3))
    assert torch.allclose(out, torch.tensor([0.1, 0.2, 0.3]).expand(8, 8, 3))


def test_eval_can_score_what_a_viewer_sees(tmp_path):
    import numpy as np

    from engine.evaluate import evaluate
    from engine.scene.model import load_run
    from engine.train import train
    from tools.synthetic import write_synthetic_capture

    cap = write_synthetic_capture(tmp_path / "cap", width=32, height=24, n_rgb=2, eval_fps=30.0)
    train(cap, tmp_path / "r", overrides={"iterations": 2, "init": "random", "init_random_points": 60}, rgb_only=True)
    filled = evaluate(tmp_path / "r", cap, write=False, fill_holes=True)
    raw = evaluate(tmp_path / "r", cap, write=False)
    assert filled["fill_holes"] is True and raw["fill_holes"] is False
    scene = load_run(tmp_path / "r")
    from engine.io.capture import load_capture

    view = load_capture(cap).view(load_capture(cap).eval_frames[0])
    a, b = scene.render([view])[0], scene.render([view], fill_holes=True)[0]
    holes = a["alpha"] < 0.5
    assert holes.any() and np.array_equal(a["alpha"], b["alpha"])
    assert b["rgb"][holes].mean() > a["rgb"][holes].mean() + 0.05  # no longer the black background
    assert filled["psnr"] != raw["psnr"]
