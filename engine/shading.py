"""Building blocks the engine's shading kernels share (reference renderer, view pass, relighting).

- :func:`phong_pow`: ``cos^s`` of the Phong lobe without 0/0 or overflow for huge exponents.
- :func:`mirror_direction`: the unit mirror direction of a direction about a normal.
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


@nb.njit(cache=True, error_model="numpy")
def mirror_direction(n0, n1, n2, w0, w1, w2):
    """The unit mirror direction ``2 (n . w) n - w`` of the direction w (toward the viewer) about the
    unit normal n."""
    c = n0 * w0 + n1 * w1 + n2 * w2
    d0, d1, d2 = 2.0 * c * n0 - w0, 2.0 * c * n1 - w1, 2.0 * c * n2 - w2
    ln = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    return d0 / ln, d1 / ln, d2 / ln
