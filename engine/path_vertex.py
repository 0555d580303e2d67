"""Per-vertex physics that the reference renderer (engine/reference.py), the caustic photon map
(engine/caustics.py) and light tracing (engine/light_tracing.py) share: ray kinds and sample
dimensions, surface frames, the lobes' directions, rect lights met by rays, the camera's frame.

They take scalars (or whole arrays in the ``lo``/``hi`` kernels) only: a jitted function called
with arrays pays atomic reference counts on them at every call (on counters both cores share), and
a call with more than 30 arguments compiles as a call with *args, which numba neither inlines nor
passes cheaply. docs/reference-renderer.md describes the conventions.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.raycast import OFFSET_EXTENT, OFFSET_REL, SHADOW_SHORTEN
from engine.sampler import derive_key, sample_2d
from engine.scene import CameraParams
from engine.shading import phong_pow

INV_PI = 1.0 / math.pi

# ray kinds in a wavefront batch
KIND_CHAIN = 0  # camera ray or a mirror / glossy continuation of one
KIND_PATH = 1  # an indirect path ray whose last lobe was diffuse
KIND_SPEC = 2  # an indirect path ray whose last lobe was mirror or glossy (it sees rect lights)
KIND_BASE = 3  # kind & KIND_BASE: one of the three above
# flag on KIND_PATH / KIND_SPEC: the ray's path is a direct camera hit, diffuse path vertices, then
# (KIND_SPEC) mirror / glossy vertices only; the light such a path finds through those lobes (a
# rect light met by its mirror / glossy ray, the glossy lobe's next-event estimation) is the light
# tracer's (engine/light_tracing.py), so these rays leave it out
LIGHT_TRACED = 4

# sample dimensions at a path vertex: derive_key(ray key, vertex, purpose)
DIM_PIXEL = 1  # (vertex 0) position in the pixel
DIM_LIGHT = 2  # rect-light positions (then derive_key(., light, stratum))
DIM_LOBE = 3  # lobe choice at a path vertex
DIM_DIR = 4  # BSDF direction
DIM_RR = 5  # Russian roulette at a path vertex


@nb.njit(cache=True, error_model="numpy")
def _mis_weight(mode, a, b):
    """Weight of strategy a (density x sample count ``a``) against strategy b (``b``): power
    heuristic (mode 0), balance heuristic (1); mode 2: light sampling alone (a = the light),
    mode 3: BSDF sampling alone (a = the light: weight 0)."""
    if mode == 0:
        a2 = a * a
        den = a2 + b * b
        return a2 / den if den > 0.0 else 0.0
    if mode == 1:
        den = a + b
        return a / den if den > 0.0 else 0.0
    return 1.0 if mode == 2 else 0.0


@nb.njit(cache=True, error_model="numpy")
def _dot(a0, a1, a2, b0, b1, b2):
    return a0 * b0 + a1 * b1 + a2 * b2


@nb.njit(cache=True, error_model="numpy")
def _offset_mag(px, py, pz, center, extent):
    m = max(abs(px - center[0]), abs(py - center[1]), abs(pz - center[2]))
    return OFFSET_REL * (m + OFFSET_EXTENT * extent)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _surface_frame(t, uu, vv, dx, dy, dz, tri_n, tri_ng):
    """Geometric and shading normals of triangle t at barycentrics (uu, vv), both flipped to
    face a ray travelling along (dx, dy, dz); a shading normal on the wrong side of the
    geometric one falls back to it. Returns (g0, g1, g2, s0, s1, s2)."""
    w0 = 1.0 - uu - vv
    g0, g1, g2 = tri_ng[t, 0], tri_ng[t, 1], tri_ng[t, 2]
    s0 = w0 * tri_n[t, 0, 0] + uu * tri_n[t, 1, 0] + vv * tri_n[t, 2, 0]
    s1 = w0 * tri_n[t, 0, 1] + uu * tri_n[t, 1, 1] + vv * tri_n[t, 2, 1]
    s2 = w0 * tri_n[t, 0, 2] + uu * tri_n[t, 1, 2] + vv * tri_n[t, 2, 2]
    ls = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    if ls > 1e-12:
        s0 /= ls
        s1 /= ls
        s2 /= ls
    else:
        s0, s1, s2 = g0, g1, g2
    if _dot(g0, g1, g2, dx, dy, dz) > 0.0:  # back side: flip both
        g0, g1, g2 = -g0, -g1, -g2
        s0, s1, s2 = -s0, -s1, -s2
    if _dot(s0, s1, s2, g0, g1, g2) <= 0.0:  # shading normal on the wrong side
        s0, s1, s2 = g0, g1, g2
    return g0, g1, g2, s0, s1, s2


@nb.njit(cache=True, error_model="numpy")
def _mean_albedos(kd0, kd1, kd2, kr0, kr1, kr2, kg0, kg1, kg2):
    """The diffuse, mirror and glossy lobes' mean albedos (ad, ar, ag)."""
    return (kd0 + kd1 + kd2) / 3.0, (kr0 + kr1 + kr2) / 3.0, (kg0 + kg1 + kg2) / 3.0


@nb.njit(cache=True, error_model="numpy")
def _frame(n0, n1, n2):
    # orthonormal basis around (n0, n1, n2) (Duff et al. 2017)
    sign = 1.0 if n2 >= 0.0 else -1.0
    a = -1.0 / (sign + n2)
    b = n0 * n1 * a
    return (1.0 + sign * n0 * n0 * a, sign * b, -sign * n0,
            b, sign + n1 * n1 * a, -n1)


@nb.njit(cache=True, error_model="numpy")
def _lobe_dir(a0, a1, a2, cos_t, phi):
    sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
    t0, t1, t2, b0, b1, b2 = _frame(a0, a1, a2)
    x = sin_t * math.cos(phi)
    y = sin_t * math.sin(phi)
    return (x * t0 + y * b0 + cos_t * a0, x * t1 + y * b1 + cos_t * a1, x * t2 + y * b2 + cos_t * a2)


@nb.njit(cache=True, error_model="numpy")
def _lobe_direction(lb, ckey, vertex, pix, cidx, scale, wr0, wr1, wr2, n0, n1, n2, ge):
    """A direction from lobe ``lb`` (0 mirror: the unit mirror direction wr itself, 1 glossy: cos^g
    around wr, 2 diffuse: cosine-weighted around the shading normal n; dimension DIM_DIR of
    ``ckey``), not normalised, with ``fk``, the factor of the lobe's albedo in the ray's weight (the
    BSDF times cos over the density: 1, or (g+2)/(g+1) cos_i for the glossy lobe, 0 below n), and
    ``bp``, a glossy ray's density over ``scale`` (the BSDF strategy of multiple importance
    sampling, 0 for the other lobes): (x0, x1, x2, fk, bp)."""
    if lb == 0:
        return wr0, wr1, wr2, 1.0, 0.0
    u0, u1 = sample_2d(derive_key(ckey, vertex, DIM_DIR), pix, cidx)
    if lb == 1:
        cos_a = math.exp(math.log(max(u0, 1e-300)) / (ge + 1.0))
        x0, x1, x2 = _lobe_dir(wr0, wr1, wr2, cos_a, 2.0 * math.pi * u1)
        bp = (ge + 1.0) * 0.5 * INV_PI * phong_pow(cos_a, ge) / scale
        cos_i = _dot(n0, n1, n2, x0, x1, x2)
        return x0, x1, x2, (ge + 2.0) / (ge + 1.0) * cos_i if cos_i > 0.0 else 0.0, bp
    x0, x1, x2 = _lobe_dir(n0, n1, n2, math.sqrt(u0), 2.0 * math.pi * u1)
    return x0, x1, x2, 1.0, 0.0


@nb.njit(cache=True, error_model="numpy")
def _rect_light_t(ox, oy, oz, dx, dy, dz, c0, c1, c2, u0, u1, u2, v0, v1, v2, n0, n1, n2, area, two_sided):
    """Distance along a ray (float64 origin, unit direction) to a rect light (corner c, edges u and
    v, unit normal n) where it meets the light's emitting side (either side if ``two_sided``); inf
    where it does not."""
    if area <= 0.0:
        return np.inf
    den = _dot(dx, dy, dz, n0, n1, n2)
    if not (den < 0.0 or (two_sided and den > 0.0)):
        return np.inf  # parallel, or the back of a one-sided light
    wx, wy, wz = c0 - ox, c1 - oy, c2 - oz
    tq = _dot(wx, wy, wz, n0, n1, n2) / den
    if not tq > 0.0:
        return np.inf
    # the hit point's coordinates along the edges: x - corner = a edge_u + b edge_v
    px, py, pz = tq * dx - wx, tq * dy - wy, tq * dz - wz
    a = _dot(py * v2 - pz * v1, pz * v0 - px * v2, px * v1 - py * v0, n0, n1, n2) / area
    b = _dot(u1 * pz - u2 * py, u2 * px - u0 * pz, u0 * py - u1 * px, n0, n1, n2) / area
    if 0.0 <= a <= 1.0 and 0.0 <= b <= 1.0:
        return tq
    return np.inf


@nb.njit(cache=True, error_model="numpy")
def _emitter_mis(bpdf, dist, cos_l, area, gg, mis):
    """The weight of a rect light met by a ray at distance ``dist`` (cos_l: the cosine at the
    light): 1 for camera and mirror rays (``bpdf`` 0); for a glossy ray (``bpdf``: its density times
    its expected count) the BSDF strategy's multiple importance sampling weight against the gg
    light samples next-event estimation takes (``_row_lobes`` weighs the other side)."""
    if not bpdf > 0.0:
        return 1.0
    n_l = gg * dist * dist / (cos_l * area) if cos_l > 0.0 else np.inf
    return 1.0 - _mis_weight(mis, n_l, bpdf) if n_l < np.inf else 1.0


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _rect_hits(lo, hi, o32, d, prim, u, v, kind, weight, bpdf, gg, mis, spec_lit, tri_p, center, rc, ru, rv, r_n,
               r_area, rL, r2s, lit, c_out):
    """Rect lights seen by the rays that see lights: camera rays and mirror / glossy continuations
    (``kind`` KIND_CHAIN or KIND_SPEC; diffuse path rays never do, next-event estimation covers
    them). A ray that meets a rect light's emitting side (either side if two-sided) before its
    first triangle ends there: ``lit`` True and ``c_out`` = weight x the light's radiance. A
    triangle hides the light only when it is nearer than the light by more than the shadow rays'
    margin (SHADOW_SHORTEN), so an emissive object modelled at the light never counts twice and a
    light seen by a mirror ray is visible exactly where a shadow ray would reach it. A light's
    back side (one-sided lights) is not there: the ray goes on, as every other ray does.
    Origins are float32 relative to ``center``; the triangle's distance is rebuilt in float64
    from its barycentrics. A glossy ray (``bpdf`` > 0: its density times its expected count)
    brings the light with the multiple importance sampling weight of the BSDF strategy against
    the gg light samples next-event estimation takes (``_light_rays`` weighs the other side);
    camera and mirror rays (``bpdf`` 0) with weight 1. ``spec_lit`` False: path rays of mirror /
    glossy lobes (KIND_SPEC) still end on a light's emitting side, bringing nothing (a caustic
    photon map brings that light, engine/caustics.py, and its photons end there too)."""
    nrect = rc.shape[0]
    for i in range(lo, hi):
        lit[i] = False
        if (kind[i] & KIND_BASE) == KIND_PATH:
            continue
        ox = np.float64(o32[i, 0]) + center[0]
        oy = np.float64(o32[i, 1]) + center[1]
        oz = np.float64(o32[i, 2]) + center[2]
        dx, dy, dz = d[i, 0], d[i, 1], d[i, 2]
        t_tri = np.inf
        t = prim[i]
        if t >= 0:
            uu = np.float64(u[i])
            vv = np.float64(v[i])
            w0 = 1.0 - uu - vv
            hx = w0 * tri_p[t, 0, 0] + uu * tri_p[t, 1, 0] + vv * tri_p[t, 2, 0]
            hy = w0 * tri_p[t, 0, 1] + uu * tri_p[t, 1, 1] + vv * tri_p[t, 2, 1]
            hz = w0 * tri_p[t, 0, 2] + uu * tri_p[t, 1, 2] + vv * tri_p[t, 2, 2]
            t_tri = _dot(hx - ox, hy - oy, hz - oz, dx, dy, dz)
        best = np.inf
        hit = -1
        for q in range(nrect):
            tq = _rect_light_t(ox, oy, oz, dx, dy, dz, rc[q, 0], rc[q, 1], rc[q, 2], ru[q, 0], ru[q, 1], ru[q, 2],
                               rv[q, 0], rv[q, 1], rv[q, 2], r_n[q, 0], r_n[q, 1], r_n[q, 2], r_area[q], r2s[q])
            if tq < best:
                best = tq
                hit = q
        if hit >= 0 and not (t_tri < best * (1.0 - SHADOW_SHORTEN)):
            lit[i] = True
            wm = _emitter_mis(bpdf[i], best, abs(_dot(dx, dy, dz, r_n[hit, 0], r_n[hit, 1], r_n[hit, 2])),
                              r_area[hit], gg, mis)
            if (kind[i] & KIND_BASE) == KIND_SPEC and (not spec_lit or kind[i] & LIGHT_TRACED):
                wm = 0.0
            c_out[i, 0] = weight[i, 0] * rL[hit, 0] * wm
            c_out[i, 1] = weight[i, 1] * rL[hit, 1] * wm
            c_out[i, 2] = weight[i, 2] * rL[hit, 2] * wm


def _camera_frame(camera: CameraParams):
    """(right, up, forward, x scale, y scale) of the camera kernels: perspective scales are
    tan(fov/2) * aspect and tan(fov/2), orthographic ones the half extents."""
    right, up, fwd = camera.basis()
    if camera.kind == "perspective":
        th = math.tan(math.radians(camera.fov_y_deg) * 0.5)
        return right, up, fwd, th * camera.width / camera.height, th
    return right, up, fwd, 0.5 * camera.ortho_height * camera.width / camera.height, 0.5 * camera.ortho_height
