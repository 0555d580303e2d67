"""Render a new view from a baked LDC (+ LLF): the first paper's rendering (ALGORITHMS.md part A).

``LDCViewRenderer(scene, ldc, llf, plan).render(camera, method, ibrt_generations=k)``:

1. **Warp** (``engine/newviews/warp.py``): every LDC sample into the camera with a depth test; holes
   flagged (uncovered pixels and far surfaces seen through cracks).
2. **Hole filling**: ``fill="ibrt"`` (default) traces one image-based ray per hole pixel from
   the eye through the LDC (``engine/newviews/ibrt.py``); a hit shows that sample's diffuse radiance,
   a miss the background. ``fill="raycast"`` (the interim fill) casts Embree rays against
   the scene's triangles instead and shades the hits with the bake's diffuse model (it
   needs the triangles; the image-based fill needs only the bake). ``fill="none"`` leaves
   holes as background. **Silhouette rays** (``silhouette_rays=True``, the default; off with
   ``fill="none"``): covered pixels at a visibility edge of the warped image (a 4-neighbour
   shows another object, nothing, the same object more than ``silhouette_rel_depth``
   deeper or nearer, or the other side of a sheet) get the same eye ray as the holes. There
   the splats' footprints, which reach up to about a sample spacing past a silhouette,
   decided what the pixel shows; the ray decides by the pixel centre, and then the **mesh
   test** (``silhouette_mesh_test=True``) by the triangles of the candidates (the ray's hit,
   the warp's 3x3 winners) that the pixel ray really crosses (mirror_box, 256x256, LDC 512:
   pixels showing another object than the point-sampled reference 450-620 -> 11-34 per view,
   LRMS 0.060 -> 0.033, ~10 % more render time; ``docs/ldc.md``). Their provenance is 2 like
   the holes'; counts ``silhouette_rays``, ``silhouette_changed`` (pixels whose object
   changed) and ``silhouette_mesh_hits``.
3. **View-dependent pass**, only on the visible pixels whose material needs it (the effect
   plan; ``force_all_passes=True`` runs every pass of the method on every covered pixel,
   for the test that skipping changes nothing): Phong highlights gated by the LDC's
   visibility bits (``engine/newviews/view_pass.py``), then reflections:

   - ``ldc``: no reflections (warp + holes + highlights: everything the LDC alone holds);
   - ``ldc+llf``: light-field gather for mirror (3-direction cone) and glossy (lobe) terms;
   - ``ldc+ibrt`` with ``ibrt_generations`` = k: the mirror term (kr) is traced through the
     LDC for k generations (at each hit: the sample's diffuse radiance + its highlights
     toward the ray + its glossy gather + kr x the next generation), the last generation
     ending in the mirror-cone gather at its hit; the glossy term is always gathered (one
     ray cannot sample a lobe). k = 0 is ``ldc+llf``. Rays that leave the LDC see the
     background.

The radiance of a pixel is the sample's view-independent radiance (direct diffuse with
shadows + ambient + emission, from the bake) + highlights + reflections.

Provenance per pixel: 0 background, 1 warped, 2 hole-filled, 3 reflections gathered,
4 reflections traced (the later stages overwrite the earlier ones).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import InvalidInputError, NonFiniteOutputError
from engine.geometry.adjacency import locate_on_mesh, triangle_neighbours
from engine.methods import IBRT_GENERATIONS, LDC_IBRT, allowed_forms
from engine.methods import parse_method as parse_wire_method
from engine.newviews.effects import EffectPlan, analyze, plan_from_dict
from engine.newviews.ldc import LDC, shade_samples, surface_attributes
from engine.newviews.llf import LLF
from engine.newviews.view_pass import gather_params, gather_point, gather_scratch, highlight_params, highlight_point_u
from engine.newviews.warp import warp_ldc
from engine.raycast import RayCaster, make_caster
from engine.scene import CameraParams, RuntimeScene
from engine.sched import next_block

PROV_NONE = 0
PROV_WARPED = 1
PROV_FILLED = 2
PROV_GATHERED = 3
PROV_TRACED = 4

FILLS = ("ibrt", "raycast", "none")


@dataclass
class LDCRenderResult:
    """radiance (h, w, 3) float32 linear; depth (h, w) float32 distance along the pixel ray (0
    where empty); normal (h, w, 3) float32 shading normal facing the camera; object_id,
    material_id (h, w) int32 (-1 where empty); provenance (h, w) uint8 (module docstring);
    hole_mask (h, w) bool (holes found by the warp, before filling); timings (seconds per
    stage), counts (work done), plan (which passes ran and why)."""

    radiance: np.ndarray
    depth: np.ndarray
    normal: np.ndarray
    object_id: np.ndarray
    material_id: np.ndarray
    provenance: np.ndarray
    hole_mask: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    plan: dict = field(default_factory=dict)


def parse_method(method: str, ibrt_generations: int = 0) -> tuple[str, int]:
    """("ldc" | "ldc+llf" | "ldc+ibrt", k) of an LDC method of the registry ``engine.methods``: a wire
    string ("ldc+ibrt:k" carries k) or "ldc+ibrt" with ``ibrt_generations`` (checked for every method)."""
    k = IBRT_GENERATIONS.check(ibrt_generations, "ibrt_generations")
    spec = LDC_IBRT.spec(k) if method == LDC_IBRT.name else parse_wire_method(method)
    if not spec.needs_bake:
        raise InvalidInputError(f"the LDC renderer renders {allowed_forms(needs_bake=True)}, got {method!r}")
    return spec.name, spec.ibrt_generations


# ----------------------------------------------------------------------------- fused per-pixel kernels
# One launch per LDC axis with that axis' arrays passed one by one: numba indexes a tuple of
# arrays with a run-time index, and unpacks tuples of arrays in calls, at the price of
# reference counting per access (measured: several times the work itself).


@nb.njit(cache=True, nogil=True, inline="always")
def _sample_point(org, fu, fv, fw, h, nu, k, dep):
    """World position of a sample in LDI pixel k at depth ``dep`` of an axis whose frame
    (origin, u, v, w) is given as 3-tuples (scalars only: an inlined function's array
    arguments are increfed and decrefed per call)."""
    aa = (k % nu + 0.5) * h
    bb = (k // nu + 0.5) * h
    return (org[0] + aa * fu[0] + bb * fv[0] + dep * fw[0],
            org[1] + aa * fu[1] + bb * fv[1] + dep * fw[1],
            org[2] + aa * fu[2] + bb * fv[2] + dep * fw[2])


@nb.njit(cache=True, nogil=True, inline="always")
def _sample_normals(a0, a1, a2, b0, b1, b2, sd):
    """Geometric (a) and shading normal (b) of a sample flipped to side sd (the shading normal
    falls back to the geometric one when it is on the other side); scalars in and out."""
    sg = 1.0 if sd == 0 else -1.0
    g0, g1, g2 = sg * a0, sg * a1, sg * a2
    n0, n1, n2 = sg * b0, sg * b1, sg * b2
    if n0 * g0 + n1 * g1 + n2 * g2 <= 0.0:
        n0, n1, n2 = g0, g1, g2
    return g0, g1, g2, n0, n1, n2


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _interp_normal(t, bw, bu, bv, tri_n, tri_ng, g0, g1, g2):
    """Triangle t's vertex normals at barycentrics (bw, bu, bv), normalised and flipped to the
    side the sample was seen from (g), falling back to g when it points the other way; ok False
    when the interpolated normal vanishes. A plain function (LLVM inlines it): inlined by numba
    its two array arguments were increfed and decrefed per call."""
    m0 = bw * tri_n[t, 0, 0] + bu * tri_n[t, 1, 0] + bv * tri_n[t, 2, 0]
    m1 = bw * tri_n[t, 0, 1] + bu * tri_n[t, 1, 1] + bv * tri_n[t, 2, 1]
    m2 = bw * tri_n[t, 0, 2] + bu * tri_n[t, 1, 2] + bv * tri_n[t, 2, 2]
    ln = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    if not ln > 1e-12:
        return False, g0, g1, g2
    sg = 1.0 if g0 * tri_ng[t, 0] + g1 * tri_ng[t, 1] + g2 * tri_ng[t, 2] >= 0.0 else -1.0
    m0, m1, m2 = sg * m0 / ln, sg * m1 / ln, sg * m2 / ln
    if m0 * g0 + m1 * g1 + m2 * g2 <= 0.0:
        m0, m1, m2 = g0, g1, g2
    return True, m0, m1, m2


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _refine_point(ox, oy, oz, dx, dy, dz, t, tri_p, tri_n, tri_ng, nbr, max_move, px, py, pz, g0, g1, g2, n0, n1,
                  n2):
    """The pixel ray o + t d meets the surface of the sample's triangle t: move p there (when
    within max_move) and interpolate the shading normal, flipped like g. With the mesh's edge
    neighbours ``nbr`` ((nt, 3), ``engine.geometry.adjacency``; (0, 3): none) the walk first
    crosses edges to the triangle the ray crosses (up to 8 steps); where it ends inside a
    triangle that triangle's barycentrics are used, otherwise (a border, a silhouette, too many
    steps) triangle t's, clamped to [-0.25, 1.25] (mild extrapolation across its edges).
    Returns (p, ns), unchanged when the ray misses the plane or the crossing is too far."""
    if nbr.shape[0] > 0:
        ok, t2, s2, bw, bu, bv = locate_on_mesh(ox, oy, oz, dx, dy, dz, t, tri_p, tri_ng, nbr, 8)
        if ok and min(bw, min(bu, bv)) >= -1e-6:
            qx, qy, qz = ox + s2 * dx, oy + s2 * dy, oz + s2 * dz
            ex, ey, ez = qx - px, qy - py, qz - pz
            if ex * ex + ey * ey + ez * ez <= max_move * max_move:
                ok, m0, m1, m2 = _interp_normal(t2, max(bw, 0.0), max(bu, 0.0), max(bv, 0.0), tri_n, tri_ng, g0,
                                                g1, g2)
                if ok:
                    return qx, qy, qz, m0, m1, m2
    den = dx * g0 + dy * g1 + dz * g2
    if abs(den) < 1e-9:
        return px, py, pz, n0, n1, n2
    ax, ay, az = tri_p[t, 0, 0], tri_p[t, 0, 1], tri_p[t, 0, 2]
    tt = ((ax - ox) * g0 + (ay - oy) * g1 + (az - oz) * g2) / den
    if not tt > 0.0:
        return px, py, pz, n0, n1, n2
    qx, qy, qz = ox + tt * dx, oy + tt * dy, oz + tt * dz
    ex, ey, ez = qx - px, qy - py, qz - pz
    if not (ex * ex + ey * ey + ez * ez <= max_move * max_move):
        return px, py, pz, n0, n1, n2
    e1x, e1y, e1z = tri_p[t, 1, 0] - ax, tri_p[t, 1, 1] - ay, tri_p[t, 1, 2] - az
    e2x, e2y, e2z = tri_p[t, 2, 0] - ax, tri_p[t, 2, 1] - ay, tri_p[t, 2, 2] - az
    vx, vy, vz = qx - ax, qy - ay, qz - az
    d00 = e1x * e1x + e1y * e1y + e1z * e1z
    d01 = e1x * e2x + e1y * e2y + e1z * e2z
    d11 = e2x * e2x + e2y * e2y + e2z * e2z
    d20 = vx * e1x + vy * e1y + vz * e1z
    d21 = vx * e2x + vy * e2y + vz * e2z
    dd = d00 * d11 - d01 * d01
    if not dd > 0.0:
        return px, py, pz, n0, n1, n2
    bu = min(max((d11 * d20 - d01 * d21) / dd, -0.25), 1.25)
    bv = min(max((d00 * d21 - d01 * d20) / dd, -0.25), 1.25)
    bw = min(max(1.0 - bu - bv, -0.25), 1.25)
    ok, m0, m1, m2 = _interp_normal(t, bw, bu, bv, tri_n, tri_ng, g0, g1, g2)
    if not ok:
        return px, py, pz, n0, n1, n2
    return qx, qy, qz, m0, m1, m2


@nb.njit(cache=True, nogil=True)
def _select_view_pass(obj_id, mat_id, hl_mat, rf_mat, want_hl, want_rf, force):
    """The covered pixels the view pass runs on (row-major) and how many get highlights and
    reflections."""
    n = obj_id.shape[0]
    out = np.empty(n, np.int64)
    m = 0
    n_hl = 0
    n_rf = 0
    for i in range(n):
        if obj_id[i] < 0:
            continue
        mt = mat_id[i]
        hl = want_hl and (force or hl_mat[mt])
        rf = want_rf and (force or rf_mat[mt])
        if hl or rf:
            out[m] = i
            m += 1
            n_hl += hl
            n_rf += rf
    return out[:m], n_hl, n_rf


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _view_pass_group(counter, axis, pix, s_axis, s_idx, s_side, org, fu, fv, fw, h, nu, spix, depth, geo, nrm,
                     mat_a, vis2, prim, rc_row, rc_p, rc_ng, rc_ns, rc_mat, rc_bits, cam, refine, nbr, ldc_h, tri_p,
                     tri_n, tri_ng, hl_mat, rf_mat, gathered_mat, want_hl, want_rf, force, mirror, trace, hp, gp,
                     radiance, normal, prov, lookups, ray_o, ray_d, ray_ng, ray_thr, ray_live):
    """One parallel group of ``_view_pass_kernel``: the whole view-dependent pass of the camera
    pixels ``pix`` whose sample is on LDC axis ``axis`` (-1: the raycast fill's records
    ``rc_*``), in one pass: surface record, ``refine`` onto the sample's triangle, direction to
    the eye, highlights and the light-field gather, added to ``radiance`` (flat (h*w, 3));
    ``normal`` gets the shading normal used. With ``trace``: the pixel's mirror ray into
    ``ray_*`` (row = position in pix). The threads take blocks of 64 pixels from ``counter``
    (``engine.sched``: mirror and glossy pixels cluster in the image, and a core may be busy)."""
    ortho, eye, right, up, fwd, W, H, th, aspect, hh, px_size, ortho_px = cam
    # unpacked once per thread (see ``gather_point``)
    kr, kg, gexp, n_c, k_dirs, f, table, dirs, pk_off, pk_depth, pk_rad, l_org, l_u, l_v, l_w, l_h, res, bg_, c_off, \
        c_idx, c_xyz = gp
    ks, shin, spec_cut, pt_pos, pt_int, dir_dir, dir_irr, rc, ru, rv, r_n, r_area, rL, r2s, r_g, stream, center, \
        extent = hp
    cand, best_c, pt = gather_scratch(dirs.shape[0])
    bits = vis2 if axis >= 0 else rc_bits
    org_t = (org[0], org[1], org[2])
    fu_t = (fu[0], fu[1], fu[2])
    fv_t = (fv[0], fv[1], fv[2])
    fw_t = (fw[0], fw[1], fw[2])
    n = pix.shape[0]
    nblk = (n + 63) // 64
    while True:
        blk = next_block(counter)
        if blk >= nblk:
            break
        for i in range(blk * 64, min(n, blk * 64 + 64)):
            r = pix[i]
            if s_axis[r] != axis:
                continue
            if axis >= 0:
                s = s_idx[r]
                sd = s_side[r]
                px, py, pz = _sample_point(org_t, fu_t, fv_t, fw_t, h, nu, np.int64(spix[s]), depth[s])
                g0, g1, g2, n0, n1, n2 = _sample_normals(geo[s, 0], geo[s, 1], geo[s, 2], nrm[s, 0], nrm[s, 1],
                                                         nrm[s, 2], sd)
                m = mat_a[s]
                brow = 2 * s + sd
                if refine:
                    ox, oy, oz, dx, dy, dz = _pixel_ray(r, ortho, eye, right, up, fwd, W, H, th, aspect, hh)
                    if ortho:
                        reach = ortho_px
                    else:
                        ex, ey, ez = px - ox, py - oy, pz - oz
                        reach = px_size * math.sqrt(ex * ex + ey * ey + ez * ez)
                    lim = 2.0 * (ldc_h + reach)
                    px, py, pz, n0, n1, n2 = _refine_point(ox, oy, oz, dx, dy, dz, prim[s], tri_p, tri_n, tri_ng,
                                                           nbr, lim, px, py, pz, g0, g1, g2, n0, n1, n2)
            else:  # a pixel of the raycast fill
                j = rc_row[r]
                px, py, pz = rc_p[j, 0], rc_p[j, 1], rc_p[j, 2]
                g0, g1, g2 = rc_ng[j, 0], rc_ng[j, 1], rc_ng[j, 2]
                n0, n1, n2 = rc_ns[j, 0], rc_ns[j, 1], rc_ns[j, 2]
                m = rc_mat[j]
                brow = j
            if ortho:
                wo0, wo1, wo2 = -fwd[0], -fwd[1], -fwd[2]
            else:
                wo0, wo1, wo2 = eye[0] - px, eye[1] - py, eye[2] - pz
                ln = math.sqrt(wo0 * wo0 + wo1 * wo1 + wo2 * wo2)
                if not ln > 0.0:
                    ln = 1.0
                wo0 /= ln
                wo1 /= ln
                wo2 /= ln
            normal[r, 0], normal[r, 1], normal[r, 2] = n0, n1, n2
            pt[0], pt[1], pt[2], pt[3], pt[4], pt[5] = px, py, pz, g0, g1, g2
            pt[6], pt[7], pt[8], pt[9], pt[10], pt[11] = n0, n1, n2, wo0, wo1, wo2
            if want_hl and (force or hl_mat[m]):
                h0, h1, h2 = highlight_point_u(r, pt, m, bits, brow, force, ks, shin, spec_cut, pt_pos, pt_int, dir_dir,
                                               dir_irr, rc, ru, rv, r_n, r_area, rL, r2s, r_g, stream, center, extent)
                radiance[r, 0] += h0
                radiance[r, 1] += h1
                radiance[r, 2] += h2
            if want_rf and (force or rf_mat[m]):
                # gathered_mat: the materials gather_point does anything for (a traced mirror's gather
                # is zero); the call passes ~20 arrays on the stack, so it is skipped where it would
                # return zeros (see _shade_group)
                if force or gathered_mat[m]:
                    f0, f1, f2, u = gather_point(pt, m, mirror, True, force, cand, best_c, kr, kg, gexp, n_c, k_dirs,
                                                 f, table, dirs, pk_off, pk_depth, pk_rad, l_org, l_u, l_v, l_w, l_h,
                                                 res, bg_, c_off, c_idx, c_xyz)
                    radiance[r, 0] += f0
                    radiance[r, 1] += f1
                    radiance[r, 2] += f2
                    lookups[i] = u
                if gathered_mat[m]:
                    prov[r] = 3
                if trace:
                    c = n0 * wo0 + n1 * wo1 + n2 * wo2
                    d0, d1, d2 = 2.0 * c * n0 - wo0, 2.0 * c * n1 - wo1, 2.0 * c * n2 - wo2
                    ln = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                    d0 /= ln
                    d1 /= ln
                    d2 /= ln
                    live = force or ((kr[m, 0] > 0.0 or kr[m, 1] > 0.0 or kr[m, 2] > 0.0) and
                                     g0 * d0 + g1 * d1 + g2 * d2 > 0.0)
                    ray_live[i] = live
                    if live:
                        ray_o[i, 0], ray_o[i, 1], ray_o[i, 2] = px, py, pz
                        ray_d[i, 0], ray_d[i, 1], ray_d[i, 2] = d0, d1, d2
                        ray_ng[i, 0], ray_ng[i, 1], ray_ng[i, 2] = g0, g1, g2
                        ray_thr[i, 0], ray_thr[i, 1], ray_thr[i, 2] = kr[m, 0], kr[m, 1], kr[m, 2]


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _view_pass_kernel(groups, with_rc, pix, s_axis, s_idx, s_side, rc_row, rc_p, rc_ng, rc_ns, rc_mat, rc_bits, cam,
                      refine, nbr, ldc_h, tri_p, tri_n, tri_ng, hl_mat, rf_mat, gathered_mat, want_hl, want_rf, force,
                      mirror, trace, hp, gp, radiance, normal, prov, lookups, ray_o, ray_d, ray_ng, ray_thr, ray_live,
                      org0, fu0, fv0, fw0, h0, nu0, spix0, dep0, geo0, nrm0, mat0, vis0, prim0,
                      org1, fu1, fv1, fw1, h1, nu1, spix1, dep1, geo1, nrm1, mat1, vis1, prim1,
                      org2, fu2, fv2, fw2, h2, nu2, spix2, dep2, geo2, nrm2, mat2, vis2, prim2):
    """The view-dependent pass of every pixel in ``pix`` in ONE parallel launch: the pixels whose
    sample is on LDC axis 0, 1, 2 (their arrays ``*0``, ``*1``, ``*2``) and, ``with_rc``, those of
    the raycast fill (axis -1, records ``rc_*``). Each part has its own block counter and a thread
    done with one goes on to the next (the parts are disjoint pixels), so there is one launch and
    one tail instead of one per axis (a numba workqueue launch costs 0.1-0.3 ms here)."""
    counters = np.zeros(4, np.int64)
    c_0 = counters[0:1]
    c_1 = counters[1:2]
    c_2 = counters[2:3]
    c_r = counters[3:4]
    for _ in nb.prange(groups):
        _view_pass_group(c_0, 0, pix, s_axis, s_idx, s_side, org0, fu0, fv0, fw0, h0, nu0, spix0, dep0, geo0, nrm0,
                         mat0, vis0, prim0, rc_row, rc_p, rc_ng, rc_ns, rc_mat, rc_bits, cam, refine, nbr, ldc_h, tri_p,
                         tri_n, tri_ng, hl_mat, rf_mat, gathered_mat, want_hl, want_rf, force, mirror, trace, hp, gp,
                         radiance, normal, prov, lookups, ray_o, ray_d, ray_ng, ray_thr, ray_live)
        _view_pass_group(c_1, 1, pix, s_axis, s_idx, s_side, org1, fu1, fv1, fw1, h1, nu1, spix1, dep1, geo1, nrm1,
                         mat1, vis1, prim1, rc_row, rc_p, rc_ng, rc_ns, rc_mat, rc_bits, cam, refine, nbr, ldc_h, tri_p,
                         tri_n, tri_ng, hl_mat, rf_mat, gathered_mat, want_hl, want_rf, force, mirror, trace, hp, gp,
                         radiance, normal, prov, lookups, ray_o, ray_d, ray_ng, ray_thr, ray_live)
        _view_pass_group(c_2, 2, pix, s_axis, s_idx, s_side, org2, fu2, fv2, fw2, h2, nu2, spix2, dep2, geo2, nrm2,
                         mat2, vis2, prim2, rc_row, rc_p, rc_ng, rc_ns, rc_mat, rc_bits, cam, refine, nbr, ldc_h, tri_p,
                         tri_n, tri_ng, hl_mat, rf_mat, gathered_mat, want_hl, want_rf, force, mirror, trace, hp, gp,
                         radiance, normal, prov, lookups, ray_o, ray_d, ray_ng, ray_thr, ray_live)
        if with_rc:  # the raycast fill's pixels (no LDC sample; axis 0's arrays are placeholders)
            _view_pass_group(c_r, -1, pix, s_axis, s_idx, s_side, org0, fu0, fv0, fw0, h0, nu0, spix0, dep0, geo0,
                             nrm0, mat0, vis0, prim0, rc_row, rc_p, rc_ng, rc_ns, rc_mat, rc_bits, cam, refine, nbr,
                             ldc_h, tri_p, tri_n, tri_ng, hl_mat, rf_mat, gathered_mat, want_hl, want_rf, force, mirror,
                             trace, hp, gp, radiance, normal, prov, lookups, ray_o, ray_d, ray_ng, ray_thr, ray_live)


@nb.njit(cache=True, nogil=True)
def _clear_pixels(pix, bg, radiance, depth, normal, obj_id, mat_id, prov, s_axis, s_idx):
    """Pixels ``pix`` show the background and no sample (before a ray's answer replaces them)."""
    for i in range(pix.shape[0]):
        r = pix[i]
        for c in range(3):
            radiance[r, c] = bg[c]
            normal[r, c] = 0.0
        depth[r] = 0.0
        obj_id[r] = -1
        mat_id[r] = -1
        prov[r] = 0
        s_axis[r] = -1
        s_idx[r] = -1


@nb.njit(cache=True, nogil=True, parallel=True)
def _to_f32_count_nonfinite(radiance, depth, out):
    """out (n, 3) float32 = radiance (n, 3) float64; returns how many radiance or depth values
    are not finite."""
    n = radiance.shape[0]
    nblk = (n + 4095) // 4096
    bad = 0
    for b in nb.prange(nblk):
        for i in range(b * 4096, min(n, b * 4096 + 4096)):
            for c in range(3):
                v = radiance[i, c]
                out[i, c] = v
                if not np.isfinite(v):
                    bad += 1
            if not np.isfinite(depth[i]):
                bad += 1
    return bad


@nb.njit(cache=True, nogil=True, inline="always")
def _pixel_ray(r, ortho, eye, right, up, fwd, W, H, th, aspect, hh):
    """The eye ray (o, d) through the centre of flat pixel r (``engine.camera.camera_rays``'
    arithmetic, operation for operation: the same float64 rays), from the items of
    ``LDCViewRenderer._camera_tuple`` (unpacked by the caller outside its loop: unpacking a tuple
    of arrays increfs and decrefs each of them)."""
    sx = 2.0 * (r % W + 0.5) / W - 1.0
    sy = 1.0 - 2.0 * (r // W + 0.5) / H
    if ortho:
        a = sx * hh * aspect
        b = sy * hh
        return (eye[0] + a * right[0] + b * up[0], eye[1] + a * right[1] + b * up[1],
                eye[2] + a * right[2] + b * up[2], fwd[0], fwd[1], fwd[2])
    a = sx * th * aspect
    b = sy * th
    dx = fwd[0] + a * right[0] + b * up[0]
    dy = fwd[1] + a * right[1] + b * up[1]
    dz = fwd[2] + a * right[2] + b * up[2]
    ln = math.sqrt(dx * dx + dy * dy + dz * dz)
    return eye[0], eye[1], eye[2], dx / ln, dy / ln, dz / ln


@nb.njit(cache=True, nogil=True, parallel=True)
def _pixel_rays(pix, cam):
    """(o, d), each (n, 3) float64: the eye rays of the flat pixels ``pix`` (``_pixel_ray``)."""
    ortho, eye, right, up, fwd, W, H, th, aspect, hh, _, _ = cam
    n = pix.shape[0]
    o = np.empty((n, 3))
    d = np.empty((n, 3))
    for i in nb.prange(n):
        o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2] = _pixel_ray(pix[i], ortho, eye, right, up, fwd, W, H,
                                                                          th, aspect, hh)
    return o, d


@nb.njit(cache=True, nogil=True, parallel=True)
def _rays_meet_box(pix, cam, lo, hi):
    """(n,) bool: the eye ray of flat pixel ``pix[i]`` meets the box [lo, hi] at t >= 0 (slab
    test; an axis the ray is parallel to is skipped, like the NaN-ignoring numpy version)."""
    ortho, eye, right, up, fwd, W, H, th, aspect, hh, _, _ = cam
    n = pix.shape[0]
    keep = np.empty(n, np.bool_)
    for i in nb.prange(n):
        ox, oy, oz, dx, dy, dz = _pixel_ray(pix[i], ortho, eye, right, up, fwd, W, H, th, aspect, hh)
        tn = -np.inf
        tf = np.inf
        for a in range(3):
            oa = ox if a == 0 else (oy if a == 1 else oz)
            da = dx if a == 0 else (dy if a == 1 else dz)
            inv = 1.0 / da if da != 0.0 else math.copysign(np.inf, da)
            t0 = (lo[a] - oa) * inv
            t1 = (hi[a] - oa) * inv
            if t0 != t0 or t1 != t1:
                continue
            tn = max(tn, min(t0, t1))
            tf = min(tf, max(t0, t1))
        keep[i] = tf >= max(tn, 0.0)
    return keep


_RAY_TILE = 16  # mirror rays are traced in 16 x 16 pixel tiles (see _tile_order)


@nb.njit(cache=True, nogil=True)
def _tile_order(pix, W, T):
    """The permutation that puts the flat pixels ``pix`` (ascending) in T x T tiles, tile rows
    top to bottom, tiles left to right, each tile's pixels in their given (row-major) order: a
    counting sort. Neighbouring mirror rays then traverse the same quadtree nodes and samples
    one after the other, so the image-based tracer finds them in its caches (mirror stage 1.04-
    1.09x against row-major order, mirror_box 512x512 LDC 128; each ray's result is independent
    of the order). The view pass itself stays row-major (measured slightly faster)."""
    n = pix.shape[0]
    tw = (W + T - 1) // T
    key = np.empty(n, np.int64)
    kmax = 0
    for i in range(n):
        k = (pix[i] // W // T) * tw + (pix[i] % W) // T
        key[i] = k
        kmax = max(kmax, k)
    start = np.zeros(kmax + 2, np.int64)
    for i in range(n):
        start[key[i] + 1] += 1
    for k in range(kmax + 1):
        start[k + 1] += start[k]
    out = np.empty(n, np.int64)
    for i in range(n):
        k = key[i]
        out[start[k]] = i
        start[k] += 1
    return out


@nb.njit(cache=True, nogil=True, parallel=True)
def _near_covered(covered, r):
    """(H, W) bool: a covered pixel within the (2r+1) x (2r+1) square around each pixel (a
    binary dilation; outside the image counts as uncovered)."""
    H, W = covered.shape
    row = np.zeros((H, W), np.bool_)
    for y in nb.prange(H):
        c = 0  # covered pixels in row y's window [x - r, x + r]
        for x in range(min(r, W)):
            c += covered[y, x]
        for x in range(W):
            if x + r < W:
                c += covered[y, x + r]
            if x - r - 1 >= 0:
                c -= covered[y, x - r - 1]
            row[y, x] = c > 0
    out = np.zeros((H, W), np.bool_)
    for y in nb.prange(H):
        for yy in range(max(0, y - r), min(H, y + r + 1)):
            for x in range(W):
                out[y, x] |= row[yy, x]
    return out


@nb.njit(cache=True, nogil=True, parallel=True)
def _silhouette_pixels(obj_id, depth, side, is_hole, h, w, rel_jump):
    """Covered pixels (row-major, not already holes) at a visibility edge of the warped image: a
    4-neighbour shows another object or nothing, the same object at a depth more than
    ``rel_jump`` (relative) away (a fold: a handle over the body), or the other side of a sheet
    (``side``: the inside of a rim next to its outside). There the splats' footprints, not the
    pixel centre, decided what the pixel shows."""
    flag = np.zeros(h * w, np.bool_)
    for y in nb.prange(h):
        for x in range(w):
            i = y * w + x
            o = obj_id[i]
            if o < 0 or is_hole[i]:
                continue
            lim = rel_jump * depth[i]
            edge = False
            for k in range(4):
                if k == 0:
                    if x == 0:
                        continue
                    j = i - 1
                elif k == 1:
                    if x == w - 1:
                        continue
                    j = i + 1
                elif k == 2:
                    if y == 0:
                        continue
                    j = i - w
                else:
                    if y == h - 1:
                        continue
                    j = i + w
                if obj_id[j] != o or abs(depth[j] - depth[i]) > lim or side[j] != side[i]:
                    edge = True
                    break
            flag[i] = edge
    return np.flatnonzero(flag)


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _silhouette_mesh_test(pix, o, d, h_axis, h_sample, h_t, s_axis, s_idx, W, H, prim0, prim1, prim2, tri_p, tri_ng,
                          tri_obj, nbr, tol):
    """Silhouette pixels ``pix`` (eye rays o, d; image-based hits h_*, updated in place): the
    candidates are the warp's winners of the 3x3 neighbourhood (one side of a silhouette shows
    the surface the other side's splats overreached) and the ray's own hit where one is given
    (h_axis >= 0; the renderer runs this test BEFORE tracing: only the pixels it leaves at -1
    take an image-based ray). Each candidate's
    triangle is walked along the ray (``locate_on_mesh``); the nearest crossing - the ray
    really crosses that mesh there - decides the surface, at the crossing's distance. Of the
    candidates on that surface (the same object, crossed within ``tol`` of it) the sample that gives the
    radiance is the pixel's own warp winner if it is one, else the ray's hit, else the first
    (the nearer a sample is to the pixel, the less its baked shading, shadow edges included,
    differs from the pixel's). Where no candidate is crossed the image-based answer stays.
    Returns how many pixels took a mesh-tested hit."""
    n = pix.shape[0]
    nblk = (n + 63) // 64
    acc = np.zeros(nblk, np.int64)
    for b in nb.prange(nblk):  # blocks of 64 pixels: the scratch is allocated once per block
        acc[b] = _silhouette_mesh_block(b * 64, min(n, b * 64 + 64), pix, o, d, h_axis, h_sample, h_t, s_axis, s_idx,
                                        W, H, prim0, prim1, prim2, tri_p, tri_ng, tri_obj, nbr, tol)
    return acc.sum()


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _silhouette_mesh_block(i0, i1, pix, o, d, h_axis, h_sample, h_t, s_axis, s_idx, W, H, prim0, prim1, prim2, tri_p,
                           tri_ng, tri_obj, nbr, tol):
    """Pixels i0 <= i < i1 of ``_silhouette_mesh_test``; returns how many took a mesh-tested hit."""
    ca = np.empty(10, np.int64)
    cs = np.empty(10, np.int64)
    ct = np.empty(10)
    co = np.empty(10, np.int64)
    wt = np.empty(10, np.int64)  # per candidate: start triangle of its walk (-1: none), the walk's result
    wok = np.empty(10, np.bool_)
    wt2 = np.empty(10, np.int64)
    ws2 = np.empty(10)
    n_acc = 0
    for i in range(i0, i1):
        r = pix[i]
        x = r % W
        y = r // W
        ct[:] = np.inf
        best_t = np.inf
        best_o = -1
        for k in range(10):
            ca[k] = -1
            wt[k] = -1
            if k == 9:
                a = h_axis[i]
                sm = h_sample[i]
            else:
                xx = x + k % 3 - 1
                yy = y + k // 3 - 1
                if xx < 0 or yy < 0 or xx >= W or yy >= H:
                    continue
                j = yy * W + xx
                a = s_axis[j]
                sm = s_idx[j]
            if a < 0:
                continue
            t = prim0[sm] if a == 0 else (prim1[sm] if a == 1 else prim2[sm])
            # the walk is a function of (ray, start triangle): neighbours splatted from one sample or
            # triangle (most of the 3x3 at LDC resolutions below the image's) share its result
            kk = -1
            for q in range(k):
                if wt[q] == t:
                    kk = q
                    break
            if kk >= 0:
                good = wok[kk]
                t2 = wt2[kk]
                s2 = ws2[kk]
            else:
                ok, t2, s2, bw, bu, bv = locate_on_mesh(o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], t, tri_p,
                                                        tri_ng, nbr, 8)
                good = ok and min(bw, min(bu, bv)) >= -1e-6 and s2 > 0.0
            wt[k] = t
            wok[k] = good
            wt2[k] = t2
            ws2[k] = s2
            if good:
                ca[k] = a
                cs[k] = sm
                ct[k] = s2
                co[k] = tri_obj[t2]
                if s2 < best_t:
                    best_t = s2
                    best_o = co[k]
        if best_t == np.inf:
            continue
        pick = -1
        for k in (4, 9, 0, 1, 2, 3, 5, 6, 7, 8):  # own winner, the ray's hit, the neighbours
            if ca[k] >= 0 and co[k] == best_o and ct[k] <= best_t + tol:
                pick = k
                break
        h_axis[i] = ca[pick]
        h_sample[i] = cs[pick]
        h_t[i] = best_t
        n_acc += 1
    return n_acc


@nb.njit(cache=True, nogil=True)
def _fill_from_hits(axis, holes, hit_axis, hit_sample, hit_t, d, geo, nrm, mat_a, obj_a, diff, radiance, depth,
                    normal, obj_id, mat_id, prov, s_axis, s_idx, s_side):
    """Hole pixels whose eye ray hit LDC axis ``axis`` show the hit sample's diffuse radiance,
    distance, shading normal and ids (provenance 2). Serial: a few thousand pixels take less
    than a parallel launch costs (0.1-0.3 ms with numba's workqueue layer here)."""
    for i in range(holes.shape[0]):
        if hit_axis[i] != axis:
            continue
        r = holes[i]
        s = hit_sample[i]
        sd = 1 if geo[s, 0] * d[i, 0] + geo[s, 1] * d[i, 1] + geo[s, 2] * d[i, 2] > 0.0 else 0
        _, _, _, n0, n1, n2 = _sample_normals(geo[s, 0], geo[s, 1], geo[s, 2], nrm[s, 0], nrm[s, 1], nrm[s, 2], sd)
        radiance[r, 0], radiance[r, 1], radiance[r, 2] = diff[s, sd, 0], diff[s, sd, 1], diff[s, sd, 2]
        depth[r] = hit_t[i]
        normal[r, 0], normal[r, 1], normal[r, 2] = n0, n1, n2
        obj_id[r] = obj_a[s]
        mat_id[r] = mat_a[s]
        prov[r] = 2
        s_axis[r] = axis
        s_idx[r] = s
        s_side[r] = sd


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _shade_group(counter, axis, hit_axis, hit_sample, hit_t, o, d, owner, thr, geo, nrm, mat_a, diff, vis2, bg,
                 last, has_llf, gather_mat, force, hp, gp, acc, lookups, cont, n_o, n_d, n_ng, n_thr, prim, tri_p,
                 tri_n, tri_ng, nbr, ldc_h):
    """One parallel group of ``_shade_hits``, one axis: the rays that hit LDC axis ``axis`` (or, with
    axis -1, missed everything). With edge neighbours ``nbr`` (non-empty) each hit is refined
    like a camera pixel: onto the triangle the ray crosses, with its interpolated normal."""
    # unpacked once per thread (see ``gather_point``)
    kr, kg, gexp, n_c, k_dirs, f, table, dirs, pk_off, pk_depth, pk_rad, l_org, l_u, l_v, l_w, l_h, res, bg_, c_off, \
        c_idx, c_xyz = gp
    ks, shin, spec_cut, pt_pos, pt_int, dir_dir, dir_irr, rc, ru, rv, r_n, r_area, rL, r2s, r_g, stream, center, \
        extent = hp
    cand, best_c, pt = gather_scratch(dirs.shape[0])
    n = o.shape[0]
    nblk = (n + 63) // 64
    while True:
        blk = next_block(counter)
        if blk >= nblk:
            break
        for i in range(blk * 64, min(n, blk * 64 + 64)):
            if hit_axis[i] != axis:
                continue
            q = owner[i]
            if axis < 0:
                for c in range(3):
                    acc[q, c] += thr[i, c] * bg[c]
                continue
            s = hit_sample[i]
            d0, d1, d2 = d[i, 0], d[i, 1], d[i, 2]
            t = hit_t[i]
            px, py, pz = o[i, 0] + t * d0, o[i, 1] + t * d1, o[i, 2] + t * d2
            sd = 1 if geo[s, 0] * d0 + geo[s, 1] * d1 + geo[s, 2] * d2 > 0.0 else 0
            g0, g1, g2, n0, n1, n2 = _sample_normals(geo[s, 0], geo[s, 1], geo[s, 2], nrm[s, 0], nrm[s, 1], nrm[s, 2],
                                                     sd)
            if nbr.shape[0] > 0:
                px, py, pz, n0, n1, n2 = _refine_point(o[i, 0], o[i, 1], o[i, 2], d0, d1, d2, prim[s], tri_p, tri_n,
                                                       tri_ng, nbr, 3.0 * ldc_h, px, py, pz, g0, g1, g2, n0, n1, n2)
            m = mat_a[s]
            wo0, wo1, wo2 = -d0, -d1, -d2
            pt[0], pt[1], pt[2], pt[3], pt[4], pt[5] = px, py, pz, g0, g1, g2
            pt[6], pt[7], pt[8], pt[9], pt[10], pt[11] = n0, n1, n2, wo0, wo1, wo2
            h0, h1, h2 = highlight_point_u(i, pt, m, vis2, 2 * s + sd, force, ks, shin, spec_cut, pt_pos, pt_int,
                                           dir_dir, dir_irr, rc, ru, rv, r_n, r_area, rL, r2s, r_g, stream, center,
                                           extent)
            l0 = diff[s, sd, 0] + h0
            l1 = diff[s, sd, 1] + h1
            l2 = diff[s, sd, 2] + h2
            # gather_mat: the materials gather_point does anything for in this generation (glossy; mirrors
            # on the last, the cone's, generation): the call is not inlined and passes ~20 arrays on the
            # stack (~160 pushes), 57 % of this kernel's samples on mirror_box when it ran for every hit
            if has_llf and (force or gather_mat[m]):
                f0, f1, f2, u = gather_point(pt, m, last, True, force, cand, best_c, kr, kg, gexp, n_c, k_dirs, f,
                                             table, dirs, pk_off, pk_depth, pk_rad, l_org, l_u, l_v, l_w, l_h, res,
                                             bg_, c_off, c_idx, c_xyz)
                l0 += f0
                l1 += f1
                l2 += f2
                lookups[i] = u
            acc[q, 0] += thr[i, 0] * l0
            acc[q, 1] += thr[i, 1] * l1
            acc[q, 2] += thr[i, 2] * l2
            if last:
                continue
            c = n0 * wo0 + n1 * wo1 + n2 * wo2
            e0, e1, e2 = 2.0 * c * n0 - wo0, 2.0 * c * n1 - wo1, 2.0 * c * n2 - wo2
            ln = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            e0 /= ln
            e1 /= ln
            e2 /= ln
            go = force or ((kr[m, 0] > 0.0 or kr[m, 1] > 0.0 or kr[m, 2] > 0.0) and g0 * e0 + g1 * e1 + g2 * e2 > 0.0)
            cont[i] = go
            if go:
                n_o[i, 0], n_o[i, 1], n_o[i, 2] = px, py, pz
                n_d[i, 0], n_d[i, 1], n_d[i, 2] = e0, e1, e2
                n_ng[i, 0], n_ng[i, 1], n_ng[i, 2] = g0, g1, g2
                for c3 in range(3):
                    n_thr[i, c3] = thr[i, c3] * kr[m, c3]


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _shade_hits(groups, hit_axis, hit_sample, hit_t, o, d, owner, thr, bg, last, has_llf, gather_mat, force, hp, gp,
                    acc, lookups, cont, n_o, n_d, n_ng, n_thr, tri_p, tri_n, tri_ng, nbr, ldc_h, geo0, nrm0, mat0,
                    diff0, vis0, prim0, geo1, nrm1, mat1, diff1, vis1, prim1, geo2, nrm2, mat2, diff2, vis2, prim2):
    """One generation of traced mirror rays (module docstring of ``_shade_group``): at each hit
    the sample's diffuse radiance + its highlights toward the ray + its glossy gather (+ the
    mirror cone on the ``last`` generation) times the ray's throughput into ``acc[owner]``
    (owners are distinct within a generation); a miss adds the background. Hits on mirrors
    continue (``cont``, ``n_*``: the next generation's rays). The misses (axis -1) and the hits
    on each LDC axis (its arrays ``*0``, ``*1``, ``*2``) in ONE call: a kernel call with these
    tuples of arrays costs ~150 us of argument typing in numba's dispatcher, and one call per
    axis was ~1 % of a render. Each axis has its own block counter; a thread done with one axis
    goes on to the next (the axes' rays are disjoint). ``gather_mat``: per material, whether the
    gather does anything in this generation (glossy, and mirrors on the last one)."""
    counters = np.zeros(4, np.int64)
    c_m = counters[0:1]
    c_0 = counters[1:2]
    c_1 = counters[2:3]
    c_2 = counters[3:4]
    for _ in nb.prange(groups):
        _shade_group(c_m, -1, hit_axis, hit_sample, hit_t, o, d, owner, thr, geo0, nrm0, mat0, diff0, vis0, bg,
                     last, has_llf, gather_mat, force, hp, gp, acc, lookups, cont, n_o, n_d, n_ng, n_thr,
                     prim0, tri_p, tri_n,
                     tri_ng, nbr, ldc_h)
        _shade_group(c_0, 0, hit_axis, hit_sample, hit_t, o, d, owner, thr, geo0, nrm0, mat0, diff0, vis0, bg,
                     last, has_llf, gather_mat, force, hp, gp, acc, lookups, cont, n_o, n_d, n_ng, n_thr,
                     prim0, tri_p, tri_n,
                     tri_ng, nbr, ldc_h)
        _shade_group(c_1, 1, hit_axis, hit_sample, hit_t, o, d, owner, thr, geo1, nrm1, mat1, diff1, vis1, bg,
                     last, has_llf, gather_mat, force, hp, gp, acc, lookups, cont, n_o, n_d, n_ng, n_thr,
                     prim1, tri_p, tri_n,
                     tri_ng, nbr, ldc_h)
        _shade_group(c_2, 2, hit_axis, hit_sample, hit_t, o, d, owner, thr, geo2, nrm2, mat2, diff2, vis2, bg,
                     last, has_llf, gather_mat, force, hp, gp, acc, lookups, cont, n_o, n_d, n_ng, n_thr,
                     prim2, tri_p, tri_n,
                     tri_ng, nbr, ldc_h)


def _ldc_axes(ldc: LDC) -> list[tuple]:
    """Per LDC axis the arrays the fused kernels take: frame (origin, u, v, w, h, nu), the LDI
    pixel of every sample (int32), depth, geometric and shading normal, material, object, diffuse, visibility as (2 n,
    W) (row 2 s + side) and triangle id."""
    out = []
    c = np.ascontiguousarray
    for ax in ldc.axes:
        f = ax.ldi.frame
        vis = c(ax.visibility, dtype=np.uint64)
        out.append((c(f.origin, np.float64), c(f.u, np.float64), c(f.v, np.float64), c(f.w, np.float64), float(f.h),
                    int(f.nu), ax.ldi.sample_pixels().astype(np.int32), c(ax.ldi.depth, np.float64),
                    c(ax.geo_normal, np.float32), c(ax.normal, np.float32), c(ax.material, np.int32),
                    c(ax.object, np.int32),
                    c(ax.diffuse, np.float32), vis.reshape(vis.shape[0] * 2, vis.shape[2]), c(ax.ldi.prim, np.int32)))
    return out


def _no_gather_params(scene: RuntimeScene) -> tuple:
    """``gather_params`` of an empty light field (typed like a real one; never gathered from)."""
    mt = scene.materials
    z3 = np.zeros((0, 3))
    return (mt.kr, mt.kg, mt.gloss_exponent, 1.0, 3, 1, np.full((3, 3, 2), -1, np.int64), z3, np.zeros(1, np.int64),
            np.zeros(0), np.zeros((0, 3), np.float32), z3, z3, z3, z3, np.zeros(0), 1,
            np.asarray(scene.background, np.float64).reshape(3), np.zeros(10, np.int64), np.zeros(0, np.int64),
            np.zeros((3, 0)))


class LDCViewRenderer:
    """Holds the scene's tables, the LDC, the LLF (None when the plan needs none) and, built
    lazily on first use, the IBRT acceleration structure. Reusable across renders (cache it
    per worker); ``render`` is not meant to run in two threads at once (numba's workqueue
    layer), a lock serialises it."""

    def __init__(self, scene: RuntimeScene, ldc: LDC, llf: LLF | None, plan: EffectPlan | dict | None = None, *,
                 caster: RayCaster | None = None, area_light_samples: int = 16, seed: int = 0,
                 warp_options: dict | None = None, hole_search_px: int | None = 3, refine_surface: bool = True,
                 refine_walk: bool = True, silhouette_mesh_test: bool = True, silhouette_rays: bool = True,
                 silhouette_rel_depth: float = 0.1):
        if not isinstance(ldc, LDC):
            raise InvalidInputError("LDCViewRenderer needs an LDC")
        if ldc.n_lights != scene.lights.count:
            raise InvalidInputError(f"the LDC was baked for {ldc.n_lights} lights, the scene has {scene.lights.count}")
        self.scene = scene
        self.ldc = ldc
        self.llf = llf
        # the plan: given, or the one stored with the LDC bake, or analysed now
        if plan is None:
            plan = plan_from_dict(ldc.plan) if ldc.plan else analyze(scene)
        elif isinstance(plan, dict):
            plan = plan_from_dict(plan)
        self.plan = plan
        self._caster = caster
        self.area_light_samples = int(area_light_samples)
        self.seed = int(seed)
        if hole_search_px is not None and not (isinstance(hole_search_px, int) and 0 <= hole_search_px <= 64):
            raise InvalidInputError("hole_search_px must be None or an integer in [0, 64]")
        self.hole_search_px = hole_search_px
        self.refine_surface = bool(refine_surface)
        self.refine_walk = bool(refine_walk)
        self.silhouette_mesh_test = bool(silhouette_mesh_test)
        # edge neighbours for the walks to the triangle a ray crosses (refinement, silhouette test)
        walk = self.refine_surface and self.refine_walk
        self._nbr = triangle_neighbours(scene.tri_p) if (walk or self.silhouette_mesh_test) \
            else np.zeros((0, 3), np.int32)
        self._nbr_refine = self._nbr if walk else np.zeros((0, 3), np.int32)
        self._tri_obj = np.ascontiguousarray(scene.tri_object, np.int64)
        self.silhouette_rays = bool(silhouette_rays)
        if not (isinstance(silhouette_rel_depth, (int, float)) and 0.0 < float(silhouette_rel_depth) <= 10.0):
            raise InvalidInputError("silhouette_rel_depth must be a number in (0, 10]")
        self.silhouette_rel_depth = float(silhouette_rel_depth)
        self.warp_options = dict(warp_options or {})
        bad = set(self.warp_options) - {"min_cos", "max_footprint", "footprint_scale", "hole_rel_depth",
                                         "hole_neighbors"}
        if bad:
            raise InvalidInputError(f"unknown warp options {sorted(bad)}")
        self._accel = None
        self._trace_args = None
        self._lock = threading.Lock()
        # kernel tables built once per renderer (the LDC, LLF and scene are immutable)
        self._axes = _ldc_axes(ldc)
        # per axis (geo, nrm, material, diffuse, visibility, triangle) for _shade_hits
        self._shade_axes = tuple(x for ax in self._axes for x in (ax[8], ax[9], ax[10], ax[12], ax[13], ax[14]))
        self._bounds = scene.bounds
        self._hp = highlight_params(scene, self.area_light_samples, self.seed)
        self._gp = gather_params(scene, llf) if llf is not None else _no_gather_params(scene)
        mt = scene.materials
        self._has_ks = (np.any(mt.ks > 0, axis=1) & (mt.shininess > 0))
        self._has_kr = np.any(mt.kr > 0, axis=1)
        self._has_kg = np.any(mt.kg > 0, axis=1)

    # ------------------------------------------------------------------ resources
    @property
    def accel(self):
        if self._accel is None:
            from engine.newviews.ibrt import build_accel

            self._accel = build_accel(self.ldc)
        return self._accel

    @property
    def caster(self) -> RayCaster:
        if self._caster is None:
            self._caster = make_caster(self.scene, "embree")
        return self._caster

    @property
    def nbytes(self) -> int:
        n = self.ldc.nbytes + (self.llf.nbytes if self.llf is not None else 0)
        if self._accel is not None:
            n += self._accel.nbytes
            if self._trace_args is not None:
                from engine.newviews.ibrt import trace_nbytes

                n += trace_nbytes(self._trace_args, self._accel)
        return int(n)

    # ------------------------------------------------------------------ helpers
    def _hole_rays(self, cam: tuple, w) -> np.ndarray:
        """The hole pixels worth a ray: covered pixels flagged as holes (a far surface seen
        through a crack), and uncovered pixels within ``hole_search_px`` of a covered one whose
        ray meets the scene's bounds. An uncovered pixel farther from every splat is background:
        any LDC sample its ray could meet would have been splatted within about a pixel of it
        (the image-based ray tracer finds nothing the warp doesn't have). ``None``: every hole."""
        hm = w.hole_mask
        if self.hole_search_px is not None:
            covered = w.sample_axis >= 0
            r = self.hole_search_px
            near = _near_covered(covered, r) if r else covered
            hm = hm & near
        pix = np.flatnonzero(hm.reshape(-1))
        if self.hole_search_px is None or not pix.size:
            return pix
        lo, hi = self._bounds
        pad = float(self.ldc.h)
        keep = _rays_meet_box(pix, cam, np.asarray(lo, np.float64) - pad,
                              np.asarray(hi, np.float64) + pad)
        return pix[keep]

    # ------------------------------------------------------------------ render
    def render(self, camera: CameraParams, method: str, *, ibrt_generations: int = 0,
               progress: Callable[[float, str], None] | None = None, force_all_passes: bool = False,
               fill: str = "ibrt", supersample: int = 1) -> LDCRenderResult:
        """Render ``camera`` with ``method`` ("ldc", "ldc+llf", "ldc+ibrt" (+ ``ibrt_generations``
        0..8) or "ldc+ibrt:k"); see the module docstring. ``supersample`` s (1..4) renders s x s
        samples per pixel on a regular grid and box-filters the radiance (antialiasing, s^2 the
        work); depth, normal, ids and provenance are those of the sample nearest the pixel
        centre, counts are summed. Raises InvalidInputError for a bad method / fill /
        supersample or when the method needs an LLF the bake doesn't have."""
        method, k = parse_method(method, ibrt_generations)
        if fill not in FILLS:
            raise InvalidInputError(f"fill must be one of {list(FILLS)}, got {fill!r}")
        if not isinstance(supersample, (int, np.integer)) or isinstance(supersample, bool) or \
                not (1 <= supersample <= 4):
            raise InvalidInputError(f"supersample must be an integer in [1, 4], got {supersample!r}")
        with self._lock:
            if supersample == 1:
                return self._render(camera, method, k, progress, bool(force_all_passes), fill)
            s = int(supersample)
            big = replace(camera, width=camera.width * s, height=camera.height * s)
            r = self._render(big, method, k, progress, bool(force_all_passes), fill)
            H, W = camera.height, camera.width
            rad = r.radiance.astype(np.float64).reshape(H, s, W, s, 3).mean(axis=(1, 3)).astype(np.float32)
            c = s // 2

            def pick(a: np.ndarray) -> np.ndarray:
                return np.ascontiguousarray(a[c::s, c::s])

            r.plan["supersample"] = s
            r.counts["supersample"] = s
            return LDCRenderResult(radiance=rad, depth=pick(r.depth), normal=pick(r.normal),
                                   object_id=pick(r.object_id), material_id=pick(r.material_id),
                                   provenance=pick(r.provenance),
                                   hole_mask=r.hole_mask.reshape(H, s, W, s).any(axis=(1, 3)),
                                   timings=r.timings, counts=r.counts, plan=r.plan)

    def _render(self, camera, method, k, progress, force, fill) -> LDCRenderResult:
        t_start = time.perf_counter()
        sc, ldc = self.scene, self.ldc
        timings: dict[str, float] = {}
        counts: dict[str, int] = {}
        passes: dict[str, dict] = {}

        def report(frac: float, stage: str) -> None:
            if progress is not None:
                progress(frac, stage)

        cam = self._camera_tuple(camera)  # the camera as the kernels take it (one basis per render)
        # ---- 1. warp
        w = warp_ldc(ldc, camera, fill="none", radiance_dtype=np.float64, **self.warp_options)
        timings["warp"] = w.timings["splat"] + w.timings["resolve"]
        timings["holes"] = w.timings["holes"]
        H, W = camera.height, camera.width
        radiance = w.radiance.reshape(-1, 3)  # float64, this render's own
        # the warp's images are this render's own: updated in place (flat views)
        depth = w.depth.reshape(-1)
        normal = w.normal.reshape(-1, 3)
        obj_id = w.object_id.reshape(-1)
        mat_id = w.material_id.reshape(-1)
        prov = w.provenance.reshape(-1)
        s_axis = w.sample_axis.reshape(-1)
        s_idx = w.sample_index.reshape(-1)
        s_side = w.sample_side.reshape(-1)
        passes["warp"] = {"ran": True, "why": "always: the LDC's view-independent radiance"}
        counts["warped_pixels"] = int((prov == PROV_WARPED).sum())
        counts["hole_pixels"] = w.n_holes
        report(0.3, "warp")

        # ---- 2. holes
        t0 = time.perf_counter()
        holes = self._hole_rays(cam, w)
        counts["hole_rays"] = int(holes.size)
        n_holes = int(holes.size)
        sil = np.zeros(0, np.int64)
        if self.silhouette_rays and fill != "none":
            # pixels at visibility edges are resolved by their own eye ray too (module docstring)
            is_hole = np.zeros(H * W, np.bool_)
            is_hole[holes] = True
            sil = _silhouette_pixels(obj_id, depth, s_side, is_hole, H, W, self.silhouette_rel_depth)
            sil_obj = obj_id[sil].copy()
            holes = np.concatenate([holes, sil])
        counts["silhouette_rays"] = int(sil.size)
        filled = 0
        rc_pix = np.zeros(0, np.int64)  # pixels filled by the raycast fill (no LDC sample)
        rc_surf = None
        if fill != "none" and holes.size:
            o, d = _pixel_rays(holes, cam)
            if fill == "ibrt":
                counts["silhouette_mesh_hits"] = 0
                if sil.size and self.silhouette_mesh_test:
                    # Silhouette pixels: the mesh test decides first, from the triangles of the warp's
                    # 3x3 winners the pixel ray crosses (docs/ldc.md); only the pixels where the ray
                    # crosses none of them take an image-based ray (whose answer is within a cell of
                    # the silhouette anyway). Hole pixels always take one.
                    h_axis = np.full(holes.size, -1, np.int8)
                    h_sample = np.full(holes.size, -1, np.int64)
                    h_t = np.full(holes.size, np.inf)
                    sl = slice(n_holes, None)
                    counts["silhouette_mesh_hits"] = int(_silhouette_mesh_test(
                        sil, o[sl], d[sl], h_axis[sl], h_sample[sl], h_t[sl], s_axis, s_idx, W, H, self._axes[0][14],
                        self._axes[1][14], self._axes[2][14], sc.tri_p, sc.tri_ng, self._tri_obj, self._nbr,
                        2.0 * float(ldc.h)))
                    ray = np.concatenate([np.arange(n_holes), n_holes + np.flatnonzero(h_axis[sl] < 0)])
                    r_axis, r_sample, r_t, n_steps, _ = self._trace(o[ray], d[ray])
                    h_axis[ray], h_sample[ray], h_t[ray] = r_axis, r_sample, r_t
                    counts["fill_ibrt_rays"] = int(ray.size)
                else:
                    h_axis, h_sample, h_t, n_steps, _ = self._trace(o, d)
                    counts["fill_ibrt_rays"] = int(holes.size)
                counts["fill_ibrt_steps"] = n_steps
                # the warp's (covered) value is replaced by the ray's answer: a sample, or the background
                _clear_pixels(holes, np.asarray(ldc.background, np.float64), radiance, depth, normal, obj_id, mat_id,
                              prov, s_axis, s_idx)
                for a, (_, _, _, _, _, _, _, _, geo, nrm, mat_a, obj_a, diff, _, _) in enumerate(self._axes):
                    _fill_from_hits(a, holes, h_axis, h_sample, h_t, d, geo, nrm, mat_a, obj_a, diff, radiance, depth,
                                    normal, obj_id, mat_id, prov, s_axis, s_idx, s_side)
                filled = int(np.count_nonzero(h_axis[:n_holes] >= 0))
            else:
                # the warp's (covered) value is replaced by the ray's answer
                _clear_pixels(holes, np.asarray(ldc.background, np.float64), radiance, depth, normal, obj_id, mat_id,
                              prov, s_axis, s_idx)
                rc_pix, rc_surf = self._raycast_fill(o, d, holes, radiance, depth, normal, obj_id, mat_id, prov)
                filled = int(np.count_nonzero(prov[holes[:n_holes]] == PROV_FILLED))
        timings["fill"] = time.perf_counter() - t0
        counts["filled_pixels"] = filled
        # hole rays that met nothing: background the warp could not tell from a hole (most of
        # ``hole_pixels`` is uncovered background next to silhouettes; Embree agrees, docs/ldc.md)
        counts["hole_ray_misses"] = int(n_holes - filled) if fill != "none" else 0
        # silhouette pixels whose own ray showed another object (or nothing) than the splats did
        counts["silhouette_changed"] = int(np.count_nonzero(obj_id[sil] != sil_obj)) if sil.size else 0
        passes["fill"] = {"ran": bool(fill != "none" and holes.size), "how": fill,
                          "why": (f"{n_holes} hole pixels, {sil.size} silhouette pixels" if holes.size
                                  else "no holes, no silhouettes")}
        report(0.5, "fill")

        # ---- 3. view-dependent pass: one fused kernel over the selected pixels
        t0 = time.perf_counter()
        nondiffuse = self._has_ks | self._has_kr | self._has_kg
        want_vp = force or self.plan.needs_view_pass
        reflect = method != "ldc"
        refl_mat = self._has_kr | self._has_kg
        want_rf = want_vp and reflect
        if want_rf and self.llf is None:
            covered = obj_id >= 0
            if force or np.any(covered & refl_mat[np.where(covered, mat_id, 0)]):
                if force and not self.plan.needs_llf:
                    want_rf = False
                    passes["gather_note"] = {"why": "forced, but there is no LLF to gather from"}
                else:
                    raise InvalidInputError(f"method {method!r} needs the bake's LLF (the scene has glossy or mirror "
                                            "materials) but this bake has none; use method 'ldc' or rebake with an "
                                            "LLF")
        vp_pix, n_hl, n_rf = _select_view_pass(obj_id, mat_id, self._has_ks, refl_mat, bool(want_vp), bool(want_rf),
                                               force)
        counts["view_pass_pixels"] = int(vp_pix.size)
        counts["highlight_pixels"] = int(n_hl)
        counts["reflection_pixels"] = int(n_rf)
        why_vp = ("forced on every covered pixel" if force else
                  ("the plan has non-diffuse materials" if self.plan.needs_view_pass
                   else "skipped: every material is diffuse"))
        trace_mirror = method == "ldc+ibrt" and k > 0
        nv = vp_pix.size
        lookups = np.zeros(nv, np.int64)
        nr = nv if (trace_mirror and n_rf) else 0
        ray_o, ray_d, ray_ng, ray_thr = (np.empty((nr, 3)) for _ in range(4))
        ray_live = np.zeros(nr, np.bool_)
        gathered_mat = self._has_kg if trace_mirror else refl_mat
        if nv:
            if rc_surf is not None:
                rc_row = np.full(H * W, -1, np.int64)
                rc_row[rc_pix] = np.arange(rc_pix.size)
                rc_p, rc_ng, rc_ns, rc_mat, rc_bits = rc_surf
                if rc_bits.shape[1] != ldc.visibility_words:
                    rc_bits = np.zeros((rc_pix.size, ldc.visibility_words), np.uint64)
            else:
                rc_row = np.zeros(0, np.int64)
                rc_p = rc_ng = rc_ns = np.zeros((0, 3))
                rc_mat = np.zeros(0, np.int32)
                rc_bits = np.zeros((0, ldc.visibility_words), np.uint64)
            vp_axes = []
            for org, fu, fv, fw, h, nu, spix, dep, geo, nrm, mat_a, _, _, vis2, prim in self._axes:
                vp_axes += [org, fu, fv, fw, h, nu, spix, dep, geo, nrm, mat_a, vis2, prim]
            _view_pass_kernel(_groups(), rc_surf is not None, vp_pix, s_axis, s_idx, s_side, rc_row,
                              np.ascontiguousarray(rc_p, np.float64), np.ascontiguousarray(rc_ng, np.float64),
                              np.ascontiguousarray(rc_ns, np.float64), np.ascontiguousarray(rc_mat, np.int32),
                              np.ascontiguousarray(rc_bits, np.uint64), cam, self.refine_surface, self._nbr_refine,
                              float(ldc.h), sc.tri_p, sc.tri_n, sc.tri_ng, self._has_ks, refl_mat, gathered_mat,
                              bool(want_vp), bool(want_rf), force, not trace_mirror, nr > 0, self._hp, self._gp,
                              radiance, normal, prov, lookups, ray_o, ray_d, ray_ng, ray_thr, ray_live, *vp_axes)
        # the fused kernel does surface records, refinement, highlights and the gather: all in "surfaces"
        timings["surfaces"] = time.perf_counter() - t0
        timings["highlights"] = 0.0
        timings["gather"] = 0.0
        passes["highlights"] = {"ran": bool(n_hl), "why": why_vp, "pixels": int(n_hl)}
        report(0.6, "highlights")
        counts["gather_lookups"] = int(lookups.sum())
        # provenance is at most PROV_FILLED before this pass: the gathered ones were set by the kernel
        counts["gather_pixels"] = int(np.count_nonzero(prov[vp_pix] == PROV_GATHERED)) if n_rf else 0
        passes["gather"] = {"ran": bool(n_rf),
                            "what": ("glossy lobe" if trace_mirror else "mirror cone + glossy lobe"),
                            "why": ("method 'ldc' has no reflections" if not reflect else why_vp)}
        report(0.75, "gather")

        t0 = time.perf_counter()
        counts["traced_rays"] = 0
        counts["ibrt_steps"] = 0
        if nr:
            # the mirror rays in 16 x 16 pixel tiles (``_tile_order``), the view pass's pixels row-major
            live = np.flatnonzero(ray_live)
            live = live[_tile_order(vp_pix[live], W, _RAY_TILE)]
            traced = vp_pix[live]
            self._trace_mirrors(traced, ray_o[live], ray_d[live], ray_ng[live], ray_thr[live], k, radiance, counts,
                                force)
            prov[traced[self._has_kr[mat_id[traced]]]] = PROV_TRACED
        timings["ibrt"] = time.perf_counter() - t0
        passes["ibrt"] = {"ran": bool(trace_mirror and n_rf), "generations": k,
                          "why": ("method is not ldc+ibrt:k with k >= 1" if not trace_mirror else why_vp)}
        report(0.95, "ibrt")

        out = np.empty((H, W, 3), np.float32)
        if _to_f32_count_nonfinite(radiance, depth, out.reshape(-1, 3)):
            raise NonFiniteOutputError("LDC render produced non-finite values")
        timings["total"] = time.perf_counter() - t_start
        plan = {"method": method if method != "ldc+ibrt" else f"ldc+ibrt:{k}", "ibrt_generations": k, "fill": fill,
                "refine_surface": self.refine_surface, "refine_walk": self.refine_surface and self.refine_walk,
                "silhouette_rays": self.silhouette_rays and fill != "none",
                "silhouette_mesh_test": self.silhouette_mesh_test and self.silhouette_rays and fill == "ibrt",
                "force_all_passes": force, "passes": passes, "effects": self.plan.to_dict(),
                "non_diffuse_materials": [int(i) for i in np.flatnonzero(nondiffuse)]}
        report(1.0, "done")
        return LDCRenderResult(radiance=out, depth=depth.reshape(H, W).astype(np.float32, copy=False),
                               normal=normal.reshape(H, W, 3).astype(np.float32, copy=False),
                               object_id=obj_id.reshape(H, W).astype(np.int32, copy=False),
                               material_id=mat_id.reshape(H, W).astype(np.int32, copy=False),
                               provenance=prov.reshape(H, W).astype(np.uint8, copy=False), hole_mask=w.hole_mask,
                               timings=timings, counts=counts, plan=plan)

    def _raycast_fill(self, o, d, holes, radiance, depth, normal, obj_id, mat_id, prov):
        """Interim fill: Embree rays against the triangles, shaded with the bake's diffuse model."""
        sc, ldc = self.scene, self.ldc
        caster = self.caster
        hit = caster.intersect(o, d)
        ok = hit.prim >= 0
        pix = holes[ok]
        if not pix.size:
            return pix, None
        p, ng, ns = surface_attributes(sc, hit.prim[ok], hit.u[ok], hit.v[ok])
        mat = sc.tri_material[hit.prim[ok]].astype(np.int32)
        occl = np.asarray(ldc.plan.get("occludable_lights", [True] * sc.lights.count), dtype=np.bool_)
        store = ldc.visibility_words > 0
        rad, vis, _ = shade_samples(sc, caster, p, ng, ns, mat, occl, store_bits=store,
                                    area_light_samples=self.area_light_samples, seed=self.seed, stream_id=3)
        side = (np.einsum("ij,ij->i", ng, d[ok]) >= 0).astype(np.int64)
        r = np.arange(side.shape[0])
        sg = np.where(side == 0, 1.0, -1.0)[:, None]
        g = ng * sg
        n = ns * sg
        n = np.where((np.einsum("ij,ij->i", n, g) > 0)[:, None], n, g)
        radiance[pix] = rad[r, side]
        depth[pix] = hit.t[ok]
        normal[pix] = n
        obj_id[pix] = sc.tri_object[hit.prim[ok]]
        mat_id[pix] = mat
        prov[pix] = PROV_FILLED
        bits = vis[r, side] if store else np.zeros((pix.size, 0), np.uint64)
        return pix, (p, g, n, mat, bits)

    def _camera_tuple(self, camera: CameraParams) -> tuple:
        right, up, fwd = camera.basis()
        th = float(np.tan(np.radians(camera.fov_y_deg) * 0.5))
        px_size = 2.0 * math.tan(math.radians(camera.fov_y_deg) * 0.5) / camera.height
        return (camera.kind == "orthographic", np.asarray(camera.eye, np.float64), right, up, fwd, int(camera.width),
                int(camera.height), th, camera.width / camera.height, 0.5 * camera.ortho_height, px_size,
                camera.ortho_height / camera.height)

    def _trace(self, o: np.ndarray, d: np.ndarray, origin_normals: np.ndarray | None = None):
        """(axis, sample, t, n_steps, n_tests) of rays o + t d (d unit) through the LDC."""
        from engine.newviews.ibrt import trace_args, trace_prepared

        if self._trace_args is None:
            self._trace_args = trace_args(self.ldc)
        return trace_prepared(self.ldc, self._trace_args, self.accel, np.ascontiguousarray(o, np.float64),
                              np.ascontiguousarray(d, np.float64), origin_normals=origin_normals)

    def _trace_mirrors(self, pix, o, d, ng_o, thr, k, radiance, counts, force) -> None:
        """k generations of image-based mirror rays (origins o, unit directions d, surface
        normals ng_o at the origins, throughput thr = kr) ending in the cone gather (module
        docstring); adds the traced radiance to ``radiance[pix]``."""
        ldc = self.ldc
        bg = np.asarray(ldc.background, np.float64)
        owner = np.arange(pix.size)
        acc = np.zeros((pix.size, 3))
        for gen in range(1, k + 1):
            n = owner.size
            if not n:
                break
            h_axis, h_sample, h_t, n_steps, _ = self._trace(o, d, ng_o)  # leaves the surface it starts on
            counts["traced_rays"] += int(n)
            counts["ibrt_steps"] += n_steps
            last = gen == k
            lookups = np.zeros(n, np.int64)
            cont = np.zeros(n, np.bool_)
            m = 0 if last else n
            n_o, n_d, n_ng, n_thr = (np.empty((m, 3)) for _ in range(4))
            sc = self.scene
            gather_mat = (self._has_kg | self._has_kr) if last else self._has_kg
            _shade_hits(_groups(), h_axis, h_sample, h_t, o, d, owner, thr, bg, last, self.llf is not None,
                        gather_mat, force, self._hp, self._gp, acc, lookups, cont, n_o, n_d, n_ng, n_thr, sc.tri_p,
                        sc.tri_n, sc.tri_ng, self._nbr_refine, float(ldc.h), *self._shade_axes)
            counts["gather_lookups"] += int(lookups.sum())
            if last:
                break
            nxt = np.flatnonzero(cont)
            owner = owner[nxt]
            o, d, ng_o, thr = n_o[nxt], n_d[nxt], n_ng[nxt], n_thr[nxt]
        radiance[pix] += acc


def _groups() -> int:
    """Parallel groups for the fused kernels: one per numba thread."""
    return max(1, int(nb.get_num_threads()))


__all__ = ["FILLS", "LDCRenderResult", "LDCViewRenderer", "PROV_FILLED",
           "PROV_GATHERED", "PROV_NONE", "PROV_TRACED", "PROV_WARPED", "parse_method"]
