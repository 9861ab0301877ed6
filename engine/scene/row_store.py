"""Per-Gaussian tensors that grow and shrink in place (issue 13: a long capture's admissions).

A Gaussian's curves hold one control-point column per third of an RGB interval, so on a capture
of seconds its parameters and Adam moments are hundreds of megabytes. Births, densification and
pruning used to rebuild each of them with ``torch.cat`` / boolean indexing: every admission of an
RGB instant wrote the whole state into fresh allocations. glibc serves blocks above 32 MiB from
fresh ``mmap`` pages, so each rebuild also paid a page fault per 4 KiB written: on a 1 s capture
(30 RGB instants, K = 88, ~70k Gaussians) a birth round's ``append`` took ~120 ms, and the
admissions were 23 % of the RGB step (``bench-step`` on a long capture, docs/experiments/benchmark-history.md "Rows
that grow in place").

Here a tensor [n, ...] is a view of the first n rows of a storage that may hold more:

* :func:`append_rows` writes the new rows into the storage's spare rows (the tensor handed in is
  not changed: its rows are not touched) and returns the longer view; only when the storage is
  full is a new one allocated, :data:`GROWTH` times the rows, so a tensor that grows by a few
  per cent per admission is reallocated once every several admissions;
* :func:`compact_rows` moves the kept rows to the front of the same storage, in order, chunk by
  chunk (a gather into a small temporary, then a write: a chunk only reads rows at or after the
  ones it writes), so pruning allocates nothing large; the tensor handed in is overwritten;
* :func:`exact` is the tensor alone, copied when its storage holds more: ``GaussianModel.trim``
  gives every parameter and moment its own-size storage, one at a time, before the state is
  saved (``torch.save`` writes a tensor's whole storage).

The values are the ones ``torch.cat`` and ``t[keep]`` give, bit for bit (``tests/test_row_store.py``,
and a training run with and without: ``ENABLED``). Works on any device. Memory: up to a quarter
more rows between reallocations, but no step holds two copies of the whole state any more: a 1 s
capture's 1000-step run peaked at 1.51 GB RGB-only and 1.56 GB with the spike branch, against
1.71 and 2.01 GB before (``ru_maxrss``; with ``engine.train.guidance.quiet_curves``' kernel).
"""
from __future__ import annotations

import math

import torch

__all__ = ["ENABLED", "GROWTH", "append_rows", "compact_rows", "exact", "capacity"]

# False: append and compact build fresh tensors (torch.cat, t[keep]) as before (bench-step "rows-copied")
ENABLED = True
# spare rows of a new storage, as a factor of the rows it holds: 1.25 reallocates once per ~25 %
# growth (a birth round adds 1-3 % of a long capture's rows) at a quarter more memory at most
GROWTH = 1.25
# rows gathered per chunk of a compaction: a temporary of at most this many bytes (below glibc's
# mmap threshold, so it reuses memory the process has instead of faulting in fresh pages)
CHUNK_BYTES = 8 << 20


def _row_numel(t: torch.Tensor) -> int:
    return math.prod(t.shape[1:])


def capacity(t: torch.Tensor) -> int:
    """Rows of ``t``'s trailing shape that its storage holds from ``t``'s first element on
    (``t.shape[0]`` for a tensor that owns its storage exactly; -1 when ``t`` is not a contiguous
    view from the storage's start, so its spare room cannot be used)."""
    if not t.is_contiguous() or t.storage_offset() != 0 or t.dim() == 0:
        return -1
    row = _row_numel(t)
    if row == 0:
        return -1
    return t.untyped_storage().nbytes() // (row * t.element_size())


def _view(storage_of: torch.Tensor, rows: int) -> torch.Tensor:
    """The first ``rows`` rows of ``storage_of``'s storage, with its trailing shape (contiguous)."""
    shape = (rows, *storage_of.shape[1:])
    stride = [1] * len(shape)
    for i in range(len(shape) - 2, -1, -1):
        stride[i] = stride[i + 1] * shape[i + 1]
    return torch.empty(0, dtype=storage_of.dtype, device=storage_of.device).set_(
        storage_of.untyped_storage(), 0, shape, stride)


def append_rows(t: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """``torch.cat([t, rows])`` [n + m, ...] (``rows`` [m, ...], converted to ``t``'s dtype and
    device), written into ``t``'s spare storage rows when there are enough, else into a new
    storage with :data:`GROWTH` x (n + m) rows. ``t`` itself is not changed."""
    t = t.detach()
    rows = rows.detach().to(dtype=t.dtype, device=t.device)
    if rows.shape[1:] != t.shape[1:]:
        raise ValueError(f"append_rows: rows {tuple(rows.shape)} do not match {tuple(t.shape)}")
    n, m = t.shape[0], rows.shape[0]
    if not ENABLED or _row_numel(t) == 0:
        return torch.cat([t, rows])
    if capacity(t) >= n + m:
        out = _view(t, n + m)
    else:
        cap = max(n + m, int(math.ceil((n + m) * GROWTH)))
        base = torch.empty((cap, *t.shape[1:]), dtype=t.dtype, device=t.device)
        out = _view(base, n + m)
        out[:n].copy_(t)
    if m:
        out[n:].copy_(rows)
    return out


def compact_rows(t: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """``t[keep]`` (``keep`` bool [n]) as the first rows of ``t``'s own storage: ``t``'s rows are
    overwritten (when it is not a contiguous view from its storage's start, a copy is returned and
    ``t`` is left alone)."""
    t = t.detach()
    keep = keep.to(device=t.device, dtype=torch.bool)
    if not ENABLED or capacity(t) < 0:
        return t[keep]
    idx = torch.nonzero(keep)[:, 0]
    k = int(idx.numel())
    first = k  # rows before the first one dropped stay where they are
    if k:
        moved = idx != torch.arange(k, device=idx.device)
        if bool(moved.any()):
            first = int(torch.nonzero(moved)[0, 0])
    chunk = max(1, CHUNK_BYTES // max(1, _row_numel(t) * t.element_size()))
    for j0 in range(first, k, chunk):
        j1 = min(k, j0 + chunk)
        # rows idx[j0:j1] >= j0 are gathered whole before rows j0..j1-1 are written, and every
        # later chunk reads rows >= j1: nothing is read after it was overwritten
        t[j0:j1] = t[idx[j0:j1]]
    return _view(t, k) if k != t.shape[0] else t


def exact(t: torch.Tensor) -> torch.Tensor:
    """``t`` alone: a copy when its storage holds more than ``t`` (``torch.save`` writes a view's
    whole storage, spare rows included)."""
    if t.untyped_storage().nbytes() != t.numel() * t.element_size() or t.storage_offset() != 0:
        return t.clone()
    return t
