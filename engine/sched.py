"""How the engine's kernels use both cores: serial ``nogil`` kernels split over a thread pool
(:func:`run_pieces_parallel`, :func:`run_on_threads`), and dynamic block scheduling between
those threads (:func:`next_block`).

Why a thread pool and not numba's ``prange``: a ``parallel=True`` kernel compiles 2-5x slower
than the same loop compiled serially (numba's parfor passes re-type and re-lower the loop body,
and the kernels that offer both a serial and a parallel form compiled twice), and cold compile
time is what a fresh machine's first render waits for (docs/performance.md, "First run"). A
serial kernel that releases the GIL, called on a slice of its batch from plain Python threads,
runs on both cores like ``prange`` does, compiles once, and is the same machine code a
pipeline thread (engine/reference.py) calls on its own.

Dynamic block scheduling, and why:

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

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numba as nb
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


_POOL: tuple[int, ThreadPoolExecutor] | None = None
_POOL_LOCK = threading.Lock()
_IN_POOL = threading.local()


def _mark_pool_thread() -> None:
    _IN_POOL.yes = True


def _pool() -> ThreadPoolExecutor:
    """This process's threads for parallel kernels: as many as numba may use (``NUMBA_NUM_THREADS``;
    a call uses ``nb.get_num_threads()`` of them, which a caller may lower). Made again after a
    fork: threads don't survive one."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL[0] != os.getpid():
            pool = ThreadPoolExecutor(max(1, nb.config.NUMBA_NUM_THREADS), thread_name_prefix="ibr-kernel",
                                      initializer=_mark_pool_thread)
            _POOL = (os.getpid(), pool)
        return _POOL[1]


def threads_for(serial: bool | None) -> int:
    """How many threads a kernel call may use: 1 when ``serial`` or when called from one of the
    pool's own threads (which must not wait on the pool they run in); by default (None) every numba
    thread when called from the main thread and 1 from any other (those are pipelines,
    engine/reference.py ``run_pieces``)."""
    if getattr(_IN_POOL, "yes", False):
        return 1
    if serial is None:
        serial = threading.current_thread() is not threading.main_thread()
    return 1 if serial else max(1, nb.get_num_threads())


def run_pieces_parallel(kernel: Callable[..., None], n: int, min_piece: int = 1, serial: bool | None = None,
                        *args: Any) -> None:
    """``kernel(lo, hi, *args)`` over 0 .. n - 1: in the calling thread (``threads_for(serial)`` is
    1, or fewer than two pieces of ``min_piece`` items), else in up to 4 pieces per thread on the pool.

    ``kernel`` must release the GIL (``nogil=True``) to run in parallel, and each piece must write
    only its own outputs, so the result does not depend on the split. More pieces than threads let
    a thread whose core is busy with other work take fewer of them. Exceptions propagate."""
    threads = threads_for(serial)
    if threads < 2 or n < 2 * max(1, min_piece):
        kernel(0, n, *args)
        return
    pieces = min(4 * threads, n // max(1, min_piece))
    cuts = [n * k // pieces for k in range(pieces + 1)]
    list(_pool().map(lambda k: kernel(cuts[k], cuts[k + 1], *args), range(pieces)))


def run_on_threads(group: Callable[[], None], serial: bool | None = None) -> None:
    """``group()`` once per thread (``threads_for(serial)`` of them, the calling thread's call
    included): for kernels whose groups take their blocks from a shared :func:`next_block`
    counter. Exceptions propagate."""
    threads = threads_for(serial)
    if threads < 2:
        group()
        return
    futures = [_pool().submit(group) for _ in range(threads - 1)]
    try:
        group()
    finally:
        for f in futures:
            f.result()


__all__ = ["next_block", "run_on_threads", "run_pieces_parallel", "threads_for"]
