"""View-dependent pass of the LDC method (docs/algorithms.md part A, "Rendering a view" step 2).

Runs only on the visible non-diffuse pixels the effect plan asks for; every function takes
flat per-surface-point arrays, so the same kernels shade camera pixels and the hits of
image-based ray tracing. Shapes: p (n, 3) float64 world points; ng, ns (n, 3) geometric and
shading normals, both flipped to the side the viewer is on (shading normal on the wrong
side of the geometric one replaced by it, as in ``engine/reference.py``); wo (n, 3) unit
direction toward the viewer; mat (n,) int32.

**Highlights** (``highlights``): the reference renderer's Phong term, per light sample
``ks (s + 2) / (2 pi) cos^s(wl . wr) E cos(ns . wl)`` with wr the mirror of wo about ns,
gated by the LDC's visibility bit of that light (bits ``(n, W)`` uint64; with ``W = 0`` -
the bake stored no bits because no light can be occluded, or was told not to - a light in
front of the surface counts as visible). Light samples, offsets and cut-offs are the
reference's (``engine/lights.py``); a rect light is gated by ONE bit (any of its samples
visible), so a highlight in its penumbra is too bright by the blocked fraction; a rect light's
points are each shaded point's own stratified (Owen-scrambled Sobol) sequence over the light,
deterministic per seed (``engine.newviews.ldc.rect_net_point``). Diffuse (LDC) + highlights equals the
reference's direct lighting at the same point (tested to 1e-5 for point and directional
lights). The glossy lobe's reflection of the rect lights, ``kg (g + 2) / (2 pi) cos^g(wl . wr) E
cos(ns . wl)``, is a highlight too, shaded here with the same samples: the light field holds
surfaces, never a light, so its gather cannot show it (rect lights only, as in the reference,
where no ray meets a point or directional light; tested against a quadrature of the lobe over the
light).

**Light-field gather** (``gather_reflections``), paper section 4.2. The radiance arriving
at p from LLF direction d is read in LLF view d: p projected onto the view's reference
plane, the 4 nearest pixels, in each the first sample beyond p, bilinear weights. "Beyond
p" is measured from where the pixel's ray crosses the tangent plane of p (clamped to 3 view
pixels either way; only for directions leaving the surface, ng . d > 0, else from p's depth)
plus 0.05 pixel, not from p's own depth: a tilted surface would otherwise reflect itself in
the neighbouring pixels. A pixel without such a sample (or
outside the view) gives the background.
- glossy (``kg``, exponent g): ``kg (g + 2) / (g + 1) sum_j w_j cos_i,j L_j / sum_j w_j`` over
  the directions above the surface (ng . d > 0 and ns . d > 0), ``w_j = cos^g(angle(d_j,
  wr))`` - the reference's estimator with its lobe samples replaced by the LLF directions
  (equal-area directions, so no area weights). Weights are formed as ``exp(g (ln cos_j -
  ln cos_max))`` (the best direction has weight 1): finite and normalised for any g
  (docs/hard-cases.md #8). A lobe narrower than the LLF can resolve (g above the cone exponent n_c
  below) would be sampled by one or two directions, and the cos_i of those (up to a
  direction spacing off wr) biases the result; there the estimate factorises instead:
  ``kg max(0, ns . wr) L_cone`` with L_cone the mirror cone's radiance below (for a lobe
  narrow against the horizon, (g+2)/(g+1) E_lobe[cos_i] = cos(ns, wr)): 3 lookups instead
  of dozens. Directions whose weight is below e^-10 of the best are skipped (the lattice
  window is sized from that angle).
- ideal mirror (``kr``): the ``cone_directions`` (3) LLF directions nearest to wr (the
  smallest cone holding 3 of them), weighted ``cos^n_c`` of their angle to wr, normalised;
  ``n_c = ln 2 / (1 - cos s)`` with s = sqrt(4 pi / n) the typical direction spacing, so a
  direction one spacing away weighs half the one on wr. No mirror term when wr is below the
  geometric surface (as in the reference).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import InvalidInputError, NonFiniteOutputError
from engine.lights import directional_light_sample, rect_light_sample
from engine.newviews.ldc import rect_net_point
from engine.newviews.llf import LLF, candidate_directions, direction_to_lattice
from engine.raycast import OFFSET_EXTENT, OFFSET_REL, SHADOW_SHORTEN
from engine.sampler import sample_key
from engine.scene import RuntimeScene
from engine.shading import mirror_direction
from engine.shading import phong_pow as _phong_pow

INV_PI = 1.0 / math.pi
GLOSSY_LOG_CUT = 10.0  # skip directions whose lobe weight is below e^-10 of the best one
CONE_DIRECTIONS = 3
MAX_CONE_DIRECTIONS = 16
_BLOCK = 64


def mirror_cone_exponent(llf: LLF) -> float:
    """n_c with cos^n_c(spacing) = 1/2 (see module docstring)."""
    return math.log(2.0) / (1.0 - math.cos(llf.spacing))


# ----------------------------------------------------------------------------- highlights


class HighlightParams(NamedTuple):
    """What ``highlight_point_u`` needs besides the point: the scene's specular material table
    and light table (``engine.scene``'s, with the derived columns the light samplers want), the
    rect-light jitter and the ray-offset scale. Built by ``highlight_params``; the kernels take it
    whole and unpack it once per thread (see ``highlight_point_u``)."""

    ks: np.ndarray  #: (n_materials, 3) float64 Phong specular colour
    shininess: np.ndarray  #: (n_materials,) float64 Phong exponent s (0: no highlight)
    spec_cut: np.ndarray  #: (n_materials,) float64 cos(wl, wr) below which cos^s < e^-40 is skipped (-1: none)
    kg: np.ndarray  #: (n_materials, 3) float64 glossy reflectance (its rect lights' reflection is a highlight)
    gloss_exponent: np.ndarray  #: (n_materials,) float64 glossy lobe exponent g
    gloss_cut: np.ndarray  #: (n_materials,) float64 cos(wl, wr) below which cos^g < e^-40 is skipped (-1: none)
    point_position: np.ndarray  #: (n_point, 3) float64 point lights' positions
    point_intensity: np.ndarray  #: (n_point, 3) float64 their intensities
    dir_direction: np.ndarray  #: (n_dir, 3) float64 directional lights' directions (of travel)
    dir_irradiance: np.ndarray  #: (n_dir, 3) float64 their irradiances
    rect_corner: np.ndarray  #: (n_rect, 3) float64 rect lights' corners
    rect_edge_u: np.ndarray  #: (n_rect, 3) float64 their first edges
    rect_edge_v: np.ndarray  #: (n_rect, 3) float64 their second edges
    rect_normal: np.ndarray  #: (n_rect, 3) float64 unit normals (edge_u x edge_v)
    rect_area: np.ndarray  #: (n_rect,) float64 areas
    rect_radiance: np.ndarray  #: (n_rect, 3) float64 emitted radiances
    rect_two_sided: np.ndarray  #: (n_rect,) bool emit from both faces
    rect_grid: int  #: g: a rect light is sampled at g x g points (g^2 ~ area_light_samples)
    stream: np.uint64  #: sampler key of the rect-light points (``engine.sampler``, ``rect_net_point``)
    center: np.ndarray  #: (3,) float64 the scene's centre, for the shadow-ray offset
    extent: float  #: the scene's extent, for the shadow-ray offset


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def highlight_point_u(key, pt, m, bits, brow, force, ks, shin, spec_cut, kg, gexp, gloss_cut, pt_pos, pt_int, dir_dir,
                      dir_irr, rc, ru, rv, r_n, r_area, rL, r2s, r_g, stream, center, extent):
    """Phong highlights (r, g, b) at one point (module docstring), and the rect lights' reflection
    in its glossy lobe. Inlined into the callers'
    loops, so its parameters are flat: an inlined function's tuple would be unpacked per point,
    and each unpacking increfs and decrefs every array, atomically, on counters both threads
    share (~6 % of an LDC render's CPU time when it was done per pixel); the callers unpack
    their ``HighlightParams`` ONCE per thread, by name. numba inlines at most 30 arguments,
    hence the scratch ``pt``.

    key: the point's number in the rect-light sampler stream (its row, pixel or ray index): its
        g*g points on a rect light are the first of its own stratified sequence (``rect_net_point``).
    pt: (12,) float64 scratch holding the point: p, ng, ns, wo (3 floats each), as
        ``gather_point`` takes it.
    m: the point's material index.
    bits, brow: ``bits[brow]`` are the point's (W,) uint64 light-visibility words (W = 0: every
        light in front of the surface counts as visible).
    force: evaluate every light even where the material has no highlight.
    ks ... extent: the fields of ``HighlightParams``, in its order (ks, shininess, spec_cut, kg,
        gloss_exponent, gloss_cut, point_position, point_intensity, dir_direction, dir_irradiance, rect_corner,
        rect_edge_u, rect_edge_v, rect_normal, rect_area, rect_radiance, rect_two_sided,
        rect_grid, stream, center, extent).
    """
    px, py, pz, g0, g1, g2 = pt[0], pt[1], pt[2], pt[3], pt[4], pt[5]
    n0, n1, n2, wo0, wo1, wo2 = pt[6], pt[7], pt[8], pt[9], pt[10], pt[11]
    npt = pt_pos.shape[0]
    ndir = dir_dir.shape[0]
    nrect = rc.shape[0]
    has_ks = (ks[m, 0] > 0.0 or ks[m, 1] > 0.0 or ks[m, 2] > 0.0) and shin[m] > 0.0
    has_kg = (kg[m, 0] > 0.0 or kg[m, 1] > 0.0 or kg[m, 2] > 0.0) and nrect > 0
    if not (force or has_ks or has_kg):
        return 0.0, 0.0, 0.0
    gg = r_g * r_g
    per = npt + ndir + nrect * gg
    words = bits.shape[1]
    c = n0 * wo0 + n1 * wo1 + n2 * wo2
    wr0, wr1, wr2 = 2 * c * n0 - wo0, 2 * c * n1 - wo1, 2 * c * n2 - wo2
    mx = max(abs(px - center[0]), abs(py - center[1]), abs(pz - center[2]))
    mag = OFFSET_REL * (mx + OFFSET_EXTENT * extent)
    ox, oy, oz = px + mag * g0, py + mag * g1, pz + mag * g2
    spec_norm = (shin[m] + 2.0) * 0.5 * INV_PI
    gloss_norm = (gexp[m] + 2.0) * 0.5 * INV_PI
    a0 = a1 = a2 = 0.0
    for j in range(per):
        li = j
        q = 0
        sx = sy = 0.0
        if j >= npt + ndir:  # rect light q's cell s
            q = (j - npt - ndir) // gg
            s = (j - npt - ndir) % gg
            li = npt + ndir + q
            sx, sy = rect_net_point(stream, q, key, s)
        if words > 0:
            if (bits[brow, li // 64] >> np.uint64(li % 64)) & np.uint64(1) == 0:
                continue
        # every light through the scalar samplers (engine/lights.py): no reference counting per light
        if j < npt:
            # A point light: the tests on the unnormalised direction first (no square root for
            # lights behind the surface, no division for lights outside the lobe), one division
            # for the rest (``point_light_sample``'s values up to rounding).
            vx, vy, vz = pt_pos[j, 0] - ox, pt_pos[j, 1] - oy, pt_pos[j, 2] - oz
            ug = g0 * vx + g1 * vy + g2 * vz
            us = n0 * vx + n1 * vy + n2 * vz
            if ug <= 0.0 or us <= 0.0:
                continue
            dist = math.sqrt(vx * vx + vy * vy + vz * vz)
            ua = wr0 * vx + wr1 * vy + wr2 * vz
            if ua <= spec_cut[m] * dist or dist * (1.0 - SHADOW_SHORTEN) - mag <= 0.0:
                continue
            inv = 1.0 / dist
            ca = ua * inv
            fs = spec_norm * _phong_pow(ca, shin[m]) * (us * inv) * (inv * inv)
            a0 += ks[m, 0] * fs * pt_int[j, 0]
            a1 += ks[m, 1] * fs * pt_int[j, 1]
            a2 += ks[m, 2] * fs * pt_int[j, 2]
            continue
        elif j < npt + ndir:
            q = j - npt
            ok, lx, ly, lz, e0, e1, e2, tmax = directional_light_sample(dir_dir[q, 0], dir_dir[q, 1], dir_dir[q, 2],
                                                                        dir_irr[q, 0], dir_irr[q, 1], dir_irr[q, 2])
        else:
            ok, lx, ly, lz, e0, e1, e2, tmax = rect_light_sample(
                ox, oy, oz, mag, sx, sy, rc[q, 0], rc[q, 1], rc[q, 2], ru[q, 0], ru[q, 1], ru[q, 2], rv[q, 0],
                rv[q, 1], rv[q, 2], r_n[q, 0], r_n[q, 1], r_n[q, 2], r_area[q], rL[q, 0], rL[q, 1], rL[q, 2],
                r2s[q], gg)
        if not ok:
            continue
        cos_g = g0 * lx + g1 * ly + g2 * lz
        cos_s = n0 * lx + n1 * ly + n2 * lz
        if cos_g <= 0.0 or cos_s <= 0.0 or tmax <= 0.0:
            continue
        ca = wr0 * lx + wr1 * ly + wr2 * lz
        fs = spec_norm * _phong_pow(ca, shin[m]) * cos_s if ca > spec_cut[m] else 0.0
        # the glossy lobe sees rect lights only, as in the reference renderer (a ray never meets a
        # point or directional light)
        fg = gloss_norm * _phong_pow(ca, gexp[m]) * cos_s if j >= npt + ndir and ca > gloss_cut[m] else 0.0
        a0 += (ks[m, 0] * fs + kg[m, 0] * fg) * e0
        a1 += (ks[m, 1] * fs + kg[m, 1] * fg) * e1
        a2 += (ks[m, 2] * fs + kg[m, 2] * fg) * e2
    return a0, a1, a2


# ``highlights``, ``gather_reflections`` and ``gather_incoming`` are the per-point entry points for
# callers outside the renderer (its fused kernels in renderer.py are the hot path): their kernels are
# serial, since a ``parallel=True`` kernel compiles 2-5x slower and these are rarely worth it.
@nb.njit(cache=True, nogil=True, error_model="numpy")
def _highlights(p, ng, ns, wo, mat, bits, force, hp, out):
    """``highlights``' kernel: ``highlight_point_u`` for every point, in blocks of 64."""
    n = p.shape[0]
    for b in range((n + _BLOCK - 1) // _BLOCK):
        ks, shin, spec_cut, stream = hp.ks, hp.shininess, hp.spec_cut, hp.stream
        kg, gexp, gloss_cut = hp.kg, hp.gloss_exponent, hp.gloss_cut
        pt_pos, pt_int, dir_dir, dir_irr = hp.point_position, hp.point_intensity, hp.dir_direction, hp.dir_irradiance
        rc, ru, rv, r_n, r_area = hp.rect_corner, hp.rect_edge_u, hp.rect_edge_v, hp.rect_normal, hp.rect_area
        rL, r2s, r_g, center, extent = hp.rect_radiance, hp.rect_two_sided, hp.rect_grid, hp.center, hp.extent
        pt = np.empty(12)
        for i in range(b * _BLOCK, min(n, (b + 1) * _BLOCK)):
            for c in range(3):
                pt[c], pt[3 + c], pt[6 + c], pt[9 + c] = p[i, c], ng[i, c], ns[i, c], wo[i, c]
            out[i, 0], out[i, 1], out[i, 2] = highlight_point_u(i, pt, mat[i], bits, i, force, ks, shin, spec_cut,
                                                                kg, gexp, gloss_cut, pt_pos, pt_int, dir_dir, dir_irr,
                                                                rc, ru, rv, r_n, r_area, rL, r2s, r_g, stream, center,
                                                                extent)


def highlight_params(scene: RuntimeScene, area_light_samples: int = 16, seed: int = 0) -> HighlightParams:
    """The scene's material and light tables as ``highlight_point_u`` takes them."""
    mt, lt = scene.materials, scene.lights
    r_n, r_area = lt.rect_frames()
    spec_cut = np.where(mt.shininess > 0, np.exp(-40.0 / np.maximum(mt.shininess, 1e-300)), -1.0)
    gloss_cut = np.where(mt.gloss_exponent > 0, np.exp(-40.0 / np.maximum(mt.gloss_exponent, 1e-300)), -1.0)
    r_g = max(1, int(round(math.sqrt(area_light_samples))))
    return HighlightParams(mt.ks, mt.shininess, spec_cut, mt.kg, mt.gloss_exponent, gloss_cut, lt.point_position,
                           lt.point_intensity, lt.dir_direction, lt.dir_irradiance, lt.rect_corner, lt.rect_edge_u,
                           lt.rect_edge_v, r_n, r_area, lt.rect_radiance, lt.rect_two_sided, r_g, sample_key(seed, 11),
                           np.asarray(scene.center, np.float64), float(scene.extent))


def _check_points(p, ng, ns, wo, mat):
    p = np.ascontiguousarray(p, dtype=np.float64).reshape(-1, 3)
    n = p.shape[0]
    arrs = [np.ascontiguousarray(a, dtype=np.float64).reshape(-1, 3) for a in (ng, ns, wo)]
    mat = np.ascontiguousarray(mat, dtype=np.int32).reshape(-1)
    if any(a.shape[0] != n for a in arrs) or mat.shape[0] != n:
        raise InvalidInputError("view pass: p, ng, ns, wo and mat must have one row per point")
    return p, arrs[0], arrs[1], arrs[2], mat


def highlights(scene: RuntimeScene, p, ng, ns, wo, mat, bits=None, *, area_light_samples: int = 16,
               seed: int = 0, force: bool = False) -> np.ndarray:
    """Phong highlights (n, 3) float64 toward wo, gated by ``bits`` (n, W) uint64 (see module doc).
    ``force``: evaluate every light for every point even where ks = 0 (adds exact zeros there)."""
    p, ng, ns, wo, mat = _check_points(p, ng, ns, wo, mat)
    n = p.shape[0]
    bits = np.zeros((n, 0), np.uint64) if bits is None else np.ascontiguousarray(bits, dtype=np.uint64)
    if bits.ndim != 2 or bits.shape[0] != n:
        raise InvalidInputError("view pass: bits must be (n, W) uint64")
    lt = scene.lights
    if bits.shape[1] and bits.shape[1] != (lt.count + 63) // 64:
        raise InvalidInputError(f"view pass: bits have {bits.shape[1]} words, the scene's lights need "
                                f"{(lt.count + 63) // 64}")
    out = np.zeros((n, 3))
    if n == 0 or lt.count == 0:
        return out
    _highlights(p, ng, ns, wo, mat, bits, bool(force), highlight_params(scene, area_light_samples, seed), out)
    return out


# ----------------------------------------------------------------------------- gather


class LLFArrays(NamedTuple):
    """An LLF as the gather kernels read it (``llf_arrays``): the direction lattice and every
    view's samples packed pixel by pixel (``engine.newviews.llf.LLF``'s ``pk_*``)."""

    f: int  #: lattice frequency (4 f^2 + 2 directions)
    table: np.ndarray  #: (2 f + 1, 2 f + 1, 2) int64 lattice cell -> direction indices
    directions: np.ndarray  #: (n_dir, 3) float64 unit directions
    pk_offsets: np.ndarray  #: (n_dir res^2 + 1,) int64 first sample of each (view, pixel)
    pk_depth: np.ndarray  #: (n_samples,) float64 sample depth along the view
    pk_radiance: np.ndarray  #: (n_samples, 3) float32 sample radiance toward the view
    pk_origin: np.ndarray  #: (n_dir, 3) float64 each view's reference-plane origin
    pk_u: np.ndarray  #: (n_dir, 3) float64 each view's image axis u
    pk_v: np.ndarray  #: (n_dir, 3) float64 each view's image axis v
    pk_w: np.ndarray  #: (n_dir, 3) float64 each view's direction (depth axis)
    pk_h: np.ndarray  #: (n_dir,) float64 each view's pixel size
    resolution: int  #: pixels per view side


class GatherParams(NamedTuple):
    """What ``gather_point`` needs besides the point: the scene's reflection material table, the
    mirror cone's parameters, the LLF's arrays (the fields of ``LLFArrays``, in its order), the
    background and the cone's per-lattice-cell candidate tables (``_cone_tables``). Built by
    ``gather_params``."""

    kr: np.ndarray  #: (n_materials, 3) float64 ideal-mirror reflectance
    kg: np.ndarray  #: (n_materials, 3) float64 glossy reflectance
    gloss_exponent: np.ndarray  #: (n_materials,) float64 glossy lobe exponent g
    n_c: float  #: mirror-cone exponent (``mirror_cone_exponent``)
    cone_directions: int  #: directions in the mirror cone (1..MAX_CONE_DIRECTIONS)
    f: int  #: ``LLFArrays.f``
    table: np.ndarray  #: ``LLFArrays.table``
    directions: np.ndarray  #: ``LLFArrays.directions``
    pk_offsets: np.ndarray  #: ``LLFArrays.pk_offsets``
    pk_depth: np.ndarray  #: ``LLFArrays.pk_depth``
    pk_radiance: np.ndarray  #: ``LLFArrays.pk_radiance``
    pk_origin: np.ndarray  #: ``LLFArrays.pk_origin``
    pk_u: np.ndarray  #: ``LLFArrays.pk_u``
    pk_v: np.ndarray  #: ``LLFArrays.pk_v``
    pk_w: np.ndarray  #: ``LLFArrays.pk_w``
    pk_h: np.ndarray  #: ``LLFArrays.pk_h``
    resolution: int  #: ``LLFArrays.resolution``
    background: np.ndarray  #: (3,) float64 radiance where a lookup finds no sample
    cone_offsets: np.ndarray  #: (cells + 1,) int64 per lattice cell: first candidate
    cone_index: np.ndarray  #: (total,) int64 candidate direction indices
    cone_xyz: np.ndarray  #: (3, total) float64 their coordinates


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _lookup(j, px, py, pz, g0, g1, g2, pk_off, pk_depth, pk_rad, origin, fu, fv, fw, fh, res, bg):
    """Radiance arriving at p from LLF direction j (bilinear over the 4 nearest pixels of view j,
    first sample beyond p's tangent plane in each). Returns (r, g, b)."""
    h = fh[j]
    rx, ry, rz = px - origin[j, 0], py - origin[j, 1], pz - origin[j, 2]
    a = (rx * fu[j, 0] + ry * fu[j, 1] + rz * fu[j, 2]) / h - 0.5
    b = (rx * fv[j, 0] + ry * fv[j, 1] + rz * fv[j, 2]) / h - 0.5
    zp = rx * fw[j, 0] + ry * fw[j, 1] + rz * fw[j, 2]
    nu_ = g0 * fu[j, 0] + g1 * fu[j, 1] + g2 * fu[j, 2]
    nv_ = g0 * fv[j, 0] + g1 * fv[j, 1] + g2 * fv[j, 2]
    nw_ = g0 * fw[j, 0] + g1 * fw[j, 1] + g2 * fw[j, 2]
    i0 = int(math.floor(a))
    j0 = int(math.floor(b))
    fa = a - i0
    fb = b - j0
    base = j * res * res
    r0 = r1 = r2 = 0.0
    for q in range(4):
        ii = i0 + (q & 1)
        jj = j0 + (q >> 1)
        wgt = (fa if (q & 1) else 1.0 - fa) * (fb if (q >> 1) else 1.0 - fb)
        if wgt == 0.0:
            continue
        c0, c1, c2 = bg[0], bg[1], bg[2]
        if 0 <= ii < res and 0 <= jj < res:
            # where this pixel's ray crosses p's tangent plane (clamped), plus a small margin
            off = 0.0
            if nw_ > 1e-3:  # only for rays leaving the surface (otherwise the plane says nothing)
                off = -h * ((ii - a) * nu_ + (jj - b) * nv_) / nw_
                lim = 3.0 * h
                if off > lim:
                    off = lim
                elif off < -lim:
                    off = -lim
            thr = zp + off + 0.05 * h
            k = base + jj * res + ii
            for s in range(pk_off[k], pk_off[k + 1]):
                if pk_depth[s] > thr:
                    c0, c1, c2 = pk_rad[s, 0], pk_rad[s, 1], pk_rad[s, 2]
                    break
        r0 += wgt * c0
        r1 += wgt * c1
        r2 += wgt * c2
    return r0, r1, r2


@nb.njit(cache=True, nogil=True)
def padded_empty(n, dtype):
    """np.empty(n, dtype) with 128 bytes of padding on each side: per-thread scratch arrays
    written per point must not share a cache line with another thread's (false sharing
    serialised the threads)."""
    return np.empty(n + 32, dtype)[16:16 + n]


@nb.njit(cache=True, nogil=True)
def gather_scratch(n_directions):
    """(cand, best_c, pt): the scratch arrays the gather needs, allocated once per thread or block."""
    return (padded_empty(n_directions + 8 + MAX_CONE_DIRECTIONS, np.int64),
            padded_empty(MAX_CONE_DIRECTIONS, np.float64), padded_empty(12, np.float64))


@nb.njit(cache=True, nogil=True)
def _cone_tables(f, table, dirs, radius):
    """Per lattice cell (a0, b0) (floor of a direction's lattice coordinates, row (a0 + f) (2 f +
    1) + b0 + f) the candidate directions ``candidate_directions`` lists for it, in its order:
    offsets, direction indices and their (3, N) coordinates (contiguous for the dot products)."""
    side = 2 * f + 1
    off = np.zeros(side * side + 1, np.int64)
    cand = np.empty(dirs.shape[0] + 8 + (2 * radius + 2) ** 2 * 2, np.int64)
    total = 0
    for pass_ in range(2):
        if pass_ == 1:
            idx = np.empty(total, np.int64)
            xyz = np.empty((3, total))
        for a0 in range(-f, f + 1):
            for b0 in range(-f, f + 1):
                cell = (a0 + f) * side + b0 + f
                n = 0
                for a in range(max(a0 - radius + 1, -f), min(a0 + radius, f) + 1):
                    rem = f - abs(a)
                    for b in range(max(b0 - radius + 1, -rem), min(b0 + radius, rem) + 1):
                        i0 = table[a + f, b + f, 0]
                        cand[n] = i0
                        n += 1
                        i1 = table[a + f, b + f, 1]
                        if i1 != i0:
                            cand[n] = i1
                            n += 1
                if pass_ == 0:
                    off[cell + 1] = n
                else:
                    for t in range(n):
                        k = off[cell] + t
                        idx[k] = cand[t]
                        xyz[0, k] = dirs[cand[t], 0]
                        xyz[1, k] = dirs[cand[t], 1]
                        xyz[2, k] = dirs[cand[t], 2]
        if pass_ == 0:
            for c in range(side * side):
                off[c + 1] += off[c]
            total = off[side * side]
    return off, idx, xyz


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _cone(px, py, pz, g0, g1, g2, d0, d1, d2, n_c, k_dirs, f, c_off, c_idx, c_xyz, cand, best_c, pk_off, pk_depth,
          pk_rad, origin, fu, fv, fw, fh, res, bg):
    """Normalised cos^n_c-weighted radiance of the k_dirs LLF directions nearest to d.
    Returns (r, g, b, lookups). The candidates are those of ``candidate_directions`` (radius 3),
    precomputed per lattice cell (``_cone_tables``: c_off, c_idx, c_xyz). Scratch (no
    allocation per call): ``cand`` (int64, n_directions + 8 + MAX_CONE_DIRECTIONS; its tail
    holds the best indices), ``best_c`` (float64, MAX_CONE_DIRECTIONS)."""
    A, B, _ = direction_to_lattice(d0, d1, d2, f)
    cell = (int(math.floor(A)) + f) * (2 * f + 1) + int(math.floor(B)) + f
    best_i = cand[cand.shape[0] - MAX_CONE_DIRECTIONS:]
    for q in range(k_dirs):
        best_c[q] = -2.0
    for t in range(c_off[cell], c_off[cell + 1]):
        c = c_xyz[0, t] * d0 + c_xyz[1, t] * d1 + c_xyz[2, t] * d2
        if c > best_c[k_dirs - 1]:
            q = k_dirs - 1
            while q > 0 and best_c[q - 1] < c:
                best_c[q] = best_c[q - 1]
                best_i[q] = best_i[q - 1]
                q -= 1
            best_c[q] = c
            best_i[q] = c_idx[t]
    lmax = n_c * math.log(max(best_c[0], 1e-300))
    sw = 0.0
    r0 = r1 = r2 = 0.0
    used = 0
    for q in range(k_dirs):
        if best_c[q] <= 0.0:
            continue
        w = math.exp(n_c * math.log(best_c[q]) - lmax)
        l0, l1, l2 = _lookup(best_i[q], px, py, pz, g0, g1, g2, pk_off, pk_depth, pk_rad, origin, fu, fv, fw, fh,
                             res, bg)
        r0 += w * l0
        r1 += w * l1
        r2 += w * l2
        sw += w
        used += 1
    if sw > 0.0:
        return r0 / sw, r1 / sw, r2 / sw, used
    return bg[0], bg[1], bg[2], used


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _lobe(px, py, pz, g0, g1, g2, s0, s1, s2, d0, d1, d2, g_eff, mode, f, table, dirs, cand, pk_off,
          pk_depth, pk_rad, origin, fu, fv, fw, fh, res, bg):
    """Weighted sums over the lobe cos^g_eff around d (see module docstring). mode 0:
    sum_j w_j cos_i,j L_j / sum_j w_j (cos_i and the horizon test from ng, ns); mode 1: sum w L /
    sum w over every direction; mode 2: the same over the directions above the surface only.
    Returns (r, g, b, lookups)."""
    x = GLOSSY_LOG_CUT / g_eff
    if x >= 20.0:
        theta = math.pi
    else:
        theta = math.acos(max(-1.0, min(1.0, math.exp(-x))))
    radius = int(math.ceil(0.6 * theta * f)) + 2
    if radius > 2 * f + 2:
        radius = 2 * f + 2
    nc = candidate_directions(d0, d1, d2, f, radius, table, cand)
    cmax = -2.0
    for t in range(nc):
        jd = cand[t]
        c = dirs[jd, 0] * d0 + dirs[jd, 1] * d1 + dirs[jd, 2] * d2
        if c > cmax:
            cmax = c
    if cmax <= 0.0:
        return 0.0, 0.0, 0.0, 0
    lmax = g_eff * math.log(cmax)
    sw = 0.0
    r0 = r1 = r2 = 0.0
    used = 0
    for t in range(nc):
        jd = cand[t]
        e0, e1, e2 = dirs[jd, 0], dirs[jd, 1], dirs[jd, 2]
        c = e0 * d0 + e1 * d1 + e2 * d2
        if c <= 0.0:
            continue
        lw = g_eff * math.log(c) - lmax
        if lw < -GLOSSY_LOG_CUT:
            continue
        w = math.exp(lw)
        cos_i = 1.0
        if mode == 0:
            sw += w
            if g0 * e0 + g1 * e1 + g2 * e2 <= 0.0:
                continue
            cos_i = s0 * e0 + s1 * e1 + s2 * e2
            if cos_i <= 0.0:
                continue
        elif mode == 2:
            if g0 * e0 + g1 * e1 + g2 * e2 <= 0.0 or s0 * e0 + s1 * e1 + s2 * e2 <= 0.0:
                continue
            sw += w
        else:
            sw += w
        l0, l1, l2 = _lookup(jd, px, py, pz, g0, g1, g2, pk_off, pk_depth, pk_rad, origin, fu, fv, fw, fh, res, bg)
        r0 += w * cos_i * l0
        r1 += w * cos_i * l1
        r2 += w * cos_i * l2
        used += 1
    if sw > 0.0:
        return r0 / sw, r1 / sw, r2 / sw, used
    return 0.0, 0.0, 0.0, used


@nb.njit(cache=True, nogil=True, error_model="numpy")
def gather_point(pt, m, do_mirror, do_glossy, force, cand, best_c, gp):
    """Reflected radiance (r, g, b) toward wo at one point by light-field gather and the number
    of lookups (module docstring). Shared by ``gather_reflections`` and the fused renderer
    kernels.

    pt: (12,) float64 scratch holding the point: p, ng, ns, wo (3 floats each).
    m: the point's material index.
    do_mirror: gather the ideal mirror term (kr) with the mirror cone.
    do_glossy: gather the glossy term (kg) over its lobe.
    force: gather even where the material's kr / kg are 0 (adds exact zeros there).
    cand, best_c: per-thread scratch arrays of ``gather_scratch``.
    gp: the ``GatherParams`` (material table, LLF arrays, cone tables). A non-inlined call: its
    arrays travel on the stack either way, one tuple or one by one.
    """
    kr, kg, gexp, n_c, k_dirs = gp.kr, gp.kg, gp.gloss_exponent, gp.n_c, gp.cone_directions
    f, table, dirs, res, bg = gp.f, gp.table, gp.directions, gp.resolution, gp.background
    pk_off, pk_depth, pk_rad = gp.pk_offsets, gp.pk_depth, gp.pk_radiance
    origin, fu, fv, fw, fh = gp.pk_origin, gp.pk_u, gp.pk_v, gp.pk_w, gp.pk_h
    c_off, c_idx, c_xyz = gp.cone_offsets, gp.cone_index, gp.cone_xyz
    px, py, pz, g0, g1, g2 = pt[0], pt[1], pt[2], pt[3], pt[4], pt[5]
    s0, s1, s2, wo0, wo1, wo2 = pt[6], pt[7], pt[8], pt[9], pt[10], pt[11]
    r0 = r1 = r2 = 0.0
    lookups = 0
    d0, d1, d2 = mirror_direction(s0, s1, s2, wo0, wo1, wo2)
    if do_mirror and (force or ((kr[m, 0] > 0.0 or kr[m, 1] > 0.0 or kr[m, 2] > 0.0) and
                                g0 * d0 + g1 * d1 + g2 * d2 > 0.0)):
        l0, l1, l2, u = _cone(px, py, pz, g0, g1, g2, d0, d1, d2, n_c, k_dirs, f, c_off, c_idx, c_xyz, cand, best_c,
                              pk_off, pk_depth, pk_rad, origin, fu, fv, fw, fh, res, bg)
        r0 += kr[m, 0] * l0
        r1 += kr[m, 1] * l1
        r2 += kr[m, 2] * l2
        lookups += u
    if do_glossy and (force or kg[m, 0] > 0.0 or kg[m, 1] > 0.0 or kg[m, 2] > 0.0):
        g = gexp[m]
        if not g >= 0.0:
            g = 0.0
        if g <= n_c:  # the LLF resolves the lobe: the reference's estimator over the directions
            g_eff = max(g, 1e-6)
            l0, l1, l2, u = _lobe(px, py, pz, g0, g1, g2, s0, s1, s2, d0, d1, d2, g_eff, 0, f, table, dirs,
                                  cand, pk_off, pk_depth, pk_rad, origin, fu, fv, fw, fh, res, bg)
            k = (g + 2.0) / (g + 1.0)
        else:  # narrower than the LLF resolves: the mirror cone's radiance x E_lobe[cos_i]
            l0, l1, l2, u = _cone(px, py, pz, g0, g1, g2, d0, d1, d2, n_c, k_dirs, f, c_off, c_idx, c_xyz, cand, best_c,
                                  pk_off, pk_depth, pk_rad, origin, fu, fv, fw, fh, res, bg)
            k = max(s0 * d0 + s1 * d1 + s2 * d2, 0.0)
        r0 += kg[m, 0] * k * l0
        r1 += kg[m, 1] * k * l1
        r2 += kg[m, 2] * k * l2
        lookups += u
    return r0, r1, r2, lookups


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _gather(p, ng, ns, wo, mat, do_mirror, force, gp, out, lookups):
    """``gather_reflections``' kernel: ``gather_point`` for every point, in blocks of 64. It passes
    ``do_glossy`` as the constant True, as the renderer's kernels do: the same compiled ``gather_point``
    (a runtime bool there compiled a second one, ~12 s on a cold cache)."""
    n = p.shape[0]
    nd = gp.directions.shape[0]
    nblk = (n + _BLOCK - 1) // _BLOCK
    for blk in range(nblk):
        cand, best_c, pt = gather_scratch(nd)
        for i in range(blk * _BLOCK, min(n, (blk + 1) * _BLOCK)):
            for c in range(3):
                pt[c], pt[3 + c], pt[6 + c], pt[9 + c] = p[i, c], ng[i, c], ns[i, c], wo[i, c]
            out[i, 0], out[i, 1], out[i, 2], lookups[i] = gather_point(pt, mat[i], do_mirror, True, force, cand,
                                                                       best_c, gp)


def gather_params(scene: RuntimeScene, llf: LLF, cone_directions: int = CONE_DIRECTIONS,
                  background=None) -> GatherParams:
    """The scene's reflection tables and the LLF's packed arrays as ``gather_point`` takes them."""
    bg = scene.background if background is None else background
    mt = scene.materials
    return _gather_params(mt.kr, mt.kg, mt.gloss_exponent, llf, cone_directions, bg)


def _gather_params(kr, kg, gloss_exponent, llf: LLF, cone_directions: int, background) -> GatherParams:
    if not (1 <= cone_directions <= MAX_CONE_DIRECTIONS):
        raise InvalidInputError("cone_directions must be in [1, 16]")
    bg = np.asarray(background, dtype=np.float64).reshape(3)
    c_off, c_idx, c_xyz = _cone_tables(llf.f, llf.table, llf.directions, 3)
    return GatherParams(kr, kg, gloss_exponent, mirror_cone_exponent(llf), int(cone_directions), *llf_arrays(llf), bg,
                        c_off, c_idx, c_xyz)


def llf_arrays(llf: LLF) -> LLFArrays:
    """The LLF's lattice and packed views as the gather kernels read them."""
    return LLFArrays(llf.f, llf.table, llf.directions, llf.pk_offsets, llf.pk_depth, llf.pk_radiance, llf.pk_origin,
                     llf.pk_u, llf.pk_v, llf.pk_w, llf.pk_h, llf.resolution)


def gather_reflections(scene: RuntimeScene, llf: LLF, p, ng, ns, wo, mat, *, mirror: bool = True,
                       cone_directions: int = CONE_DIRECTIONS, background=None,
                       force: bool = False) -> tuple[np.ndarray, int]:
    """Reflected radiance (n, 3) float64 toward wo by light-field gather (mirror cone and
    glossy lobe, see module docstring) and the number of LLF lookups made. ``mirror=False``
    leaves out the mirror term (the glossy lobe is still gathered, as in the renderer unless it
    traces the lobe: ``engine.newviews.renderer``, ``glossy_rays``).
    ``force``: gather for every point even where kr / kg are 0 (adds exact zeros there)."""
    p, ng, ns, wo, mat = _check_points(p, ng, ns, wo, mat)
    gp = gather_params(scene, llf, cone_directions, background)
    n = p.shape[0]
    out = np.zeros((n, 3))
    lookups = np.zeros(n, np.int64)
    if n == 0:
        return out, 0
    _gather(p, ng, ns, wo, mat, mirror, bool(force), gp, out, lookups)
    if not np.all(np.isfinite(out)):
        raise NonFiniteOutputError("light-field gather produced non-finite radiance")
    return out, int(lookups.sum())


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _incoming(p, ng, d, exponent, gp, out):
    """``gather_incoming``'s kernel: per point, the lobe (``exponent`` > 0) or the mirror cone
    around d, from the LLF of ``gp`` (a ``GatherParams``; its material tables are not read)."""
    n = p.shape[0]
    f, table, dirs, res, bg = gp.f, gp.table, gp.directions, gp.resolution, gp.background
    pk_off, pk_depth, pk_rad = gp.pk_offsets, gp.pk_depth, gp.pk_radiance
    origin, fu, fv, fw, fh = gp.pk_origin, gp.pk_u, gp.pk_v, gp.pk_w, gp.pk_h
    c_off, c_idx, c_xyz, n_c, k_dirs = gp.cone_offsets, gp.cone_index, gp.cone_xyz, gp.n_c, gp.cone_directions
    nd = dirs.shape[0]
    nblk = (n + _BLOCK - 1) // _BLOCK
    for blk in range(nblk):
        cand, best_c, _ = gather_scratch(nd)
        for i in range(blk * _BLOCK, min(n, (blk + 1) * _BLOCK)):
            g0, g1, g2 = ng[i, 0], ng[i, 1], ng[i, 2]
            if exponent > 0.0:
                # normalised lobe without the cosine: sum w L / sum w
                r0, r1, r2, _ = _lobe(p[i, 0], p[i, 1], p[i, 2], g0, g1, g2, 0.0, 0.0, 0.0, d[i, 0], d[i, 1], d[i, 2],
                                      exponent, 1, f, table, dirs, cand, pk_off, pk_depth, pk_rad, origin, fu,
                                      fv, fw, fh, res, bg)
            else:
                r0, r1, r2, _ = _cone(p[i, 0], p[i, 1], p[i, 2], g0, g1, g2, d[i, 0], d[i, 1], d[i, 2], n_c, k_dirs,
                                      f, c_off, c_idx, c_xyz, cand, best_c, pk_off, pk_depth, pk_rad, origin, fu,
                                      fv, fw, fh, res, bg)
            out[i, 0], out[i, 1], out[i, 2] = r0, r1, r2


def lookup_direction(llf: LLF, j: int, p, ng, background=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(n, 3) radiance arriving at points p from LLF direction j (one view, bilinear)."""
    p = np.ascontiguousarray(p, dtype=np.float64).reshape(-1, 3)
    ng = np.ascontiguousarray(ng, dtype=np.float64).reshape(-1, 3)
    bg = np.asarray(background, dtype=np.float64).reshape(3)
    if not (0 <= j < llf.n_directions):
        raise InvalidInputError(f"LLF direction index must be in [0, {llf.n_directions - 1}]")
    out = np.empty((p.shape[0], 3))
    la = llf_arrays(llf)
    for i in range(p.shape[0]):
        out[i] = _lookup(j, p[i, 0], p[i, 1], p[i, 2], ng[i, 0], ng[i, 1], ng[i, 2], la.pk_offsets, la.pk_depth,
                         la.pk_radiance, la.pk_origin, la.pk_u, la.pk_v, la.pk_w, la.pk_h, la.resolution, bg)
    return out


def gather_incoming(llf: LLF, p, ng, d, *, exponent: float = 0.0, cone_directions: int = CONE_DIRECTIONS,
                    background=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(n, 3) float64 estimate of the radiance arriving at p from direction d (unit, (n, 3)):
    the mirror cone (exponent 0) or the normalised cos^exponent lobe over the LLF directions
    (no cosine factor, no BRDF). ng orients the tangent plane used by the lookups."""
    p = np.ascontiguousarray(p, dtype=np.float64).reshape(-1, 3)
    ng = np.ascontiguousarray(ng, dtype=np.float64).reshape(-1, 3)
    d = np.ascontiguousarray(d, dtype=np.float64).reshape(-1, 3)
    if not (ng.shape == p.shape == d.shape):
        raise InvalidInputError("gather_incoming: p, ng and d must be (n, 3)")
    if not (np.isfinite(exponent) and exponent >= 0):
        raise InvalidInputError("gather_incoming: exponent must be finite and >= 0")
    out = np.zeros(p.shape)
    no_mat = np.zeros((0, 3))
    gp = _gather_params(no_mat, no_mat, np.zeros(0), llf, int(cone_directions), background)
    _incoming(p, ng, d, float(exponent), gp, out)
    return out

