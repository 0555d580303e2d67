"""numba's process-wide configuration for the engine's kernels.

Every engine module that compiles kernels imports this module before it defines one
(``from engine import _numba_setup  # noqa: F401``), so the settings below are in place before
numba creates a kernel's disk cache or starts its thread pool. Modules without kernels do not
import it, which keeps ``import engine`` free of numba for the API process.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numba

# Numba's default pick on Linux is GNU OpenMP, whose idle worker threads spin after each
# parallel region. The renderer alternates numba kernels with single-threaded Embree
# calls, and on 2 cores the spinning threads steal the core Embree needs: shading time
# measured 4x longer than with the workqueue layer (docs/performance.md). GNU OpenMP is
# also not fork-safe, and RQ bake workers fork. An explicit NUMBA_THREADING_LAYER wins.
if numba.config.THREADING_LAYER == "default":
    numba.config.THREADING_LAYER = "workqueue"


# numba's disk cache (``cache=True``) checks only the source file of the function it caches. The
# engine's kernels inline helpers from other files (lights, view_pass, geometry/adjacency, sched):
# after a change to such a helper, a cached caller would keep running the OLD machine code (an
# A/B of view_pass.py once ran its callers' stale kernels this way). So the cache lives in a
# directory named by a hash of every engine source file: any change to the engine compiles
# afresh (on first use of each kernel), an unchanged engine loads. NUMBA_CACHE_DIR, when set,
# is the parent of that directory; otherwise the engine's own __pycache__ is.
def engine_source_hash() -> str:
    """First 16 hex digits of a SHA-256 over every engine source file's path and bytes."""
    h = hashlib.sha256()
    root = Path(__file__).resolve().parent
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def _numba_cache_dir() -> str:
    base = numba.config.CACHE_DIR or os.path.join(os.path.dirname(os.path.abspath(__file__)), "__pycache__")
    return os.path.join(base, f"ibr-engine-{engine_source_hash()}")


NUMBA_CACHE_DIR = _numba_cache_dir()
numba.config.CACHE_DIR = NUMBA_CACHE_DIR
