"""The compiled loop of ``engine.imageio``'s 8-bit sRGB encoding (the thresholds and their tables
are in ``engine/imageio.py``).

A module of its own so that importing ``engine.imageio`` (and ``engine.metrics``) needs no numba:
the API process reads images and computes metrics with them but never writes 8-bit ones, and must
not load numba. ``engine.imageio`` imports this module on the first 8-bit encode. The same loop
in NumPy (bucket look-up, compare, add) is about 2x slower at 512x512: 4.7 vs 2.3 ms, the render
preview's encode.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)


@nb.njit(cache=True, nogil=True)
def srgb8_kernel(flat, scale, base, thresh, shift, out):
    """code = base[bucket(c)] + (c >= thresh[bucket(c)]) with c = clip(x * scale, 0, 1) in float64 and
    bucket(c) = bits(c) >> shift (serial, nogil: safe from several threads at once)."""
    bits = np.empty(1, np.float64)
    ibits = bits.view(np.int64)
    for i in range(flat.size):
        c = np.float64(flat[i]) * scale
        if c > 1.0:
            c = 1.0
        elif not c >= 0.0:  # negative (or NaN, which callers never pass)
            c = 0.0
        c += 0.0  # -0.0 -> +0.0 (its sign bit would make a negative index)
        bits[0] = c
        b = ibits[0] >> shift
        code = base[b]
        if c >= thresh[b]:
            code += 1
        out[i] = code
