"""Gaussian dropout (DropGaussian) in training renders: seeded masks, training renders only."""
from __future__ import annotations

import pytest
import torch

from engine.io.capture import load_capture
from engine.scene import model as model_mod
from engine.scene.dropout import GaussianDropout
from engine.train.config import get_preset
from engine.train.loop.trainer import Trainer
from tools.synthetic import write_synthetic_capture


def test_masks_are_seeded_by_step_and_keep_the_expected_opacity():
    o = torch.rand(40000) * 0.9 + 0.05
    a = GaussianDropout(0.2, seed=3, step=7)(o)
    assert torch.equal(a, GaussianDropout(0.2, seed=3, step=7)(o))      # a resumed run draws the same
    assert not torch.equal(a, GaussianDropout(0.2, seed=3, step=8)(o))
    dropped = a == 0
    assert abs(float(dropped.float().mean()) - 0.2) < 0.01
    torch.testing.assert_close(a[~dropped], o[~dropped] / 0.8)
    assert abs(float(a.mean() / o.mean()) - 1.0) < 0.02                  # the expected opacity is kept
    assert GaussianDropout.for_step(0.0, 3, 7) is None
    assert GaussianDropout.for_step(0.1, 3, 6, densifying=True) is not None
    assert GaussianDropout.for_step(0.1, 3, 7, densifying=False) is None  # the trainer: the densify window
    with pytest.raises(ValueError, match="drop_rate"):
        GaussianDropout(1.0, 0, 0)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return write_synthetic_capture(tmp_path_factory.mktemp("drop") / "cap", width=32, height=24, n_rgb=3,
                                   eval_fps=60.0, with_points=True)


def _rasterized_opacities(monkeypatch):
    seen = []
    real = model_mod.rasterization

    def spy(means, quats, scales, opacities, *args, **kwargs):
        seen.append((opacities.detach().clone(), torch.is_grad_enabled()))
        return real(means, quats, scales, opacities, *args, **kwargs)

    monkeypatch.setattr(model_mod, "rasterization", spy)
    return seen


@pytest.mark.parametrize("rate", [0.0, 0.3])
def test_a_training_step_renders_without_a_share_of_the_gaussians_and_evaluation_with_all(capture, monkeypatch,
                                                                                          rate):
    cfg = get_preset("fast", {"init": "ply", "iterations": 10, "gaussians.drop_rate": rate})
    tr = Trainer(load_capture(capture), cfg, device="cpu", rgb_only=True, total_steps=10)
    tr.init_model()
    seen = _rasterized_opacities(monkeypatch)
    tr.step(0)
    assert tr.model.dropout is None                      # nothing outside the step is dropped
    trained = [o for o, grad in seen if grad]
    assert trained
    zero_share = float((trained[0] == 0).float().mean())
    if rate == 0:
        assert zero_share == 0.0
    else:
        assert abs(zero_share - rate) < 0.1, zero_share
    seen.clear()
    with torch.no_grad():
        tr.model.render(tr.items[0])
    assert seen and all(float((o == 0).float().mean()) == 0.0 for o, _ in seen)
    seen.clear()
    tr.step(9)                                           # after densify.stop (0.7 x 10 steps): all of them
    assert seen and all(float((o == 0).float().mean()) == 0.0 for o, grad in seen if grad)
