"""Process memory policy for long-lived rendering processes (workers, benchmarks).

A render allocates tens of MiB of image-sized arrays (a 512x512 LDC render: the warp's float64
radiance, depth and normal images, the view pass's ray buffers, the float32 output; a reference
render: its wavefront buffers) and frees them when it returns. glibc's malloc serves blocks
above its mmap threshold (128 KiB, raised dynamically up to 32 MiB) with fresh ``mmap`` pages
and gives freed heap tops back to the kernel above its trim threshold, so the next render of
ANOTHER kind (sizes differ, the dynamic threshold has not caught up) touches fresh pages again:
on mirror_box 512x512, an LDC render right after a reference render took 800-2,200 minor page
faults (3-9 MiB), none right after another LDC render. With the policy, LDC and reference
renders alternating ran ~1.2x faster each (separate-process runs; docs/service-design.md,
"Memory between jobs").

:func:`keep_freed_memory` raises both thresholds once per process (``mallopt``): blocks up to
32 MiB come from the heap and up to ``keep_bytes`` of freed memory stays mapped for the next
render. The cost is resident memory: a worker keeps up to ``keep_bytes`` more than it uses.
Not glibc (musl, macOS): a no-op that returns False.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading

__all__ = ["DEFAULT_KEEP_BYTES", "MMAP_THRESHOLD_BYTES", "keep_freed_memory", "malloc_policy"]

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 << 20
"""glibc's largest mmap threshold on 64-bit (``DEFAULT_MMAP_THRESHOLD_MAX``): larger blocks are
always mapped (and unmapped on free)."""
DEFAULT_KEEP_BYTES = 256 << 20

_lock = threading.Lock()
_policy: dict | None = None


def keep_freed_memory(keep_bytes: int = DEFAULT_KEEP_BYTES) -> bool:
    """Have glibc's malloc serve blocks up to 32 MiB from the heap and keep up to ``keep_bytes``
    of freed heap mapped (module docstring). Idempotent per process (the first call's value
    holds); ``keep_bytes <= 0`` leaves malloc as it is. Returns whether the policy is in effect."""
    global _policy
    with _lock:
        if _policy is not None:
            return bool(_policy["active"])
        active = False
        if keep_bytes > 0:
            try:
                libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
                mallopt = libc.mallopt
            except (OSError, AttributeError):
                mallopt = None
            if mallopt is not None:
                mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
                mallopt.restype = ctypes.c_int
                keep = int(min(keep_bytes, 2**31 - 1))
                # mallopt returns 1 on success; setting either one turns off the dynamic thresholds
                active = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, keep))
        _policy = {"active": active, "keep_bytes": int(keep_bytes) if active else 0,
                   "mmap_threshold_bytes": MMAP_THRESHOLD_BYTES if active else None}
        return active


def malloc_policy() -> dict:
    """What :func:`keep_freed_memory` set in this process (``active`` False when never called)."""
    with _lock:
        return dict(_policy) if _policy is not None else {"active": False, "keep_bytes": 0,
                                                           "mmap_threshold_bytes": None}
