"""Local rigidity priors (Luiten et al. 2024) over kNN (engine.scene.rigidity)."""
from __future__ import annotations

import math

import torch

from engine.scene.rigidity import knn_neighbours, rigidity_losses


def _axis_angle_quat(axis, angle):
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    return torch.cat([torch.tensor([math.cos(angle / 2)], dtype=torch.float64), a * math.sin(angle / 2)])


def _rot(q):
    from engine.scene.gaussians import quat_to_rotmat
    return quat_to_rotmat(q[None])[0]


def test_rigid_motion_costs_nothing_and_deformation_costs():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(50, 3, generator=g, dtype=torch.float64)
    q0 = torch.randn(50, 4, generator=g, dtype=torch.float64)
    nbr, w = knn_neighbours(x, 6)
    assert nbr.shape == (50, 6) and (nbr != torch.arange(50)[:, None]).all() and (w > 0).all()
    # a rigid motion: rotate every mean and every Gaussian's frame by R, translate
    r = _axis_angle_quat([0.3, -1.0, 0.5], 0.9)
    R = _rot(r)
    from engine.scene.rigidity import _qmul
    xt = x @ R.T + torch.tensor([1.0, 2.0, -0.5], dtype=torch.float64)
    qt = _qmul(r.expand(50, 4), q0)
    rigid = rigidity_losses(x, q0, xt, qt, nbr, w)
    for k, v in rigid.items():
        assert float(v) < 1e-9, k
    # stretch: isometry and rigidity both see it; rotations unchanged keep rot at 0
    xs = x * torch.tensor([1.5, 1.0, 1.0], dtype=torch.float64)
    st = rigidity_losses(x, q0, xs, q0, nbr, w)
    assert float(st["iso"]) > 0.05 and float(st["rigid"]) > 0.05 and float(st["rot"]) < 1e-9
    # one Gaussian turning alone: rotation similarity sees it
    qa = q0.clone()
    qa[0] = _qmul(_axis_angle_quat([0, 0, 1], 1.0)[None], q0[:1])[0]
    assert float(rigidity_losses(x, q0, x, qa, nbr, w)["rot"]) > 1e-3


def test_gradients_flow_to_positions_and_rotations():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(20, 3, generator=g, dtype=torch.float64)
    q = torch.randn(20, 4, generator=g, dtype=torch.float64)
    nbr, w = knn_neighbours(x, 4)
    xt = (x + 0.1 * torch.randn(20, 3, generator=g, dtype=torch.float64)).requires_grad_(True)
    qt = (q + 0.1 * torch.randn(20, 4, generator=g, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: sum(rigidity_losses(x, q, a, b, nbr, w).values()), (xt, qt))
