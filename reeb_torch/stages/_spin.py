"""A compiled wait on a counter another thread bumps: the helper thread's hand-over.

Handing a half of a kernel's work to a helper thread that sleeps on a lock costs the
thread's wake-up twice (its start, and the caller's wake when it is done): 55–70 µs each on
the two-core VM of this project (an idle virtual CPU halts, and waking it goes through the
host), five times per single image. :func:`wait_while` instead watches the counter in
compiled code without the GIL, with the CPU's spin-wait hint between reads, for a bounded
number of reads; the caller sleeps on a lock only after that (:mod:`._threads`).

The read is an atomic acquire load (an ordinary load could be hoisted out of the loop by
the compiler, and then never see the change). Where the CPU has no spin-wait hint that
numba can emit (other than x86-64 and arm64), or where ``$REEB_TORCH_SPIN`` is ``0``
(for a machine whose second core has other work to do: the helper spins up to ~2 ms after
each call), :data:`SPINS` is ``False`` and callers sleep at once.
"""

from __future__ import annotations

import os
import platform

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

__all__ = ["SPINS", "wait_while"]

_HINT = {"x86_64": "x86", "amd64": "x86", "aarch64": "arm", "arm64": "arm"}.get(platform.machine().lower())
SPINS = _HINT is not None and os.environ.get("REEB_TORCH_SPIN", "1").strip().lower() not in ("0", "off", "no", "false")
"""Whether :func:`wait_while` spins here (else the helper's callers only sleep on locks)."""


@intrinsic
def _load_acquire(typingctx, arr, idx):  # pragma: no cover - compiled
    """``arr[idx]`` (int64, C-contiguous, 1-d) as an atomic load with acquire ordering."""
    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1]])
        return builder.load_atomic(ptr, "acquire", 8)

    return types.int64(arr, idx), codegen


@intrinsic
def _pause(typingctx):  # pragma: no cover - compiled
    """The CPU's spin-wait hint (x86 ``pause``, arm ``yield``): lets the other hardware
    thread of the core run, and costs less power than a bare loop."""
    def codegen(context, builder, signature, args):
        if _HINT == "x86":
            fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), []),
                                                "llvm.x86.sse2.pause")
            builder.call(fn, [])
        elif _HINT == "arm":
            i32 = ir.IntType(32)
            fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [i32]),
                                                "llvm.aarch64.hint")
            builder.call(fn, [ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return types.void(), codegen


@numba.njit(cache=True, nogil=True)
def wait_while(counter: np.ndarray, i: int, value: int, reads: int) -> int:  # pragma: no cover - compiled
    """Read ``counter[i]`` (``int64 [N]``) until it differs from ``value``, at most
    ``reads`` times (each ~25 ns on this project's CPUs, hint included), without the GIL;
    returns the last value read (``value`` when it did not change)."""
    for _ in range(reads):
        v = _load_acquire(counter, i)
        if v != value:
            return v
        _pause()
    return value
