"""Light sampling shared by every kernel that shades with the scene's lights.

One row index ``j`` per light sample, in the engine's fixed light order: point lights,
directional lights, then rectangular lights x ``r_g * r_g`` jittered samples
(docs/reference-renderer.md). Used by the reference renderer, the LDC bake and the LDC
renderer's highlights so all shade with exactly the same light model.

Every function here takes and returns scalars only: a caller's loop reads its light's row of the
scene's light table (``engine.scene.LightTable``) and passes the numbers. A function inlined by
numba with array arguments costs an atomic reference-count increment and decrement per array and
call (docs/performance.md); these cost none, and LLVM inlines them anyway.
"""

from __future__ import annotations

import math

import numba as nb

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.raycast import SHADOW_SHORTEN


@nb.njit(cache=True, error_model="numpy")
def point_light_sample(ox, oy, oz, mag, qx, qy, qz, i0, i1, i2):
    """Light sample of a point light at q with intensity i, seen from the origin o (a surface point
    moved off its surface by ``mag``).

    Returns (ok, lx, ly, lz, e0, e1, e2, tmax): the unit direction to the light, the irradiance it
    delivers on a surface facing it (before the receiver's cosine) and the shadow ray's length,
    stopping short of the light; ok is False when the sample cannot light o (zero distance, or o
    behind a one-sided rect light). The same for every light kind below."""
    lx, ly, lz = qx - ox, qy - oy, qz - oz
    dist = math.sqrt(lx * lx + ly * ly + lz * lz)
    if dist <= 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    inv_d2 = 1.0 / (dist * dist)
    return (True, lx / dist, ly / dist, lz / dist, i0 * inv_d2, i1 * inv_d2, i2 * inv_d2,
            dist * (1.0 - SHADOW_SHORTEN) - mag)


@nb.njit(cache=True, error_model="numpy")
def directional_light_sample(d0, d1, d2, e0, e1, e2):
    """Light sample of a directional light travelling along d with irradiance e (returns as
    ``point_light_sample``)."""
    return True, -d0, -d1, -d2, e0, e1, e2, 3.0e38


@nb.njit(cache=True, error_model="numpy")
def rect_light_sample(ox, oy, oz, mag, sx, sy, c0, c1, c2, u0, u1, u2, v0, v1, v2, n0, n1, n2, area, L0, L1, L2,
                      two_sided, gg):
    """Light sample at the point ``c + sx u + sy v`` (sx, sy in [0, 1], ``rect_cell_point``) of a
    rectangular light with corner c, edges u and v, unit normal n, area and radiance L, one of
    ``gg`` samples of the light at this origin (returns as ``point_light_sample``)."""
    lx = c0 + sx * u0 + sy * v0 - ox
    ly = c1 + sx * u1 + sy * v1 - oy
    lz = c2 + sx * u2 + sy * v2 - oz
    dist = math.sqrt(lx * lx + ly * ly + lz * lz)
    if dist <= 0.0 or area <= 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    inv = 1.0 / dist
    lx *= inv
    ly *= inv
    lz *= inv
    cos_l = -(n0 * lx + n1 * ly + n2 * lz)
    if two_sided:
        cos_l = abs(cos_l)
    if cos_l <= 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    geo = cos_l * area / (dist * dist * gg)
    return True, lx, ly, lz, L0 * geo, L1 * geo, L2 * geo, dist * (1.0 - SHADOW_SHORTEN) - mag


@nb.njit(cache=True, error_model="numpy")
def rect_cell_point(s, r_g, su, sv):
    """(sx, sy) for ``rect_light_sample``: the point of cell ``s`` (of the r_g x r_g grid over a rect
    light, row-major) jittered by (su, sv), in cell widths: the reference renderer's cell-stratified
    points (the LDC's are whole sequences over the light, ``engine.newviews.ldc.rect_net_point``).
    Rect-light row j (after the point and directional lights) is light
    q = (j - n_point - n_directional) // (r_g * r_g), cell s = the remainder."""
    return (s % r_g + su) / r_g, (s // r_g + sv) / r_g
