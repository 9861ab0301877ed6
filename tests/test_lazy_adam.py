"""LazyCurveAdam (engine.scene.lazy_adam): FusedAdam bit for bit when every curve column is
touched at every step; dense Adam to rounding after the skipped steps are caught up; the
numba kernels against the plain-torch reference; untouched columns left alone until a touch
or ``settle``; densification, checkpoints and the curriculum's carry settle first."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from train_util import fake_run

from engine.scene import fused_adam, lazy_adam, trajectory
from engine.scene import gaussians as gaussians_mod
from engine.scene.fused_adam import FusedAdam
from engine.scene.lazy_adam import LazyCurveAdam
from engine.scene.model import TRAJ_MEANS, TRAJ_QUATS
from engine.train.config import get_preset
from tests.test_selective_adam import _model, _view  # a 300-Gaussian model with 4-knot curves, a 48x32 view

N, K = 1031, 19
SHAPES = [(N, 3), (N, K, 3), (N, K, 4)]  # one plain group, two curves


def _params(seed=0):
    g = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(s, generator=g) * 10.0 ** -i) for i, s in enumerate(SHAPES)]


def _opts(a, b):
    groups = lambda ps: [{"params": [p], "lr": 10.0 ** -(i + 1), "name": f"g{i}"} for i, p in enumerate(ps)]  # noqa: E731
    dense = FusedAdam(groups(a), lr=0.0, eps=1e-15)
    lazy = LazyCurveAdam(groups(b), lr=0.0, eps=1e-15)
    lazy.curves.update({"g1", "g2"})
    return dense, lazy


def _run(steps: int, touch, seed=3):
    """``steps`` steps of both optimizers on the same gradients, zero outside the columns
    ``touch(step)`` (and a decaying learning rate, as the trainer's)."""
    a, b = _params(), _params()
    dense, lazy = _opts(a, b)
    rng = np.random.default_rng(seed)
    for step in range(steps):
        cols = touch(step, rng)
        for opt in (dense, lazy):
            for i, grp in enumerate(opt.param_groups):
                grp["lr"] = 10.0 ** -(i + 1) * 0.995 ** step
        _step_both(a, b, dense, lazy, cols, step, sparse=True)
    return a, b, dense, lazy


def _step_both(a, b, dense, lazy, cols, step: int, sparse: bool) -> None:
    """One step of both optimizers on the same random gradients (``sparse``: 30 % of the entries
    zero), the curves' zero outside columns ``cols``, which the step records as touched."""
    gen = torch.Generator().manual_seed(100 + step)
    for pa, pb in zip(a, b):
        gr = torch.randn(pa.shape, generator=gen)
        if sparse:
            gr = gr * (torch.rand(pa.shape, generator=gen) < 0.7)
        if pa.dim() == 3:
            keep = torch.zeros(K, dtype=torch.bool)
            keep[cols] = True
            gr[:, ~keep] = 0.0
        pa.grad, pb.grad = gr.clone(), gr.clone()
    trajectory._note_touched(K, cols)
    dense.step()
    lazy.step()


def test_every_column_touched_is_fused_adam_bit_for_bit():
    assert fused_adam.exact()
    a, b, dense, lazy = _run(6, lambda s, r: list(range(K)))
    for pa, pb in zip(a, b):
        assert torch.equal(pa, pb)
        for key in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(dense.state[pa][key], lazy.state[pb][key])


def test_sparse_touches_caught_up_equal_dense_adam_to_rounding():
    touch = lambda s, r: sorted(set(r.choice(K, size=int(r.integers(1, 5)), replace=False).tolist()))  # noqa: E731
    a, b, dense, lazy = _run(200, touch)
    assert not torch.equal(a[1], b[1])  # before settle: skipped columns have not moved yet
    lazy.settle()
    assert torch.equal(a[0], b[0])  # the plain group is FusedAdam's
    for i, (pa, pb) in enumerate(zip(a, b)):
        if i == 0:
            continue
        moved = (pa - _params()[i]).abs().max()
        assert float((pa - pb).detach().abs().max()) < 1e-4 * float(moved.detach())
        for key in ("exp_avg", "exp_avg_sq"):
            x, y = dense.state[pa][key], lazy.state[pb][key]
            assert float((x - y).abs().max()) <= 1e-5 * float(x.abs().max())


def test_kernels_match_the_torch_reference():
    touch = lambda s, r: sorted(set(r.choice(K, size=int(r.integers(1, 4)), replace=False).tolist()))  # noqa: E731
    _, fused, _, lf = _run(60, touch)
    lf.settle()
    lazy_adam.FUSED = False
    try:
        _, ref, _, lr_ = _run(60, touch)
        lr_.settle()
    finally:
        lazy_adam.FUSED = True
    for x, y in zip(fused, ref):
        np.testing.assert_allclose(x.detach().numpy(), y.detach().numpy(), rtol=1e-6, atol=1e-7)


def test_untouched_columns_wait_until_touched_or_settled():
    a, b, dense, lazy = _run(5, lambda s, r: list(range(K)))
    p = b[1]
    before = p.detach().clone()
    m_before = lazy.state[p]["exp_avg"].clone()
    gr = torch.zeros_like(p)
    gr[:, 3] = 1.0
    p.grad = gr
    for q in (b[0], b[2]):
        q.grad = torch.zeros_like(q)
    trajectory._note_touched(K, [3])
    lazy.step()
    others = [c for c in range(K) if c != 3]
    assert torch.equal(p.detach()[:, others], before[:, others])
    assert torch.equal(lazy.state[p]["exp_avg"][:, others], m_before[:, others])
    assert not torch.equal(p.detach()[:, 3], before[:, 3])
    lazy.settle()  # one skipped step: every other column coasts on its momentum once
    assert not torch.equal(p.detach()[:, others], before[:, others])
    assert lazy._cols[id(p)][1].tolist() == [6] * K


def test_no_touched_record_updates_every_column():
    a, b, dense, lazy = _run(3, lambda s, r: [0])
    lazy.settle()
    for pa, pb in ((a[1], b[1]),):
        pa.grad = torch.ones_like(pa)
        pb.grad = torch.ones_like(pb)
    for q in (a[0], a[2], b[0], b[2]):
        q.grad = None
    trajectory.clear_touched()  # a plain autograd reader: no record
    dense.step()
    lazy.step()
    assert lazy.last_touched == K
    assert float((a[1] - b[1]).detach().abs().max()) < 1e-6


def test_a_plain_autograd_reader_makes_every_column_touched():
    """A gradient that autograd accumulates into a lazy curve (a reader that notes no columns)
    may be anywhere: that step updates every column, so nothing it reached is dropped."""
    m = _model(get_preset("fast", {"gaussian_adam": "lazy"}))
    g = m.gaussians
    opt = g.optimizer
    _train_steps(m, [0.1])  # registers the curves
    tm = getattr(g, TRAJ_MEANS)
    before = tm.detach().clone()
    opt.zero_grad(set_to_none=True)
    rgb, _, _, _ = m.render(_view(t=0.1))  # notes column 3
    with trajectory.gradient_sink():
        (rgb.mean() + (tm[:, 7] ** 2).sum() * 1e-3 + tm[:, 7].sum()).backward()
    opt.step()
    assert opt.last_touched == K_MODEL + 1  # the positions: every column; the rotations: junction 3
    assert not torch.equal(tm.detach()[:, 7], before[:, 7])
    _train_steps(m, [0.1])  # the next step is lazy again: junction 3 alone
    assert opt.last_touched == 2


K_MODEL = 10  # _model's curves: 4 knots


def _train_steps(m, times):
    """Steps as the trainer takes them: the backward inside ``gradient_sink`` (the curves'
    readers write their columns themselves; outside it autograd sums them, which the lazy
    optimizer cannot tell from any other reader's: it then updates every column)."""
    g = m.gaussians
    for t in times:
        g.optimizer.zero_grad(set_to_none=True)
        rgb, _, _, _ = m.render(_view(t=t))
        with trajectory.gradient_sink():
            rgb.mean().backward()
        g.optimizer.step()


def test_renders_touch_their_columns_and_pruning_settles_first():
    m = _model(get_preset("fast", {"gaussian_adam": "lazy"}))
    g = m.gaussians
    opt = g.optimizer
    assert isinstance(opt, LazyCurveAdam) and {TRAJ_MEANS, TRAJ_QUATS} <= opt.curves
    _train_steps(m, [0.1, 0.15, 0.1])  # an RGB instant reads one junction; 0.15 a whole segment
    tm = getattr(g, TRAJ_MEANS)
    assert opt.last_touched == 2  # the last step: junction 3 of both curves
    at = opt._cols[id(tm)][1]
    # t = 0.15 read segment 1 (columns 4, 5) and through the tangents the junctions 0, 3, 6, 9
    assert at[3] == 3 and at[0] == at[4] == at[6] == at[9] == 2 and at[1] == at[7] == 0
    # densification's row surgery brings every column up first
    keep = torch.ones(g.num_gaussians, dtype=torch.bool)
    keep[:10] = False
    settled = _model(get_preset("fast", {"gaussian_adam": "lazy"}))
    _train_steps(settled, [0.1, 0.15, 0.1])
    settled.gaussians.settle()
    g.prune(~keep)
    ref = getattr(settled.gaussians, TRAJ_MEANS).detach()[keep]
    assert torch.equal(getattr(g, TRAJ_MEANS).detach(), ref)
    now = getattr(g, TRAJ_MEANS).detach().clone()
    opt.settle()  # the new tensor starts with every column current: nothing left to catch up
    assert torch.equal(getattr(g, TRAJ_MEANS).detach(), now)


def test_a_checkpoint_is_settled():
    m = _model(get_preset("fast", {"gaussian_adam": "lazy"}))
    _train_steps(m, [0.1, 0.15, 0.1])
    ref = _model(get_preset("fast", {"gaussian_adam": "lazy"}))
    _train_steps(ref, [0.1, 0.15, 0.1])
    ref.gaussians.settle()
    st = m.state()
    assert torch.equal(st["gaussians"]["params"][TRAJ_MEANS], getattr(ref.gaussians, TRAJ_MEANS).detach())


def test_auto_steps_short_curves_whole_as_fused_adam_bit_for_bit(monkeypatch):
    """gaussian_adam=auto with curves under LAZY_MIN_COLUMNS: the same numbers as exact (the
    prior stays a loss term, every column moves at every step, the quiet hook applies whole)."""
    from engine.train.losses.terms import _traj_reg

    class _Ctx:
        def __init__(self, m):
            self.run = fake_run(model=m)

    runs = {}
    for adam in ("exact", "auto"):
        monkeypatch.setattr(gaussians_mod, "LAZY_MIN_COLUMNS", 40)
        m = _model(get_preset("fast", {"gaussian_adam": adam}))
        g = m.gaussians
        for t in (0.1, 0.15, 0.25):
            g.optimizer.zero_grad(set_to_none=True)
            rgb, _, _, _ = m.render(_view(t=t))
            loss = rgb.mean()
            with torch.no_grad():
                getattr(g, TRAJ_MEANS)[:, 1::3] += 1e-3  # nonzero residuals: the prior has a gradient
            reg = _traj_reg(_Ctx(m))
            assert reg is not None  # not folded: K = 10 < 40
            (loss + reg).backward()
            g.optimizer.step()
        runs[adam] = m
    assert isinstance(runs["auto"].gaussians.optimizer, LazyCurveAdam)
    assert not runs["auto"].gaussians.optimizer.lazy_for(getattr(runs["auto"].gaussians, TRAJ_MEANS))
    assert runs["auto"].gaussians.optimizer.last_columns(getattr(runs["auto"].gaussians, TRAJ_MEANS)) is None
    for n in runs["exact"].gaussians.param_names:
        assert torch.equal(getattr(runs["exact"].gaussians, n), getattr(runs["auto"].gaussians, n)), n
    monkeypatch.setattr(gaussians_mod, "LAZY_MIN_COLUMNS", 10)
    m = _model(get_preset("fast", {"gaussian_adam": "auto"}))  # K = 10: lazy
    assert m.gaussians.optimizer.lazy_for(getattr(m.gaussians, TRAJ_MEANS))
    assert _traj_reg(_Ctx(m)) is None and m.gaussians.optimizer.inner_decay[TRAJ_MEANS] > 0


def test_the_switch_rejects_a_bad_name():
    with pytest.raises(ValueError, match="lazy"):
        _model(get_preset("fast", {"gaussian_adam": "lazyy"}))


def test_the_inner_prior_folded_in_is_its_gradient_on_the_touched_columns():
    """inner_decay adds d/dD of w mean|D|^2 / extent^2 (the traj_reg term) on the updated inner
    columns only: the same step as the term's autograd gradient there, to rounding."""
    w, extent, cols = 0.7, 1.3, [3, 4, 5, 6]
    a, b = _params(), _params()
    _, la = _opts(_params(), a)
    _, lb = _opts(_params(), b)
    la.inner_decay["g1"] = w / extent ** 2
    gen = torch.Generator().manual_seed(5)
    gr = torch.randn(SHAPES[1], generator=gen)
    keep = torch.zeros(K, dtype=torch.bool)
    keep[cols] = True
    gr[:, ~keep] = 0.0
    with torch.enable_grad():
        prior = trajectory.inner_residual_sq(b[1]).mean() * (w / extent ** 2)
        (pg,) = torch.autograd.grad(prior, b[1])
    a[1].grad = gr.clone()
    b[1].grad = gr + pg * keep[None, :, None]
    for p in (a[0], a[2], b[0], b[2]):
        p.grad = None
    for opt in (la, lb):
        trajectory._note_touched(K, cols)
        opt.step()
    np.testing.assert_allclose(a[1].detach().numpy(), b[1].detach().numpy(), rtol=1e-6, atol=1e-9)
    assert not torch.equal(a[1], _params()[1])
    # the junctions got no prior: without a gradient elsewhere the decay changes nothing there
    assert torch.equal(la.state[a[1]]["exp_avg"][:, 3], lb.state[b[1]]["exp_avg"][:, 3])


@pytest.mark.slow
def test_lazy_training_holds_quiet_curves_also_after_a_settle(demo_capture, monkeypatch):
    """Real guided steps on the demo with gaussian_adam=lazy: the quiet hook zeroes the columns
    each step updated (not the whole curves), and a settle (here a checkpoint's) re-applies the
    mask whole, so the quiet segments' inner points are zero in the saved model too; the
    inner-residual prior is folded into the optimizer (no traj_reg loss)."""
    from engine.io.capture import load_capture
    from engine.train.loop.trainer import Trainer
    from tests.test_quiet_curves import _TINY, _inner_norms

    tr = Trainer(load_capture(demo_capture), get_preset("fast", {**_TINY, "quiet_curves": True,
                                                              "gaussian_adam": "lazy"}), device="cpu")
    tr.init_model()
    calls = {"local": 0}
    orig = tr.quiet_curves._apply

    def spy(g, local):
        calls["local"] += local
        return orig(g, local)
    tr.quiet_curves._apply = spy
    reads = {"checked": 0}
    read = trajectory.before_read

    def checked_read(params, cols):  # what a render reads of a quiet segment is zero, caught up or not
        read(params, cols)
        hit = tr.quiet_curves._mask
        if hit is not None and params is getattr(tr.model.gaussians, TRAJ_MEANS) and hit[1] == params.shape[0]:
            for c in cols:
                if c % 3:
                    assert not params.detach()[hit[2][:, c // 3], c].any()
                    reads["checked"] += 1
    monkeypatch.setattr(trajectory, "before_read", checked_read)
    for step in range(_TINY["iterations"]):
        tr.step(step)
    opt = tr.model.gaussians.optimizer
    assert reads["checked"] > 0 and opt.caught_up > 0
    assert isinstance(opt, LazyCurveAdam) and "traj_reg" not in tr.last_losses
    assert opt.inner_decay[TRAJ_MEANS] > 0
    assert calls["local"] >= 1  # steps without a settle before them zeroed their updated columns only
    used = tr.quiet_curves._mask[2]
    assert 0.05 < float(used.float().mean()) < 0.95
    assert float(_inner_norms(tr)[used].max()) == 0.0
    assert float(_inner_norms(tr)[~used].max()) > 0.0
    behind = opt._cols[id(getattr(tr.model.gaussians, TRAJ_MEANS))][1]
    assert (behind < behind.max()).any()  # some columns wait for their catch-up
    state = tr.model.state()  # settles: the skipped momentum lands, then the mask again
    saved = state["gaussians"]["params"][TRAJ_MEANS]
    for k in range(used.shape[1]):
        assert (saved[used[:, k], 3 * k + 1:3 * k + 3] == 0).all()


@pytest.mark.slow
def test_auto_on_a_short_capture_trains_bit_for_bit_as_exact(demo_capture):
    """The demo (K = 19 < lazy_min_columns): gaussian_adam=auto is FusedAdam's run bit for bit,
    through admissions, spike-flow fits, quiet curves and densification (a settle that moves
    nothing must not re-apply the quiet mask either: it did, and the runs parted at a fit)."""
    import hashlib

    from engine.io.capture import load_capture
    from engine.train.guidance.spike_flow import close_flow_worker
    from engine.train.loop.trainer import Trainer

    cap = load_capture(demo_capture)
    digests = {}
    for adam in ("exact", "auto"):
        tr = Trainer(cap, get_preset("fast", {"iterations": 120, "gaussian_adam": adam}), device="cpu")
        tr.init_model()
        try:
            for step in range(120):
                tr.step(step)
        finally:
            close_flow_worker(tr.run)
        g = tr.model.gaussians
        h = hashlib.sha1()
        for n in g.param_names:
            h.update(getattr(g, n).detach().numpy().tobytes())
        digests[adam] = (h.hexdigest(), len(getattr(tr.spike_flow, "fitted", {}) or {}))
    assert digests["exact"][1] >= 1  # the schedule reached a spike-flow fit
    assert digests["auto"] == digests["exact"]


def test_a_kept_gradient_buffer_is_zeroed_by_the_step_that_reads_it(monkeypatch):
    """On long captures the curves' gradients live in kept buffers (engine.scene.grad_buffers);
    the lazy step zeroes the columns it read in its own pass and says so, so the next step's
    first reader finds nothing to clean, and the training is the same bit for bit."""
    from engine.scene import grad_buffers

    monkeypatch.setattr(grad_buffers, "MIN_BYTES", 0)  # the test's small curves get buffers too
    runs = {}
    for clear in (True, False):
        monkeypatch.setattr(lazy_adam, "CLEAR_BUFFERS", clear)
        grad_buffers.clear()
        m = _model(get_preset("fast", {"gaussian_adam": "lazy"}))
        _train_steps(m, [0.1, 0.15, 0.2, 0.15, 0.1])
        tm = getattr(m.gaussians, TRAJ_MEANS)
        e = grad_buffers._BUFFERS[id(tm)]
        assert tm.grad is e.buf
        if clear:
            assert not e.dirty and float(e.buf.abs().max()) == 0.0
        else:
            assert e.dirty == {3}
        runs[clear] = [getattr(m.gaussians, n).detach().clone() for n in m.gaussians.param_names]
    grad_buffers.clear()
    assert all(torch.equal(a, b) for a, b in zip(runs[True], runs[False]))


def _read_and_step(catch_up: bool, steps: int = 150):
    """Dense and lazy Adam on the same gradients, each step's columns those a curve evaluation at a
    random time reads (through ``trajectory.evaluate``, whose read hook runs first); returns the
    largest difference between what the two read, relative to how far the curve moved."""
    knots = [0.1 * i for i in range(7)]  # K = 19
    a, b = _params(), _params()
    dense, lazy = _opts(a, b)
    rng = np.random.default_rng(4)
    worst, moved = 0.0, 0.0
    old = lazy_adam.READ_CATCH_UP
    lazy_adam.READ_CATCH_UP = catch_up
    try:
        for step in range(steps):
            t = float(rng.choice(knots)) if rng.random() < 0.5 else float(rng.uniform(0.0, 0.6))
            cols = [c for c, _ in trajectory.segment_weights(knots, t)]
            with torch.no_grad():
                for pa, pb in zip(a[1:], b[1:]):
                    ya, yb = trajectory.evaluate(pa, knots, t), trajectory.evaluate(pb, knots, t)
                    worst = max(worst, float((ya - yb).abs().max()))
            moved = max(moved, float((a[1] - _params()[1]).detach().abs().max()))
            _step_both(a, b, dense, lazy, cols, step, sparse=False)
    finally:
        lazy_adam.READ_CATCH_UP = old
    return worst / moved, lazy


def test_a_render_reads_what_dense_adam_would_have_left_there():
    """With the read catch-up a curve evaluation reads, to rounding, dense Adam's values, not where
    the columns' last touch left them (without it they lag by the skipped steps' momentum)."""
    fresh, lazy = _read_and_step(True)
    assert fresh < 1e-4 and lazy.caught_up > 0
    stale, lazy = _read_and_step(False)
    assert stale > 1e-2 and lazy.caught_up == 0


def test_a_promise_of_no_inner_reads_broken_goes_back_to_dense():
    """A run that promised renders at RGB instants only (dense_inner_below) steps its short curves
    lazily; the first step that reads an inner column settles them and steps them whole from then on."""
    a = _params()
    groups = [{"params": [p], "lr": 1e-2, "name": f"g{i}"} for i, p in enumerate(a)]
    opt = LazyCurveAdam(groups, min_columns=0, dense_inner_below=40, lr=0.0, eps=1e-15)
    opt.curves.update({"g1", "g2"})
    for cols in ([3], [6], [3]):  # junctions only: lazy
        for p in a:
            p.grad = torch.ones_like(p)
        trajectory._note_touched(K, cols)
        opt.step()
    assert opt.lazy_for(a[1]) and opt.last_columns(a[1]).tolist() == [3]
    for p in a:
        p.grad = torch.ones_like(p)
    trajectory._note_touched(K, [3, 4, 5, 6])  # a between-instant read
    opt.step()
    assert opt.min_columns == 40 and not opt.lazy_for(a[1])
    assert (opt._cols[id(a[1])][1] == 3).all()  # settled to the step before the switch, then dense


@pytest.mark.slow
def test_rgb_only_runs_step_every_curve_lazily_with_reads_caught_up(demo_capture, monkeypatch):
    """An RGB-only run renders only at RGB instants: every curve is stepped lazily (lazy_rgb_only),
    the inner columns are never read and stay zero, and the reads catch their columns up; a full
    run or the switch off keep the short curves whole."""
    from engine.io.capture import load_capture
    from engine.train.guidance.spike_flow import close_flow_worker
    from engine.train.loop.trainer import Trainer
    from tests.test_quiet_curves import _TINY

    cap = load_capture(demo_capture)
    cfg = {**_TINY, "iterations": 40, "static_fraction": 0.1}

    def trainer(rgb_only=True, **over):
        tr = Trainer(cap, get_preset("fast", {**cfg, **over}), device="cpu", rgb_only=rgb_only)
        tr.init_model()
        return tr

    tr = trainer()
    g = tr.model.gaussians
    assert g.instants_only
    for step in range(cfg["iterations"]):
        tr.step(step)
    opt, curve = g.optimizer, getattr(g, TRAJ_MEANS)
    assert opt.lazy_for(curve) and curve.shape[1] < 40 and "traj_reg" not in tr.last_losses
    assert opt.caught_up > 0 and opt.min_columns == 0
    g.settle()
    assert float(curve.detach()[:, 1::3].abs().max()) == 0.0 and float(curve.detach()[:, 2::3].abs().max()) == 0.0
    from engine.scene.model import Model4D
    back = Model4D.from_state(tr.model.state(), tr.cfg.gaussians).gaussians  # a resumed run keeps the promise
    assert back.instants_only and back.optimizer.min_columns == 0
    monkeypatch.setattr(gaussians_mod, "LAZY_RGB_ONLY", False)
    off = trainer().model.gaussians.optimizer
    assert (off.min_columns, off.dense_inner_below) == (40, 0)  # short curves whole, as exact
    monkeypatch.setattr(gaussians_mod, "LAZY_RGB_ONLY", True)
    full = trainer(rgb_only=False)
    try:
        assert not full.model.gaussians.instants_only
        assert (full.model.gaussians.optimizer.min_columns, full.model.gaussians.optimizer.dense_inner_below) == (40, 0)
    finally:
        close_flow_worker(full.run)


def test_a_read_catches_up_the_values_alone_with_the_same_numbers():
    """The read's catch-up moves the values and leaves the moments (their decay waits for the column's
    next step or settle, which write them anyway); the training is the same as when the read also
    decayed and wrote them, including columns read at several steps between touches."""
    runs = {}
    for values_only in (True, False):
        old = lazy_adam.READ_VALUES_ONLY
        lazy_adam.READ_VALUES_ONLY = values_only
        try:
            _, lazy = _read_and_step(True, steps=80)
            p = next(q for grp in lazy.param_groups for q in grp["params"] if q.dim() == 3)
            m_before = lazy.state[p]["exp_avg"].clone()
            cols = [c for c in range(K) if lazy._cols[id(p)][2][c] < int(lazy.state[p]["step"].item())]
            assert cols
            trajectory.before_read(p, cols[:1])  # a read between touches (no gradient follows)
            if values_only:
                assert torch.equal(lazy.state[p]["exp_avg"], m_before)
            lazy.settle()
            runs[values_only] = [q.detach().clone() for grp in lazy.param_groups for q in grp["params"]] + [
                lazy.state[q][key].clone() for grp in lazy.param_groups for q in grp["params"]
                for key in ("exp_avg", "exp_avg_sq")]
        finally:
            lazy_adam.READ_VALUES_ONLY = old
    for x, y in zip(runs[True], runs[False]):
        np.testing.assert_allclose(x.numpy(), y.numpy(), rtol=1e-5, atol=1e-7)
