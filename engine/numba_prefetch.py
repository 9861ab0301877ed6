"""``prefetch``: ask the CPU to start loading a cache line a kernel will touch soon.

The curves' kernels read and write a few columns of every row of an [N, K, C] array: a few
cache lines per row, rows ``K C`` floats apart. Neither of the hardware prefetchers follows that
(the same load instruction steps within a row, then jumps to the next one), so each line is a
full memory latency, with few misses in flight: on a 1 s capture (70k Gaussians, K = 91) the lazy
Adam step over a guided step's 7 columns took 2.6x as long as with the lines of the row 8 ahead
requested first, the curve evaluation over a segment's 4 columns 3x (docs/experiments/benchmark-history.md,
"Prefetching the
curves' rows"). A prefetch changes no value. Imported only by kernel modules (numba is loaded on
first use, never by ``import engine``).
"""
from __future__ import annotations

from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["prefetch", "prefetch_columns", "ROWS_AHEAD"]

# rows between the one a kernel works on and the one whose lines it requests (4-32 measured alike
# for the lazy step; 8 for a margin either way)
ROWS_AHEAD = 8


@intrinsic
def prefetch(typingctx, arr, idx):
    """Request the cache line of ``arr``'s element at flat offset ``idx`` (a C-contiguous array;
    for writing, kept close: LLVM's ``llvm.prefetch(ptr, 1, 3, 1)``). Never faults, even past
    the array's end."""
    sig = types.void(arr, idx)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        ptr = builder.bitcast(builder.gep(ary.data, [args[1]]), ir.IntType(8).as_pointer())
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [ir.IntType(8).as_pointer(), i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        builder.call(fn, [ptr, i32(1), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


@njit(cache=True, nogil=True, inline="always")
def prefetch_columns(flat, base, cols, C):
    """Request the lines of columns ``cols`` (ascending, of ``C`` entries each) of the row that
    starts at flat offset ``base`` of ``flat`` (a row-major [N, K, C] array, flat): each column's
    first entry, and the last column's last entry (a column may straddle a line)."""
    if cols.size > 0:
        for j in range(cols.size):
            prefetch(flat, base + cols[j] * C)
        prefetch(flat, base + cols[cols.size - 1] * C + C - 1)
