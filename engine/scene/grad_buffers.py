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
whoever wants a step's gradient later must copy it. The buffer lives as long as its leaf; a leaf
that densification or births replace hands it, zeroed and grown in place, to its successor
(:func:`carry`); a leaf's entry is dropped when the leaf dies.
"""
from __future__ import annotations

import functools
import weakref

import torch

from . import row_store

# False: every step's first reader writes a fresh full gradient, as before (bench-step "grad-fresh")
ENABLED = True
# Smaller gradients are written fresh. glibc serves an allocation below its largest mmap threshold
# (32 MiB on 64-bit) from memory the process already has once a block that size was freed, so a
# fresh gradient costs no page faults; and writing every entry of it is faster than adding into a
# reused buffer's few columns, which reads them back from memory: on the demo (K = 19, 22k Gaussians,
# 5-7 MB) the reused buffers made the RGB step 0.86x as fast (bench-step --variants grad-fresh,current).
MIN_BYTES = 32 << 20
# False: a replaced leaf (densification, births) gets a fresh zero buffer at its first take, as
# before :func:`carry` (bench-step "rows-copied")
CARRY = True


class _Buffer:
    __slots__ = ("leaf", "buf", "dirty", "all_dirty")

    def __init__(self, leaf: torch.Tensor, buf: torch.Tensor | None = None):
        self.leaf = weakref.ref(leaf)
        self.buf = torch.zeros_like(leaf, memory_format=torch.contiguous_format) if buf is None else buf
        self.dirty: set[int] = set()
        self.all_dirty = False

    def clean(self) -> None:
        b = self.buf
        # past half the columns, one contiguous zero_ instead of a strided write per row and column
        if self.all_dirty or len(self.dirty) * 2 > b.shape[1]:
            b.zero_()
        elif self.dirty:
            b.numpy()[:, sorted(self.dirty)] = 0
        self.dirty.clear()
        self.all_dirty = False


_BUFFERS: dict[int, _Buffer] = {}  # id(leaf) -> its buffer


def usable(leaf: torch.Tensor) -> bool:
    """A CPU float leaf curve [N, K, C] of at least :data:`MIN_BYTES` whose gradient can live in a
    reused buffer."""
    return (ENABLED and leaf.is_leaf and leaf.device.type == "cpu" and leaf.dim() == 3
            and leaf.dtype in (torch.float32, torch.float64) and leaf.numel() * leaf.element_size() >= MIN_BYTES)


def take(leaf: torch.Tensor) -> torch.Tensor:
    """``leaf``'s gradient buffer, every entry zero (:func:`usable` leaves only)."""
    key = id(leaf)
    e = _BUFFERS.get(key)
    if e is None or e.leaf() is not leaf or e.buf.shape != leaf.shape or e.buf.dtype != leaf.dtype:
        return _adopt(leaf, None, e).buf
    e.clean()
    return e.buf


def _adopt(leaf: torch.Tensor, buf: torch.Tensor | None, e=None) -> _Buffer:
    """``leaf``'s entry with ``buf`` (every entry zero; None: a new zero buffer)."""
    key = id(leaf)
    if e is None or e.leaf() is not leaf:  # once per leaf: a hook registered again would stay on it too
        leaf.register_hook(functools.partial(_foreign, key))
        # the buffer goes with its leaf (a finished run's model), not at the next run's first take
        weakref.finalize(leaf, _drop, key)
    e = _BUFFERS[key] = _Buffer(leaf, buf)
    return e


def carry(old: torch.Tensor, new: torch.Tensor, keep: torch.Tensor | None, n_new: int) -> None:
    """``new`` replaces the leaf ``old`` (densification, births: ``old``'s rows where ``keep`` holds,
    or all of them, then ``n_new`` rows): ``old``'s buffer, zeroed, becomes ``new``'s, grown in place
    (engine.scene.row_store) instead of a fresh zero buffer the size of the curve, whose page faults a
    long capture paid at every admission (~20 ms for 70k Gaussians' two curves)."""
    e = _BUFFERS.get(id(old))
    if not (ENABLED and CARRY) or e is None or e.leaf() is not old or not usable(new) or e.buf.dtype != new.dtype:
        return
    e.clean()  # every entry zero: its first rows serve as the kept ones
    kept = e.buf.shape[0] if keep is None else int(keep.sum())
    buf = row_store.append_rows(e.buf[:kept], torch.zeros((n_new, *e.buf.shape[1:]), dtype=e.buf.dtype,
                                                         device=e.buf.device))
    if buf.shape != new.shape:
        return
    del _BUFFERS[id(old)]
    _adopt(new, buf)


def _foreign(key: int, grad) -> None:
    """Tensor hook of a leaf with a buffer: a gradient that did not come through ``sunk`` (None
    when every reader of this backward summed in place) may be anywhere in the buffer."""
    e = _BUFFERS.get(key)
    if grad is not None and e is not None:
        e.all_dirty = True


def _drop(key: int) -> None:
    """The leaf ``key`` died (its weak references are cleared before this runs)."""
    e = _BUFFERS.get(key)
    if e is not None and e.leaf() is None:
        del _BUFFERS[key]


def mark(leaf: torch.Tensor, cols) -> None:
    """Columns ``cols`` (of axis 1; None: any) of ``leaf``'s buffer may now be nonzero."""
    e = _BUFFERS.get(id(leaf))
    if e is None or e.leaf() is not leaf:
        return
    if cols is None:
        e.all_dirty = True
    else:
        e.dirty.update(map(int, cols))


def holds(leaf: torch.Tensor, grad: torch.Tensor) -> bool:
    """Whether ``grad`` is ``leaf``'s buffer with only marked columns possibly nonzero (no foreign
    gradient since it was handed out): then whoever zeroes some of them may say so (:func:`cleaned`)."""
    e = _BUFFERS.get(id(leaf))
    return e is not None and e.leaf() is leaf and e.buf is grad and not e.all_dirty


def cleaned(leaf: torch.Tensor, cols) -> None:
    """Columns ``cols`` of ``leaf``'s buffer are zero again (the lazy optimizer zeroed them as it
    read them, engine.scene.lazy_adam): the next :func:`take` need not."""
    e = _BUFFERS.get(id(leaf))
    if e is not None and e.leaf() is leaf:
        e.dirty.difference_update(map(int, cols))


def clear() -> None:
    """Drop every buffer (tests)."""
    _BUFFERS.clear()
