"""The curves' gradient buffers, kept from one step to the next (issue 13).

A per-Gaussian curve (``engine.scene.trajectory``) has one control-point column per third of
an RGB interval, so its [N, K, C] gradient grows with the capture's length, while a step's
readers write a few columns of it (one junction at an RGB instant, at most six columns between
two). A fresh zero gradient per step is a fresh allocation the size of the whole curve, and
the first writes into it take its page faults: 20 / 26 ms per step for the position /
rotation curves of 45k Gaussians over 30 RGB instants (K = 88; a 1 s capture), against
1.3 ms to zero the columns written the step before and add into the same buffer (micro-
benchmark, one thread). Below :data:`MIN_BYTES` a fresh gradient is cheaper (its docstring).

:func:`take` hands out a leaf's buffer with every entry zero: created once (``zeros_like``),
then reused, with only the columns some writer :func:`mark` ed since the last :func:`take`
zeroed again. The readers that write into it are :func:`engine.scene.trajectory.sunk`'s (the
curve evaluations, the inner-residual prior, the spike-view flow term's subset), which say
which columns they wrote. Any other gradient reaching the leaf (plain autograd through an
index, ``torch.autograd.grad``) fires the tensor hook registered on the leaf, and the whole
buffer is zeroed at the next :func:`take`: the buffer is all zeros whenever it is handed out,
so the gradient is the same as in a fresh one (the same numbers; +0.0 where a fresh gradient
written by a kernel could hold -0.0, which Adam treats alike).

A buffer set as a leaf's ``.grad`` is valid until the next backward that reaches that leaf:
whoever wants a step's gradient later must copy it. The buffer lives as long as its leaf
(densification's new parameters get new buffers; a leaf's entry is dropped when the leaf dies).
"""
from __future__ import annotations

import weakref

import numpy as np
import torch

# False: every step's first reader writes a fresh full gradient, as before (bench-step "grad-fresh")
ENABLED = True
# Smaller gradients are written fresh. glibc serves an allocation below its largest mmap threshold
# (32 MiB on 64-bit) from memory the process already has once a block that size was freed, so a
# fresh gradient costs no page faults; and writing every entry of it is faster than adding into a
# reused buffer's few columns, which reads them back from memory: on the demo (K = 19, 22k Gaussians,
# 5-7 MB) the reused buffers made the RGB step 0.86x as fast (bench-step --variants grad-fresh,current).
MIN_BYTES = 32 << 20


class _Buffer:
    __slots__ = ("leaf", "buf", "dirty", "all_dirty", "__weakref__")

    def __init__(self, leaf: torch.Tensor):
        self.leaf = weakref.ref(leaf)
        self.buf = torch.zeros_like(leaf, memory_format=torch.contiguous_format)
        self.dirty: set[int] = set()
        self.all_dirty = False

    def foreign(self, grad):
        """Tensor hook of the leaf: a gradient that did not come through ``sunk`` (None when
        every reader of this backward summed in place) may be anywhere in the buffer."""
        if grad is not None:
            self.all_dirty = True

    def clean(self) -> None:
        b = self.buf
        if self.all_dirty or len(self.dirty) * 2 > b.shape[1]:
            b.zero_()
        elif self.dirty:
            b.numpy()[:, sorted(self.dirty)] = 0
        self.dirty.clear()
        self.all_dirty = False


_BUFFERS: dict[int, _Buffer] = {}


def usable(leaf: torch.Tensor) -> bool:
    """A CPU float leaf curve [N, K, C] of at least :data:`MIN_BYTES` whose gradient can live in a
    reused buffer."""
    return (ENABLED and leaf.is_leaf and leaf.device.type == "cpu" and leaf.dim() == 3
            and leaf.dtype in (torch.float32, torch.float64) and leaf.numel() * leaf.element_size() >= MIN_BYTES)


def take(leaf: torch.Tensor) -> torch.Tensor:
    """``leaf``'s gradient buffer, every entry zero (:func:`usable` leaves only)."""
    e = _BUFFERS.get(id(leaf))
    if e is None or e.leaf() is not leaf or e.buf.shape != leaf.shape or e.buf.dtype != leaf.dtype:
        fresh = e is None or e.leaf() is not leaf
        e = _BUFFERS[id(leaf)] = _Buffer(leaf)
        if fresh:  # once per leaf: a hook registered again would stay on it as well
            leaf.register_hook(_Hook(e))
            # the buffer goes with its leaf (a finished run's model), not at the next run's first take
            weakref.finalize(leaf, _drop, id(leaf), weakref.ref(e))
        return e.buf
    e.clean()
    return e.buf


class _Hook:
    """The leaf's hook, holding its buffer weakly (the hook lives on the leaf; the buffer's
    entry may be replaced if the leaf's shape changed)."""

    def __init__(self, e: _Buffer):
        self.key = id(e.leaf())

    def __call__(self, grad):
        e = _BUFFERS.get(self.key)
        if e is not None:
            e.foreign(grad)


def _drop(key: int, entry) -> None:
    e = entry()
    if e is not None and _BUFFERS.get(key) is e:
        del _BUFFERS[key]


def mark(leaf: torch.Tensor, cols) -> None:
    """Columns ``cols`` (of axis 1; None: any) of ``leaf``'s buffer may now be nonzero."""
    e = _BUFFERS.get(id(leaf))
    if e is None or e.leaf() is not leaf:
        return
    if cols is None:
        e.all_dirty = True
    else:
        e.dirty.update(int(c) for c in np.asarray(cols).reshape(-1))


def clear() -> None:
    """Drop every buffer (tests)."""
    _BUFFERS.clear()
