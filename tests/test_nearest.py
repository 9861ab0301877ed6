"""Exact grid nearest-neighbour search (engine.train.motion.nearest) against brute force, and
propagate_to_hidden on it against the dense torch.cdist search it replaced (issue 13)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from engine.train.motion import nearest as nn_mod
from engine.train.motion.nearest import nearest_within
from engine.train.motion.scene_flow import propagate_to_hidden, propagate_to_hidden_dense


def _brute(q, p, max_dist):
    """float64 squared distances (the kernel's formula), argmin = lowest index among ties."""
    q64, p64 = q.astype(np.float32).astype(np.float64), p.astype(np.float32).astype(np.float64)
    idx = np.full(len(q), -1, np.int64)
    dist = np.full(len(q), np.inf)
    if len(p) == 0:
        return idx, dist
    for i in range(len(q)):
        d = q64[i] - p64
        d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
        j = int(np.argmin(d2))  # first occurrence of the minimum
        if math.sqrt(d2[j]) <= max_dist:
            idx[i], dist[i] = j, math.sqrt(d2[j])
    return idx, dist


def _clouds(seed):
    rng = np.random.default_rng(seed)
    uniform = rng.uniform(-1, 1, size=(700, 3))
    blobs = np.concatenate([rng.normal(c, 0.02, size=(150, 3)) for c in rng.uniform(-2, 2, size=(4, 3))])
    flat = np.c_[rng.uniform(-1, 1, size=(300, 2)), np.zeros(300)]  # a plane: zero extent along z
    line = np.c_[np.linspace(0, 1, 200), np.zeros((200, 2))]
    return {"uniform": uniform, "blobs": blobs, "flat": flat, "line": line}


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("max_dist", [math.inf, 0.5, 0.05, 0.004, 1e-9, 0.0])
def test_matches_brute_force(seed, max_dist):
    rng = np.random.default_rng(100 + seed)
    for name, pts in _clouds(seed).items():
        pts = pts.astype(np.float32)
        split = rng.uniform(size=len(pts)) < 0.4
        # queries: the rest of the cloud, points far outside its box, and exact copies of points
        q = np.concatenate([pts[~split], rng.uniform(-6, 6, size=(40, 3)), pts[split][:10]]).astype(np.float32)
        idx, dist = nearest_within(q, pts[split], max_dist)
        ref_idx, ref_dist = _brute(q, pts[split], max_dist)
        np.testing.assert_array_equal(idx, ref_idx, err_msg=name)
        np.testing.assert_array_equal(dist, ref_dist, err_msg=name)


def test_ties_go_to_the_lower_index_and_duplicates():
    p = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [1.0, 0, 0]], np.float32)
    idx, dist = nearest_within(np.zeros((1, 3), np.float32), p, 2.0)
    assert idx.tolist() == [0] and dist.tolist() == [1.0]
    idx, _ = nearest_within(p[3:], p, 0.0)  # distance 0 to both copies
    assert idx.tolist() == [0]


def test_empty_sets_one_point_and_cut_off():
    p = np.array([[0.0, 0.0, 0.0]], np.float32)
    idx, dist = nearest_within(np.zeros((0, 3)), p, 1.0)
    assert idx.shape == (0,) and dist.shape == (0,)
    idx, dist = nearest_within(np.ones((3, 3)), np.zeros((0, 3)), 1.0)
    assert idx.tolist() == [-1, -1, -1] and np.isinf(dist).all()
    q = np.array([[0.0, 0.5, 0.0], [3.0, 4.0, 0.0], [0.0, 0.0, 0.0]], np.float32)
    idx, dist = nearest_within(q, p, 0.5)  # one point: exactly at max_dist counts
    assert idx.tolist() == [0, -1, 0]
    np.testing.assert_allclose(dist[[0, 2]], [0.5, 0.0], atol=1e-7)
    idx, _ = nearest_within(q, p)  # no cut-off
    assert idx.tolist() == [0, 0, 0]
    far = np.array([[1e6, -1e6, 3.0], [-3e7, 0.0, 1e7]], np.float32)
    pts = np.random.default_rng(5).uniform(-1, 1, size=(50, 3)).astype(np.float32)
    np.testing.assert_array_equal(nearest_within(far, pts)[0], _brute(far, pts, math.inf)[0])
    idx, _ = nearest_within(q, p, -1.0)
    assert idx.tolist() == [-1, -1, -1]
    with pytest.raises(ValueError, match="non-finite"):
        nearest_within(np.array([[np.nan, 0, 0]]), p, 1.0)


def test_grid_size_is_bounded(monkeypatch):
    monkeypatch.setattr(nn_mod, "MAX_CELLS", 64)  # cells wider than max_dist: still exact
    rng = np.random.default_rng(3)
    p = rng.uniform(-1, 1, size=(500, 3)).astype(np.float32)
    q = rng.uniform(-1.2, 1.2, size=(200, 3)).astype(np.float32)
    for r in (0.01, 0.1, math.inf):
        lo, cell, dims = nn_mod._grid(p, r)
        assert np.prod(dims) <= 64
        np.testing.assert_array_equal(nearest_within(q, p, r)[0], _brute(q, p, r)[0])


def test_propagate_to_hidden_matches_the_dense_search():
    rng = np.random.default_rng(7)
    pos = rng.uniform(-1, 1, size=(3000, 3)).astype(np.float32)
    delta = np.zeros((3000, 3), np.float32)
    decided = rng.uniform(size=3000) < 0.5
    delta[decided] = rng.normal(size=(int(decided.sum()), 3))
    for r in (0.05, 0.2, 10.0):
        a, ta = propagate_to_hidden(pos, delta, decided, r)
        b, tb = propagate_to_hidden_dense(pos, delta, decided, r)
        # cdist works in float32 (|x|^2 + |y|^2 - 2 x.y): near ties and rows at max_dist may
        # differ; everywhere else the two searches agree
        src = np.nonzero(decided)[0]
        d = np.sqrt(((pos[:, None] - pos[src][None]) ** 2).astype(np.float64).sum(-1))
        order = np.sort(d, axis=1)
        clear = (order[:, 1] - order[:, 0] > 1e-4) & (np.abs(order[:, 0] - r) > 1e-4)
        assert np.array_equal(ta[clear], tb[clear])
        np.testing.assert_array_equal(a[clear], b[clear])
        assert clear[~decided].mean() > 0.9
    out, taken = propagate_to_hidden(pos, delta, np.zeros(3000, bool), 1.0)  # nothing decided
    assert not taken.any() and np.array_equal(out, delta)
