"""SelectiveAdam (engine.scene.selective_adam): FusedAdam bit for bit when everything is
selected, untouched entries left exactly as they were, the plain-torch reference on random
masks, and the rows / curve columns a training step's renders select."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from engine.scene import fused_adam, trajectory
from engine.scene.fused_adam import FusedAdam
from engine.scene.gaussians import GaussianModel
from engine.scene.model import TRAJ_MEANS, TRAJ_QUATS, Model4D
from engine.scene.selective_adam import SelectiveAdam, _spans, reference_step
from engine.train.config import get_preset

N = 2053
SHAPES = [(N,), (N, 3), (N, 1, 3), (N, 19, 3), (N, 19, 4)]
CURVES = {"g3", "g4"}  # the [N, 19, C] groups


def _params(seed=0):
    g = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(s, generator=g) * 10.0 ** (i % 4 - 2)) for i, s in enumerate(SHAPES)]


def _groups(ps):
    return [{"params": [p], "lr": 10.0 ** -(i % 5 + 1), "name": f"g{i}"} for i, p in enumerate(ps)]


def _grads(k, seed=1, rows=None, cols=None):
    """Sparse-ish gradients with a wide range; with ``rows`` / ``cols`` zero elsewhere (what a
    render gives: nothing outside what it saw)."""
    g = torch.Generator().manual_seed(seed * 1000 + k)
    out = []
    for s in SHAPES:
        gr = torch.randn(s, generator=g) * torch.rand(s, generator=g).pow(6) * 10.0 * (torch.rand(s, generator=g) < 0.6)
        if rows is not None:
            gr[~rows] = 0.0
        if cols is not None and len(s) == 3 and s[1] == 19:
            keep = torch.zeros(19, dtype=torch.bool)
            keep[cols] = True
            gr[:, ~keep] = 0.0
        out.append(gr)
    return out


def _radii(rows):
    return rows.to(torch.int32)[None] * 3  # [1, N]: radius 3 where visible, 0 elsewhere


def _state(opt, p):
    st = opt.state[p]
    return st["exp_avg"], st["exp_avg_sq"]


def test_all_selected_equals_fused_adam_bit_for_bit():
    assert fused_adam.exact()
    ref, fus = _params(), _params()
    o_ref = FusedAdam(_groups(ref), lr=0.0, eps=1e-15)
    o_sel = SelectiveAdam(_groups(fus), lr=0.0, eps=1e-15)
    o_sel.curves |= CURVES
    everything = torch.ones(N, dtype=torch.bool)
    for k in range(6):
        gs = _grads(k)
        for a, b, gr in zip(ref, fus, gs):
            a.grad, b.grad = gr.clone(), gr.clone()
        o_ref.step()
        o_sel.note_visible(_radii(everything))
        trajectory._note_touched(19, range(19))  # every column read
        o_sel.step()
        assert o_sel.last_selected == (N, N)
    for a, b in zip(ref, fus):
        assert torch.equal(a, b)
        for x, y in zip(_state(o_ref, a), _state(o_sel, b)):
            assert torch.equal(x, y)
        assert torch.equal(o_ref.state[a]["step"], o_sel.state[b]["step"])


def test_all_rows_with_a_strict_column_subset_still_matches_fused_adam_there():
    """Every row visible, curve columns {3, 4, 9}: those columns as FusedAdam's on gradients
    that are zero elsewhere, the other columns untouched."""
    ref, fus = _params(), _params()
    o_ref = FusedAdam(_groups(ref), lr=0.0, eps=1e-15)
    o_sel = SelectiveAdam(_groups(fus), lr=0.0, eps=1e-15)
    o_sel.curves |= CURVES
    cols = [3, 4, 9]
    everything = torch.ones(N, dtype=torch.bool)
    for k in range(3):
        gs = _grads(k, cols=cols)
        for a, b, gr in zip(ref, fus, gs):
            a.grad, b.grad = gr.clone(), gr.clone()
        o_ref.step()
        o_sel.note_visible(_radii(everything))
        trajectory._note_touched(19, cols)
        o_sel.step()
    for i, (a, b) in enumerate(zip(ref, fus)):
        if f"g{i}" in CURVES:
            assert torch.equal(a[:, cols], b[:, cols])
            other = [c for c in range(19) if c not in cols]
            assert torch.equal(b[:, other], _params()[i][:, other])  # never moved
            assert float(_state(o_sel, b)[0][:, other].abs().sum()) == 0.0
        else:
            assert torch.equal(a, b)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_masks_match_the_torch_reference_and_leave_the_rest(seed):
    gen = torch.Generator().manual_seed(100 + seed)
    fus, ref = _params(seed), _params(seed)
    o_sel = SelectiveAdam(_groups(fus), lr=0.0, eps=1e-15)
    o_sel.curves |= CURVES
    moments = [(torch.zeros_like(p), torch.zeros_like(p)) for p in ref]
    for k in range(5):
        rows = torch.rand(N, generator=gen) < 0.3
        cols = sorted(torch.randperm(19, generator=gen)[: 1 + k].tolist())
        gs = _grads(k, seed, rows=rows, cols=cols)
        extra = torch.randint(0, N, (7,), generator=gen)  # invisible rows a prior reaches: updated too
        for gr in gs:
            gr[extra] = 1e-3
        before = [(p.detach().clone(), *(t.clone() for t in _state(o_sel, p))) if o_sel.state.get(p) else None
                  for p in fus]
        for p, gr in zip(fus, gs):
            p.grad = gr.clone()
        o_sel.note_visible(_radii(rows))
        trajectory._note_touched(19, cols)
        o_sel.step()
        assert trajectory.touched_columns(19) is None  # the record is cleared by the step
        for i, (p, q, gr, (m, v)) in enumerate(zip(fus, ref, gs, moments)):
            curve = f"g{i}" in CURVES
            with torch.no_grad():
                reference_step(q, gr, m, v, k + 1, 10.0 ** -(i % 5 + 1), eps=1e-15, rows=rows,
                               cols=cols if curve else None)
            assert torch.equal(p, q), f"group {i} step {k}"
            sm, sv = _state(o_sel, p)
            assert torch.equal(sm, m) and torch.equal(sv, v)
            if before[i] is not None:  # what no render saw and no gradient reached did not move
                sel = rows.clone()
                sel[extra] = True
                for now, then in zip((p.detach(), sm, sv), before[i]):
                    assert torch.equal(now[~sel], then[~sel])
                    if curve:
                        other = [c for c in range(19) if c not in cols]
                        assert torch.equal(now[:, other], then[:, other])


def test_without_a_noted_render_the_step_is_fused_adam():
    ref, fus = _params(), _params()
    o_ref = FusedAdam(_groups(ref), lr=0.0, eps=1e-15)
    o_sel = SelectiveAdam(_groups(fus), lr=0.0, eps=1e-15)
    for k in range(2):
        for a, b, gr in zip(ref, fus, _grads(k)):
            a.grad, b.grad = gr.clone(), gr.clone()
        o_ref.step()
        o_sel.step()
    assert all(torch.equal(a, b) for a, b in zip(ref, fus))


def test_spans_merge_adjacent_columns():
    assert _spans(None, (5, 19, 3)).tolist() == [[0, 57]]
    assert _spans([0, 1, 2, 6], (5, 19, 3)).tolist() == [[0, 9], [18, 21]]
    assert _spans(None, (5,)).tolist() == [[0, 1]]


def _model(cfg, n=300, seed=0):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1, 1, size=(n, 3)) * [1.5, 1.0, 0.3] + [0, 0, 4.0]
    g = GaussianModel(pts, rng.uniform(size=(n, 3)))
    g.setup_optimizer(cfg.gaussians, 1.0)
    m = Model4D(g)
    m.add_trajectories([0.0, 0.1, 0.2, 0.3], 1e-3, 1e-3)
    m.use_deformation = True
    return m


def _view(width=48, height=32, t=0.1):
    K = torch.tensor([[[40.0, 0, width / 2], [0, 40.0, height / 2], [0, 0, 1]]])
    return {"viewmat": torch.eye(4)[None], "K": K, "width": width, "height": height, "time": t,
            "campos": torch.zeros(3)}


def test_a_training_step_moves_only_visible_rows_and_read_columns():
    cfg = get_preset("fast", {"gaussian_adam": "selective"})
    m = _model(cfg)
    g = m.gaussians
    assert isinstance(g.optimizer, SelectiveAdam) and {TRAJ_MEANS, TRAJ_QUATS} <= g.optimizer.curves
    with torch.no_grad():  # a third of the Gaussians behind the camera: never visible
        g.means[:100, 2] = -4.0
    before = {n: getattr(g, n).detach().clone() for n in g.param_names}
    rgb, _, meta, _ = m.render(_view(t=0.1))  # an RGB instant: one junction column (3)
    visible = meta["radii"][0] > 0
    assert 0 < int(visible.sum()) < g.num_gaussians and not bool(visible[:100].any())
    rgb.mean().backward()
    g.optimizer.step()
    assert g.optimizer.last_selected[0] == int(visible.sum())
    for n in g.param_names:
        now = getattr(g, n).detach()
        assert torch.equal(now[~visible], before[n][~visible]), n
    tm = getattr(g, TRAJ_MEANS).detach()
    assert not torch.equal(tm[visible][:, 3], before[TRAJ_MEANS][visible][:, 3])
    other = [c for c in range(tm.shape[1]) if c != 3]
    assert torch.equal(tm[:, other], before[TRAJ_MEANS][:, other])
    # a no-grad render notes nothing: the next plain step is a dense one
    with torch.no_grad():
        m.render(_view(t=0.15))
    assert g.optimizer._visible is None and trajectory.touched_columns(tm.shape[1]) is None


def test_the_switch_picks_the_optimizer_and_rejects_a_bad_name():
    assert type(_model(get_preset("fast", {"gaussian_adam": "exact"})).gaussians.optimizer) is FusedAdam
    with pytest.raises(ValueError, match="gaussians.optimizer"):
        _model(get_preset("fast", {"gaussian_adam": "sparse"}))
