"""Issue 13's step-cost fast paths (round "stepcost"), each against the code it replaces, bit
for bit: the flow term's subset positions (a numba gather / scatter instead of per-column
torch ops and row gathers), the stereo depth term (flat pixel indices hoisted out of the
step) and OpenCV's DIS flow through one reused object."""
from __future__ import annotations

import types

import pytest
import torch

from engine.scene import trajectory as traj
from engine.scene.model import TRAJ_MEANS
from engine.train.guidance import spike_flow, spike_flow_pairs
from engine.train.losses import terms as losses

pytestmark = pytest.mark.skipif(not traj.KERNELS.available(), reason="numba kernels unavailable")


def _bits(x: torch.Tensor) -> torch.Tensor:
    """Integer view of a float tensor: equality of these is equality bit for bit (signed zeros, NaNs)."""
    return x.contiguous().view(torch.int32 if x.dtype == torch.float32 else torch.int64)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_inner_only_positions_kernel_equals_the_torch_columns(dtype, monkeypatch):
    """Value and gradient of the flow term's subset positions: numba pair = per-column torch
    ops, bit for bit, at and between the knots, for a random distinct subset (gradient only in
    the subset's rows' inner columns)."""
    gen = torch.Generator().manual_seed(5)
    n, knots = 300, [0.0, 0.1, 0.2, 0.3]
    params = (torch.randn(n, 3 * (len(knots) - 1) + 1, 3, generator=gen, dtype=dtype) * 0.01).requires_grad_(True)
    means = torch.randn(n, 3, generator=gen, dtype=dtype).requires_grad_(True)
    model = types.SimpleNamespace(gaussians=types.SimpleNamespace(means=means, **{TRAJ_MEANS: params}),
                                  trajectory={"knots": knots})
    idx = torch.randperm(n, generator=torch.Generator().manual_seed(6))[: n // 3]
    w = torch.randn(idx.numel(), 3, generator=torch.Generator().manual_seed(7), dtype=dtype)
    calls = []
    for name in ("inner_at", "inner_at_backward"):
        kernel = getattr(traj.KERNELS.module, name)
        monkeypatch.setattr(traj.KERNELS.module, name, lambda *a, _k=kernel, _n=name: (calls.append(_n), _k(*a))[1])
    for t in (knots[0], 0.05, knots[1], 0.137, 0.29, knots[-1]):
        out = []
        for fused in (False, True):
            monkeypatch.setattr(spike_flow, "FUSED_INNER", fused)
            params.grad = None
            x = spike_flow.inner_only_positions(model, t, idx)
            (x * w).sum().backward()
            out.append((x.detach(), params.grad.clone()))
        assert out[0][0].dtype == dtype and means.grad is None
        assert torch.equal(_bits(out[0][0]), _bits(out[1][0])) and torch.equal(_bits(out[0][1]), _bits(out[1][1]))
        rows = torch.zeros(n, dtype=torch.bool)
        rows[idx] = True
        assert torch.all(out[1][1][~rows] == 0) and torch.all(out[1][1][:, 0::3] == 0)
    assert calls == ["inner_at", "inner_at_backward"] * 6  # the fused runs took the kernels


def test_subset_positions_equal_the_gathered_evaluation(monkeypatch):
    """The flow term's no-gradient positions of a row subset (surface reprojection, interval fit):
    the kernel reading the rows in place = ``means[idx] + evaluate(curves[idx])``, bit for bit."""
    gen = torch.Generator().manual_seed(8)
    n, knots = 500, [0.0, 0.04, 0.1, 0.13, 0.2]
    params = (torch.randn(n, 3 * (len(knots) - 1) + 1, 3, generator=gen) * 0.05).requires_grad_(True)
    means = torch.randn(n, 3, generator=gen).requires_grad_(True)
    model = types.SimpleNamespace(gaussians=types.SimpleNamespace(means=means, **{TRAJ_MEANS: params}),
                                  trajectory={"knots": knots})
    idx = torch.randperm(n, generator=gen)[:123]
    calls = []
    kernel = traj.KERNELS.module.inner_at
    monkeypatch.setattr(traj.KERNELS.module, "inner_at", lambda *a: (calls.append(1), kernel(*a))[1])
    for t in (0.0, 0.013, 0.04, 0.0999, 0.17, 0.2, 0.25):
        with torch.no_grad():
            ref = means[idx] + traj.evaluate(params[idx], knots, t)
        fast = spike_flow.subset_positions(model, t, idx)
        assert not fast.requires_grad and torch.equal(_bits(fast), _bits(ref))
    assert len(calls) == 7
    monkeypatch.setattr(spike_flow, "FUSED_INNER", False)
    assert torch.equal(spike_flow.subset_positions(model, 0.013, idx), means.detach()[idx]
                       + traj.evaluate(params.detach()[idx], knots, 0.013)) and len(calls) == 7


def _stereo_ctx(trainer, h=12, w=16, seed=0):
    gen = torch.Generator().manual_seed(seed)
    mask = torch.rand(h, w, generator=gen) < 0.4
    item = {"stereo_depth": 1.0 + torch.rand(h, w, generator=gen), "stereo_mask": mask}
    depth = (1.0 + torch.rand(1, h, w, 1, generator=gen)).requires_grad_(True)
    return types.SimpleNamespace(run=trainer, item=item, meta={"depths": depth}), depth


def test_stereo_depth_hoisted_indices_equal_the_boolean_masks(monkeypatch):
    """Loss and depth gradient bit for bit the boolean-mask form's, on the first call (cache
    filled), a second one (cache hit) and another item (its own entry)."""
    from train_util import fake_run

    trainer = fake_run()
    for ctx, depth in (_stereo_ctx(trainer, seed=0),) * 2 + (_stereo_ctx(trainer, seed=1),):
        out = []
        for hoist in (False, True):
            monkeypatch.setattr(losses, "HOIST_STEREO", hoist)
            depth.grad = None
            val = losses._stereo_depth(ctx)
            (val * 3.0).backward()
            out.append((val.detach(), depth.grad.clone()))
        assert torch.equal(_bits(out[0][0]), _bits(out[1][0])) and torch.equal(_bits(out[0][1]), _bits(out[1][1]))
    assert len(trainer.memo["stereo_pixels"]) == 2


def _textures(seed=0):
    """Small 8-bit grey images: a blurred random texture, shifted a few pixels, with noise, at
    two sizes (80 x 60 and 120 x 90)."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(seed)
    out = []
    for w, h in ((80, 60), (120, 90)):
        base = cv2.GaussianBlur(rng.random((h + 20, w + 20)).astype(np.float32), (0, 0), 1.5)
        base = (base - base.min()) / (base.max() - base.min())
        for dx, dy in ((0, 0), (3, 1), (1, 4)):
            img = base[10 + dy:10 + dy + h, 10 + dx:10 + dx + w] + 0.03 * rng.standard_normal((h, w))
            out.append((np.clip(img, 0, 1) * 255).astype(np.uint8))
    return out


def test_dense_flow_with_a_reused_dis_object_is_a_fresh_ones_bit_for_bit(monkeypatch):
    """DIS keeps no state between calc() calls without an initial flow: flows through this
    thread's one object (sizes, scales and pairs interleaved) equal a new object's per call."""
    import numpy as np

    from engine.train.motion import scene_flow

    imgs = _textures()
    pairs = [(a, b) for a in range(6) for b in range(6) if a != b and (a < 3) == (b < 3)]
    for a, b in pairs:
        for up, scale in ((2, 0), (1, None), (1, 0)):
            monkeypatch.setattr(scene_flow, "REUSE_DIS", True)
            reused = scene_flow.dense_flow(imgs[a], imgs[b], up, scale)
            monkeypatch.setattr(scene_flow, "REUSE_DIS", False)
            fresh = scene_flow.dense_flow(imgs[a], imgs[b], up, scale)
            assert np.array_equal(reused.view(np.int32), fresh.view(np.int32)), (a, b, up, scale)
    monkeypatch.setattr(scene_flow, "REUSE_DIS", True)
    assert scene_flow._dis(0) is scene_flow._dis(0) and scene_flow._dis(None) is not scene_flow._dis(0)
    assert np.abs(scene_flow.dense_flow(imgs[0], imgs[1])).max() > 1.0  # a real flow, not zeros


def test_flow_pair_on_two_threads_equals_one_after_the_other(monkeypatch):
    """The spike-view flow term's pair (forward flow here, backward flow on the worker thread):
    the same flow and validity, bit for bit, as computing them in turn."""
    import numpy as np

    imgs = [i.astype(np.float32) / 255.0 for i in _textures(1)[:3]]
    for a, b in ((0, 1), (1, 2), (2, 0)):
        out = []
        for parallel in (False, True):
            monkeypatch.setattr(spike_flow_pairs, "PARALLEL_PAIR", parallel)
            out.append(spike_flow_pairs.flow_pair(imgs[a], imgs[b]))
        assert np.array_equal(out[0][0].view(np.int32), out[1][0].view(np.int32))
        assert np.array_equal(out[0][1], out[1][1]) and out[1][1].any()
    assert spike_flow_pairs._PAIR_POOL  # the worker was used
