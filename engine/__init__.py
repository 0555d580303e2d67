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
