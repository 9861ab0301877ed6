"""Per-Gaussian tensors that grow and shrink in place (engine.scene.row_store): the values of
``torch.cat`` and ``t[keep]``, written into spare storage rows instead of fresh tensors."""
from __future__ import annotations

import hashlib
import io

import pytest
import torch

from engine.scene import row_store
from engine.scene.gaussians import GaussianModel
from engine.train.config import get_preset


@pytest.fixture(autouse=True)
def _enabled():
    row_store.ENABLED = True
    yield
    row_store.ENABLED = True


def _rand(*shape, seed=0):
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed))


def test_append_writes_into_spare_rows_and_grows_geometrically():
    t = _rand(10, 4, 3)
    a = row_store.append_rows(t, _rand(2, 4, 3, seed=1))
    assert torch.equal(a, torch.cat([t, _rand(2, 4, 3, seed=1)]))
    assert row_store.capacity(a) == 15  # ceil(12 x 1.25)
    b = row_store.append_rows(a, _rand(3, 4, 3, seed=2))  # fits: same storage, a's rows untouched
    assert b.data_ptr() == a.data_ptr() and b.shape[0] == 15
    assert torch.equal(b, torch.cat([t, _rand(2, 4, 3, seed=1), _rand(3, 4, 3, seed=2)]))
    assert a.shape[0] == 12 and torch.equal(a, torch.cat([t, _rand(2, 4, 3, seed=1)]))
    c = row_store.append_rows(b, _rand(1, 4, 3, seed=3))  # full: a new storage
    assert c.data_ptr() != b.data_ptr() and row_store.capacity(c) == 20
    assert torch.equal(c[:15], b)
    assert c.is_contiguous() and c.storage_offset() == 0


def test_compact_moves_kept_rows_to_the_front_in_place():
    for seed in range(6):
        base = row_store.append_rows(_rand(37, 5, 2, seed=seed), _rand(4, 5, 2, seed=seed + 9))  # spare rows
        want_src = base.clone()
        keep = torch.rand(41, generator=torch.Generator().manual_seed(seed)) > 0.3
        if seed == 0:
            keep[:] = True
        if seed == 1:
            keep[:] = False
        ptr = base.data_ptr()
        old_chunk = row_store.CHUNK_BYTES
        row_store.CHUNK_BYTES = 40 * (seed + 1)  # a few rows per chunk: chunk borders are exercised
        try:
            out = row_store.compact_rows(base, keep)
        finally:
            row_store.CHUNK_BYTES = old_chunk
        assert torch.equal(out, want_src[keep])
        assert out.data_ptr() == ptr or out.numel() == 0
        assert row_store.capacity(out) == row_store.capacity(base)


def test_zero_width_rows_and_foreign_views_fall_back_to_copies():
    empty = torch.zeros(6, 0, 3)  # sh_rest at degree 0
    assert row_store.append_rows(empty, torch.zeros(2, 0, 3)).shape == (8, 0, 3)
    assert row_store.compact_rows(empty, torch.tensor([True, False] * 3)).shape == (3, 0, 3)
    t = _rand(8, 3)
    strided = t[:, :2]  # not contiguous: a copy, t untouched
    keep = torch.tensor([True, False] * 4)
    assert torch.equal(row_store.compact_rows(strided, keep), t[keep][:, :2])
    offset = t[2:]  # not at its storage's start
    assert torch.equal(row_store.compact_rows(offset, keep[:6]), t[2:][keep[:6]])
    assert torch.equal(t, _rand(8, 3))
    with pytest.raises(ValueError, match="do not match"):
        row_store.append_rows(t, _rand(2, 4))


def test_exact_copies_only_a_view_with_spare_rows():
    t = _rand(5, 3)
    assert row_store.exact(t) is t
    a = row_store.append_rows(t, _rand(1, 3))
    e = row_store.exact(a)
    assert e is not a and torch.equal(e, a)
    assert e.untyped_storage().nbytes() == e.numel() * e.element_size()


def _model(n=50):
    g = GaussianModel(_rand(n, 3), _rand(n, 3, seed=1).abs() + 0.1)
    g.add_extra("traj_means", _rand(n, 7, 3, seed=2), 1e-3)
    g.setup_optimizer(get_preset("fast", {"gaussian_adam": "exact"}).gaussians, 1.0)
    return g


def _train_a_little(g, steps=3, seed=0):
    for s in range(steps):
        gen = torch.Generator().manual_seed(seed * 100 + s)
        loss = sum((getattr(g, n) * torch.randn(getattr(g, n).shape, generator=gen)).sum() for n in g.param_names)
        g.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        g.optimizer.step()


def _digest(g) -> str:
    h = hashlib.sha1()
    for n in g.param_names:
        p = getattr(g, n)
        h.update(n.encode() + p.detach().numpy().tobytes())
        st = g.optimizer.state.get(p, {})
        for key in ("exp_avg", "exp_avg_sq"):
            if key in st:
                h.update(st[key].numpy().tobytes())
    return h.hexdigest()


def _history(enabled: bool) -> list[str]:
    row_store.ENABLED = enabled
    torch.manual_seed(0)
    g = _model()
    out = []
    _train_a_little(g, seed=1)
    g.append({n: _rand(7, *getattr(g, n).shape[1:], seed=5) for n in g.param_names})
    out.append(_digest(g))
    _train_a_little(g, seed=2)
    g.prune(torch.arange(g.num_gaussians) % 4 == 1)
    out.append(_digest(g))
    g.append({n: _rand(3, *getattr(g, n).shape[1:], seed=6) for n in g.param_names})
    _train_a_little(g, seed=3)
    g.grad_accum += torch.rand(g.num_gaussians, generator=torch.Generator().manual_seed(4))
    g.grad_count += 1
    g.densify_and_prune(grad_threshold=0.5, percent_dense=0.01, min_opacity=0.2, max_world_scale=10.0,
                        max_gaussians=10_000, generator=torch.Generator().manual_seed(7))
    out.append(_digest(g))
    _train_a_little(g, seed=4)
    out.append(_digest(g))
    if enabled:  # the path under test ran: some tensor has spare rows
        assert any(row_store.capacity(getattr(g, n)) > g.num_gaussians for n in g.param_names)
    buf = io.BytesIO()
    torch.save(g.state(), buf)  # trims: every tensor its own size, so no spare row is written
    out.append(len(buf.getvalue()))
    assert all(row_store.capacity(getattr(g, n)) in (g.num_gaussians, -1) for n in g.param_names)
    g.append({n: _rand(4, *getattr(g, n).shape[1:], seed=8) for n in g.param_names})  # after a trim
    _train_a_little(g, seed=5)
    out.append(_digest(g))
    return out


def test_model_append_prune_densify_equal_the_copying_path():
    """Parameters and Adam moments after appends, a prune and a densification, with training
    between, are bit for bit the copying path's; the saved state is no larger (spare rows are
    not written)."""
    assert _history(True) == _history(False)


def test_training_in_place_is_bit_for_bit_the_copying_path(demo_capture):
    """Real RGB and guided steps on the demo, with densification (clone, split, prune) and the
    births of the time curriculum's admissions: the same parameters and Adam moments with and
    without the in-place rows."""
    from engine.io.capture import load_capture
    from engine.train.guidance.spike_flow import close_flow_worker
    from engine.train.loop.trainer import Trainer

    cap = load_capture(demo_capture)
    tiny = {"iterations": 24, "static_fraction": 0.2, "init_max_points": 300, "init_random_points": 100,
            "densify_from": 0.25, "densify_until": 0.9, "densify_every": 4, "time_curriculum": 0.5,
            "between_colocated_p": 1.0, "spike_skip_static": False}
    for rgb_only in (True, False):
        digests = []
        for enabled in (False, True):
            row_store.ENABLED = enabled
            torch.manual_seed(0)
            tr = Trainer(cap, get_preset("fast", tiny), device="cpu", rgb_only=rgb_only)
            tr.init_model()
            n0 = tr.model.gaussians.num_gaussians
            for i in range(24):
                tr.step(i)
            close_flow_worker(tr.run)
            g = tr.model.gaussians
            assert g.num_gaussians != n0
            if enabled:  # rows were appended in place: some storage holds spare rows
                assert any(row_store.capacity(getattr(g, n)) > g.num_gaussians for n in g.param_names)
            digests.append(_digest(g))
        assert digests[0] == digests[1], f"rgb_only={rgb_only}"
