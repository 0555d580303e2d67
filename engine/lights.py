"""Light sampling shared by every kernel that shades with the scene's lights.

One row index ``j`` per light sample, in the engine's fixed light order: point lights,
directional lights, then rectangular lights x ``r_g * r_g`` jittered samples
(docs/reference-renderer.md). Used by the reference renderer and the LDC bake so both
shade with exactly the same light model.
"""

from __future__ import annotations

import math

import numba as nb

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.raycast import SHADOW_SHORTEN


@nb.njit(cache=True, error_model="numpy")
def point_light_sample(ox, oy, oz, mag, qx, qy, qz, i0, i1, i2):
    """``light_sample`` of a point light at q with intensity i, in scalars: called in a loop it
    costs no reference counting (an inlined function's array arguments are increfed
    and decrefed at every call: measured at ~5 % of an LDC render's CPU time in the
    highlight loop)."""
    lx, ly, lz = qx - ox, qy - oy, qz - oz
    dist = math.sqrt(lx * lx + ly * ly + lz * lz)
    if dist <= 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    inv_d2 = 1.0 / (dist * dist)
    return (True, lx / dist, ly / dist, lz / dist, i0 * inv_d2, i1 * inv_d2, i2 * inv_d2,
            dist * (1.0 - SHADOW_SHORTEN) - mag)


@nb.njit(cache=True, error_model="numpy")
def directional_light_sample(d0, d1, d2, e0, e1, e2):
    """``light_sample`` of a directional light travelling along d with irradiance e, in scalars
    (see ``point_light_sample``)."""
    return True, -d0, -d1, -d2, e0, e1, e2, 3.0e38


@nb.njit(cache=True, error_model="numpy")
def rect_light_sample(ox, oy, oz, mag, sx, sy, c0, c1, c2, u0, u1, u2, v0, v1, v2, n0, n1, n2, area, L0, L1, L2,
                      two_sided, gg):
    """``light_sample`` of the point ``c + sx u + sy v`` (sx, sy in [0, 1]) of a rectangular light
    with corner c, edges u and v, unit normal n, area and radiance L, one of ``gg`` samples of
    the light at this origin, in scalars (see ``point_light_sample``)."""
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


@nb.njit(cache=True, inline="always", error_model="numpy")
def light_sample(j, ox, oy, oz, mag, su, sv, pt_pos, pt_int, dir_dir, dir_irr, rc, ru, rv, r_n, r_area, rL,
                 r2s, r_g):
    """Light sample ``j`` seen from the origin o (a surface point moved off its surface by ``mag``).

    su, sv: the jitter in [0, 1) of a rect-light sample (ignored for other lights);
    r_n, r_area: unit normal and area of each rect light.
    Returns (ok, lx, ly, lz, e0, e1, e2, tmax): the unit direction to the light, the
    irradiance it delivers on a surface facing it (before the receiver's cosine) and the
    shadow ray's length, stopping short of the light; ok is False when the sample cannot
    light o (zero distance, or o behind a one-sided rect light).

    Inlined with its array arguments, it costs two atomic reference-count operations per array
    and call; a hot loop calls the scalar functions above instead (``_light_rays`` in
    engine/reference.py).
    """
    npt = pt_pos.shape[0]
    ndir = dir_dir.shape[0]
    if j < npt:
        return point_light_sample(ox, oy, oz, mag, pt_pos[j, 0], pt_pos[j, 1], pt_pos[j, 2], pt_int[j, 0],
                                  pt_int[j, 1], pt_int[j, 2])
    if j < npt + ndir:
        q = j - npt
        return directional_light_sample(dir_dir[q, 0], dir_dir[q, 1], dir_dir[q, 2], dir_irr[q, 0], dir_irr[q, 1],
                                        dir_irr[q, 2])
    gg = r_g * r_g
    q = (j - npt - ndir) // gg
    s = (j - npt - ndir) % gg
    sx = (s % r_g + su) / r_g
    sy = (s // r_g + sv) / r_g
    return rect_light_sample(ox, oy, oz, mag, sx, sy, rc[q, 0], rc[q, 1], rc[q, 2], ru[q, 0], ru[q, 1], ru[q, 2],
                             rv[q, 0], rv[q, 1], rv[q, 2], r_n[q, 0], r_n[q, 1], r_n[q, 2], r_area[q], rL[q, 0],
                             rL[q, 1], rL[q, 2], r2s[q], gg)
