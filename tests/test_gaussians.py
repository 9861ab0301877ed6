"""GaussianModel: activation, SH convention, densification with Adam state, serialisation."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from engine.scene.gaussians import GaussianModel, eval_sh, knn_mean_distance, num_sh_bases, rgb_to_sh, sh_to_rgb
from engine.train.config import get_preset


def _model(n=6, sh_degree=0, seed=0):
    rng = np.random.default_rng(seed)
    g = GaussianModel(rng.normal(size=(n, 3)), rng.uniform(size=(n, 3)), sh_degree=sh_degree, init_opacity=0.5)
    g.setup_optimizer(get_preset("fast").gaussians, extent=2.0)
    return g


def _adam_step(g):
    g.optimizer.zero_grad()
    loss = sum((p ** 2).sum() for p in g.params().values()) + g.means.sum()
    loss.backward()
    g.optimizer.step()


def test_init_colours_round_trip_and_scales_from_neighbours():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5]], np.float32)
    cols = np.array([[0.1, 0.5, 0.9]] * 5, np.float32)
    g = GaussianModel(pts, cols, sh_degree=2)
    assert g.sh.shape == (5, num_sh_bases(2), 3)
    np.testing.assert_allclose(g.colors().detach().numpy(), cols, atol=1e-6)
    d = knn_mean_distance(torch.as_tensor(pts), k=3)
    np.testing.assert_allclose(g.scales[:, 0].detach().numpy(), d.numpy(), rtol=1e-5)
    assert float(d[0]) == pytest.approx(1.0)
    np.testing.assert_allclose(g.opacities.detach().numpy(), 0.1, rtol=1e-5)
    assert float(sh_to_rgb(rgb_to_sh(torch.tensor(0.3)))) == pytest.approx(0.3)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_sh_matches_the_rasterizer_convention(degree):
    from engine.raster.projection import eval_colors

    torch.manual_seed(degree)
    n = 7
    means = torch.randn(n, 3)
    sh = torch.randn(n, num_sh_bases(degree), 3) * 0.3
    viewmat = torch.eye(4)
    viewmat[:3, 3] = torch.tensor([0.3, -0.2, 4.0])
    campos = -viewmat[:3, :3].T @ viewmat[:3, 3]
    mine = (eval_sh(degree, sh, means - campos) + 0.5).clamp_min(0)
    theirs = eval_colors(means, sh, viewmat[None], degree)[0]
    torch.testing.assert_close(mine, theirs, atol=1e-5, rtol=1e-5)


def test_clone_split_prune_rebuilds_optimizer_and_keeps_moments():
    g = _model(n=6)
    _adam_step(g)
    # Gaussians 0, 1 small (clone), 2 big (split), 3 transparent (prune), 4, 5 untouched
    with torch.no_grad():
        g.log_scales[:] = np.log(0.001)
        g.log_scales[2] = np.log(0.5)
        g.opacity_logits[3] = -10.0
    g.grad_accum[:] = torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])
    g.grad_count[:] = 1.0
    old_avg = g.optimizer.state[g.means]["exp_avg"].clone()
    old_means = g.means.detach().clone()
    info = g.densify_and_prune(grad_threshold=0.5, percent_dense=0.01, min_opacity=0.005, max_world_scale=10.0,
                               max_gaussians=100, generator=torch.Generator().manual_seed(0))
    assert info["cloned"] == 2 and info["split"] == 1 and info["pruned"] == 1
    # kept: 0, 1, 4, 5 ; added: 2 clones + 2 split children
    assert g.num_gaussians == 4 + 2 + 2
    keep = [0, 1, 4, 5]
    torch.testing.assert_close(g.means.detach()[:4], old_means[keep])
    torch.testing.assert_close(g.means.detach()[4:6], old_means[[0, 1]])
    children = g.means.detach()[6:]
    assert torch.all((children - old_means[2]).norm(dim=1) < 5 * 0.5)
    np.testing.assert_allclose(g.scales.detach()[6:].numpy(), 0.5 / 1.6, rtol=1e-5)
    # optimiser: every group holds the new tensor; moments carried for kept rows, zero for new
    for grp in g.optimizer.param_groups:
        p = grp["params"][0]
        assert p is getattr(g, grp["name"])
        st = g.optimizer.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape
    avg = g.optimizer.state[g.means]["exp_avg"]
    torch.testing.assert_close(avg[:4], old_avg[keep])
    assert torch.all(avg[4:] == 0)
    assert g.grad_accum.shape == (8,) and float(g.grad_accum.sum()) == 0
    _adam_step(g)  # the rebuilt optimiser still steps


def test_densify_respects_the_gaussian_cap():
    g = _model(n=10)
    with torch.no_grad():
        g.log_scales[:] = np.log(0.001)
    g.grad_accum[:] = torch.arange(10, dtype=torch.float32) + 1
    g.grad_count[:] = 1
    g.densify_and_prune(grad_threshold=0.5, percent_dense=0.01, min_opacity=0.0, max_world_scale=10.0,
                        max_gaussians=13)
    assert g.num_gaussians == 13


def test_prune_big_in_world_space():
    g = _model(n=4)
    with torch.no_grad():
        g.log_scales[:] = np.log(0.01)
        g.log_scales[1] = np.log(3.0)  # > 0.2 * extent (extent 2)
    g.densify_and_prune(grad_threshold=1e9, percent_dense=0.01, min_opacity=0.0, max_world_scale=0.2,
                        max_gaussians=100)
    assert g.num_gaussians == 3


def test_densification_stats_are_in_ndc_units_and_visible_only():
    g = _model(n=3)
    grad = torch.tensor([[[1e-4, 0.0], [0.0, 1e-4], [1.0, 1.0]]])
    radii = torch.tensor([[1, 1, 0]], dtype=torch.int32)
    g.add_densification_stats(grad, radii, width=200, height=100)
    np.testing.assert_allclose(g.grad_accum.numpy(), [1e-4 * 100, 1e-4 * 50, 0.0], rtol=1e-5)
    np.testing.assert_allclose(g.grad_count.numpy(), [1, 1, 0])


def test_opacity_reset_and_means_lr_decay():
    g = _model(n=5)
    _adam_step(g)
    g.reset_opacity(0.01)
    assert float(g.opacities.detach().max()) <= 0.01 + 1e-6
    assert float(g.optimizer.state[g.opacity_logits]["exp_avg"].abs().sum()) == 0
    cfg = get_preset("fast")
    lr0 = g.update_learning_rate(0.0)
    lr1 = g.update_learning_rate(1.0)
    assert lr0 == pytest.approx(cfg.gaussians.lr_means * 2.0)
    assert lr1 == pytest.approx(cfg.gaussians.lr_means_final * 2.0)
    assert lr1 < g.update_learning_rate(0.5) < lr0


def test_state_round_trip_with_optimizer():
    g = _model(n=5, sh_degree=1)
    _adam_step(g)
    g.oneup_sh_degree()
    g2 = GaussianModel.from_state(g.state(), get_preset("fast").gaussians)
    assert g2.active_sh_degree == 1 and g2.max_sh_degree == 1 and g2.extent == 2.0
    for n, p in g.params().items():
        torch.testing.assert_close(getattr(g2, n).detach(), p.detach())
    torch.testing.assert_close(g2.optimizer.state[g2.means]["exp_avg"], g.optimizer.state[g.means]["exp_avg"])
    _adam_step(g)
    _adam_step(g2)
    torch.testing.assert_close(g2.means.detach(), g.means.detach())
