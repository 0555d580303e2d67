"""Dynamic block scheduling for the engine's parallel kernels.

numba's ``prange`` splits its range into one equal, contiguous chunk per thread, decided
before the loop starts. Per-pixel work in the renderers is uneven (mirror and glossy pixels
cluster, LDI samples cluster by depth complexity) and, more to the point on a shared machine,
the two cores are not equally available: when another process (the API, Redis, another
worker) takes one core for a few milliseconds, the thread on it finishes late and the whole
stage waits for it. Round-robin groups (one per thread) fixed the first problem, not the
second.

Here the threads take blocks from a shared counter instead: ``next_block(counter)`` is an
atomic fetch-and-add (LLVM ``atomicrmw add``, ``monotonic``: only the counter's own value is
ordered; the blocks' outputs are disjoint and the parallel region's join orders them), so a
thread that was descheduled simply takes fewer blocks. Usage::

    counter = np.zeros(1, np.int64)         # one per kernel call
    for _ in nb.prange(n_threads):
        while True:
            blk = next_block(counter)
            if blk >= n_blocks:
                break
            ...  # the block's items

Results do not depend on which thread takes which block as long as each block writes only
its own outputs (every kernel using this keeps that rule), so images stay bit-identical for
any thread count and timing.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types as nbtypes
from numba.core import cgutils
from numba.extending import intrinsic

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)


@intrinsic
def next_block(typingctx, counter):
    """``counter[0]`` before atomically adding 1 to it (int64)."""
    if not (isinstance(counter, nbtypes.Array) and counter.ndim == 1 and counter.dtype == nbtypes.int64):
        return None

    def codegen(context, builder, sig, args):
        aryty = sig.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [ir.Constant(ir.IntType(64), 0)],
                                       wraparound=False)
        return builder.atomic_rmw("add", ptr, ir.Constant(ir.IntType(64), 1), "monotonic")

    return nbtypes.int64(counter), codegen


__all__ = ["next_block"]
