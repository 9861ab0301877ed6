"""The curves' gradient buffers (engine.scene.grad_buffers): one buffer per leaf, reused from
step to step, all zeros whenever it is handed out, so every gradient is the fresh path's."""
from __future__ import annotations

import gc

import pytest
import torch

from engine.scene import grad_buffers
from engine.scene import trajectory as traj

KNOTS = [0.0, 0.1, 0.2, 0.3, 0.4]


@pytest.fixture(autouse=True)
def _fresh(monkeypatch):
    monkeypatch.setattr(grad_buffers, "MIN_BYTES", 0)  # the tests' curves are small
    grad_buffers.clear()
    yield
    grad_buffers.ENABLED = True
    grad_buffers.clear()


def _curves(seed=0, n=40, c=3):
    g = torch.Generator().manual_seed(seed)
    return torch.nn.Parameter(torch.randn(n, traj.num_controls(len(KNOTS)), c, generator=g))


def _backward(p, times, foreign=False, prior=False):
    """One step's backward: curve readers at ``times`` (and optionally the inner-residual prior
    and a plain-autograd reader of one column that does not go through the sink)."""
    g = torch.Generator().manual_seed(len(times))
    loss = sum((traj.evaluate(p, KNOTS, t) * torch.randn(p.shape[0], p.shape[2], generator=g)).sum()
               for t in times)
    if prior:
        loss = loss + traj.inner_residual_sq(p).mean()
    if foreign:
        loss = loss + (p[:, 11] * 3.0).sum()  # autograd's own accumulation into .grad
    with traj.gradient_sink():
        loss.backward()
    return p.grad


def _run(enabled, steps):
    grad_buffers.ENABLED = enabled
    grad_buffers.clear()
    p = _curves()
    out = []
    for kw in steps:
        p.grad = None  # what zero_grad(set_to_none=True) does
        out.append(_backward(p, **kw).clone())
    return out


STEPS = [dict(times=[0.1]), dict(times=[0.25, 0.3]), dict(times=[0.05], prior=True),
         dict(times=[0.35], foreign=True), dict(times=[0.2]), dict(times=[0.15, 0.4], prior=True), dict(times=[0.0])]


def test_reused_buffers_give_the_fresh_path_s_gradients():
    fresh, pooled = _run(False, STEPS), _run(True, STEPS)
    for a, b in zip(fresh, pooled):
        assert torch.equal(a, b)  # == (a fresh kernel-written -0.0 equals the buffer's +0.0)


def test_one_buffer_per_leaf_zeroed_where_it_was_written():
    p = _curves()
    first = _backward(p, [0.25])
    ptr = first.data_ptr()
    written = set(traj.segment_weights(KNOTS, 0.25)[i][0] for i in range(len(traj.segment_weights(KNOTS, 0.25))))
    assert {c for c in range(p.shape[1]) if first[:, c].abs().sum() > 0} == written
    p.grad = None
    second = _backward(p, [0.1])  # an RGB instant: one junction column
    assert second.data_ptr() == ptr  # the same memory, no new allocation
    assert {c for c in range(p.shape[1]) if second[:, c].abs().sum() > 0} == {3}


def test_a_gradient_from_outside_the_sink_zeroes_the_whole_buffer_next_time(monkeypatch):
    p = _curves()
    _backward(p, [0.1], foreign=True)
    assert p.grad[:, 11].abs().sum() > 0  # the foreign reader's column, not marked by any sunk reader
    p.grad = None
    zeroed = []
    real = torch.Tensor.zero_
    monkeypatch.setattr(torch.Tensor, "zero_", lambda t: (zeroed.append(t.shape), real(t))[1])
    g = _backward(p, [0.1])
    assert zeroed and g[:, 11].abs().sum() == 0
    p.grad = None
    zeroed.clear()
    _backward(p, [0.1])  # only the sink's readers since: the written column is zeroed, not the whole
    assert not zeroed


def test_a_dead_leaf_s_buffer_is_dropped():
    p = _curves()
    _backward(p, [0.1])
    assert len(grad_buffers._BUFFERS) == 1
    del p
    gc.collect()
    assert not grad_buffers._BUFFERS  # with its leaf, not at the next take
    q = _curves(1)
    _backward(q, [0.1])
    assert len(grad_buffers._BUFFERS) == 1 and next(iter(grad_buffers._BUFFERS.values())).leaf() is q


def test_off_the_sink_disabled_or_small_nothing_is_kept(monkeypatch):
    p = _curves()
    (traj.evaluate(p, KNOTS, 0.1).sum()).backward()  # no gradient_sink: autograd as usual
    assert not grad_buffers._BUFFERS
    monkeypatch.setattr(grad_buffers, "MIN_BYTES", p.numel() * 4 + 1)  # one byte short
    p.grad = None
    _backward(p, [0.1])
    assert not grad_buffers._BUFFERS
    monkeypatch.setattr(grad_buffers, "MIN_BYTES", 0)
    grad_buffers.ENABLED = False
    p.grad = None
    _backward(p, [0.1])
    assert not grad_buffers._BUFFERS


@pytest.mark.slow
def test_training_with_reused_buffers_is_bit_for_bit_the_fresh_path(demo_capture):
    """Real RGB and guided steps on the demo (densification included): the same parameters and
    Adam moments with and without the buffers."""
    import hashlib

    from engine.io.capture import load_capture
    from engine.train.config import get_preset
    from engine.train.guidance.spike_flow import close_flow_worker
    from engine.train.loop.trainer import Trainer

    cap = load_capture(demo_capture)
    tiny = {"iterations": 10, "static_fraction": 0.2, "init_max_points": 300, "init_random_points": 100,
            "densify_from": 0.3, "densify_until": 0.9, "densify_every": 3, "time_curriculum": 0.0,
            "between_colocated_p": 1.0, "spike_skip_static": False, "traj_carry": "velocity"}
    for rgb_only in (True, False):
        digests = []
        for enabled in (False, True):
            grad_buffers.ENABLED = enabled
            grad_buffers.clear()
            torch.manual_seed(0)
            tr = Trainer(cap, get_preset("fast", tiny), device="cpu", rgb_only=rgb_only)
            tr.init_model()
            for i in range(10):
                tr.step(i)
            close_flow_worker(tr.run)
            opt = tr.model.gaussians.optimizer
            h = hashlib.sha1()
            for grp in opt.param_groups:
                for q in grp["params"]:
                    h.update(q.detach().numpy().tobytes())
                    for key in ("exp_avg", "exp_avg_sq"):
                        if key in opt.state.get(q, {}):
                            h.update(opt.state[q][key].numpy().tobytes())
            digests.append(h.hexdigest())
            assert bool(grad_buffers._BUFFERS) == enabled
        assert digests[0] == digests[1], f"rgb_only={rgb_only}"


def test_a_replaced_leaf_s_buffer_is_carried_zeroed_and_grown_in_place():
    """Densification / births replace a curve's leaf: its buffer, zeroed, becomes the new leaf's,
    in the same storage while it has room (no fresh zero buffer), and gradients stay the fresh
    path's."""
    from engine.scene import row_store

    old = _curves(n=40)
    _backward(old, [0.1, 0.25])  # the buffer is taken and written
    buf = old.grad
    assert grad_buffers.holds(old, buf) and buf.abs().sum() > 0
    keep = torch.arange(40) % 5 != 0  # 32 kept, 6 appended: 38 rows fit in the 40-row buffer
    extra = torch.randn(6, *old.shape[1:], generator=torch.Generator().manual_seed(1))
    new = torch.nn.Parameter(row_store.append_rows(old.detach()[keep], extra))
    grad_buffers.carry(old, new, keep, 6)
    got = grad_buffers.take(new)
    assert got.shape == new.shape and not got.any() and got.data_ptr() == buf.data_ptr()
    carried = _backward(new, [0.3], prior=True).clone()
    grad_buffers.ENABLED = False
    fresh_leaf = torch.nn.Parameter(new.detach().clone())
    assert torch.equal(carried, _backward(fresh_leaf, [0.3], prior=True))
    grad_buffers.ENABLED = True
    grows = torch.nn.Parameter(row_store.append_rows(new.detach(), torch.zeros(30, *new.shape[1:])))
    grad_buffers.carry(new, grows, None, 30)  # no room: a larger storage, still all zeros
    assert not grad_buffers.take(grows).any() and grad_buffers.take(grows).shape == grows.shape
