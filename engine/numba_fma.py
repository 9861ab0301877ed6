"""``fma32``: a float32 fused multiply-add for the numba kernels.

LLVM contracts ``a * b + c`` into an fma only when it may; torch's AVX2 kernels use fused
multiply-adds in fixed places, so kernels that must match torch bit for bit (FusedAdam's
update, the Lucas-Kanade warp) spell each one out. Imported only by kernel modules (numba is
loaded on first use, never by ``import engine``).
"""
from __future__ import annotations

from numba import types
from numba.extending import intrinsic

__all__ = ["fma32"]


@intrinsic
def fma32(typingctx, a, b, c):
    """``a * b + c`` rounded once (float32 in, float32 out)."""
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return sig, codegen
