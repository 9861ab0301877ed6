"""``vml_sqrt32``: torch's own float32 square root, callable from a numba kernel.

torch's CPU ``sqrt`` on a contiguous float32 tensor is MKL VML's ``vmsSqrt`` (mode
``VML_HA | VML_FTZDAZ_OFF | VML_ERRMODE_IGNORE``, ATen/cpu/vml.h), which is not correctly
rounded (+-1 ulp against IEEE on some inputs, measured), so a kernel that must match torch bit
for bit cannot use the CPU's ``sqrtps``. torch's wheel exports ``vmsSqrt`` from
``libtorch_cpu``; this module hands its address to LLVM's symbol table (the name, not the
address, goes into numba's on-disk cache, so cached kernels keep working) and declares it for
numba. :data:`AVAILABLE` is False where the symbol is missing (a torch built without MKL:
ARM, macOS); callers then keep torch's ``sqrt`` (``engine.scene.fused_adam``), and check that
the two agree before relying on it. Imported by kernel modules and by their callers' checks
(it loads numba).
"""
from __future__ import annotations

import ctypes
import os

import llvmlite.binding as llvm
import torch
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["AVAILABLE", "MODE", "vml_sqrt32"]

# mkl_vml_defines.h: VML_HA 0x2 | VML_FTZDAZ_OFF 0x140000 | VML_ERRMODE_IGNORE 0x100, as torch
MODE = 0x2 | 0x140000 | 0x100
SYMBOL = "vmsSqrt"


def _register() -> bool:
    """Put ``vmsSqrt`` (LP64: ``MKL_INT`` = int32, as torch's wheels) into LLVM's symbol table."""
    for name in ("libtorch_cpu.so", "torch_cpu.dll"):  # Linux, Windows (macOS wheels have no MKL)
        path = os.path.join(os.path.dirname(torch.__file__), "lib", name)
        if not os.path.exists(path):
            continue
        try:
            fn = getattr(ctypes.CDLL(path), SYMBOL)
        except (OSError, AttributeError):  # not exported: torch's sqrt is not reachable
            return False
        llvm.add_symbol(SYMBOL, ctypes.cast(fn, ctypes.c_void_p).value)
        return True
    return False


AVAILABLE = _register()


@intrinsic
def vml_sqrt32(typingctx, src, dst):
    """``dst[:] = sqrt(src)`` by MKL's ``vmsSqrt`` in torch's mode; ``src`` and ``dst``:
    contiguous 1-D float32 arrays of one length (below 2**31), may be the same array. Call
    it only where :data:`AVAILABLE`."""
    sig = types.void(src, dst)

    def codegen(context, builder, signature, args):
        fty = ir.FunctionType(ir.VoidType(), [ir.IntType(32), ir.PointerType(ir.FloatType()),
                                              ir.PointerType(ir.FloatType()), ir.IntType(64)])
        fn = cgutils.get_or_insert_function(builder.module, fty, SYMBOL)
        s = context.make_array(signature.args[0])(context, builder, args[0])
        d = context.make_array(signature.args[1])(context, builder, args[1])
        n = builder.trunc(s.nitems, ir.IntType(32))
        builder.call(fn, [n, s.data, d.data, ir.Constant(ir.IntType(64), MODE)])
        return context.get_dummy_value()

    return sig, codegen
