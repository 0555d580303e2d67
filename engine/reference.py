"""Reference renderer: the yardstick every image-based method is measured against.

Whitted-style ray tracing with shadow rays, energy-normalised Phong highlights,
ideal-mirror recursion, glossy reflection by sampling the Phong lobe, rectangular
area lights by stratified sampling, box-filtered antialiasing, and an optional
path-traced indirect term. Organised as a wavefront: every stage handles a whole
batch of rays (Embree queries on arrays, numba kernels for shading), and the
image is processed in chunks so progress and cancellation get a say between them.

Shading model (ALGORITHMS.md, shared conventions), at a point with shading normal
n, direction to the viewer wo, mirror direction wr = reflect(wo, n):
- lights:   (kd/pi + ks (s+2)/(2 pi) max(0, wl.wr)^s) * E_l, with E_l the light's
            irradiance (I cos/d^2, E cos, or L_e cos cos'/d^2 dA), gated by a shadow ray;
- ambient:  kd * ambient (camera and specular chains only; path vertices skip it);
- emission: added where a camera or specular-chain ray lands (lights are the only
            sources of illumination: emission lights nothing by itself);
- mirror:   kr * L(wr);
- glossy:   kg * integral (g+2)/(2 pi) cos^g(angle(wi, wr)) L(wi) cos(theta_i) dwi,
            sampled with M directions from the cos^g lobe around wr;
- indirect: K diffuse paths per pixel (spread over the antialiasing samples), each
            with ``indirect_bounces`` bounces and next-event estimation at every vertex.
- rect lights seen: a camera ray, or a ray whose last lobe was mirror or glossy (at a camera
            chain hit or a path vertex), that meets a rect light's emitting side (either side if
            two-sided) before any surface ends there with weight x the light's radiance. So light
            reaches a diffuse surface through mirrors and glossy lobes (caustic paths: diffuse ->
            mirror -> light), the lights show in mirrors and glossy surfaces, and camera rays see
            them directly, as Mitsuba's area emitters are seen. A surface hides a light only when
            it is nearer by more than the shadow rays' margin (SHADOW_SHORTEN), so an emissive
            luminaire modelled at the light's place shows the light once. Diffuse path rays and
            shadow rays pass through lights (and so does every ray through a one-sided light's
            back): the diffuse lobe's light is next-event estimation's. A path vertex with no
            bounce left still sends its mirror / glossy ray when the scene has rect lights,
            counting only the light it meets, so every vertex gets the light of all its lobes and
            ``indirect_bounces`` B stays Mitsuba's ``path`` with ``max_depth`` B + 2.
            Point and directional lights cannot be met by a ray: they reach surfaces through kd
            and ks only, never through a mirror or a glossy lobe.

Multiple importance sampling: next-event estimation evaluates the kd and ks lobes, rays that
meet lights leave the camera and the kr lobe; those terms have one strategy each and are added
plainly. The kg lobe has both (next-event estimation evaluates it too, and its rays meet lights):
each side is weighted by the power heuristic over (sample count x density), so the weights sum to
one per direction and the sum stays unbiased (docs/reference-renderer.md, ``_light_rays`` and
``_rect_hits``; tests/engine/test_reference_mis.py). Russian roulette cuts path vertices past
RR_MIN_BOUNCES bounces with a survival probability from the path's throughput (``_spawn``).

Sampling: every sample value comes from engine/sampler.py (Owen-scrambled Sobol), keyed by
(seed, pixel, the sample's index among the pixel's samples, the dimension it serves): the pixel
position, each rect light's position at each vertex, the lobe choice and the BSDF direction at
each vertex. A ray carries its pixel, its sample index and its dimension key; a branch into B
rays numbers its children parent * B + b, so a pixel's samples of one dimension are one
stratified sequence. A render is bit-for-bit deterministic for a given seed, whatever the
number of threads, pipelines or chunks.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Protocol

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.camera import camera_rays, pixel_centers
from engine.error_region import emitter_pixels, region_around
from engine.errors import InvalidInputError, NonFiniteOutputError
from engine.light_tracing import CausticLightTracer, light_tracer
from engine.lights import directional_light_sample, point_light_sample, rect_cell_point, rect_light_sample
from engine.methods import REFERENCE
from engine.path_vertex import (
    DIM_DIR,
    DIM_LIGHT,
    DIM_LOBE,
    DIM_PIXEL,
    DIM_RR,
    INV_PI,
    KIND_BASE,
    KIND_CHAIN,
    KIND_PATH,
    KIND_SPEC,
    LIGHT_TRACED,
    _camera_frame,
    _dot,
    _lobe_dir,
    _lobe_direction,
    _mean_albedos,
    _mis_weight,
    _offset_mag,
    _rect_hits,
    _surface_frame,
)
from engine.progressive import pass_pieces, run_progressive
from engine.raycast import SHADOW_SHORTEN, RayCaster, make_caster
from engine.sampler import derive_key, sample_1d, sample_2d, sample_key
from engine.scene import CameraParams, RuntimeScene
from engine.sched import run_pieces_parallel
from engine.shading import phong_pow

_NO_LIT = np.zeros(0, np.bool_)  # "no ray ended on a rect light" for _accumulate_misses_and_emission
_NO_LIT_C = np.zeros((0, 3))

# a chain hit's children: their key is derive_key(key, vertex, BRANCH_*)
BRANCH_MIRROR = 10
BRANCH_GLOSSY = 11
BRANCH_DIFFUSE = 12

# how the kg lobe's light from rect lights is estimated (ReferenceRenderer(glossy_mis=...))
MIS_MODES = {"power": 0, "balance": 1, "light": 2, "bsdf": 3}
# Russian roulette: a path vertex that has used RR_MIN_BOUNCES bounces or more continues with
# probability min(1, max(throughput) / max(throughput at the path's first ray))
RR_MIN_BOUNCES = 3
# jittered samples per pixel that look for emitters seen through mirrors (ReferenceRenderer.error_region)
MIRROR_EMITTER_SPP = 16


@dataclass(frozen=True)
class ReferenceParams:
    """Reference renderer settings.

    spp: antialiasing samples per pixel (N), box filter: the first N points of the pixel's
        scrambled Sobol sequence (engine/sampler.py).
    pixel_jitter: True: those random, stratified positions (the box-filtered image); False: the
        centres of N equal-area cells (rows of ceil(sqrt(N)) or fewer cells; spp=1: the pixel
        centre, the image model of one point sample per pixel that the image-based methods
        render; used as their ground truth in bench/ldc_equal_error.py).
    max_depth: mirror / glossy recursion depth (0 = no reflections).
    glossy_samples: M lobe samples per glossy hit (only the first glossy bounce
        of a chain branches; deeper glossy bounces take one sample).
    area_light_samples: samples per rectangular light per shading point, on a g x g
        jittered grid with g = round(sqrt(value)); the jitter in each cell is stratified over the
        pixel's samples.
    indirect_samples: K indirect paths per pixel (0 = direct lighting only); the hits of the
        M rays of a first glossy bounce share one hit's paths (``_plan``).
    indirect_bounces: diffuse bounces per indirect path (>= 1).
    seed: random seed; equal seeds give identical images.
    chunk_pixels: upper bound on pixels per wavefront chunk (memory bound and progress
        granularity); images are split into at least 8 chunks of >= 1024 pixels.
    pipelines: chunks rendered concurrently in threads (kernels that release the GIL
        overlap with Embree calls); 1 = one chunk at a time, each kernel split over the
        thread pool (engine/sched.py). The image does not depend on it.
    max_error: progressive, adaptive rendering (engine/progressive.py) until the estimated LRMS
        against the converged image is at most this, in (0, 1); ``spp`` is then the cap on any
        pixel's samples. None (the default): a plain render of ``spp`` samples per pixel.
    max_ms: progressive rendering that stops when this many milliseconds of render time are
        spent, in (0, engine.methods.MAX_RENDER_MS] (the render job's timeout), alone or with
        ``max_error``; None: no time budget.
    light_paths: light paths per camera sample that bring the caustics the camera sees
        (engine/light_tracing.py): where light reaches a directly seen diffuse surface through
        mirror / glossy lobes (a pinhole camera, indirect paths, a rect light, mirror or glossy
        triangles), those paths are traced from the lights and joined to the camera, and the
        camera's paths leave them out; 0: the camera's paths find them too (unbiased either way,
        far noisier on a mirror scene: docs/reference-renderer.md).
    """

    spp: int = 4
    max_depth: int = 4
    glossy_samples: int = 16
    area_light_samples: int = 16
    indirect_samples: int = 0
    indirect_bounces: int = 2
    seed: int = 0
    chunk_pixels: int = 16384
    pipelines: int = 2
    pixel_jitter: bool = True
    max_error: float | None = None
    max_ms: float | None = None
    light_paths: float = 1.0

    def __post_init__(self) -> None:
        checks = {
            "spp": (1, 4096), "max_depth": (0, 64), "glossy_samples": (1, 4096),
            "area_light_samples": (1, 4096), "indirect_samples": (0, 1 << 16),
            "indirect_bounces": (1, 64), "chunk_pixels": (1, 1 << 22), "pipelines": (1, 64),
        }
        for name, (lo, hi) in checks.items():
            v = getattr(self, name)
            if not isinstance(v, int) or not (lo <= v <= hi):
                raise InvalidInputError(f"{name} must be an integer in [{lo}, {hi}], got {v!r}")
        REFERENCE.param("light_paths").check(self.light_paths)
        if not isinstance(self.pixel_jitter, bool):
            raise InvalidInputError(f"pixel_jitter must be true or false, got {self.pixel_jitter!r}")
        for name in ("max_error", "max_ms"):  # ranges: the registry's (engine/methods.py)
            if getattr(self, name) is not None:
                REFERENCE.param(name).check(getattr(self, name))
        if self.adaptive:
            if self.spp < 2:
                raise InvalidInputError(f"progressive rendering (max_error / max_ms) needs spp >= 2 (the cap on "
                                        f"each pixel's samples, split over two half buffers), got {self.spp}")
            if not self.pixel_jitter:
                raise InvalidInputError("progressive rendering (max_error / max_ms) needs pixel_jitter")

    @property
    def adaptive(self) -> bool:
        """True when a progressive, adaptive render is asked for (an error target or a time budget)."""
        return self.max_error is not None or self.max_ms is not None

    def to_dict(self) -> dict:
        """The settings as a dict; the progressive settings only when set (a plain render's
        description is what it was before they existed)."""
        d = asdict(self)
        for name in ("max_error", "max_ms"):
            if d[name] is None:
                del d[name]
        return d


@dataclass
class RenderOutput:
    """radiance (h, w, 3) float32 linear; depth (h, w) float32 distance along the pixel-centre
    ray (0 where nothing is hit); normal (h, w, 3) float32 world shading normal facing the
    camera; object_id / material_id (h, w) int32 (-1 where nothing is hit); timings in
    seconds per stage; counts of rays per kind; ``adaptive``: see below."""

    radiance: np.ndarray
    depth: np.ndarray
    normal: np.ndarray
    object_id: np.ndarray
    material_id: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    adaptive: dict[str, Any] | None = None
    """Progressive renders only (``max_error`` / ``max_ms``): the estimated error and how it was
    reached (``engine.progressive.AdaptiveReport`` as a dict); None for a plain render."""
    error_region: np.ndarray | None = None
    """Progressive renders only: (h, w) bool, the pixels the estimated error is over
    (:meth:`ReferenceRenderer.error_region`), for a caller that measures an error on them too;
    None for a plain render."""

    @property
    def coverage(self) -> np.ndarray:
        return self.object_id >= 0


class _Timer:
    def __init__(self) -> None:
        self.t: dict[str, float] = {}

    def add(self, name: str, dt: float) -> None:
        self.t[name] = self.t.get(name, 0.0) + dt


# ============================================================================ kernels
#
# Every kernel below is compiled once, serially, and releases the GIL; the batch kernels take the
# range ``lo .. hi - 1`` of their items and write only those items' outputs (rows of the output
# arrays that no other item writes), so ``engine.sched.run_pieces_parallel`` can run them on slices of
# a batch from its thread pool and the image does not depend on the split. A pipeline thread
# (``pipelines`` >= 2) calls them on the whole batch.

# fewest items per piece when a kernel is split over threads (a piece costs ~20-50 us to dispatch):
_MIN_HEAVY = 512  # per item: light samples or secondary rays (_light_rays, _spawn)
_MIN_ITEMS = 4096  # per item: a surface frame, a ray's rect-light test, a camera ray or a few
_MIN_COPY = 16384  # per item: a few loads and stores (_plan, compactions)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _surface(lo, hi, d, prim, u, v, tri_p, tri_n, tri_ng, p_out, ng_out, ns_out):
    """Hit point, and geometric / shading normals flipped to face the incoming ray."""
    for i in range(lo, hi):
        t = prim[i]
        w0 = 1.0 - u[i] - v[i]
        for k in range(3):
            p_out[i, k] = w0 * tri_p[t, 0, k] + u[i] * tri_p[t, 1, k] + v[i] * tri_p[t, 2, k]
        g0, g1, g2, s0, s1, s2 = _surface_frame(t, np.float64(u[i]), np.float64(v[i]), d[i, 0], d[i, 1], d[i, 2],
                                                tri_n, tri_ng)
        ng_out[i, 0], ng_out[i, 1], ng_out[i, 2] = g0, g1, g2
        ns_out[i, 0], ns_out[i, 1], ns_out[i, 2] = s0, s1, s2


# Per-vertex physics of the stages, one function per piece. They take scalars only: a jitted
# function called with arrays pays atomic reference counts on them at every call (on counters both
# cores share), and a call with more than 30 arguments compiles as a call with *args, which numba
# neither inlines nor passes cheaply.

@nb.njit(cache=True, error_model="numpy")
def _glossy_rays_sent(ad, ar, ag, kind, depth, bounces, max_depth, glossy_samples):
    """c_b: the glossy rays a hit sends (as ``_plan`` / ``_spawn`` decide), in expected count: M or 1
    at chain hits below ``max_depth``, the lobe's choice probability at path vertices, 0 without
    a glossy lobe (ag = 0)."""
    if not ag > 0.0:
        return 0.0
    if kind == KIND_CHAIN:
        if depth < max_depth:
            return np.float64(glossy_samples) if depth == 0 else 1.0
        return 0.0
    if not bounces > 0:
        ad = 0.0
    return ag / (ad + ar + ag)


@nb.njit(cache=True, error_model="numpy")
def _row_lobes(ca, has_spec, spec_cut, shin, rect, c_b, ge, tmax, mag, cos_l, area, gg, mis):
    """The Phong (ks) and glossy (kg) lobes' values toward one light sample, (fs, fg), with
    ``ca`` the cosine to the mirror direction. The kg lobe takes rect lights only (``rect``), weighted
    by multiple importance sampling against the glossy rays the hit sends (``c_b``,
    ``_glossy_rays_sent``; ``mis``: MIS_MODES): the light strategy's density is g*g / (pdf of a point
    of the light in solid angle: distance^2 / (cos_l area)), the BSDF strategy's
    c_b (g+1)/(2 pi) cos^g(alpha)."""
    fs = 0.0
    if has_spec and ca > spec_cut:  # below spec_cut cos^s < e^-40: skip the exp/log
        fs = (shin + 2.0) * 0.5 * INV_PI * phong_pow(ca, shin)
    fg = 0.0
    if c_b > 0.0 and ca > 0.0 and rect:
        lobe = phong_pow(ca, ge)
        dist = (tmax + mag) / (1.0 - SHADOW_SHORTEN)
        if lobe > 0.0 and cos_l > 0.0:
            n_l = gg * dist * dist / (cos_l * area)
            n_b = c_b * (ge + 1.0) * 0.5 * INV_PI * lobe
            fg = (ge + 2.0) * 0.5 * INV_PI * lobe * _mis_weight(mis, n_l, n_b)
    return fs, fg


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _light_rays(lo, hi, p, ng, ns, d, mat, weight, kind, depth, bounces, kd, ks, shin, spec_cut, kr, kg, gexp,
                max_depth, glossy_samples, mis,
                pt_pos, pt_int, dir_dir, dir_irr,
                rc, ru, rv, r_n, r_area, rL, r2s, r_g, pix, sidx, skey, vertex, path_glossy,
                center, extent, o_out, d_out, tmax_out, c_out, alive):
    """One shadow ray per (hit, light sample) with its unshadowed contribution.

    Row layout per hit: point lights, directional lights, then rect lights x g*g samples.
    The jitter of rect light l's cell s at a hit is sample ``sidx`` of pixel ``pix`` in the
    dimension derive_key(derive_key(skey, vertex, DIM_LIGHT), l, s): each cell's jitter is
    stratified over the pixel's samples. Origins are written in float32 relative to ``center``
    (Embree's frame); ``alive`` marks rows worth casting.

    Rect-light rows also carry the glossy (kg) lobe's share, weighted by multiple importance
    sampling against the glossy rays that ``_plan`` / ``_spawn`` send from the same hit (``mis``:
    MIS_MODES): the light strategy's density is g*g / (pdf of a point of the light in solid angle),
    the BSDF strategy's c_b (g+1)/(2 pi) cos^g(alpha), c_b the hit's glossy rays (M or 1 at chain
    hits, the lobe's choice probability at path vertices). A hit that sends no glossy ray (a chain
    at max_depth) gets no kg light from either strategy, as before. ``path_glossy`` False: path
    vertices get no kg light here either (a caustic photon map brings it, engine/caustics.py).
    """
    npt = pt_pos.shape[0]
    ndir = dir_dir.shape[0]
    nrect = rc.shape[0]
    gg = r_g * r_g
    per = npt + ndir + nrect * gg
    for i in range(lo, hi):
        m = mat[i]
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        g0, g1, g2 = ng[i, 0], ng[i, 1], ng[i, 2]
        n0, n1, n2 = ns[i, 0], ns[i, 1], ns[i, 2]
        wo0, wo1, wo2 = -d[i, 0], -d[i, 1], -d[i, 2]
        c = _dot(n0, n1, n2, wo0, wo1, wo2)
        wr0, wr1, wr2 = 2 * c * n0 - wo0, 2 * c * n1 - wo1, 2 * c * n2 - wo2
        mag = _offset_mag(px, py, pz, center, extent)
        ox, oy, oz = px + mag * g0, py + mag * g1, pz + mag * g2
        has_spec = ks[m, 0] > 0 or ks[m, 1] > 0 or ks[m, 2] > 0
        ad, ar, ag = _mean_albedos(kd[m, 0], kd[m, 1], kd[m, 2], kr[m, 0], kr[m, 1], kr[m, 2], kg[m, 0], kg[m, 1],
                                   kg[m, 2])
        c_b = _glossy_rays_sent(ad, ar, ag, kind[i], depth[i], bounces[i], max_depth, glossy_samples)
        if (not path_glossy and kind[i] != KIND_CHAIN) or kind[i] & LIGHT_TRACED:
            c_b = 0.0
        ge = gexp[m]
        base = i * per
        lkey = derive_key(skey[i], vertex, DIM_LIGHT)
        for j in range(per):
            row = base + j
            alive[row] = False
            c_out[row, 0] = c_out[row, 1] = c_out[row, 2] = 0.0
            # the scalar light functions, called with this row's light read out of the tables: a
            # function inlined with the table arrays as arguments would cost atomic reference counts
            # on arrays both cores share, per row
            if j < npt:
                ok, lx, ly, lz, e0, e1, e2, tmax = point_light_sample(
                    ox, oy, oz, mag, pt_pos[j, 0], pt_pos[j, 1], pt_pos[j, 2], pt_int[j, 0], pt_int[j, 1],
                    pt_int[j, 2])
            elif j < npt + ndir:
                q = j - npt
                ok, lx, ly, lz, e0, e1, e2, tmax = directional_light_sample(
                    dir_dir[q, 0], dir_dir[q, 1], dir_dir[q, 2], dir_irr[q, 0], dir_irr[q, 1], dir_irr[q, 2])
            else:  # rect light q, cell s
                js = j - npt - ndir
                q = js // gg
                s = js % gg
                su, sv = sample_2d(derive_key(lkey, q, s), pix[i], sidx[i])
                sx, sy = rect_cell_point(s, r_g, su, sv)
                ok, lx, ly, lz, e0, e1, e2, tmax = rect_light_sample(
                    ox, oy, oz, mag, sx, sy, rc[q, 0], rc[q, 1], rc[q, 2], ru[q, 0], ru[q, 1], ru[q, 2], rv[q, 0],
                    rv[q, 1], rv[q, 2], r_n[q, 0], r_n[q, 1], r_n[q, 2], r_area[q], rL[q, 0], rL[q, 1], rL[q, 2],
                    r2s[q], gg)
            if not ok:
                continue
            cos_g = _dot(g0, g1, g2, lx, ly, lz)
            cos_s = _dot(n0, n1, n2, lx, ly, lz)
            if cos_g <= 0.0 or cos_s <= 0.0 or tmax <= 0.0:
                continue
            rect = j >= npt + ndir
            cos_l = area = 0.0
            if rect:  # q: the rect light this row sampled
                cos_l = abs(_dot(r_n[q, 0], r_n[q, 1], r_n[q, 2], lx, ly, lz))
                area = r_area[q]
            fs, fg = _row_lobes(_dot(wr0, wr1, wr2, lx, ly, lz), has_spec, spec_cut[m], shin[m], rect, c_b, ge, tmax,
                                mag, cos_l, area, gg, mis)
            c0 = weight[i, 0] * (kd[m, 0] * INV_PI + ks[m, 0] * fs + kg[m, 0] * fg) * e0 * cos_s
            c1 = weight[i, 1] * (kd[m, 1] * INV_PI + ks[m, 1] * fs + kg[m, 1] * fg) * e1 * cos_s
            c2 = weight[i, 2] * (kd[m, 2] * INV_PI + ks[m, 2] * fs + kg[m, 2] * fg) * e2 * cos_s
            if c0 > 0.0 or c1 > 0.0 or c2 > 0.0 or not (c0 == c0 and c1 == c1 and c2 == c2):
                alive[row] = True
                c_out[row, 0], c_out[row, 1], c_out[row, 2] = c0, c1, c2
                o_out[row, 0] = ox - center[0]
                o_out[row, 1] = oy - center[1]
                o_out[row, 2] = oz - center[2]
                d_out[row, 0], d_out[row, 1], d_out[row, 2] = lx, ly, lz
                tmax_out[row] = min(tmax, 3.0e38)


@nb.njit(cache=True, error_model="numpy")
def _path_lobe(ad, ar, ag, bounces, key, vertex, pix, cidx):
    """The lobe a path vertex continues with, (lobe, scale): 0 mirror, 1 glossy, 2 diffuse, picked
    with probability proportional to the lobes' mean albedos (dimension DIM_LOBE); ``scale`` is the
    inverse of that probability. A last vertex (no bounce left) looks for lights through its mirror
    / glossy lobes only."""
    if not bounces > 0:
        ad = 0.0
    tot = ad + ar + ag
    u = 0.0  # one lobe (e.g. diffuse only): u = 0 picks it, as any u would
    if (ad > 0.0) + (ar > 0.0) + (ag > 0.0) > 1:
        u = sample_1d(derive_key(key, vertex, DIM_LOBE), pix, cidx) * tot
    if u < ad:
        return 2, tot / ad
    if u < ad + ar:
        return 0, tot / ar
    return 1, tot / ag


@nb.njit(cache=True, error_model="numpy")
def _roulette(w0, w1, w2, wref, bounces, total_bounces, rr_min, key, vertex, pix, cidx):
    """Russian roulette of a path vertex's continuation of weight w: past ``rr_min`` used bounces it
    survives with probability q = min(1, max(w) / wref) (dimension DIM_RR) and a survivor's weight
    is divided by q, so its expected contribution is unchanged; otherwise w is zero."""
    if bounces > 0 and total_bounces - bounces >= rr_min and wref > 0.0:
        qs = min(1.0, max(w0, w1, w2) / wref)
        if qs < 1.0:
            if sample_1d(derive_key(key, vertex, DIM_RR), pix, cidx) < qs:
                return w0 / qs, w1 / qs, w2 / qs
            return 0.0, 0.0, 0.0
    return w0, w1, w2


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _plan(lo, hi, mat, weight, kind, depth, bounces, split, kd, kr, kg, max_depth, glossy_samples, k_per_hit,
          rect_lights, n_mirror, n_glossy, n_ind, count):
    """Secondary rays per hit: chain hits spawn a mirror ray, M (first glossy bounce) or 1
    glossy rays and K' indirect rays; path hits continue with one ray while bounces remain.
    A chain hit reached by one of the M glossy rays of a first glossy bounce (``split``) shares
    the K' indirect paths with its M - 1 siblings: ceil(K' / M) each, so a glossy pixel's
    reflected surfaces get about the paths a diffuse pixel's surface gets, not M times as many.
    A path's last vertex (no bounce left) with a mirror or glossy lobe still sends one ray of
    that lobe when the scene has rect lights (``rect_lights``): the light it meets completes the
    vertex's direct light, as next-event estimation does for its kd / ks lobes; whatever else it
    meets is dropped (its bounces are -1)."""
    for i in range(lo, hi):
        m = mat[i]
        has_kr = kr[m, 0] > 0 or kr[m, 1] > 0 or kr[m, 2] > 0
        has_kg = kg[m, 0] > 0 or kg[m, 1] > 0 or kg[m, 2] > 0
        has_kd = kd[m, 0] > 0 or kd[m, 1] > 0 or kd[m, 2] > 0
        nm = 0
        ngl = 0
        nin = 0
        npath = 0
        if weight[i, 0] <= 0.0 and weight[i, 1] <= 0.0 and weight[i, 2] <= 0.0:
            count[i] = 0
            n_mirror[i] = n_glossy[i] = n_ind[i] = 0
            continue
        if kind[i] == KIND_CHAIN:
            if depth[i] < max_depth:
                if has_kr:
                    nm = 1
                if has_kg:
                    ngl = glossy_samples if depth[i] == 0 else 1
            if has_kd:
                nin = k_per_hit
                if split[i]:
                    nin = (k_per_hit + glossy_samples - 1) // glossy_samples
        elif bounces[i] > 0 and (has_kd or has_kr or has_kg):
            npath = 1
        elif bounces[i] == 0 and rect_lights and (has_kr or has_kg) and not (kind[i] & LIGHT_TRACED):
            npath = 1
        n_mirror[i] = nm
        n_glossy[i] = ngl
        n_ind[i] = nin
        count[i] = nm + ngl + nin + npath


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _spawn(lo, hi, p, ng, ns, d, mat, weight, wref, kind, depth, bounces, pix, sidx, skey, first, n_mirror, n_glossy,
           n_ind, count, vertex, total_bounces, rr_min, light_traced, kd, kr, kg, gexp, center, extent,
           o_out, d_out, d32_out, w_out, kind_out, depth_out, bounces_out, pix_out, sidx_out, skey_out, bpdf_out,
           wref_out, alive):
    """Fill the secondary rays planned by ``_plan``. Lobes: mirror, glossy (cos^g around the
    mirror direction, weight kg (g+2)/(g+1) cos_i / M), diffuse (cosine-weighted, weight kd / K').
    Path vertices pick one lobe with probability proportional to its mean albedo.
    Samples: a chain hit's B glossy (diffuse) children are samples parent * B + b of the key
    derive_key(key, vertex, BRANCH_GLOSSY (DIFFUSE)); a path vertex keeps its index and key and
    draws its lobe choice from dimension DIM_LOBE; directions come from the child's DIM_DIR.
    Origins are written float32 relative to ``center``.
    ``bpdf_out``: a glossy ray's sampling density times its expected count (the BSDF strategy of
    multiple importance sampling, see ``_rect_hits``), 0 for other rays. ``wref_out``: the
    largest component of a path's first ray's weight (a diffuse child of a chain hit; inherited
    along the path), the reference of Russian roulette: a path vertex that has used ``rr_min``
    (RR_MIN_BOUNCES; larger: no roulette) of its ``total_bounces`` bounces or more continues with probability
    q = min(1, max(new weight) / wref), decided by dimension DIM_RR, and a survivor's weight is
    divided by q (so its expected contribution is unchanged). ``light_traced``: the diffuse
    children of direct camera hits (chain depth 0) carry LIGHT_TRACED; a flagged path keeps it
    through diffuse vertices, then through mirror / glossy ones, and loses it at a diffuse vertex
    after a mirror / glossy one (engine/light_tracing.py: the light tracer's paths are
    light -> (mirror | glossy)+ -> diffuse+ -> camera)."""
    for i in range(lo, hi):
        if count[i] == 0:
            continue
        m = mat[i]
        g0, g1, g2 = ng[i, 0], ng[i, 1], ng[i, 2]
        n0, n1, n2 = ns[i, 0], ns[i, 1], ns[i, 2]
        wo0, wo1, wo2 = -d[i, 0], -d[i, 1], -d[i, 2]
        c = _dot(n0, n1, n2, wo0, wo1, wo2)
        wr0, wr1, wr2 = 2 * c * n0 - wo0, 2 * c * n1 - wo1, 2 * c * n2 - wo2
        lr = math.sqrt(wr0 * wr0 + wr1 * wr1 + wr2 * wr2)
        wr0 /= lr
        wr1 /= lr
        wr2 /= lr
        mag = _offset_mag(p[i, 0], p[i, 1], p[i, 2], center, extent)
        ox = p[i, 0] + mag * g0 - center[0]
        oy = p[i, 1] + mag * g1 - center[1]
        oz = p[i, 2] + mag * g2 - center[2]
        ad, ar, ag = _mean_albedos(kd[m, 0], kd[m, 1], kd[m, 2], kr[m, 0], kr[m, 1], kr[m, 2], kg[m, 0], kg[m, 1],
                                   kg[m, 2])
        key = skey[i]
        for r in range(first[i], first[i] + count[i]):
            local = r - first[i]
            if kind[i] == KIND_CHAIN:
                if local < n_mirror[i]:
                    lb, scale = 0, 1.0
                    ckey = derive_key(key, vertex, BRANCH_MIRROR)
                    cidx = sidx[i]
                elif local < n_mirror[i] + n_glossy[i]:
                    lb, scale = 1, 1.0 / n_glossy[i]
                    ckey = derive_key(key, vertex, BRANCH_GLOSSY)
                    cidx = sidx[i] * n_glossy[i] + (local - n_mirror[i])
                else:
                    lb, scale = 2, 1.0 / n_ind[i]
                    ckey = derive_key(key, vertex, BRANCH_DIFFUSE)
                    cidx = sidx[i] * n_ind[i] + (local - n_mirror[i] - n_glossy[i])
            else:
                ckey = key
                cidx = sidx[i]
                lb, scale = _path_lobe(ad, ar, ag, bounces[i], key, vertex, pix[i], cidx)
            x0, x1, x2, fk, bp = _lobe_direction(lb, ckey, vertex, pix[i], cidx, scale, wr0, wr1, wr2, n0, n1, n2,
                                                 gexp[m])
            if lb == 0:
                f0, f1, f2 = kr[m, 0], kr[m, 1], kr[m, 2]
            elif lb == 1:
                f0, f1, f2 = kg[m, 0] * fk, kg[m, 1] * fk, kg[m, 2] * fk
            else:
                f0, f1, f2 = kd[m, 0], kd[m, 1], kd[m, 2]
            if _dot(g0, g1, g2, x0, x1, x2) <= 0.0:  # below the geometric surface
                f0 = f1 = f2 = 0.0
            ln = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
            o_out[r, 0], o_out[r, 1], o_out[r, 2] = ox, oy, oz
            x0, x1, x2 = x0 / ln, x1 / ln, x2 / ln
            d_out[r, 0], d_out[r, 1], d_out[r, 2] = x0, x1, x2
            d32_out[r, 0], d32_out[r, 1], d32_out[r, 2] = x0, x1, x2
            w0 = weight[i, 0] * f0 * scale
            w1 = weight[i, 1] * f1 * scale
            w2 = weight[i, 2] * f2 * scale
            wr_ = wref[i]
            if kind[i] == KIND_CHAIN:
                wr_ = max(w0, w1, w2) if lb == 2 else 0.0
            else:
                w0, w1, w2 = _roulette(w0, w1, w2, wr_, bounces[i], total_bounces, rr_min, key, vertex, pix[i], cidx)
            w_out[r, 0], w_out[r, 1], w_out[r, 2] = w0, w1, w2
            bpdf_out[r] = bp
            wref_out[r] = wr_
            alive[r] = w0 > 0.0 or w1 > 0.0 or w2 > 0.0
            pix_out[r] = pix[i]
            sidx_out[r] = cidx
            skey_out[r] = ckey
            # every diffuse bounce and every continuation of a path uses up one bounce
            if kind[i] != KIND_CHAIN or lb == 2:
                bounces_out[r] = bounces[i] - 1
            else:
                bounces_out[r] = bounces[i]
            if lb == 2:
                if kind[i] == KIND_CHAIN:
                    lt = light_traced and depth[i] == 0
                else:
                    lt = kind[i] == (KIND_PATH | LIGHT_TRACED)
                kind_out[r] = (KIND_PATH | LIGHT_TRACED) if lt else KIND_PATH
            elif kind[i] == KIND_CHAIN:
                kind_out[r] = KIND_CHAIN
            else:
                kind_out[r] = KIND_SPEC | (kind[i] & LIGHT_TRACED)
            depth_out[r] = depth[i] if lb == 2 else depth[i] + 1



@nb.njit(cache=True, nogil=True, error_model="numpy")
def _diffuse_starts(lo, hi, p, ng, ns, mat, pix, sidx, key, kd, center, extent, o_out, d_out, d32_out, w_out, alive):
    """One cosine-distributed diffuse ray per row leaving point ``p`` on the side ``ng`` points to
    (``ns`` is that side's shading normal): its weight is kd (BRDF kd/pi times cos over the pdf
    cos/pi), zero when the direction dips below the geometric surface. Its direction is sample
    ``sidx`` of pixel ``pix`` in dimension derive_key(key, 0, DIM_DIR), so the rows of one pixel
    are one stratified sequence. Origins are written float32 relative to ``center``."""
    dkey = derive_key(key, 0, DIM_DIR)
    for i in range(lo, hi):
        m = mat[i]
        g0, g1, g2 = ng[i, 0], ng[i, 1], ng[i, 2]
        n0, n1, n2 = ns[i, 0], ns[i, 1], ns[i, 2]
        u0, u1 = sample_2d(dkey, pix[i], sidx[i])
        x0, x1, x2 = _lobe_dir(n0, n1, n2, math.sqrt(u0), 2.0 * math.pi * u1)
        ln = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        x0, x1, x2 = x0 / ln, x1 / ln, x2 / ln
        ok = _dot(g0, g1, g2, x0, x1, x2) > 0.0
        mag = _offset_mag(p[i, 0], p[i, 1], p[i, 2], center, extent)
        o_out[i, 0] = p[i, 0] + mag * g0 - center[0]
        o_out[i, 1] = p[i, 1] + mag * g1 - center[1]
        o_out[i, 2] = p[i, 2] + mag * g2 - center[2]
        d_out[i, 0], d_out[i, 1], d_out[i, 2] = x0, x1, x2
        d32_out[i, 0], d32_out[i, 1], d32_out[i, 2] = x0, x1, x2
        for k in range(3):
            w_out[i, k] = kd[m, k] if ok else 0.0
        alive[i] = ok and (kd[m, 0] > 0.0 or kd[m, 1] > 0.0 or kd[m, 2] > 0.0)

@nb.njit(cache=True, nogil=True, error_model="numpy")
def _gather_hits(lo, hi, idx, prim, u, v, d, w, wref, kind, depth, bounces, pix, sidx, skey, tri_p, tri_n, tri_ng,
                 tri_mat, p_out, ng_out, ns_out, mat_out, d_out, w_out, wref_out, kind_out, depth_out, bounces_out,
                 pix_out, sidx_out, skey_out):
    """Compact the rays that hit something and compute their surface frames."""
    for j in range(lo, hi):
        i = idx[j]
        t = prim[i]
        uu = np.float64(u[i])
        vv = np.float64(v[i])
        w0 = 1.0 - uu - vv
        for k in range(3):
            p_out[j, k] = w0 * tri_p[t, 0, k] + uu * tri_p[t, 1, k] + vv * tri_p[t, 2, k]
            d_out[j, k] = d[i, k]
            w_out[j, k] = w[i, k]
        g0, g1, g2, s0, s1, s2 = _surface_frame(t, uu, vv, d[i, 0], d[i, 1], d[i, 2], tri_n, tri_ng)
        ng_out[j, 0], ng_out[j, 1], ng_out[j, 2] = g0, g1, g2
        ns_out[j, 0], ns_out[j, 1], ns_out[j, 2] = s0, s1, s2
        mat_out[j] = tri_mat[t]
        wref_out[j] = wref[i]
        kind_out[j] = kind[i]
        depth_out[j] = depth[i]
        bounces_out[j] = bounces[i]
        pix_out[j] = pix[i]
        sidx_out[j] = sidx[i]
        skey_out[j] = skey[i]


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _accumulate_misses_and_emission(acc, prim, w, pix, background, idx_hit, mat_h, kind_h, w_h, pix_h,
                                    emission, kd, ambient, lit, lit_c):
    """Rect lights where rays end on one (``lit``, contribution ``lit_c``; empty arrays: none),
    background where rays escape, emission + kd * ambient where camera/specular chains land.
    Serial on purpose: many rays share a pixel (and the order of the sums is the rays' order)."""
    has_lit = lit.shape[0] > 0
    if has_lit:
        for i in range(prim.shape[0]):
            if lit[i]:
                q = pix[i]
                for k in range(3):
                    acc[q, k] += lit_c[i, k]
    if background[0] > 0 or background[1] > 0 or background[2] > 0:
        for i in range(prim.shape[0]):
            if prim[i] < 0 and not (has_lit and lit[i]):
                q = pix[i]
                for k in range(3):
                    acc[q, k] += w[i, k] * background[k]
    for j in range(idx_hit.shape[0]):
        if kind_h[j] != KIND_CHAIN:
            continue
        m = mat_h[j]
        q = pix_h[j]
        for k in range(3):
            e = emission[m, k] + kd[m, k] * ambient[k]
            if e != 0.0:
                acc[q, k] += w_h[j, k] * e


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _accumulate_shadow(acc, live, occ, contrib, pix_h, per):
    for k in range(live.shape[0]):
        if not occ[k]:
            row = live[k]
            q = pix_h[row // per]
            acc[q, 0] += contrib[row, 0]
            acc[q, 1] += contrib[row, 1]
            acc[q, 2] += contrib[row, 2]


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _compact_rays(lo, hi, idx, o, d, w, bpdf, wref, kind, depth, bounces, pix, sidx, skey,
                  o_out, d_out, d32_out, w_out, bpdf_out, wref_out, kind_out, depth_out, bounces_out, pix_out,
                  sidx_out, skey_out):
    for j in range(lo, hi):
        i = idx[j]
        for k in range(3):
            o_out[j, k] = o[i, k]
            d_out[j, k] = d[i, k]
            d32_out[j, k] = d[i, k]
            w_out[j, k] = w[i, k]
        bpdf_out[j] = bpdf[i]
        wref_out[j] = wref[i]
        kind_out[j] = kind[i]
        depth_out[j] = depth[i]
        bounces_out[j] = bounces[i]
        pix_out[j] = pix[i]
        sidx_out[j] = sidx[i]
        skey_out[j] = skey[i]


@nb.njit(cache=True, error_model="numpy")
def _cell_centre(j, spp, gx):
    """Centre of cell j of spp equal-area cells tiling the unit square: gy = ceil(spp / gx) rows,
    the first spp % gy rows with one cell more than the others, each row as tall as its share
    of the cells (spp = g * g: the g x g grid). Their mean is the square's centre for every spp."""
    gy = -(-spp // gx)
    base = spp // gy
    big = (spp % gy) * (base + 1)
    if j < big:
        c = base + 1
        k = j % c
        before = j - k
    else:
        c = base
        k = (j - big) % c
        before = j - k
    return (k + 0.5) / c, (before + 0.5 * c) / spp


@nb.njit(cache=True, inline="always", error_model="numpy")
def _pixel_ray(r, x, y, width, height, ortho, eye, right, up, fwd, sx_scale, sy_scale, center, o_out, d_out, d32_out):
    """Row r of the ray arrays: the camera ray through image position (x, y) in pixels."""
    fx = x / width
    fy = y / height
    sx = (2.0 * fx - 1.0) * sx_scale
    sy = (1.0 - 2.0 * fy) * sy_scale
    if ortho:
        ox = eye[0] + sx * right[0] + sy * up[0]
        oy = eye[1] + sx * right[1] + sy * up[1]
        oz = eye[2] + sx * right[2] + sy * up[2]
        dx, dy, dz = fwd[0], fwd[1], fwd[2]
    else:
        ox, oy, oz = eye[0], eye[1], eye[2]
        dx = fwd[0] + sx * right[0] + sy * up[0]
        dy = fwd[1] + sx * right[1] + sy * up[1]
        dz = fwd[2] + sx * right[2] + sy * up[2]
        ln = math.sqrt(dx * dx + dy * dy + dz * dz)
        dx /= ln
        dy /= ln
        dz /= ln
    o_out[r, 0] = ox - center[0]
    o_out[r, 1] = oy - center[1]
    o_out[r, 2] = oz - center[2]
    d_out[r, 0], d_out[r, 1], d_out[r, 2] = dx, dy, dz
    d32_out[r, 0], d32_out[r, 1], d32_out[r, 2] = dx, dy, dz


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _camera_batch(lo, hi, ids, spp, gx, width, height, ortho, eye, right, up, fwd, sx_scale, sy_scale, key, center,
                  o_out, d_out, d32_out, pix_out, sidx_out, skey_out, jitter=True):
    """spp camera rays per pixel (box filter): sample j of pixel q is at sample j of q in the
    dimension derive_key(key, 0, DIM_PIXEL) (stratified: engine/sampler.py), independent of
    chunking; ``jitter`` False: at the centre of cell j of ``_cell_centre``'s tiling.
    The rays start paths with sample index j and key ``key``.
    Perspective: sx_scale = tan(fov/2) * aspect, sy_scale = tan(fov/2); orthographic: half extents."""
    pkey = derive_key(key, 0, DIM_PIXEL)
    for a in range(lo, hi):
        q = ids[a]
        qx = q % width
        qy = q // width
        for j in range(spp):
            r = a * spp + j
            if jitter:
                jx, jy = sample_2d(pkey, q, j)
            else:
                jx, jy = _cell_centre(j, spp, gx)
            _pixel_ray(r, qx + jx, qy + jy, width, height, ortho, eye, right, up, fwd, sx_scale, sy_scale, center,
                       o_out, d_out, d32_out)
            pix_out[r] = q
            sidx_out[r] = j
            skey_out[r] = key


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _camera_rows(lo, hi, rid, start, cnt, first, npix, width, height, ortho, eye, right, up, fwd, sx_scale, sy_scale,
                 key, center, o_out, d_out, d32_out, pix_out, sidx_out, skey_out):
    """Camera rays of one pass of a progressive render (engine/progressive.py): row a is the
    (virtual) pixel ``rid[a]``, samples ``start[a] .. start[a] + cnt[a] - 1``, written from ray
    ``first[a]``. A virtual pixel v is image pixel v % npix; v < npix is its half buffer A, whose
    samples are those ``_camera_batch`` gives the pixel, v >= npix its half buffer B, an
    independent sequence (every sample value is keyed by the pixel number, engine/sampler.py)."""
    pkey = derive_key(key, 0, DIM_PIXEL)
    for a in range(lo, hi):
        v = rid[a]
        q = v % npix
        qx = q % width
        qy = q // width
        for t in range(cnt[a]):
            j = start[a] + t
            r = first[a] + t
            jx, jy = sample_2d(pkey, v, j)
            _pixel_ray(r, qx + jx, qy + jy, width, height, ortho, eye, right, up, fwd, sx_scale, sy_scale,
                       center, o_out, d_out, d32_out)
            pix_out[r] = v
            sidx_out[r] = j
            skey_out[r] = key


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _compact_shadow(lo, hi, live, so, sd, tmax, so_out, sd_out, tm_out):
    for j in range(lo, hi):
        i = live[j]
        for k in range(3):
            so_out[j, k] = so[i, k]
            sd_out[j, k] = sd[i, k]
        tm_out[j] = tmax[i]


# ============================================================================ driver


def run_pieces(run_piece: Callable[[int, _Timer, dict[str, int], bool], None], n_pieces: int, pipelines: int,
               timer: _Timer, counts: dict[str, int], done: Callable[[float], None] | None = None) -> None:
    """Run pieces 0 .. n_pieces - 1 of a render, which accumulate into disjoint rows (so no locks):
    ``run_piece(i, timer, counts, serial)``. ``pipelines`` <= 1: one piece at a time, each kernel
    split over the thread pool (``serial`` False, ``engine.sched.run_pieces_parallel``); else that
    many in flight, one per thread, each calling the nogil kernels on its whole batch (``serial``
    True): while one pipeline holds the GIL the others shade or trace. ``done(fraction of pieces finished)``
    after each piece (it may raise to cancel: in-flight pieces finish, no more start)."""
    if pipelines <= 1:
        for i in range(n_pieces):
            run_piece(i, timer, counts, False)
            if done is not None:
                done((i + 1) / n_pieces)
        return
    lock = threading.Lock()
    finished = [0]
    stop = threading.Event()

    def run(i: int) -> None:
        if stop.is_set():
            return
        t_local = _Timer()
        c_local = dict.fromkeys(counts, 0)
        run_piece(i, t_local, c_local, True)
        with lock:
            for k, v in t_local.t.items():
                timer.add(k, v)
            for k, c in c_local.items():
                counts[k] += c
            finished[0] += 1

    with ThreadPoolExecutor(max_workers=pipelines, thread_name_prefix="ibr-ref") as pool:
        futures = [pool.submit(run, i) for i in range(n_pieces)]
        try:
            for f in futures:
                f.result()
                if done is not None:
                    with lock:
                        frac = finished[0] / n_pieces
                    done(frac)
        except BaseException:
            stop.set()  # cancellation / errors: let in-flight pieces finish, start no more
            for f in futures:
                f.cancel()
            raise


class PathLight(Protocol):
    """Light that paths get from elsewhere at their diffuse vertices (``engine.caustics.CausticMap``:
    the caustics), in place of the paths that would find it through mirror / glossy lobes."""

    def add_path_light(self, acc: np.ndarray, pix: np.ndarray, pix_base: int, is_path: np.ndarray, mat: np.ndarray,
                       w: np.ndarray, p: np.ndarray, ng: np.ndarray, kd: np.ndarray) -> None: ...


class ReferenceRenderer:
    """Reusable renderer bound to one scene (keeps its Embree scene warm)."""

    def __init__(self, scene: RuntimeScene, caster: RayCaster | None = None, glossy_mis: str = "power",
                 roulette: bool = True):
        """``glossy_mis``: how rect lights reach glossy (kg) lobes: "power" (the default) or
        "balance" weigh next-event estimation and the lobe's own rays by multiple importance
        sampling with that heuristic; "light" / "bsdf" use one strategy alone (the same image in
        the mean, with more noise: for tests and benchmarks). ``roulette``: Russian roulette on
        path vertices past RR_MIN_BOUNCES bounces (``_spawn``); False traces every path to its
        last bounce (the same image in the mean, slower)."""
        if glossy_mis not in MIS_MODES:
            raise InvalidInputError(f"glossy_mis must be one of {sorted(MIS_MODES)}, got {glossy_mis!r}")
        self._mis = MIS_MODES[glossy_mis]
        self._rr_min = RR_MIN_BOUNCES if roulette else 1 << 30
        self.scene = scene
        self.caster = caster if caster is not None else make_caster(scene, "embree")
        lt = scene.lights
        self._rect_n, self._rect_area = lt.rect_frames()
        # cos(alpha) below which cos^s < e^-40 (negligible next to the lobe's peak (s+2)/2pi)
        shin = scene.materials.shininess
        self._spec_cut = np.where(shin > 0, np.exp(-40.0 / np.maximum(shin, 1e-300)), -1.0)

    # ------------------------------------------------------------------ public
    def render(self, camera: CameraParams, params: ReferenceParams | None = None,
               progress: Callable[[float, str], None] | None = None) -> RenderOutput:
        """Render ``camera`` view; raises NonFiniteOutputError if any pixel is NaN/Inf.

        With ``max_error`` or ``max_ms`` set the render is progressive and adaptive
        (engine/progressive.py: passes until the estimated error or the time budget is reached,
        ``spp`` samples per pixel at most) and ``RenderOutput.adaptive`` says how it ended."""
        params = params or ReferenceParams()
        if params.adaptive:
            return self._render_progressive(camera, params, progress)
        timer = _Timer()
        counts = {"camera": 0, "shadow": 0, "reflection": 0, "indirect": 0}
        t0 = time.perf_counter()
        if hasattr(self.caster, "_get"):
            self.caster._get()  # build the BVH now so its cost is reported on its own
        timer.add("bvh_build", time.perf_counter() - t0)

        w, h = camera.width, camera.height
        npix = w * h
        acc = np.zeros((npix, 3))
        aov = self._aovs(camera, timer)
        # The chunking depends only on the image size, never on the number of pipelines, so
        # the image is identical for any ``pipelines`` (each chunk seeds its own generators).
        chunk = max(1, min(params.chunk_pixels, max(1024, -(-npix // 8))))
        n_chunks = (npix + chunk - 1) // chunk
        chunks = [np.arange(ci * chunk, min(npix, (ci + 1) * chunk)) for ci in range(n_chunks)]
        tracer = self._light_tracer(camera, params)
        run_pieces(lambda ci, t, c, serial: self._render_chunk(camera, params, chunks[ci], ci, acc, t, c, serial,
                                                               tracer is not None),
                   n_chunks, min(params.pipelines, n_chunks), timer, counts,
                   None if progress is None else (lambda f: progress(f, "render")))
        radiance = acc / params.spp
        if tracer is not None:
            n_light = max(1, round(params.light_paths * params.spp * npix))
            light = np.zeros((npix, 3))
            tracer.trace(0, n_light, 0, light, timer.add, counts)
            radiance += light / n_light
        radiance = radiance.reshape(h, w, 3)
        bad = ~np.isfinite(radiance)
        if np.any(bad):
            raise NonFiniteOutputError(f"reference render produced {int(bad.sum())} non-finite values")
        timer.add("total", time.perf_counter() - t0)
        depth, normal, oid, mid = aov
        return RenderOutput(radiance.astype(np.float32), depth, normal, oid, mid, timer.t, counts)

    def _render_progressive(self, camera: CameraParams, params: ReferenceParams,
                            progress: Callable[[float, str], None] | None) -> RenderOutput:
        """``render`` with ``max_error`` / ``max_ms``: passes planned by engine/progressive.py, each
        traced here in pieces (``pass_pieces``, ``run_pieces``)."""
        t_start = time.perf_counter()
        timer = _Timer()
        counts = {"camera": 0, "shadow": 0, "reflection": 0, "indirect": 0}
        if hasattr(self.caster, "_get"):
            self.caster._get()  # build the BVH now so its cost is reported on its own
        timer.add("bvh_build", time.perf_counter() - t_start)
        depth, normal, oid, mid = self._aovs(camera, timer)
        npix = camera.width * camera.height

        tracer = self._light_tracer(camera, params)

        def render_rows(rid, start, cnt, acc, tick) -> None:
            pieces = pass_pieces(cnt, npix, params.chunk_pixels, params.spp, params.pipelines)

            def piece(i: int, t: _Timer, c: dict[str, int], serial: bool) -> None:
                a, b = pieces[i]
                self._render_rows(camera, params, rid[a:b], start[a:b], cnt[a:b], acc, t, c, serial,
                                  tracer is not None)

            run_pieces(piece, len(pieces), min(params.pipelines, len(pieces)), timer, counts, lambda _: tick())

        light_pass = None
        if tracer is not None:
            light = np.zeros((2, npix, 3))
            traced = [0, 0]

            def light_pass(samples: int) -> tuple[np.ndarray, np.ndarray]:
                # each half buffer gets light paths in proportion to the camera samples of the pass
                k = max(1, round(params.light_paths * samples / 2))
                for half in (0, 1):
                    tracer.trace(traced[half], k, half, light[half], timer.add, counts)
                    traced[half] += k
                return light[0] / traced[0], light[1] / traced[1]

        t0 = time.perf_counter()
        region = self.error_region(camera, oid, depth, params.max_depth)
        timer.add("error_region", time.perf_counter() - t0)
        radiance, rep = run_progressive(render_rows, camera.width, camera.height, params.spp, params.max_error,
                                        params.max_ms, t_start, timer.add, progress, region, light_pass)
        timer.add("total", time.perf_counter() - t_start)
        if progress is not None:
            progress(1.0, "render")
        return RenderOutput(radiance.astype(np.float32), depth, normal, oid, mid, timer.t, counts, rep.to_dict(),
                            region)

    def _light_tracer(self, camera: CameraParams, params: ReferenceParams) -> CausticLightTracer | None:
        """The render's light tracer (engine/light_tracing.py), None where no path is light-traced
        (``light_paths`` 0, or ``engine.light_tracing.applies`` says no)."""
        if params.light_paths <= 0.0:
            return None
        return light_tracer(self.scene, self.caster, camera, params.indirect_samples, params.indirect_bounces,
                            params.seed)

    def error_region(self, camera: CameraParams, object_id: np.ndarray, depth: np.ndarray,
                     max_depth: int) -> np.ndarray:
        """(h, w) bool: the pixels an error of this view is measured on: covered and not next to an
        emitter (``engine.error_region``; ``object_id`` and ``depth`` are the pixel-centre ray's) nor
        to an emitter seen through mirrors within ``max_depth`` reflections
        (:meth:`emitters_in_mirrors`). Adaptive renders estimate their error here, and every error
        the project quotes is measured here: a luminaire's image in a mirror sphere is as bright as
        the luminaire, and its outline as noisy."""
        seen = emitter_pixels(self.scene, camera, object_id, depth)
        seen |= self.emitters_in_mirrors(camera, max_depth)
        return region_around(object_id >= 0, seen)

    def emitters_in_mirrors(self, camera: CameraParams, max_depth: int, spp: int = MIRROR_EMITTER_SPP) -> np.ndarray:
        """(h, w) bool: some of the pixel's ``spp`` jittered samples see an emitter (a rect light or
        an emissive surface), directly or through up to ``max_depth`` mirror reflections (``kr``):
        this renderer on a copy of the scene whose materials keep only their mirror lobe and
        emission, with no ambient light and a black background. All False, at no cost, when no
        mirror can show one (no mirror, no emitter, or ``max_depth`` 0)."""
        sc = self.scene
        mt = sc.materials
        mirrors = bool(np.any(mt.kr > 0))
        emitters = bool(np.any(self._rect_area > 0)) or bool(np.any(mt.emission > 0))
        if max_depth <= 0 or not mirrors or not emitters:
            return np.zeros((camera.height, camera.width), np.bool_)
        zero = np.zeros_like(mt.kd)
        stripped = replace(sc, materials=replace(mt, kd=zero, ks=zero, kg=zero), ambient=np.zeros(3),
                           background=np.zeros(3))
        out = ReferenceRenderer(stripped, self.caster).render(
            camera, ReferenceParams(spp=spp, max_depth=max_depth, area_light_samples=1))
        return np.any(out.radiance > 0, axis=2)

    def shade_hits(self, prim: np.ndarray, u: np.ndarray, v: np.ndarray, directions: np.ndarray,
                   params: ReferenceParams | None = None, *, stream_id: int = 0, chunk: int = 1 << 15,
                   progress: Callable[[float], None] | None = None) -> np.ndarray:
        """Radiance (n, 3) float64 leaving given surface hits toward ``-directions``.

        Each hit (triangle ``prim`` int32, barycentrics ``u``, ``v`` float32) is treated as the
        first intersection of a camera ray travelling along ``directions`` (n, 3) unit float64,
        and shaded exactly as the renderer shades a camera hit: emission + kd ambient, direct
        light with shadow rays (diffuse + Phong highlights), mirror / glossy recursion up to
        ``max_depth`` and indirect paths when ``indirect_samples`` > 0 (``spp`` is ignored: one
        chain per hit). Surfaces are two-sided: the side the ray arrives on is shaded.
        Deterministic for a given (seed, stream_id): hit i's samples are those of pixel i of a
        sampler keyed by both, whatever ``chunk`` (hits are processed ``chunk`` at a time)."""
        params = replace(params or ReferenceParams(), spp=1)
        prim = np.ascontiguousarray(prim, dtype=np.int32).reshape(-1)
        n = prim.shape[0]
        u = np.ascontiguousarray(u, dtype=np.float32).reshape(-1)
        v = np.ascontiguousarray(v, dtype=np.float32).reshape(-1)
        d_all = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
        if u.shape[0] != n or v.shape[0] != n or d_all.shape[0] != n:
            raise InvalidInputError("shade_hits: prim, u, v and directions must have the same length")
        if n and (prim.min() < 0 or prim.max() >= self.scene.n_triangles):
            raise InvalidInputError("shade_hits: prim holds triangle ids outside the scene")
        if not np.all(np.isfinite(d_all)):
            raise InvalidInputError("shade_hits: directions must be finite")
        acc = np.zeros((n, 3))
        timer = _Timer()
        counts = {"camera": 0, "shadow": 0, "reflection": 0, "indirect": 0}
        chunk = max(1, int(chunk))
        n_chunks = -(-n // chunk)
        root = sample_key(params.seed, 1, int(stream_id))  # apart from the renderer's own (0)
        for ci in range(n_chunks):
            sl = slice(ci * chunk, min(n, (ci + 1) * chunk))
            k = sl.stop - sl.start
            d = np.ascontiguousarray(d_all[sl])
            o32 = np.zeros((k, 3), np.float32)  # never cast: the first hit is given
            pix = np.arange(sl.start, sl.stop, dtype=np.int64)
            self._trace(params, o32, d, d.astype(np.float32),
                        np.ones((k, 3)), np.zeros(k, np.int8), np.zeros(k, np.int32),
                        np.full(k, params.indirect_bounces, np.int32), pix, np.zeros(k, np.int64),
                        np.full(k, root, np.uint64), acc, timer, counts, serial=False,
                        first_hits=(prim[sl], u[sl], v[sl]))
            if progress is not None:
                progress((ci + 1) / n_chunks)
        if not np.all(np.isfinite(acc)):
            raise NonFiniteOutputError("shade_hits produced non-finite radiance")
        return acc

    def trace_diffuse_paths(self, p: np.ndarray, ng: np.ndarray, ns: np.ndarray, mat: np.ndarray,
                            pix: np.ndarray, sidx: np.ndarray, key: np.uint64, bounces: int, acc: np.ndarray, *,
                            pix_base: int = 0, params: ReferenceParams | None = None,
                            timings: dict[str, float] | None = None, counts: dict[str, int] | None = None,
                            caustics: PathLight | None = None) -> None:
        """Indirect diffuse light leaving surface points, one path per row, added to ``acc``.

        Row i starts a diffuse path at point ``p[i]`` on the side its geometric normal ``ng[i]``
        points to (``ns[i]``: that side's shading normal; both unit float64), exactly as the
        renderer's camera hits start their indirect paths: a cosine-distributed first direction,
        ``bounces`` diffuse vertices with next-event estimation at each (``bounces`` >= 1) and the
        mirror / glossy lobes where paths meet them. The path's estimate of kd/pi times the light
        it brings back (weight kd) is added to ``acc[pix[i] - pix_base]``. Sample values are sample
        ``sidx[i]`` (int64) of pixel ``pix[i]`` (int64) under ``key``: give the rows of one point
        one pixel and consecutive indices and its paths are one stratified sequence, whatever the
        batching. ``params`` supplies the light sampling and lobe settings (area_light_samples,
        max_depth); ``timings`` / ``counts`` collect the stage times and ray counts. ``caustics``: a
        caustic photon map of the scene (engine/caustics.py) brings the light that reaches the
        paths' diffuse vertices through mirror / glossy lobes (``_trace``); the caustic light of
        the start points themselves is the caller's (``CausticMap.irradiance``)."""
        params = params or ReferenceParams()
        if not isinstance(bounces, (int, np.integer)) or not 1 <= bounces <= 64:
            raise InvalidInputError(f"bounces must be an integer in [1, 64], got {bounces!r}")
        n = p.shape[0]
        if not (ng.shape == ns.shape == p.shape == (n, 3) and mat.shape == pix.shape == sidx.shape == (n,)):
            raise InvalidInputError("trace_diffuse_paths: p, ng, ns (n, 3) and mat, pix, sidx (n,) must agree")
        if n == 0:
            return
        sc = self.scene
        timer = _Timer()
        c = dict.fromkeys(("camera", "shadow", "reflection", "indirect"), 0)
        t0 = time.perf_counter()
        o32 = np.empty((n, 3), np.float32)
        d = np.empty((n, 3))
        d32 = np.empty((n, 3), np.float32)
        w = np.empty((n, 3))
        alive = np.empty(n, np.bool_)
        pix = np.ascontiguousarray(pix, dtype=np.int64)
        sidx = np.ascontiguousarray(sidx, dtype=np.int64)
        run_pieces_parallel(_diffuse_starts, n, _MIN_ITEMS, False, np.ascontiguousarray(p, np.float64),
                            np.ascontiguousarray(ng, np.float64), np.ascontiguousarray(ns, np.float64),
                            np.ascontiguousarray(mat, np.int32), pix, sidx, np.uint64(key), sc.materials.kd, sc.center,
                            sc.extent, o32, d, d32, w, alive)
        live = np.flatnonzero(alive)
        k = live.size
        timer.add("shading", time.perf_counter() - t0)
        c["indirect"] += k
        if k:
            self._trace(params, o32[live], d[live], d32[live], w[live], np.full(k, KIND_PATH, np.int8),
                        np.zeros(k, np.int32), np.full(k, int(bounces) - 1, np.int32), pix[live], sidx[live],
                        np.full(k, np.uint64(key), np.uint64), acc, timer, c, serial=False, pix_base=pix_base,
                        wref=w[live].max(axis=1), total_bounces=int(bounces), caustics=caustics)
        if timings is not None:
            for name, dt in timer.t.items():
                timings[name] = timings.get(name, 0.0) + dt
        if counts is not None:
            for name, v in c.items():
                counts[name] = counts.get(name, 0) + v

    # ------------------------------------------------------------------ stages
    def _aovs(self, camera: CameraParams, timer: _Timer):
        sc = self.scene
        px, py = pixel_centers(camera)
        o, d = camera_rays(camera, px, py)
        t0 = time.perf_counter()
        hits = self.caster.intersect(o, d)
        timer.add("intersect", time.perf_counter() - t0)
        t0 = time.perf_counter()
        h, w = camera.height, camera.width
        hit = hits.prim >= 0
        depth = np.where(hit, hits.t, 0.0).astype(np.float32).reshape(h, w)
        prim = np.where(hit, hits.prim, 0)
        oid = np.where(hit, sc.tri_object[prim] if sc.n_triangles else -1, -1).astype(np.int32).reshape(h, w)
        mid = np.where(hit, sc.tri_material[prim] if sc.n_triangles else -1, -1).astype(np.int32).reshape(h, w)
        normal = np.zeros((h * w, 3))
        if np.any(hit):
            idx = np.nonzero(hit)[0]
            p = np.empty((idx.size, 3))
            ng = np.empty((idx.size, 3))
            ns = np.empty((idx.size, 3))
            run_pieces_parallel(_surface, idx.size, _MIN_ITEMS, None, d[idx], hits.prim[idx], hits.u[idx], hits.v[idx],
                                sc.tri_p, sc.tri_n, sc.tri_ng, p, ng, ns)
            normal[idx] = ns
        timer.add("aov", time.perf_counter() - t0)
        return depth, normal.reshape(h, w, 3).astype(np.float32), oid, mid

    def _render_chunk(self, camera, params: ReferenceParams, ids, ci, acc, timer, counts,
                      serial: bool, light_traced: bool = False) -> None:
        right, up, fwd, sxs, sys_ = _camera_frame(camera)
        gx = int(math.ceil(math.sqrt(params.spp)))

        def fill(o32, d, d32, pix, sidx, skey):
            run_pieces_parallel(_camera_batch, ids.shape[0], _MIN_ITEMS // max(1, params.spp), serial, ids, params.spp,
                                gx, camera.width, camera.height, camera.kind == "orthographic",
                                np.asarray(camera.eye, np.float64), right, up, fwd, sxs, sys_,
                                sample_key(params.seed, 0), self.scene.center, o32, d, d32, pix, sidx, skey,
                                bool(params.pixel_jitter))

        self._trace_camera_rays(params, ids.shape[0] * params.spp, fill, acc, timer, counts, serial, light_traced)

    def _render_rows(self, camera, params: ReferenceParams, rid, start, cnt, acc, timer, counts,
                     serial: bool, light_traced: bool = False) -> None:
        """Samples ``start[a] .. start[a] + cnt[a] - 1`` of each virtual pixel ``rid[a]`` (see
        ``_camera_rows``), accumulated into ``acc[rid]`` (acc has a row per virtual pixel)."""
        first = np.zeros(rid.shape[0], np.int64)
        np.cumsum(cnt[:-1], out=first[1:])
        right, up, fwd, sxs, sys_ = _camera_frame(camera)

        def fill(o32, d, d32, pix, sidx, skey):
            run_pieces_parallel(_camera_rows, rid.shape[0], _MIN_ITEMS // max(1, params.spp), serial, rid, start, cnt,
                                first, camera.width * camera.height, camera.width, camera.height,
                                camera.kind == "orthographic", np.asarray(camera.eye, np.float64), right, up, fwd, sxs,
                                sys_, sample_key(params.seed, 0), self.scene.center, o32, d, d32, pix, sidx, skey)

        self._trace_camera_rays(params, int(cnt.sum()), fill, acc, timer, counts, serial, light_traced)

    def _trace_camera_rays(self, params: ReferenceParams, n: int, fill, acc, timer, counts, serial: bool,
                           light_traced: bool = False) -> None:
        """n camera rays, written by ``fill(o32, d, d32, pix, sidx, skey)``, traced into ``acc``
        (``light_traced``: see ``_trace``)."""
        t0 = time.perf_counter()
        o32 = np.empty((n, 3), np.float32)
        d = np.empty((n, 3))
        d32 = np.empty((n, 3), np.float32)
        pix = np.empty(n, np.int64)
        sidx = np.empty(n, np.int64)
        skey = np.empty(n, np.uint64)
        fill(o32, d, d32, pix, sidx, skey)
        counts["camera"] += n
        timer.add("camera_rays", time.perf_counter() - t0)
        self._trace(params, o32, d, d32, np.ones((n, 3)), np.zeros(n, np.int8), np.zeros(n, np.int32),
                    np.full(n, params.indirect_bounces, np.int32), pix, sidx, skey, acc, timer, counts, serial,
                    light_traced=light_traced)

    def _trace(self, params: ReferenceParams, o32, d, d32, weight, kind, depth, bounces, pix, sidx, skey, acc,
               timer, counts, serial: bool, first_hits=None, pix_base: int = 0, wref=None,
               total_bounces: int | None = None, caustics: PathLight | None = None, light_traced: bool = False) -> None:
        """Trace a batch of chain rays and everything they spawn, accumulating into acc[pix - pix_base];
        ``sidx`` (int64) and ``skey`` (uint64) are each ray's sample index and dimension key
        (engine/sampler.py). ``first_hits`` = (prim int32, u, v float32): the first intersection of
        every ray is given (no Embree query for it), e.g. a sample of a layered depth image.
        ``wref``: the throughput reference of Russian roulette of path rays (``_spawn``; default 0:
        none); ``total_bounces``: the bounce budget the paths started with (default
        ``params.indirect_bounces``). ``caustics``: a caustic photon map (engine/caustics.py) that
        brings the light paths would find through mirror / glossy lobes to lights: path vertices
        then neither see lights through those lobes nor take the glossy lobe's next-event
        estimation, and every diffuse path vertex with a bounce left gets the map's irradiance (a
        last vertex's light through a mirror would be a path longer than the bounce budget).
        ``light_traced``: the diffuse paths of direct camera hits carry the LIGHT_TRACED flag (their
        light through mirror / glossy lobes is a ``CausticLightTracer``'s, engine/light_tracing.py)."""
        sc = self.scene
        mt = sc.materials
        lt = sc.lights
        caster = self.caster
        n = d.shape[0]
        # K paths per pixel spread over the spp camera samples
        k_per_hit = 0
        if params.indirect_samples > 0:
            k_per_hit = max(1, math.ceil(params.indirect_samples / params.spp))
        r_g = max(1, int(round(math.sqrt(params.area_light_samples))))
        total = params.indirect_bounces if total_bounces is None else int(total_bounces)
        bpdf = np.zeros(n)  # camera rays (and given starts): no BSDF strategy to weigh
        wref = np.zeros(n) if wref is None else np.ascontiguousarray(wref, np.float64)
        it = 0
        while n > 0:
            it += 1
            t0 = time.perf_counter()
            if it == 1 and first_hits is not None:
                prim, u, v = first_hits
            else:
                prim, u, v = caster.intersect_local(o32, d32, serial)
            timer.add("intersect", time.perf_counter() - t0)
            t0 = time.perf_counter()
            # rect lights seen by camera / mirror / glossy rays (a given first hit has no ray to test)
            lit = _NO_LIT
            lit_c = _NO_LIT_C
            if lt.n_rect and not (it == 1 and first_hits is not None) and np.any((kind & KIND_BASE) != KIND_PATH):
                lit = np.empty(n, np.bool_)
                lit_c = np.empty((n, 3))
                run_pieces_parallel(_rect_hits, n, _MIN_ITEMS, serial, o32, d, prim, u, v, kind, weight, bpdf,
                                    r_g * r_g, self._mis, caustics is None, sc.tri_p, sc.center, lt.rect_corner,
                                    lt.rect_edge_u, lt.rect_edge_v, self._rect_n, self._rect_area, lt.rect_radiance,
                                    lt.rect_two_sided, lit, lit_c)
                # a ray that ends on a light hits nothing; a last vertex's light-seeking ray (bounces
                # -1, see _plan) only counts the light it meets
                idx = np.flatnonzero((prim >= 0) & ~lit & (bounces >= 0))
            else:
                idx = np.flatnonzero(prim >= 0)
            m = idx.size
            p = np.empty((m, 3))
            ng = np.empty((m, 3))
            ns = np.empty((m, 3))
            mat = np.empty(m, np.int32)
            d_h = np.empty((m, 3))
            w_h = np.empty((m, 3))
            wref_h = np.empty(m)
            kind_h = np.empty(m, np.int8)
            depth_h = np.empty(m, np.int32)
            bnc_h = np.empty(m, np.int32)
            pix_h = np.empty(m, np.int64)
            sidx_h = np.empty(m, np.int64)
            skey_h = np.empty(m, np.uint64)
            run_pieces_parallel(_gather_hits, m, _MIN_ITEMS, serial, idx, prim, u, v, d, weight, wref, kind, depth,
                                bounces, pix, sidx, skey, sc.tri_p, sc.tri_n, sc.tri_ng, sc.tri_material, p, ng, ns,
                                mat, d_h, w_h, wref_h, kind_h, depth_h, bnc_h, pix_h, sidx_h, skey_h)
            _accumulate_misses_and_emission(acc, prim, weight, pix - pix_base if pix_base else pix, sc.background,
                                            idx, mat, kind_h, w_h, pix_h - pix_base if pix_base else pix_h,
                                            mt.emission, mt.kd, sc.ambient, lit, lit_c)
            if caustics is not None and m:
                # a vertex with no bounce left gets no caustic light, as with paths alone: its light
                # through a mirror would be a path one segment longer than the bounce budget
                caustics.add_path_light(acc, pix_h, pix_base, (kind_h != KIND_CHAIN) & (bnc_h > 0), mat, w_h, p, ng,
                                        mt.kd)
            timer.add("shading", time.perf_counter() - t0)
            if m == 0:
                break

            # ---- direct light (next-event estimation) at every hit
            if lt.count:
                self._direct(params, it, p, ng, ns, d_h, mat, w_h, kind_h, depth_h, bnc_h, pix_h, sidx_h, skey_h,
                             r_g, acc, timer, counts, serial, pix_base, path_glossy=caustics is None)

            # ---- secondary rays
            t0 = time.perf_counter()
            n_mirror = np.empty(m, np.int64)
            n_glossy = np.empty(m, np.int64)
            n_ind = np.empty(m, np.int64)
            count = np.empty(m, np.int64)
            # hits of the glossy rays of a first glossy bounce: depth 1, arrived by a glossy ray (bpdf > 0)
            split = (depth_h == 1) & (bpdf[idx] > 0.0) if k_per_hit > 1 else np.zeros(m, np.bool_)
            run_pieces_parallel(_plan, m, _MIN_COPY, serial, mat, w_h, kind_h, depth_h, bnc_h, split, mt.kd, mt.kr,
                                mt.kg, params.max_depth, params.glossy_samples, k_per_hit,
                                lt.n_rect > 0 and caustics is None, n_mirror,
                                n_glossy, n_ind, count)
            first = np.zeros(m, np.int64)
            np.cumsum(count[:-1], out=first[1:])
            tot = int(first[-1] + count[-1])
            if tot == 0:
                timer.add("shading", time.perf_counter() - t0)
                break
            o2 = np.empty((tot, 3), np.float32)
            d2 = np.empty((tot, 3))
            w2 = np.empty((tot, 3))
            kind2 = np.empty(tot, np.int8)
            depth2 = np.empty(tot, np.int32)
            bnc2 = np.empty(tot, np.int32)
            pix2 = np.empty(tot, np.int64)
            sidx2 = np.empty(tot, np.int64)
            skey2 = np.empty(tot, np.uint64)
            bpdf2 = np.empty(tot)
            wref2 = np.empty(tot)
            alive = np.empty(tot, np.bool_)
            d2_32 = np.empty((tot, 3), np.float32)
            run_pieces_parallel(_spawn, m, _MIN_HEAVY, serial, p, ng, ns, d_h, mat, w_h, wref_h, kind_h, depth_h, bnc_h,
                                pix_h, sidx_h, skey_h, first, n_mirror, n_glossy, n_ind, count, it, total, self._rr_min,
                                light_traced, mt.kd, mt.kr, mt.kg, mt.gloss_exponent, sc.center, sc.extent, o2, d2,
                                d2_32, w2, kind2, depth2, bnc2, pix2, sidx2, skey2, bpdf2, wref2, alive)
            n_alive = int(np.count_nonzero(alive))
            if n_alive >= 0.95 * tot:
                # few dead rays: tracing them (weight 0, they spawn nothing) is cheaper than a copy
                o32, d, d32, weight, kind, depth, bounces, pix = o2, d2, d2_32, w2, kind2, depth2, bnc2, pix2
                sidx, skey, bpdf, wref = sidx2, skey2, bpdf2, wref2
                n = tot
            else:
                live = np.flatnonzero(alive)
                n = live.size
                o32 = np.empty((n, 3), np.float32)
                d = np.empty((n, 3))
                d32 = np.empty((n, 3), np.float32)
                weight = np.empty((n, 3))
                kind = np.empty(n, np.int8)
                depth = np.empty(n, np.int32)
                bounces = np.empty(n, np.int32)
                pix = np.empty(n, np.int64)
                sidx = np.empty(n, np.int64)
                skey = np.empty(n, np.uint64)
                bpdf = np.empty(n)
                wref = np.empty(n)
                run_pieces_parallel(_compact_rays, n, _MIN_COPY, serial, live, o2, d2, w2, bpdf2, wref2, kind2, depth2,
                                    bnc2, pix2, sidx2, skey2, o32, d, d32, weight, bpdf, wref, kind, depth, bounces,
                                    pix, sidx, skey)
            n_path = int(np.count_nonzero(kind))
            counts["indirect"] += n_path
            counts["reflection"] += n - n_path
            timer.add("shading", time.perf_counter() - t0)

    def _direct(self, params: ReferenceParams, it, p, ng, ns, d_h, mat, w_h, kind_h, depth_h, bnc_h, pix_h, sidx_h,
                skey_h, r_g, acc, timer, counts, serial, pix_base: int = 0, path_glossy: bool = True):
        sc, mt, lt = self.scene, self.scene.materials, self.scene.lights
        gg = r_g * r_g
        per = lt.n_point + lt.n_directional + lt.n_rect * gg
        m = p.shape[0]
        # bound memory: process hits in slices of at most ~2M shadow rays
        step = max(1, (1 << 21) // per)
        for s in range(0, m, step):
            t0 = time.perf_counter()
            sl = slice(s, min(m, s + step))
            k = sl.stop - sl.start
            rows = k * per
            so = np.empty((rows, 3), np.float32)
            sd = np.empty((rows, 3), np.float32)
            tmax = np.empty(rows, np.float32)
            contrib = np.empty((rows, 3))
            alive = np.empty(rows, np.bool_)
            run_pieces_parallel(_light_rays, k, _MIN_HEAVY, serial, p[sl], ng[sl], ns[sl], d_h[sl], mat[sl], w_h[sl],
                                kind_h[sl], depth_h[sl], bnc_h[sl], mt.kd, mt.ks, mt.shininess, self._spec_cut, mt.kr,
                                mt.kg, mt.gloss_exponent, params.max_depth, params.glossy_samples, self._mis,
                                lt.point_position, lt.point_intensity, lt.dir_direction, lt.dir_irradiance,
                                lt.rect_corner, lt.rect_edge_u, lt.rect_edge_v, self._rect_n, self._rect_area,
                                lt.rect_radiance, lt.rect_two_sided, r_g, pix_h[sl], sidx_h[sl], skey_h[sl], it,
                                path_glossy, sc.center, sc.extent, so, sd, tmax, contrib, alive)
            live = np.flatnonzero(alive)
            timer.add("shading", time.perf_counter() - t0)
            if live.size == 0:
                continue
            t0 = time.perf_counter()
            so_l = np.empty((live.size, 3), np.float32)
            sd_l = np.empty((live.size, 3), np.float32)
            tm_l = np.empty(live.size, np.float32)
            run_pieces_parallel(_compact_shadow, live.size, _MIN_COPY, serial, live, so, sd, tmax, so_l, sd_l, tm_l)
            timer.add("shading", time.perf_counter() - t0)
            t0 = time.perf_counter()
            occ = self.caster.occluded_local(so_l, sd_l, tm_l, serial)
            timer.add("shadow", time.perf_counter() - t0)
            counts["shadow"] += int(live.size)
            t0 = time.perf_counter()
            _accumulate_shadow(acc, live, occ, contrib, pix_h[sl] - pix_base if pix_base else pix_h[sl], per)
            timer.add("shading", time.perf_counter() - t0)


def render_reference(scene: RuntimeScene, camera: CameraParams, params: ReferenceParams | None = None,
                     backend: str = "embree",
                     progress: Callable[[float, str], None] | None = None) -> RenderOutput:
    """Convenience wrapper: build a caster for ``scene`` and render one view."""
    return ReferenceRenderer(scene, make_caster(scene, backend)).render(camera, params, progress)
