"""Building blocks the engine's shading kernels share (reference renderer, view pass, relighting).

- :func:`phong_pow`: ``cos^s`` of the Phong lobe without 0/0 or overflow for huge exponents.
"""

from __future__ import annotations

import math

import numba as nb

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)


@nb.njit(cache=True, error_model="numpy")
def phong_pow(c, s):
    """``c^s`` for a cosine c and a Phong exponent s >= 0: 0 for c <= 0, 1 for c >= 1 (no 0/0 at
    c = 0, s = 0 and no overflow for huge s; docs/hard-cases.md #8), else ``exp(s log c)``."""
    if c <= 0.0:
        return 0.0
    if c >= 1.0:
        return 1.0
    return math.exp(s * math.log(c))
