"""The ibr-service rendering engine.

Pure arrays in, arrays out. Shared by every worker type. Never imports
``api_schemas``, ``service`` or ``workers`` and never reads the environment.
"""

import numba as _numba

# Part of every artifact key (bakes, renders, relights): bump it when the same request would
# now produce different bytes, so caches never serve an older engine's answer.
# 0.2.0: LDC renders (silhouette rays, the refinement's mesh walk) and relights (float32 kernel).
# 0.2.1: LDC renders (silhouette pixels: the mesh test before the image-based ray) and relights
# (float32 point-light geometry with a float64 re-test of borderline rows).
ENGINE_VERSION = "0.2.1"

# Numba's default pick on Linux is GNU OpenMP, whose idle worker threads spin after each
# parallel region. The renderer alternates numba kernels with single-threaded Embree
# calls, and on 2 cores the spinning threads steal the core Embree needs: shading time
# measured 4x longer than with the workqueue layer (docs/performance.md). GNU OpenMP is
# also not fork-safe, and RQ bake workers fork. An explicit NUMBA_THREADING_LAYER wins.
if _numba.config.THREADING_LAYER == "default":
    _numba.config.THREADING_LAYER = "workqueue"

# numba's disk cache (``cache=True``) checks only the source file of the function it caches. The
# engine's kernels inline helpers from other files (lights, view_pass, geometry/adjacency, sched):
# after a change to such a helper, a cached caller would keep running the OLD machine code (seen
# in session 6: an A/B of view_pass.py ran its callers' stale kernels). So the cache lives in a
# directory named by a hash of every engine source file: any change to the engine compiles
# afresh (on first use of each kernel), an unchanged engine loads. NUMBA_CACHE_DIR, when set,
# is the parent of that directory; otherwise the engine's own __pycache__ is.
def _engine_source_hash() -> str:
    import hashlib
    from pathlib import Path

    h = hashlib.sha256()
    root = Path(__file__).resolve().parent
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def _numba_cache_dir() -> str:
    import os

    base = _numba.config.CACHE_DIR or os.path.join(os.path.dirname(os.path.abspath(__file__)), "__pycache__")
    return os.path.join(base, f"ibr-engine-{_engine_source_hash()}")


NUMBA_CACHE_DIR = _numba_cache_dir()
_numba.config.CACHE_DIR = NUMBA_CACHE_DIR
