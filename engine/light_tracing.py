"""Light tracing of caustics for the reference renderer: paths from the rect lights through
mirror / glossy lobes to the diffuse surfaces the camera sees, splatted into the image.

Why. A diffuse surface lit through a mirror or a glossy surface (light -> mirror / glossy ... ->
diffuse -> camera) is what path tracing from the camera finds worst: its paths must leave in the
few directions that see the light's image in the mirror. On the mirror / glossy Cornell box those
paths are 98 % of a path-traced render's variance, and a ground truth stopped at its 135 s budget
kept a noise floor of 6.9 % where the Cornell box's reaches 1 % (docs/accuracy/gi.md, "Where the
mirror / glossy box's noise comes from"). Traced from the light the same light is easy: every path
aimed at the mirror lands somewhere on the walls. Unlike the caustic photon map of the bakes
(engine/caustics.py), nothing is blurred: each light path's last vertex is joined to the camera and
adds its exact contribution to the pixel it projects to, so the sum is unbiased and a ground truth
rendered this way converges to the path tracer's mean (Veach's light tracing; the "t = 1"
strategy of bidirectional path tracing).

The split of path space (no path counted twice, none lost). With D a vertex's diffuse lobe and S
its mirror or glossy lobe, the camera side (``engine.reference``) leaves out every path
E D+ S+ L: a direct camera hit, diffuse path vertices, then mirror / glossy vertices only, then a
rect light, whether the light is met by the last mirror / glossy ray or by the glossy lobe's
next-event estimation (rays of such paths carry the ``LIGHT_TRACED`` flag of their kind). This
module traces exactly those paths from the light: a point on a rect light (by power) joined to a
point on a mirror / glossy triangle (by area; ``engine.caustics.emit_photons``), one or more mirror /
glossy bounces, then diffuse bounces, and every vertex with a diffuse lobe after at least one
mirror / glossy one is joined to the camera. The bounce budget is the camera side's: a path of
s mirror / glossy and d diffuse vertices before the one joined to the camera is counted when
s + d <= ``indirect_bounces`` (the camera's diffuse paths have that many vertices after the
camera hit). Lobes are picked by their mean albedos as the path tracer picks them (unbiased:
each lobe's weight is divided by its probability).

Weights (area measure, shading normals as the camera side uses them). A light path's weight after
a vertex x with incoming direction wi (toward the light) and sampled outgoing wo is multiplied by
f(wi, wo) cos_s(wi) / cos_g(wi) * cos_g(wo) / pdf(wo), the camera side's integrand (BSDF times the
shading-normal cosine of the light's direction) over the light side's density: mirror
kr cos_g(wo) / cos_g(wi); glossy (cos^g lobe around the mirror direction of wi)
kg (g+2)/(g+1) cos_s(wi) / cos_g(wi) cos_g(wo); diffuse (cosine around the shading normal)
kd cos_s(wi) / cos_g(wi) cos_g(wo) / cos_s(wo). The join to a pinhole camera at distance r, seen at
angle theta_c from the optical axis, adds to its pixel (of area A on the image plane at distance 1)
w kd / pi cos_s(wi) / cos_g(wi) cos_g(x -> eye) / (r^2 cos^3 theta_c A): the box-filtered pixel
value the camera's rays estimate, written over the surface's area. A join is kept only when the
segment to the eye is clear and no rect light shows its emitting side to the eye in front of the
point (the camera ray would end there).

Lights in the way. The camera side's mirror / glossy rays end where they meet a rect light's
emitting side; its diffuse rays pass through lights. A light-path segment that passes a light
whose emitting side faces the segment's far end is therefore followed on only through a diffuse
lobe there (``through_light``).

Sampling: the engine's Owen-scrambled Sobol sampler (engine/sampler.py), light path i being sample
i of "pixel" 0 in each dimension, keyed by the render's seed and the half buffer (``stream``).
Deterministic for a seed, whatever the threads: every path is independent, and the joins are added
to the image serially in the paths' order. Point and directional lights have no caustics (no ray
meets them, as in the reference renderer); orthographic cameras are not joined to (the camera side
then keeps every path, ``applies``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.caustics import PhotonSources, emit_photons, has_caustics, passes_light_toward_origin, photon_sources
from engine.path_vertex import (
    DIM_LOBE,
    INV_PI,
    _camera_frame,
    _dot,
    _lobe_direction,
    _offset_mag,
    _rect_light_t,
    _surface_frame,
)
from engine.raycast import SHADOW_SHORTEN, RayCaster
from engine.sampler import derive_key, sample_1d, sample_key
from engine.scene import CameraParams, RuntimeScene
from engine.sched import run_pieces_parallel

__all__ = ["BATCH", "CausticLightTracer", "applies", "light_tracer"]

_STREAM = 24
"""The sampler stream of light paths: sample_key(seed, _STREAM, half), apart from every other
stream of the engine (caustic photons use 4, LDC glossy rays 23)."""

BATCH = 1 << 18
"""Light paths traced together (bounded memory: about 300 bytes of arrays per path; a 512 x 512
render of the mirror / glossy box peaked 19 MiB higher with light paths than without)."""

_MIN_ITEMS = 4096


def _may_apply(scene: RuntimeScene, camera: CameraParams, indirect_samples: int) -> bool:
    """A pinhole camera, indirect paths and a diffuse surface: what ``applies`` needs besides caustics."""
    return (camera.kind == "perspective" and indirect_samples > 0 and scene.n_triangles > 0
            and bool(np.any(scene.materials.kd[scene.tri_material] > 0.0)))


def applies(scene: RuntimeScene, camera: CameraParams, indirect_samples: int) -> bool:
    """Are some paths of this render light-traced? A pinhole camera, indirect paths, and light that
    can reach a diffuse surface through a mirror or a glossy lobe (``engine.caustics.has_caustics``:
    a rect light that emits and mirror / glossy triangles)."""
    return _may_apply(scene, camera, indirect_samples) and has_caustics(scene)


def light_tracer(scene: RuntimeScene, caster: RayCaster, camera: CameraParams, indirect_samples: int, bounces: int,
                 seed: int) -> CausticLightTracer | None:
    """The render's tracer, None where ``applies`` says no (the scene's photon sources are built once)."""
    if not _may_apply(scene, camera, indirect_samples):
        return None
    src = photon_sources(scene)
    return None if src is None else CausticLightTracer(scene, caster, camera, src, bounces, seed)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _light_vertex(lo, hi, prim, bu, bv, d, w, pid, n_spec, n_diff, through, key, vertex, bounces, kd, kr, kg, gexp,
                  tri_p, tri_n, tri_ng, tri_mat, center, extent, cam, rc, ru, rv, r_n, r_area, r2s,
                  j_o, j_d, j_tmax, j_pix, j_c, j_ok, o_out, d_out, d32_out, w_out, ns_out, nd_out, alive):
    """Light path i at its hit (triangle ``prim``, barycentrics, arriving along ``d`` with weight
    ``w`` after ``n_spec`` mirror / glossy and ``n_diff`` diffuse vertices): its join to the camera
    (``j_*``: shadow ray, pixel, contribution, ``j_ok``) and its next ray (``*_out``, ``alive``).
    ``cam``: eye (3), right (3), up (3), forward (3), x scale, y scale, width, height, 1 / pixel area."""
    width = int(cam[14])
    height = int(cam[15])
    for i in range(lo, hi):
        j_ok[i] = False
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
        cos_gi = -_dot(g0, g1, g2, d0, d1, d2)
        cos_si = -_dot(n0, n1, n2, d0, d1, d2)
        if not cos_gi > 0.0:
            continue
        ns = n_spec[i]
        nd = n_diff[i]
        has_kd = kd[m, 0] > 0.0 or kd[m, 1] > 0.0 or kd[m, 2] > 0.0
        mag = _offset_mag(p0, p1, p2, center, extent)
        # ---- the join to the camera: this vertex as the camera's direct hit, its diffuse lobe
        if ns >= 1 and ns + nd <= bounces and has_kd and cos_si > 0.0:
            e0, e1, e2 = cam[0] - p0, cam[1] - p1, cam[2] - p2
            dist = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            cz = -(e0 * cam[9] + e1 * cam[10] + e2 * cam[11])
            if dist > 0.0 and cz > 0.0:
                cos_ge = _dot(g0, g1, g2, e0, e1, e2) / dist
                sx = -(e0 * cam[3] + e1 * cam[4] + e2 * cam[5]) / cz
                sy = -(e0 * cam[6] + e1 * cam[7] + e2 * cam[8]) / cz
                fx = 0.5 * (sx / cam[12] + 1.0) * width
                fy = 0.5 * (1.0 - sy / cam[13]) * height
                if cos_ge > 0.0 and 0.0 <= fx < width and 0.0 <= fy < height:
                    # a rect light showing its emitting side to the eye in front of the point hides it
                    hidden = False
                    for q in range(rc.shape[0]):
                        tq = _rect_light_t(cam[0], cam[1], cam[2], -e0 / dist, -e1 / dist, -e2 / dist, rc[q, 0],
                                           rc[q, 1], rc[q, 2], ru[q, 0], ru[q, 1], ru[q, 2], rv[q, 0], rv[q, 1],
                                           rv[q, 2], r_n[q, 0], r_n[q, 1], r_n[q, 2], r_area[q], r2s[q])
                        if not (dist < tq * (1.0 - SHADOW_SHORTEN)):
                            hidden = True
                    if not hidden:
                        cos_c = cz / dist
                        f = INV_PI * cos_si / cos_gi * cos_ge / (dist * dist * cos_c * cos_c * cos_c) * cam[16]
                        j_c[i, 0] = w[i, 0] * kd[m, 0] * f
                        j_c[i, 1] = w[i, 1] * kd[m, 1] * f
                        j_c[i, 2] = w[i, 2] * kd[m, 2] * f
                        j_o[i, 0] = p0 + mag * g0 - center[0]
                        j_o[i, 1] = p1 + mag * g1 - center[1]
                        j_o[i, 2] = p2 + mag * g2 - center[2]
                        j_d[i, 0], j_d[i, 1], j_d[i, 2] = e0 / dist, e1 / dist, e2 / dist
                        j_tmax[i] = max(dist * (1.0 - SHADOW_SHORTEN) - mag, 0.0)
                        j_pix[i] = min(int(fy), height - 1) * width + min(int(fx), width - 1)
                        j_ok[i] = True
        # ---- the next vertex: it must still be joinable within the bounce budget
        if ns + nd + 1 > bounces:
            continue
        ad = (kd[m, 0] + kd[m, 1] + kd[m, 2]) / 3.0 if (ns >= 1 and cos_si > 0.0) else 0.0
        ar = ag = 0.0
        if nd == 0 and not through[i]:  # mirror / glossy lobes: only before any diffuse vertex
            ar = (kr[m, 0] + kr[m, 1] + kr[m, 2]) / 3.0
            ag = (kg[m, 0] + kg[m, 1] + kg[m, 2]) / 3.0 if cos_si > 0.0 else 0.0
        tot = ad + ar + ag
        if not tot > 0.0:
            continue
        norm = max(1.0, tot)  # lobes that reflect more than all the light: pick among them only
        u = sample_1d(derive_key(key, vertex, DIM_LOBE), 0, pid[i]) * norm
        if u < ar:
            lb, scale = 0, norm / ar
        elif u < ar + ag:
            lb, scale = 1, norm / ag
        elif u < tot:
            lb, scale = 2, norm / ad
        else:
            continue  # absorbed
        # the mirror direction of wi = -d about the shading normal
        wr0, wr1, wr2 = d0 + 2.0 * cos_si * n0, d1 + 2.0 * cos_si * n1, d2 + 2.0 * cos_si * n2
        if lb != 2:
            lr = math.sqrt(wr0 * wr0 + wr1 * wr1 + wr2 * wr2)
            wr0, wr1, wr2 = wr0 / lr, wr1 / lr, wr2 / lr
        x0, x1, x2, _, _ = _lobe_direction(lb, key, vertex, 0, pid[i], 1.0, wr0, wr1, wr2, n0, n1, n2, gexp[m])
        ln = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        x0, x1, x2 = x0 / ln, x1 / ln, x2 / ln
        cos_go = _dot(g0, g1, g2, x0, x1, x2)
        if not cos_go > 0.0:
            continue
        if lb == 0:
            fk = cos_go / cos_gi
            f0, f1, f2 = kr[m, 0] * fk, kr[m, 1] * fk, kr[m, 2] * fk
        elif lb == 1:
            ge = gexp[m]
            fk = (ge + 2.0) / (ge + 1.0) * cos_si / cos_gi * cos_go
            f0, f1, f2 = kg[m, 0] * fk, kg[m, 1] * fk, kg[m, 2] * fk
        else:
            cos_so = _dot(n0, n1, n2, x0, x1, x2)
            if not cos_so > 0.0:
                continue
            fk = cos_si / cos_gi * cos_go / cos_so
            f0, f1, f2 = kd[m, 0] * fk, kd[m, 1] * fk, kd[m, 2] * fk
        o_out[i, 0] = p0 + mag * g0 - center[0]
        o_out[i, 1] = p1 + mag * g1 - center[1]
        o_out[i, 2] = p2 + mag * g2 - center[2]
        d_out[i, 0], d_out[i, 1], d_out[i, 2] = x0, x1, x2
        d32_out[i, 0], d32_out[i, 1], d32_out[i, 2] = x0, x1, x2
        w_out[i, 0], w_out[i, 1], w_out[i, 2] = w[i, 0] * f0 * scale, w[i, 1] * f1 * scale, w[i, 2] * f2 * scale
        ns_out[i] = ns + (1 if lb != 2 else 0)
        nd_out[i] = nd + (1 if lb == 2 else 0)
        alive[i] = w_out[i, 0] > 0.0 or w_out[i, 1] > 0.0 or w_out[i, 2] > 0.0


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _splat(out, rows, occ, pix, contrib):
    """out[pix] += contrib for the joins ``rows`` whose shadow ray is clear. Serial: joins share
    pixels, and the sums' order is the paths' order."""
    for k in range(rows.shape[0]):
        if not occ[k]:
            j = rows[k]
            q = pix[j]
            out[q, 0] += contrib[j, 0]
            out[q, 1] += contrib[j, 1]
            out[q, 2] += contrib[j, 2]


class CausticLightTracer:
    """The light-traced paths (E D+ S+ L, module docstring) of one render: ``trace`` adds light
    paths ``first .. first + count - 1`` of a stream to an image's sums; the image's estimate is
    those sums over the paths traced (``counts["light_paths"]``)."""

    def __init__(self, scene: RuntimeScene, caster: RayCaster, camera: CameraParams, src: PhotonSources,
                 bounces: int, seed: int):
        if camera.kind != "perspective":
            raise ValueError("light tracing joins light paths to a pinhole camera only")
        self.scene, self.caster, self.src, self.bounces, self.seed = scene, caster, src, int(bounces), int(seed)
        right, up, fwd, sxs, sys_ = _camera_frame(camera)
        pix_area = (2.0 * sxs / camera.width) * (2.0 * sys_ / camera.height)
        self._cam = np.concatenate([np.asarray(camera.eye, np.float64), right, up, fwd,
                                    [sxs, sys_, camera.width, camera.height, 1.0 / pix_area]])
        self.npix = camera.width * camera.height

    def trace(self, first: int, count: int, stream: int, out: np.ndarray, add_time: Callable[[str, float], None],
              counts: dict[str, int], serial: bool | None = None) -> None:
        """Light paths ``first`` .. ``first + count - 1`` of ``stream`` (0: a plain render and the
        progressive render's half A, 1: its half B) added to ``out`` (npix, 3), unnormalised;
        ``add_time(stage, seconds)`` collects the time (``light_tracing``: the kernels,
        ``light_tracing_rays``: Embree), ``counts`` the paths and rays."""
        key = sample_key(self.seed, _STREAM, int(stream))
        for b0 in range(first, first + count, BATCH):
            self._batch(key, b0, min(BATCH, first + count - b0), out, add_time, counts, serial)

    def _batch(self, key, first: int, n: int, out: np.ndarray, add_time: Callable[[str, float], None],
               counts: dict[str, int], serial: bool | None) -> None:
        sc, lt, mt, caster = self.scene, self.scene.lights, self.scene.materials, self.caster
        t0 = time.perf_counter()
        pid, d, prim, bu, bv, w, rays, t_rays = emit_photons(sc, caster, self.src, key, first, n, 1.0, serial)
        k = pid.size
        n_spec = np.zeros(k, np.int32)
        n_diff = np.zeros(k, np.int32)
        through = np.zeros(k, np.bool_)
        joins = 0
        for vertex in range(1, 2 * self.bounces + 2):
            if k == 0:
                break
            j_o = np.empty((k, 3), np.float32)
            j_d = np.empty((k, 3), np.float32)
            j_tmax = np.empty(k, np.float32)
            j_pix = np.empty(k, np.int64)
            j_c = np.empty((k, 3))
            j_ok = np.empty(k, np.bool_)
            o2 = np.empty((k, 3), np.float32)
            d2 = np.empty((k, 3))
            d2_32 = np.empty((k, 3), np.float32)
            w2 = np.empty((k, 3))
            ns2 = np.empty(k, np.int32)
            nd2 = np.empty(k, np.int32)
            alive = np.empty(k, np.bool_)
            run_pieces_parallel(_light_vertex, k, _MIN_ITEMS, serial, prim, bu, bv, d, w, pid, n_spec, n_diff,
                                through, key, vertex, self.bounces, mt.kd, mt.kr, mt.kg, mt.gloss_exponent, sc.tri_p,
                                sc.tri_n, sc.tri_ng, sc.tri_material, sc.center, sc.extent, self._cam,
                                lt.rect_corner, lt.rect_edge_u, lt.rect_edge_v, self.src.r_n, self.src.r_area,
                                lt.rect_two_sided, j_o, j_d, j_tmax, j_pix, j_c, j_ok, o2, d2, d2_32, w2, ns2, nd2,
                                alive)
            rows = np.flatnonzero(j_ok)
            t1 = time.perf_counter()
            jocc = caster.occluded_local(j_o[rows], j_d[rows], j_tmax[rows], serial)
            t_rays += time.perf_counter() - t1
            _splat(out, rows, jocc, j_pix, j_c)
            joins += int(rows.size)
            go = np.flatnonzero(alive)
            if go.size == 0:
                break
            t1 = time.perf_counter()
            prim, bu, bv = caster.intersect_local(o2[go], d2_32[go], serial)
            t_rays += time.perf_counter() - t1
            rays += int(go.size)
            # a segment that passes a light's emitting side seen from its far end: the camera side's
            # mirror / glossy ray along it would end there
            passed = passes_light_toward_origin(sc, self.src, o2[go], d2[go], prim, bu, bv, serial)
            hit = prim >= 0
            go = go[hit]
            prim, bu, bv, through = prim[hit], bu[hit], bv[hit], passed[hit]
            pid, d, w, n_spec, n_diff = pid[go], d2[go], w2[go], ns2[go], nd2[go]
            k = go.size
        total = time.perf_counter() - t0
        add_time("light_tracing_rays", t_rays)
        add_time("light_tracing", total - t_rays)
        counts["light_paths"] = counts.get("light_paths", 0) + n
        counts["light_rays"] = counts.get("light_rays", 0) + rays + joins
