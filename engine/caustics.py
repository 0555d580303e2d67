"""Caustic photon map: light that reaches diffuse surfaces through mirror and glossy bounces.

A diffuse surface lit by a rect light through a mirror or a glossy surface (a caustic: light ->
mirror / glossy ... -> diffuse) is what path tracing from the diffuse surface finds worst. Its
paths must leave in the few directions that see the light's image in the mirror, so a handful of
paths in a thousand carry all of it and the rest carry nothing: on the mirror / glossy Cornell
box these paths are 98 % of a path-traced render's variance (docs/accuracy/gi.md, "Where the
mirror / glossy box's noise comes from"). Traced from the light instead, the same light is easy:
every photon aimed at the mirror lands somewhere on the walls, and the density of the photons that
land near a point is the caustic irradiance there (Jensen, "Global illumination using photon
maps", 1996).

Photons (``build_caustic_map``):

- each photon joins a point y on a rect light to a point z on a mirror or glossy triangle, both
  drawn from their own dimensions of the Owen-scrambled Sobol sampler (engine/sampler.py; light by
  its power, triangle by its area), and carries L cos_y cos_z / |y - z|^2 over the pair's density
  when the segment is unoccluded (the shadow rays' convention, ``SHADOW_SHORTEN``). Aiming at the
  mirror and glossy surfaces, rather than emitting over the light's hemisphere, spends every photon
  on a caustic: on the Cornell box the sphere covers about 5 % of the light's hemisphere;
- at z and every later mirror / glossy hit the photon goes on through the mirror lobe (kr) or the
  glossy lobe (cos^g around the mirror direction, as the reference renderer samples it:
  ``engine.path_vertex._lobe_direction``), chosen with probability equal to the lobes' mean albedos
  (the rest is absorbed), at most ``max_depth`` times;
- after its first mirror / glossy bounce, every hit on a surface with a diffuse lobe (kd > 0) stores
  the photon (position, the side it arrived on, power). A photon ends on a rect light where the
  renderer's mirror / glossy ray along the same segment, travelling the other way, would end
  (``engine.path_vertex._rect_hits``: on the light's emitting side): the photon then passes the
  light from its back, one-sided lights being transparent from the back in that direction only.

Lookups:

- ``irradiance``: the photons within ``radius`` of a point on its side of the surface (normals
  within 60 degrees), weighted by the Epanechnikov kernel 2 / (pi r^2) (1 - d^2 / r^2), which
  integrates to one over the disk. Used where the caustic is seen: the LDC samples themselves.
- ``cell_irradiance``: a piecewise-constant version for the vertices of paths (one lookup per path
  vertex, millions per bake): per grid cell of size ``radius`` and orientation (the normal's
  dominant axis and sign), the power of the photons that landed there over the area of the
  diffuse surfaces there, measured by points spread uniformly over those surfaces
  (``AREA_SAMPLES_PER_CELL`` per cell on average). Not the photons' own kernel estimates averaged
  per cell: an estimate at a photon's own position counts that photon, which biases it up where
  photons are sparse (with a few photons per disk, by a large factor). Its blur (one cell) is
  smoothed further by the diffuse bounce that follows.

What the path tracer leaves to the map (``engine.reference.ReferenceRenderer.trace_diffuse_paths``
with a map): a path vertex's rect lights met through mirror / glossy rays and its glossy lobe's
next-event estimation, i.e. every path diffuse -> (mirror | glossy)+ -> light; each diffuse
vertex with a bounce left gets the map's irradiance instead (the paths' own budget: a last vertex
would need one more segment to reach a light through a mirror). The estimate is biased by the
kernel's blur (edges of a caustic spread over ``radius``) and consistent: more photons and a
smaller radius converge to the path tracer's mean. Point and directional lights have no caustics
here, as in the reference renderer (a ray never meets them).
"""

from __future__ import annotations

import math
import threading
import time
import weakref
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import InvalidInputError
from engine.path_vertex import (
    DIM_LIGHT,
    DIM_LOBE,
    KIND_SPEC,
    _dot,
    _lobe_direction,
    _mean_albedos,
    _offset_mag,
    _rect_hits,
    _surface_frame,
)
from engine.raycast import SHADOW_SHORTEN, RayCaster
from engine.sampler import derive_key, sample_1d, sample_2d, sample_key
from engine.scene import RuntimeScene
from engine.sched import run_pieces_parallel

_STREAM = 4
"""The sampler stream of caustic photons: sample_key(seed, _STREAM) (indirect paths use 3)."""

# dimensions of a photon's emission (vertex 0): derive_key(key, 0, DIM_*)
_DIM_PICK_LIGHT = 20
_DIM_PICK_TRI = 21
_DIM_TRI_POS = 22

_GRID_BITS = 20
"""Bits per axis of a grid cell's coordinate in its int64 key (cells along the scene's diagonal
are at most 2^20)."""

MIN_NORMAL_COS = 0.5
"""A photon counts at a point only when their sides' normals are within 60 degrees: photons on
the other side of a thin wall, or on the floor near a wall, light neither."""

_MIN_ITEMS = 4096

_AREA_BATCH = 1 << 20

AREA_SAMPLES_PER_CELL = 16
"""Points per cell (on average over the diffuse surfaces' cells) that measure each cell's surface
area for ``cell_irradiance``: its relative noise is about 1 / sqrt(16) = 25 % per cell, averaged
away over the many cells a path's vertices visit."""


@nb.njit(cache=True, error_model="numpy")
def _pick(cdf, u):
    """Index k with cdf[k] <= u < cdf[k + 1] (cdf: increasing, cdf[0] = 0, cdf[-1] = 1)."""
    k = np.searchsorted(cdf, u, side="right") - 1
    return min(max(k, 0), cdf.shape[0] - 2)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _emit(lo, hi, key, first, n_total, light_cdf, rc, ru, rv, r_n, r_area, rL, r2s, tri_cdf, sg_tri, tri_p, tri_ng,
          a_sg, center, extent, so_out, sd_out, tmax_out, d_out, prim_out, bu_out, bv_out, w_out, ok_out):
    """Photon i: a point y on a rect light (picked by power), a point z on a mirror / glossy
    triangle (picked by area), the power L cos_y cos_z / |y - z|^2 over their density, and the
    shadow ray from z back to y that decides whether the photon gets there. Row i is photon
    ``first + i`` (its sample index)."""
    for i in range(lo, hi):
        ok_out[i] = False
        pid = first + i
        q = _pick(light_cdf, sample_1d(derive_key(key, 0, _DIM_PICK_LIGHT), 0, pid))
        su, sv = sample_2d(derive_key(key, 0, DIM_LIGHT), 0, pid)
        y0 = rc[q, 0] + su * ru[q, 0] + sv * rv[q, 0]
        y1 = rc[q, 1] + su * ru[q, 1] + sv * rv[q, 1]
        y2 = rc[q, 2] + su * ru[q, 2] + sv * rv[q, 2]
        k = _pick(tri_cdf, sample_1d(derive_key(key, 0, _DIM_PICK_TRI), 0, pid))
        t = sg_tri[k]
        a, b = sample_2d(derive_key(key, 0, _DIM_TRI_POS), 0, pid)
        if a + b > 1.0:
            a, b = 1.0 - a, 1.0 - b
        c = 1.0 - a - b
        z0 = c * tri_p[t, 0, 0] + a * tri_p[t, 1, 0] + b * tri_p[t, 2, 0]
        z1 = c * tri_p[t, 0, 1] + a * tri_p[t, 1, 1] + b * tri_p[t, 2, 1]
        z2 = c * tri_p[t, 0, 2] + a * tri_p[t, 1, 2] + b * tri_p[t, 2, 2]
        x0, x1, x2 = z0 - y0, z1 - y1, z2 - y2
        dist = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        if not dist > 0.0:
            continue
        x0, x1, x2 = x0 / dist, x1 / dist, x2 / dist
        cos_y = _dot(r_n[q, 0], r_n[q, 1], r_n[q, 2], x0, x1, x2)
        if r2s[q]:
            cos_y = abs(cos_y)
        cz = _dot(tri_ng[t, 0], tri_ng[t, 1], tri_ng[t, 2], x0, x1, x2)
        if cos_y <= 0.0 or cz == 0.0:
            continue
        p_q = light_cdf[q + 1] - light_cdf[q]
        g = cos_y * abs(cz) / (dist * dist) * r_area[q] / p_q * a_sg / n_total
        # the shadow ray leaves z on the side the photon arrives from
        s = -1.0 if cz > 0.0 else 1.0
        mag = _offset_mag(z0, z1, z2, center, extent)
        so_out[i, 0] = z0 + s * mag * tri_ng[t, 0] - center[0]
        so_out[i, 1] = z1 + s * mag * tri_ng[t, 1] - center[1]
        so_out[i, 2] = z2 + s * mag * tri_ng[t, 2] - center[2]
        sd_out[i, 0], sd_out[i, 1], sd_out[i, 2] = -x0, -x1, -x2
        tmax_out[i] = max(dist * (1.0 - SHADOW_SHORTEN) - mag, 0.0)
        d_out[i, 0], d_out[i, 1], d_out[i, 2] = x0, x1, x2
        prim_out[i] = t
        bu_out[i] = a
        bv_out[i] = b
        w_out[i, 0], w_out[i, 1], w_out[i, 2] = rL[q, 0] * g, rL[q, 1] * g, rL[q, 2] * g
        ok_out[i] = True


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _scatter(lo, hi, prim, bu, bv, d, w, pid, key, vertex, store, go_on, kd, kr, kg, gexp, tri_p, tri_n, tri_ng,
             tri_mat, center, extent, pos_out, nrm_out, pw_out, stored, o_out, d_out, d32_out, w_out, alive):
    """A photon at its hit (triangle ``prim``, barycentrics): stored there when ``store`` and the
    surface is diffuse; sent on through its mirror or glossy lobe when ``go_on`` (lobe by
    dimension DIM_LOBE, direction by DIM_DIR of derive_key(key, vertex, .), sample ``pid``)."""
    for i in range(lo, hi):
        stored[i] = False
        alive[i] = False
        t = prim[i]
        uu = np.float64(bu[i])
        vv = np.float64(bv[i])
        c = 1.0 - uu - vv
        p0 = c * tri_p[t, 0, 0] + uu * tri_p[t, 1, 0] + vv * tri_p[t, 2, 0]
        p1 = c * tri_p[t, 0, 1] + uu * tri_p[t, 1, 1] + vv * tri_p[t, 2, 1]
        p2 = c * tri_p[t, 0, 2] + uu * tri_p[t, 1, 2] + vv * tri_p[t, 2, 2]
        d0, d1, d2 = d[i, 0], d[i, 1], d[i, 2]
        g0, g1, g2, n0, n1, n2 = _surface_frame(t, uu, vv, d0, d1, d2, tri_n, tri_ng)
        m = tri_mat[t]
        if store and (kd[m, 0] > 0.0 or kd[m, 1] > 0.0 or kd[m, 2] > 0.0):
            stored[i] = True
            pos_out[i, 0], pos_out[i, 1], pos_out[i, 2] = p0, p1, p2
            nrm_out[i, 0], nrm_out[i, 1], nrm_out[i, 2] = g0, g1, g2
            pw_out[i, 0], pw_out[i, 1], pw_out[i, 2] = w[i, 0], w[i, 1], w[i, 2]
        if not go_on:
            continue
        _, ar, ag = _mean_albedos(kd[m, 0], kd[m, 1], kd[m, 2], kr[m, 0], kr[m, 1], kr[m, 2], kg[m, 0], kg[m, 1],
                                  kg[m, 2])
        tot = ar + ag
        if not tot > 0.0:
            continue
        norm = max(1.0, tot)  # lobes that reflect more than all the light: pick among them only
        u = sample_1d(derive_key(key, vertex, DIM_LOBE), 0, pid[i]) * norm
        if u < ar:
            lb, scale = 0, norm / ar
        elif u < tot:
            lb, scale = 1, norm / ag
        else:
            continue  # absorbed (or diffusely reflected: the path tracer's part)
        cw = -_dot(n0, n1, n2, d0, d1, d2)
        wr0, wr1, wr2 = d0 + 2.0 * cw * n0, d1 + 2.0 * cw * n1, d2 + 2.0 * cw * n2
        lr = math.sqrt(wr0 * wr0 + wr1 * wr1 + wr2 * wr2)
        wr0, wr1, wr2 = wr0 / lr, wr1 / lr, wr2 / lr
        x0, x1, x2, fk, _ = _lobe_direction(lb, key, vertex, 0, pid[i], 1.0, wr0, wr1, wr2, n0, n1, n2, gexp[m])
        if lb == 0:
            f0, f1, f2 = kr[m, 0], kr[m, 1], kr[m, 2]
        else:
            f0, f1, f2 = kg[m, 0] * fk, kg[m, 1] * fk, kg[m, 2] * fk
        if _dot(g0, g1, g2, x0, x1, x2) <= 0.0 or not (f0 > 0.0 or f1 > 0.0 or f2 > 0.0):
            continue
        ln = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        x0, x1, x2 = x0 / ln, x1 / ln, x2 / ln
        mag = _offset_mag(p0, p1, p2, center, extent)
        o_out[i, 0] = p0 + mag * g0 - center[0]
        o_out[i, 1] = p1 + mag * g1 - center[1]
        o_out[i, 2] = p2 + mag * g2 - center[2]
        d_out[i, 0], d_out[i, 1], d_out[i, 2] = x0, x1, x2
        d32_out[i, 0], d32_out[i, 1], d32_out[i, 2] = x0, x1, x2
        w_out[i, 0], w_out[i, 1], w_out[i, 2] = w[i, 0] * f0 * scale, w[i, 1] * f1 * scale, w[i, 2] * f2 * scale
        alive[i] = True


@nb.njit(cache=True, error_model="numpy")
def _cell_key(ix, iy, iz):
    return (np.int64(ix) << (2 * _GRID_BITS)) | (np.int64(iy) << _GRID_BITS) | np.int64(iz)


@nb.njit(cache=True, error_model="numpy")
def _cell_of(x, origin, inv_cell):
    return np.int64(math.floor((x - origin) * inv_cell))


@nb.njit(cache=True, error_model="numpy")
def _orientation(n0, n1, n2):
    """0 .. 5: the normal's dominant axis and its sign."""
    a0, a1, a2 = abs(n0), abs(n1), abs(n2)
    if a0 >= a1 and a0 >= a2:
        return 0 if n0 >= 0.0 else 1
    if a1 >= a2:
        return 2 if n1 >= 0.0 else 3
    return 4 if n2 >= 0.0 else 5


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _keys(lo, hi, pos, nrm, origin, inv_cell, key_out, okey_out):
    """Each photon's cell key, and its (cell, orientation) key."""
    for i in range(lo, hi):
        ix = _cell_of(pos[i, 0], origin[0], inv_cell)
        iy = _cell_of(pos[i, 1], origin[1], inv_cell)
        iz = _cell_of(pos[i, 2], origin[2], inv_cell)
        key_out[i] = _cell_key(ix, iy, iz)
        okey_out[i] = key_out[i] * 8 + _orientation(nrm[i, 0], nrm[i, 1], nrm[i, 2])


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _kernel_irradiance(lo, hi, qp, qn, keys, pos, nrm, pw, origin, inv_cell, r2, norm, out):
    """Irradiance at points ``qp`` on the side ``qn``: the photons within sqrt(r2) whose normals are
    within 60 degrees, weighted by (1 - d^2 / r2) times ``norm`` (2 / (pi r2))."""
    for i in range(lo, hi):
        x0, x1, x2 = qp[i, 0], qp[i, 1], qp[i, 2]
        m0, m1, m2 = qn[i, 0], qn[i, 1], qn[i, 2]
        cx = _cell_of(x0, origin[0], inv_cell)
        cy = _cell_of(x1, origin[1], inv_cell)
        cz = _cell_of(x2, origin[2], inv_cell)
        e0 = e1 = e2 = 0.0
        for ax in range(cx - 1, cx + 2):
            for ay in range(cy - 1, cy + 2):
                for az in range(cz - 1, cz + 2):
                    if ax < 0 or ay < 0 or az < 0:
                        continue
                    k = _cell_key(ax, ay, az)
                    j = np.searchsorted(keys, k)
                    while j < keys.shape[0] and keys[j] == k:
                        dx, dy, dz = pos[j, 0] - x0, pos[j, 1] - x1, pos[j, 2] - x2
                        dd = dx * dx + dy * dy + dz * dz
                        if dd < r2 and _dot(nrm[j, 0], nrm[j, 1], nrm[j, 2], m0, m1, m2) > MIN_NORMAL_COS:
                            wk = 1.0 - dd / r2
                            e0 += wk * pw[j, 0]
                            e1 += wk * pw[j, 1]
                            e2 += wk * pw[j, 2]
                        j += 1
        out[i, 0], out[i, 1], out[i, 2] = e0 * norm, e1 * norm, e2 * norm


@nb.njit(cache=True, error_model="numpy")
def _cell_lookup(x0, x1, x2, n0, n1, n2, origin, inv_cell, okeys):
    """Index into ``okeys`` (and the map's ``irr``) of the (cell, orientation) of point x with
    normal n, -1 when no photon landed there."""
    ix = _cell_of(x0, origin[0], inv_cell)
    iy = _cell_of(x1, origin[1], inv_cell)
    iz = _cell_of(x2, origin[2], inv_cell)
    if ix < 0 or iy < 0 or iz < 0:
        return -1
    k = _cell_key(ix, iy, iz) * 8 + _orientation(n0, n1, n2)
    j = np.searchsorted(okeys, k)
    if j < okeys.shape[0] and okeys[j] == k:
        return j
    return -1


@nb.njit(cache=True, nogil=True, error_model="numpy")
def add_cell_light(acc, pix, pix_base, is_path, mat, w, p, ng, kd, origin, inv_cell, okeys, irr):
    """acc[pix - pix_base] += w kd / pi E for every path hit (``is_path``) on a diffuse surface,
    E the map's ``cell_irradiance`` at it. Serial: rows share pixels."""
    for j in range(pix.shape[0]):
        if not is_path[j]:
            continue
        m = mat[j]
        if not (kd[m, 0] > 0.0 or kd[m, 1] > 0.0 or kd[m, 2] > 0.0):
            continue
        c = _cell_lookup(p[j, 0], p[j, 1], p[j, 2], ng[j, 0], ng[j, 1], ng[j, 2], origin, inv_cell, okeys)
        if c < 0:
            continue
        q = pix[j] - pix_base
        for k in range(3):
            acc[q, k] += w[j, k] * kd[m, k] * (1.0 / math.pi) * irr[c, k]


@nb.njit(cache=True, error_model="numpy")
def _cell_irradiances(p, n, origin, inv_cell, okeys, irr, out):
    for j in range(p.shape[0]):
        c = _cell_lookup(p[j, 0], p[j, 1], p[j, 2], n[j, 0], n[j, 1], n[j, 2], origin, inv_cell, okeys)
        if c >= 0:
            out[j, 0], out[j, 1], out[j, 2] = irr[c, 0], irr[c, 1], irr[c, 2]


@dataclass(frozen=True)
class CausticMap:
    """Stored caustic photons of one scene, sorted by grid cell (``build_caustic_map``).

    radius: the kernel's radius (scene units), also the grid's cell size; origin: the grid's
    corner; keys / pos / nrm / power: the photons' cell keys (sorted), positions, the normals of
    the sides they landed on and their power (W, RGB); okeys / irr: the (cell, orientation) keys
    with a photon and their ``cell_irradiance``; stats: photons aimed, stored, time."""

    radius: float
    origin: np.ndarray
    keys: np.ndarray
    pos: np.ndarray
    nrm: np.ndarray
    power: np.ndarray
    okeys: np.ndarray
    irr: np.ndarray
    stats: dict = field(default_factory=dict)

    @property
    def inv_cell(self) -> float:
        return 1.0 / self.radius

    def irradiance(self, p: np.ndarray, n: np.ndarray, serial: bool | None = None) -> np.ndarray:
        """Caustic irradiance (m, 3) at points ``p`` (m, 3) on the side with unit normal ``n``."""
        p = np.ascontiguousarray(p, np.float64)
        n = np.ascontiguousarray(n, np.float64)
        out = np.zeros((p.shape[0], 3))
        r2 = self.radius * self.radius
        run_pieces_parallel(_kernel_irradiance, p.shape[0], 256, serial, p, n, self.keys, self.pos, self.nrm,
                            self.power, self.origin, self.inv_cell, r2, 2.0 / (math.pi * r2), out)
        return out

    def add_path_light(self, acc: np.ndarray, pix: np.ndarray, pix_base: int, is_path: np.ndarray, mat: np.ndarray,
                       w: np.ndarray, p: np.ndarray, ng: np.ndarray, kd: np.ndarray) -> None:
        """The reference renderer's hook (``ReferenceRenderer._trace``): adds ``cell_irradiance``
        times the weight w and kd / pi to acc[pix - pix_base] for path hits on diffuse surfaces."""
        add_cell_light(acc, pix, pix_base, is_path, mat, w, p, ng, kd, self.origin, self.inv_cell, self.okeys,
                       self.irr)

    def cell_irradiance(self, p: np.ndarray, n: np.ndarray) -> np.ndarray:
        """The piecewise-constant caustic irradiance (m, 3) that path vertices get."""
        out = np.zeros((p.shape[0], 3))
        _cell_irradiances(np.ascontiguousarray(p, np.float64), np.ascontiguousarray(n, np.float64), self.origin,
                          self.inv_cell, self.okeys, self.irr, out)
        return out


def caustic_surfaces(scene: RuntimeScene) -> np.ndarray:
    """Triangles with a mirror or glossy lobe (int64 ids); empty: the scene has no caustics."""
    mt = scene.materials
    spec = np.any(mt.kr > 0.0, axis=1) | np.any(mt.kg > 0.0, axis=1)
    return np.flatnonzero(spec[scene.tri_material]) if scene.n_triangles else np.zeros(0, np.int64)


def has_caustics(scene: RuntimeScene) -> bool:
    """Can light reach a diffuse surface through a mirror or a glossy lobe? (a rect light that
    emits and mirror / glossy triangles of some area; the map is built only then.)"""
    return _sources(scene) is not None


def _triangle_areas(tri: np.ndarray) -> np.ndarray:
    """Areas of triangles given by their corners (m, 3, 3)."""
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def _sources(scene: RuntimeScene) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """What photons leave and aim at: the rect lights' power (picking weights), the mirror / glossy
    triangles and their areas; None when the scene has no caustics."""
    lt = scene.lights
    if not lt.n_rect:
        return None
    _, area = lt.rect_frames()
    power = area * lt.rect_radiance.reshape(-1, 3).mean(axis=1) * np.where(lt.rect_two_sided, 2.0, 1.0)
    sg = caustic_surfaces(scene).astype(np.int64)
    tri_area = _triangle_areas(scene.tri_p[sg])
    if not (np.any(power > 0.0) and tri_area.sum() > 0.0):
        return None
    return power, sg, tri_area


@dataclass(frozen=True)
class PhotonSources:
    """What photons leave and aim at (``photon_sources``): the rect lights' picking CDF (by power), the
    mirror / glossy triangles (``sg``), their picking CDF (by area) and total area, and the rect
    lights' unit normals and areas."""

    light_cdf: np.ndarray
    sg: np.ndarray
    tri_cdf: np.ndarray
    a_sg: float
    r_n: np.ndarray
    r_area: np.ndarray


def photon_sources(scene: RuntimeScene) -> PhotonSources | None:
    """The scene's ``PhotonSources``; None when it has no caustics (``has_caustics``)."""
    sources = _sources(scene)
    if sources is None:
        return None
    power, sg, tri_area = sources
    a_sg = float(tri_area.sum())
    r_n, r_area = scene.lights.rect_frames()
    return PhotonSources(np.concatenate([[0.0], np.cumsum(power) / power.sum()]), sg,
                         np.concatenate([[0.0], np.cumsum(tri_area) / a_sg]), a_sg, r_n, r_area)


class Emitted(NamedTuple):
    """Photons that reached a mirror / glossy point (``emit_photons``): their numbers (int64), directions,
    triangles, barycentrics and power; the shadow rays cast and the seconds Embree took for them."""

    pid: np.ndarray
    d: np.ndarray
    prim: np.ndarray
    bu: np.ndarray
    bv: np.ndarray
    w: np.ndarray
    shadow_rays: int
    embree_s: float


def emit_photons(scene: RuntimeScene, caster: RayCaster, src: PhotonSources, key: Any, first: int, n: int,
                 n_total: float, serial: bool | None = None) -> Emitted:
    """Photons ``first`` .. ``first + n - 1`` of ``key`` (``_emit``, power over ``n_total``), kept where
    the segment from the light to the mirror / glossy point is clear."""
    lt = scene.lights
    so = np.empty((n, 3), np.float32)
    sd = np.empty((n, 3), np.float32)
    tmax = np.empty(n, np.float32)
    d = np.empty((n, 3))
    prim = np.empty(n, np.int32)
    bu = np.empty(n, np.float32)
    bv = np.empty(n, np.float32)
    w = np.empty((n, 3))
    ok = np.empty(n, np.bool_)
    run_pieces_parallel(_emit, n, _MIN_ITEMS, serial, key, first, float(n_total), src.light_cdf, lt.rect_corner,
                        lt.rect_edge_u, lt.rect_edge_v, src.r_n, src.r_area, lt.rect_radiance, lt.rect_two_sided,
                        src.tri_cdf, src.sg, scene.tri_p, scene.tri_ng, src.a_sg, scene.center, scene.extent, so, sd,
                        tmax, d, prim, bu, bv, w, ok)
    live = np.flatnonzero(ok)
    t0 = time.perf_counter()
    occ = caster.occluded_local(so[live], sd[live], tmax[live], serial)
    embree_s = time.perf_counter() - t0
    rays = int(live.size)
    live = live[~occ]
    return Emitted((first + live).astype(np.int64), d[live], prim[live], bu[live], bv[live], w[live], rays, embree_s)


def passes_light_toward_origin(scene: RuntimeScene, src: PhotonSources, o32: np.ndarray, d: np.ndarray,
                               prim: np.ndarray, bu: np.ndarray, bv: np.ndarray,
                               serial: bool | None = None) -> np.ndarray:
    """(k,) bool: the segment from each origin to its hit passes a rect light whose emitting side faces
    the origin, where the path tracer's mirror / glossy ray along the same segment, travelling the
    other way, would end: ``_rect_hits``' test on the lights turned around (edges swapped, so the
    normal is negated)."""
    lt = scene.lights
    k = o32.shape[0]
    out = np.empty(k, np.bool_)
    run_pieces_parallel(_rect_hits, k, _MIN_ITEMS, serial, o32, d, prim, bu, bv, np.full(k, KIND_SPEC, np.int8),
                        np.zeros((k, 3)), np.zeros(k), 1, 0, True, scene.tri_p, scene.center, lt.rect_corner,
                        lt.rect_edge_v, lt.rect_edge_u, -src.r_n, src.r_area, lt.rect_radiance, lt.rect_two_sided,
                        out, np.empty((k, 3)))
    return out


def build_caustic_map(scene: RuntimeScene, caster: RayCaster, photons: int, radius: float, max_depth: int,
                      seed: int = 0, serial: bool | None = None) -> CausticMap | None:
    """Trace ``photons`` photons aimed at the scene's mirror / glossy surfaces and store those that
    land on diffuse ones; None when the scene has no caustics (``has_caustics``). ``radius``: the
    kernel's radius as a fraction of the scene's diagonal; ``max_depth``: mirror / glossy bounces
    a photon takes at most. Deterministic for a given seed, whatever the number of threads."""
    if not isinstance(photons, (int, np.integer)) or photons < 1:
        raise InvalidInputError(f"caustic photons must be a positive integer, got {photons!r}")
    if not (isinstance(radius, (int, float)) and 0.0 < radius < 1.0):
        raise InvalidInputError(f"caustic radius must be in (0, 1) of the scene's diagonal, got {radius!r}")
    src = photon_sources(scene)
    if src is None:
        return None
    t0 = time.perf_counter()
    mt = scene.materials
    key = sample_key(int(seed), _STREAM)
    n = int(photons)
    pid, d, prim, bu, bv, w, _, _ = emit_photons(scene, caster, src, key, 0, n, n, serial)
    reached = pid.size
    parts_pos, parts_nrm, parts_pw = [], [], []
    rays = int(n)
    for vertex in range(1, max_depth + 2):
        k = pid.size
        if k == 0:
            break
        pos = np.empty((k, 3))
        nrm = np.empty((k, 3))
        pw = np.empty((k, 3))
        stored = np.empty(k, np.bool_)
        o2 = np.empty((k, 3), np.float32)
        d2 = np.empty((k, 3))
        d2_32 = np.empty((k, 3), np.float32)
        w2 = np.empty((k, 3))
        alive = np.empty(k, np.bool_)
        run_pieces_parallel(_scatter, k, _MIN_ITEMS, serial, prim, bu, bv, d, w, pid, key, vertex, vertex > 1,
                            vertex <= max_depth, mt.kd, mt.kr, mt.kg, mt.gloss_exponent, scene.tri_p, scene.tri_n,
                            scene.tri_ng, scene.tri_material, scene.center, scene.extent, pos, nrm, pw, stored, o2, d2,
                            d2_32, w2, alive)
        parts_pos.append(pos[stored])
        parts_nrm.append(nrm[stored])
        parts_pw.append(pw[stored])
        go = np.flatnonzero(alive)
        if go.size == 0:
            break
        prim, bu, bv = caster.intersect_local(o2[go], d2_32[go], serial)
        rays += go.size
        # a photon ends on a rect light where the path tracer's mirror / glossy ray along the same
        # segment, travelling the other way, would end (on the light's emitting side)
        ends = passes_light_toward_origin(scene, src, o2[go], d2[go], prim, bu, bv, serial)
        hit = (prim >= 0) & ~ends
        go = go[hit]
        pid, d, w = pid[go], d2[go], w2[go]
        prim, bu, bv = prim[hit], bu[hit], bv[hit]
    pos = np.concatenate(parts_pos) if parts_pos else np.zeros((0, 3))
    nrm = np.concatenate(parts_nrm) if parts_nrm else np.zeros((0, 3))
    pw = np.concatenate(parts_pw) if parts_pw else np.zeros((0, 3))
    return _index(scene, pos, nrm, pw, float(radius) * scene.extent, serial,
                  {"photons": n, "reached": int(reached), "stored": int(pos.shape[0]), "rays": rays,
                   "radius": float(radius), "max_depth": int(max_depth), "trace_s": time.perf_counter() - t0})


_MAPS: weakref.WeakKeyDictionary[Any, dict[tuple, CausticMap | None]] = weakref.WeakKeyDictionary()
_MAPS_LOCK = threading.Lock()


def caustic_map(renderer: Any, photons: int, radius: float, max_depth: int, seed: int = 0) -> CausticMap | None:
    """``build_caustic_map`` for a renderer's scene and caster, built once per renderer and
    settings: every chunk of a bake that a worker traces with the same renderer shares it."""
    k = (int(photons), float(radius), int(max_depth), int(seed))
    with _MAPS_LOCK:
        maps = _MAPS.setdefault(renderer, {})
        if k not in maps:
            maps[k] = build_caustic_map(renderer.scene, renderer.caster, photons, radius, max_depth, seed)
        return maps[k]


def _index(scene: RuntimeScene, pos: np.ndarray, nrm: np.ndarray, pw: np.ndarray, radius: float,
           serial: bool | None, stats: dict) -> CausticMap:
    """Sort the photons by grid cell and compute the per-cell irradiance."""
    t0 = time.perf_counter()
    lo, hi = scene.bounds if scene.n_triangles else (np.zeros(3), np.zeros(3))
    cells = np.ceil((np.asarray(hi) - np.asarray(lo)) / radius) + 4
    if np.any(cells >= 2 ** _GRID_BITS):
        raise InvalidInputError(f"caustic radius {radius:g} is too small for the scene's size")
    origin = np.asarray(lo, np.float64) - 2.0 * radius
    m = pos.shape[0]
    keys = np.empty(m, np.int64)
    okeys = np.empty(m, np.int64)
    run_pieces_parallel(_keys, m, _MIN_ITEMS, serial, pos, nrm, origin, 1.0 / radius, keys, okeys)
    order = np.argsort(keys, kind="stable")
    keys, okeys = keys[order], okeys[order]
    pos, nrm, pw = (np.ascontiguousarray(a[order]) for a in (pos, nrm, pw))
    uniq, inv_idx = np.unique(okeys, return_inverse=True)
    power = np.zeros((uniq.size, 3))
    np.add.at(power, inv_idx, pw)
    area, n_area = _cell_areas(scene, uniq, origin, radius)
    irr = power / area[:, None]
    stats = dict(stats, index_s=time.perf_counter() - t0, cells=int(uniq.size), area_points=n_area)
    return CausticMap(radius=radius, origin=origin, keys=keys, pos=pos, nrm=nrm, power=pw,
                      okeys=np.ascontiguousarray(uniq, np.int64), irr=np.ascontiguousarray(irr), stats=stats)


def _cell_areas(scene: RuntimeScene, okeys: np.ndarray, origin: np.ndarray, radius: float) -> tuple[np.ndarray, int]:
    """Area of the diffuse surfaces in each (cell, orientation) of ``okeys`` (sorted), measured by
    points spread uniformly over them (a fixed seed: the same map every time; in batches of
    ``_AREA_BATCH`` points, so memory stays bounded), each point counting for both sides; a cell no
    point fell in gets one point's area. Returns (areas, points)."""
    mt = scene.materials
    diffuse = np.flatnonzero(np.any(mt.kd[scene.tri_material] > 0.0, axis=1))
    tri = scene.tri_p[diffuse]
    a = _triangle_areas(tri)
    total = float(a.sum())
    n = int(np.clip(AREA_SAMPLES_PER_CELL * total / radius ** 2, 1 << 16, 1 << 23))
    cdf = np.cumsum(a) / total
    rng = np.random.default_rng(0x0A7EA)
    counts = np.zeros(okeys.size, np.int64)
    for start in range(0, n, _AREA_BATCH):
        m = min(_AREA_BATCH, n - start)
        k = np.minimum(np.searchsorted(cdf, rng.random(m), side="right"), a.size - 1)
        u, v = rng.random(m), rng.random(m)
        flip = u + v > 1.0
        u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
        p = (1.0 - u - v)[:, None] * tri[k, 0] + u[:, None] * tri[k, 1] + v[:, None] * tri[k, 2]
        ng = scene.tri_ng[diffuse[k]]
        keys = np.empty(m, np.int64)
        sides = np.empty((2, m), np.int64)
        _keys(0, m, p, ng, origin, 1.0 / radius, keys, sides[0])
        _keys(0, m, p, -ng, origin, 1.0 / radius, keys, sides[1])
        if okeys.size:
            both = sides.reshape(-1)
            j = np.minimum(np.searchsorted(okeys, both), okeys.size - 1)
            counts += np.bincount(j[okeys[j] == both], minlength=okeys.size)
    return total * np.maximum(counts, 1) / n, n
