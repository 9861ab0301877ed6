"""What the renders read of the per-Gaussian curves (``engine.scene.trajectory``): the columns a
step read for a gradient (the touched record the lazy and selective optimizers step), and the
read hooks a lazy optimizer uses to bring columns up to its last step before a render reads them.

Re-exported by :mod:`engine.scene.trajectory`, whose curve evaluations fill the record and call
the hooks (:func:`before_read`); the spike-view flow term's row subsets do the same."""
from __future__ import annotations

import functools
import weakref

import torch

# Control-point columns that a curve evaluation (``trajectory.evaluate``) read for a gradient
# since :func:`clear_touched`, per curve length ``K``: {K: {column}}. The selective and lazy
# optimizers (engine.scene.selective_adam, lazy_adam) update only these columns of the curves;
# they clear the record after each step.
_TOUCHED: dict[int, set[int]] = {}


def _note_touched(n_controls: int, cols) -> None:
    _TOUCHED.setdefault(int(n_controls), set()).update(int(c) for c in cols)


def touched_columns(n_controls: int) -> list[int] | None:
    """Ascending columns of [N, ``n_controls``, C] curves that a ``trajectory.evaluate`` under
    autograd read since the last :func:`clear_touched` (None: none)."""
    cols = _TOUCHED.get(int(n_controls))
    return sorted(cols) if cols else None


def clear_touched() -> None:
    _TOUCHED.clear()


# A curve's reader hook: id(params) -> (weakref to params, fn(params, cols)). A lazy optimiser
# (engine.scene.lazy_adam) registers one per curve it steps lazily; :func:`before_read` calls it
# before a render reads columns ``cols``, so that they are first brought up to its last step
# (a read sees what dense Adam would have left there, not the column's last touch).
_READ_HOOKS: dict[int, tuple] = {}


def on_read(params: torch.Tensor, fn) -> None:
    """Call ``fn(params, cols)`` before every ``trajectory.evaluate`` (and the spike-view flow term's
    row subsets) reads columns ``cols`` of ``params``; ``fn`` None removes the hook. Held per
    tensor (a new tensor after densification registers again)."""
    if fn is None:
        _READ_HOOKS.pop(id(params), None)
    else:
        _READ_HOOKS[id(params)] = (weakref.ref(params, functools.partial(_drop_hook, id(params))), fn)


def _drop_hook(key: int, _ref) -> None:
    hit = _READ_HOOKS.get(key)
    if hit is not None and hit[0]() is None:
        del _READ_HOOKS[key]


def before_read(params: torch.Tensor, cols) -> None:
    """Run ``params``' :func:`on_read` hook for the columns ``cols`` about to be read."""
    hit = _READ_HOOKS.get(id(params))
    if hit is not None and hit[0]() is params:
        hit[1](params, cols)
