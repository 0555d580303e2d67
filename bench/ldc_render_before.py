"""FROZEN COPY, for the A/B in ``bench/ldc_speed.py`` only: ``engine/ldc_render.py`` as of commit
e20c1cc (session 3, before the fused per-pixel kernels), imports made absolute. It renders the
same images as the current renderer (the benchmark checks that) through numpy gathers and one
numba kernel per stage. Not part of the product; do not import it elsewhere.

Original module docstring follows.

Render a new view from a baked LDC (+ LLF): the first paper's rendering (ALGORITHMS.md part A).

``LDCViewRenderer(scene, ldc, llf, plan).render(camera, method, ibrt_generations=k)``:

1. **Warp** (``engine/warp.py``): every LDC sample into the camera with a depth test; holes
   flagged (uncovered pixels and far surfaces seen through cracks).
2. **Hole filling**: ``fill="ibrt"`` (default) traces one image-based ray per hole pixel from
   the eye through the LDC (``engine/ibrt.py``); a hit shows that sample's diffuse radiance,
   a miss the background. ``fill="raycast"`` (the interim fill) casts Embree rays against
   the scene's triangles instead and shades the hits with the bake's diffuse model (it
   needs the triangles; the image-based fill needs only the bake). ``fill="none"`` leaves
   holes as background.
3. **View-dependent pass**, only on the visible pixels whose material needs it (the effect
   plan; ``force_all_passes=True`` runs every pass of the method on every covered pixel,
   for the test that skipping changes nothing): Phong highlights gated by the LDC's
   visibility bits (``engine/view_pass.py``), then reflections:

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
from scipy.ndimage import maximum_filter

from engine.camera import camera_rays
from engine.effects import EffectPlan, analyze, plan_from_dict
from engine.errors import InvalidInputError, NonFiniteOutputError
from engine.ldc import LDC, shade_samples, surface_attributes
from engine.llf import LLF
from engine.raycast import RayCaster, make_caster
from engine.scene import CameraParams, RuntimeScene
from engine.view_pass import gather_reflections, highlights
from engine.warp import warp_ldc

PROV_NONE = 0
PROV_WARPED = 1
PROV_FILLED = 2
PROV_GATHERED = 3
PROV_TRACED = 4

METHODS = ("ldc", "ldc+llf", "ldc+ibrt")
FILLS = ("ibrt", "raycast", "none")
MAX_IBRT_GENERATIONS = 8


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
    """("ldc" | "ldc+llf" | "ldc+ibrt", k); also accepts the API's "ldc+ibrt:k"."""
    if isinstance(method, str) and method.startswith("ldc+ibrt:"):
        try:
            ibrt_generations = int(method.split(":", 1)[1])
        except ValueError:
            raise InvalidInputError(f"method {method!r}: the part after ':' must be an integer 0..8") from None
        method = "ldc+ibrt"
    if method not in METHODS:
        raise InvalidInputError(f"method must be one of {list(METHODS)} or 'ldc+ibrt:k', got {method!r}")
    if not isinstance(ibrt_generations, (int, np.integer)) or isinstance(ibrt_generations, bool) or \
            not (0 <= ibrt_generations <= MAX_IBRT_GENERATIONS):
        raise InvalidInputError(f"ibrt_generations must be an integer in [0, {MAX_IBRT_GENERATIONS}], "
                                f"got {ibrt_generations!r}")
    if method != "ldc+ibrt":
        ibrt_generations = 0
    return method, int(ibrt_generations)


@nb.njit(cache=True, parallel=True, nogil=True)
def _gather_samples(sel, idx, side, origin, fu, fv, fw, h, nu, offsets, depth, geo, nrm, material, obj, diffuse,
                    vis, p, ng, ns, mat, obj_out, diff, bits):
    """Rows ``sel`` of the outputs from LDC samples ``idx[sel]`` on ``side[sel]`` of one axis:
    world point (pixel found by binary search in the CSR offsets), normals flipped to the side
    (shading normal falling back to the geometric one), ids, diffuse radiance, bits."""
    words = bits.shape[1]
    for t in nb.prange(sel.shape[0]):
        r = sel[t]
        s = idx[r]
        k = np.searchsorted(offsets, s, side="right") - 1
        a = (k % nu + 0.5) * h
        b = (k // nu + 0.5) * h
        for c in range(3):
            p[r, c] = origin[c] + a * fu[c] + b * fv[c] + depth[s] * fw[c]
        sd = side[r]
        sg = 1.0 if sd == 0 else -1.0
        g0, g1, g2 = sg * geo[s, 0], sg * geo[s, 1], sg * geo[s, 2]
        n0, n1, n2 = sg * nrm[s, 0], sg * nrm[s, 1], sg * nrm[s, 2]
        if n0 * g0 + n1 * g1 + n2 * g2 <= 0.0:
            n0, n1, n2 = g0, g1, g2
        ng[r, 0], ng[r, 1], ng[r, 2] = g0, g1, g2
        ns[r, 0], ns[r, 1], ns[r, 2] = n0, n1, n2
        mat[r] = material[s]
        obj_out[r] = obj[s]
        for c in range(3):
            diff[r, c] = diffuse[s, sd, c]
        for q in range(words):
            bits[r, q] = vis[s, sd, q]


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _refine(rows, o, d, prim, tri_p, tri_n, tri_ng, max_move, p, ng, ns):
    """For row rows[i] (pixel ray o[i] + t d[i], sample triangle prim[i]): move p to the ray's
    crossing with the triangle's plane (when within max_move[i] of the sample) and interpolate
    the shading normal there (barycentrics clamped to [-0.25, 1.25]: mild extrapolation
    across the triangle's edges), flipped like ng; ng is unchanged."""
    for i in nb.prange(rows.shape[0]):
        r = rows[i]
        t = prim[i]
        g0, g1, g2 = ng[r, 0], ng[r, 1], ng[r, 2]
        den = d[i, 0] * g0 + d[i, 1] * g1 + d[i, 2] * g2
        if abs(den) < 1e-9:
            continue
        ax, ay, az = tri_p[t, 0, 0], tri_p[t, 0, 1], tri_p[t, 0, 2]
        tt = ((ax - o[i, 0]) * g0 + (ay - o[i, 1]) * g1 + (az - o[i, 2]) * g2) / den
        if not tt > 0.0:
            continue
        qx, qy, qz = o[i, 0] + tt * d[i, 0], o[i, 1] + tt * d[i, 1], o[i, 2] + tt * d[i, 2]
        dx, dy, dz = qx - p[r, 0], qy - p[r, 1], qz - p[r, 2]
        if not (dx * dx + dy * dy + dz * dz <= max_move[i] * max_move[i]):
            continue
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
            continue
        bu = min(max((d11 * d20 - d01 * d21) / dd, -0.25), 1.25)
        bv = min(max((d00 * d21 - d01 * d20) / dd, -0.25), 1.25)
        bw = min(max(1.0 - bu - bv, -0.25), 1.25)
        n0 = bw * tri_n[t, 0, 0] + bu * tri_n[t, 1, 0] + bv * tri_n[t, 2, 0]
        n1 = bw * tri_n[t, 0, 1] + bu * tri_n[t, 1, 1] + bv * tri_n[t, 2, 1]
        n2 = bw * tri_n[t, 0, 2] + bu * tri_n[t, 1, 2] + bv * tri_n[t, 2, 2]
        ln = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        if not ln > 1e-12:
            continue
        sg = 1.0 if g0 * tri_ng[t, 0] + g1 * tri_ng[t, 1] + g2 * tri_ng[t, 2] >= 0.0 else -1.0
        n0, n1, n2 = sg * n0 / ln, sg * n1 / ln, sg * n2 / ln
        if n0 * g0 + n1 * g1 + n2 * g2 <= 0.0:
            n0, n1, n2 = g0, g1, g2
        p[r, 0], p[r, 1], p[r, 2] = qx, qy, qz
        ns[r, 0], ns[r, 1], ns[r, 2] = n0, n1, n2


class LDCViewRenderer:
    """Holds the scene's tables, the LDC, the LLF (None when the plan needs none) and, built
    lazily on first use, the IBRT acceleration structure. Reusable across renders (cache it
    per worker); ``render`` is not meant to run in two threads at once (numba's workqueue
    layer), a lock serialises it."""

    def __init__(self, scene: RuntimeScene, ldc: LDC, llf: LLF | None, plan: EffectPlan | dict | None = None, *,
                 caster: RayCaster | None = None, area_light_samples: int = 16, seed: int = 0,
                 warp_options: dict | None = None, hole_search_px: int | None = 3, refine_surface: bool = True):
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
        self.warp_options = dict(warp_options or {})
        bad = set(self.warp_options) - {"min_cos", "max_footprint", "footprint_scale", "hole_rel_depth",
                                         "hole_neighbors"}
        if bad:
            raise InvalidInputError(f"unknown warp options {sorted(bad)}")
        self._accel = None
        self._lock = threading.Lock()
        mt = scene.materials
        self._has_ks = (np.any(mt.ks > 0, axis=1) & (mt.shininess > 0))
        self._has_kr = np.any(mt.kr > 0, axis=1)
        self._has_kg = np.any(mt.kg > 0, axis=1)

    # ------------------------------------------------------------------ resources
    @property
    def accel(self):
        if self._accel is None:
            from engine.ibrt import build_accel

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
        return int(n)

    # ------------------------------------------------------------------ helpers
    def _sample_surface(self, axis: np.ndarray, idx: np.ndarray, side: np.ndarray):
        """World point, normals (flipped to ``side``, shading normal falling back to the
        geometric one), material and visibility bits of LDC samples."""
        ldc = self.ldc
        m = axis.shape[0]
        p = np.empty((m, 3))
        ng = np.empty((m, 3))
        ns = np.empty((m, 3))
        mat = np.empty(m, np.int32)
        obj = np.empty(m, np.int32)
        diff = np.empty((m, 3))
        bits = np.zeros((m, ldc.visibility_words), np.uint64)
        for a, ax in enumerate(ldc.axes):
            sel = np.flatnonzero(axis == a)
            if not sel.size:
                continue
            fr = ax.ldi.frame
            _gather_samples(sel, idx, side, fr.origin, fr.u, fr.v, fr.w, fr.h, fr.nu, ax.ldi.offsets, ax.ldi.depth,
                            ax.geo_normal, ax.normal, ax.material, ax.object, ax.diffuse, ax.visibility,
                            p, ng, ns, mat, obj, diff, bits)
        return p, ng, ns, mat, obj, diff, bits

    def _hole_rays(self, camera: CameraParams, w) -> np.ndarray:
        """The hole pixels worth a ray: covered pixels flagged as holes (a far surface seen
        through a crack), and uncovered pixels within ``hole_search_px`` of a covered one whose
        ray meets the scene's bounds. An uncovered pixel farther from every splat is background:
        any LDC sample its ray could meet would have been splatted within about a pixel of it
        (the image-based ray tracer finds nothing the warp doesn't have). ``None``: every hole."""
        hm = w.hole_mask
        if self.hole_search_px is not None:
            covered = w.sample_axis >= 0
            r = self.hole_search_px
            near = maximum_filter(covered.view(np.uint8), size=2 * r + 1, mode="constant") > 0 if r else covered
            hm = hm & near
        pix = np.flatnonzero(hm.reshape(-1))
        if self.hole_search_px is None or not pix.size:
            return pix
        o, d = camera_rays(camera, pix % camera.width + 0.5, pix // camera.width + 0.5)
        lo, hi = self.scene.bounds
        pad = self.ldc.h
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            t0 = ((lo - pad) - o) * inv
            t1 = ((hi + pad) - o) * inv
        tn = np.nanmax(np.minimum(t0, t1), axis=1)
        tf = np.nanmin(np.maximum(t0, t1), axis=1)
        return pix[tf >= np.maximum(tn, 0.0)]

    def _wo(self, camera: CameraParams, p: np.ndarray) -> np.ndarray:
        _, _, fwd = camera.basis()
        if camera.kind == "orthographic":
            return np.ascontiguousarray(np.broadcast_to(-fwd, p.shape))
        wo = np.asarray(camera.eye, np.float64)[None] - p
        ln = np.linalg.norm(wo, axis=1, keepdims=True)
        return wo / np.where(ln > 0, ln, 1.0)

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

        # ---- 1. warp
        w = warp_ldc(ldc, camera, fill="none", **self.warp_options)
        timings["warp"] = w.timings["splat"] + w.timings["resolve"]
        timings["holes"] = w.timings["holes"]
        H, W = camera.height, camera.width
        radiance = w.radiance.reshape(-1, 3).astype(np.float64)
        depth = w.depth.reshape(-1).copy()
        normal = w.normal.reshape(-1, 3).copy()
        obj_id = w.object_id.reshape(-1).copy()
        mat_id = w.material_id.reshape(-1).copy()
        prov = w.provenance.reshape(-1).copy()
        s_axis = w.sample_axis.reshape(-1).copy()
        s_idx = w.sample_index.reshape(-1).copy()
        s_side = w.sample_side.reshape(-1).copy()
        passes["warp"] = {"ran": True, "why": "always: the LDC's view-independent radiance"}
        counts["warped_pixels"] = int((prov == PROV_WARPED).sum())
        counts["hole_pixels"] = w.n_holes
        report(0.3, "warp")

        # ---- 2. holes
        t0 = time.perf_counter()
        holes = self._hole_rays(camera, w)
        counts["hole_rays"] = int(holes.size)
        filled = 0
        rc_pix = np.zeros(0, np.int64)  # pixels filled by the raycast fill (no LDC sample)
        rc_surf = None
        if fill != "none" and holes.size:
            o, d = camera_rays(camera, holes % W + 0.5, holes // W + 0.5)
            # the warp's (covered) value is replaced by the ray's answer
            radiance[holes] = ldc.background
            depth[holes] = 0.0
            normal[holes] = 0.0
            obj_id[holes] = -1
            mat_id[holes] = -1
            prov[holes] = PROV_NONE
            s_axis[holes] = -1
            s_idx[holes] = -1
            if fill == "ibrt":
                from engine.ibrt import trace

                hits = trace(ldc, self.accel, o, d)
                counts["fill_ibrt_steps"] = hits.n_steps
                hp = holes[hits.hit]
                if hp.size:
                    s_axis[hp] = hits.axis[hits.hit]
                    s_idx[hp] = hits.sample[hits.hit]
                    s_side[hp] = hits.side[hits.hit]
                    _, _, ns_, mat_, obj_, diff_, _ = self._sample_surface(s_axis[hp], s_idx[hp], s_side[hp])
                    radiance[hp] = diff_
                    depth[hp] = hits.t[hits.hit]
                    normal[hp] = ns_
                    obj_id[hp] = obj_
                    mat_id[hp] = mat_
                    prov[hp] = PROV_FILLED
                filled = int(hp.size)
            else:
                rc_pix, rc_surf = self._raycast_fill(o, d, holes, radiance, depth, normal, obj_id, mat_id, prov)
                filled = int(rc_pix.size)
        timings["fill"] = time.perf_counter() - t0
        counts["filled_pixels"] = filled
        passes["fill"] = {"ran": bool(fill != "none" and holes.size), "how": fill,
                          "why": f"{holes.size} hole pixels" if holes.size else "no holes"}
        report(0.5, "fill")

        # ---- 3. view-dependent pass
        covered = obj_id >= 0
        mats = np.where(covered, mat_id, 0)
        nondiffuse = self._has_ks | self._has_kr | self._has_kg
        want_vp = force or self.plan.needs_view_pass
        sel_hl = covered & (True if force else self._has_ks[mats]) if want_vp else np.zeros_like(covered)
        reflect = method != "ldc"
        refl_mat = self._has_kr | self._has_kg
        sel_rf = covered & (True if force else refl_mat[mats]) if (want_vp and reflect) else np.zeros_like(covered)
        if reflect and self.llf is None and sel_rf.any():
            if force and not self.plan.needs_llf:
                sel_rf[:] = False
                passes["gather_note"] = {"why": "forced, but there is no LLF to gather from"}
            else:
                raise InvalidInputError(f"method {method!r} needs the bake's LLF (the scene has glossy or mirror "
                                        "materials) but this bake has none; use method 'ldc' or rebake with an LLF")
        vp_pix = np.flatnonzero(sel_hl | sel_rf)
        counts["view_pass_pixels"] = int(vp_pix.size)
        counts["highlight_pixels"] = int(sel_hl.sum())
        counts["reflection_pixels"] = int(sel_rf.sum())
        why_vp = ("forced on every covered pixel" if force else
                  ("the plan has non-diffuse materials" if self.plan.needs_view_pass
                   else "skipped: every material is diffuse"))
        t0 = time.perf_counter()
        if vp_pix.size:
            p, ng, ns, mat, bits = self._pixel_surfaces(camera, vp_pix, s_axis, s_idx, s_side, rc_pix, rc_surf)
            wo = self._wo(camera, p)
            normal[vp_pix] = ns  # the (refined) shading normal the view pass used
        timings["surfaces"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        if sel_hl.any():
            pos = np.flatnonzero(sel_hl[vp_pix])
            spec = highlights(sc, p[pos], ng[pos], ns[pos], wo[pos], mat[pos], bits[pos],
                              area_light_samples=self.area_light_samples, seed=self.seed, force=force)
            radiance[vp_pix[pos]] += spec
        timings["highlights"] = time.perf_counter() - t0
        passes["highlights"] = {"ran": bool(sel_hl.any()), "why": why_vp,
                                "pixels": int(sel_hl.sum())}
        report(0.6, "highlights")

        t0 = time.perf_counter()
        counts["gather_lookups"] = 0
        counts["gather_pixels"] = 0
        trace_mirror = method == "ldc+ibrt" and k > 0
        if sel_rf.any():
            pos = np.flatnonzero(sel_rf[vp_pix])
            refl, n_look = gather_reflections(sc, self.llf, p[pos], ng[pos], ns[pos], wo[pos], mat[pos],
                                              mirror=not trace_mirror, glossy=True, force=force)
            radiance[vp_pix[pos]] += refl
            counts["gather_lookups"] = n_look
            gathered = vp_pix[pos][refl_mat[mat[pos]] if not trace_mirror else self._has_kg[mat[pos]]]
            prov[gathered] = PROV_GATHERED
            counts["gather_pixels"] = int(gathered.size)
        timings["gather"] = time.perf_counter() - t0
        passes["gather"] = {"ran": bool(sel_rf.any()),
                            "what": ("glossy lobe" if trace_mirror else "mirror cone + glossy lobe"),
                            "why": ("method 'ldc' has no reflections" if not reflect else why_vp)}
        report(0.75, "gather")

        t0 = time.perf_counter()
        counts["traced_rays"] = 0
        counts["ibrt_steps"] = 0
        if trace_mirror and sel_rf.any():
            pos = np.flatnonzero(sel_rf[vp_pix])
            traced = self._trace_mirrors(vp_pix[pos], p[pos], ng[pos], ns[pos], wo[pos], mat[pos], k, radiance,
                                         counts, force)
            prov[traced[self._has_kr[mat_id[traced]]]] = PROV_TRACED
        timings["ibrt"] = time.perf_counter() - t0
        passes["ibrt"] = {"ran": bool(trace_mirror and sel_rf.any()), "generations": k,
                          "why": ("method is not ldc+ibrt:k with k >= 1" if not trace_mirror else why_vp)}
        report(0.95, "ibrt")

        out = radiance.reshape(H, W, 3).astype(np.float32)
        if not np.all(np.isfinite(out)) or not np.all(np.isfinite(depth)):
            raise NonFiniteOutputError("LDC render produced non-finite values")
        timings["total"] = time.perf_counter() - t_start
        plan = {"method": method if method != "ldc+ibrt" else f"ldc+ibrt:{k}", "ibrt_generations": k, "fill": fill,
                "refine_surface": self.refine_surface,
                "force_all_passes": force, "passes": passes, "effects": self.plan.to_dict(),
                "non_diffuse_materials": [int(i) for i in np.flatnonzero(nondiffuse)]}
        report(1.0, "done")
        return LDCRenderResult(radiance=out, depth=depth.reshape(H, W).astype(np.float32),
                               normal=normal.reshape(H, W, 3).astype(np.float32),
                               object_id=obj_id.reshape(H, W).astype(np.int32),
                               material_id=mat_id.reshape(H, W).astype(np.int32),
                               provenance=prov.reshape(H, W).astype(np.uint8), hole_mask=w.hole_mask,
                               timings=timings, counts=counts, plan=plan)

    def _pixel_surfaces(self, camera, pix, s_axis, s_idx, s_side, rc_pix, rc_surf):
        """Surface records (point, normals facing the eye, material, bits) of covered pixels.
        With ``refine_surface`` an LDC sample's point moves to where the pixel-centre ray meets
        the sample's triangle plane and its shading normal is interpolated there (the LDI keeps
        triangle id and barycentrics per sample): highlights and reflection directions are then
        evaluated per pixel instead of per (up to several pixels wide) splat."""
        m = pix.shape[0]
        p = np.empty((m, 3))
        ng = np.empty((m, 3))
        ns = np.empty((m, 3))
        mat = np.empty(m, np.int32)
        bits = np.zeros((m, self.ldc.visibility_words), np.uint64)
        from_ldc = s_axis[pix] >= 0
        if from_ldc.any():
            q = pix[from_ldc]
            p[from_ldc], ng[from_ldc], ns[from_ldc], mat[from_ldc], _, _, bits[from_ldc] = \
                self._sample_surface(s_axis[q], s_idx[q], s_side[q])
            if self.refine_surface:
                sel = np.flatnonzero(from_ldc)
                prim = np.empty(q.size, np.int32)
                for a, ax in enumerate(self.ldc.axes):
                    on = s_axis[q] == a
                    prim[on] = ax.ldi.prim[s_idx[q][on]]
                o, d = camera_rays(camera, q % camera.width + 0.5, q // camera.width + 0.5)
                sc = self.scene
                # the winning sample lies within about a pixel footprint or an LDC cell of the pixel's ray
                if camera.kind == "perspective":
                    px_size = 2.0 * math.tan(math.radians(camera.fov_y_deg) * 0.5) / camera.height
                    reach = px_size * np.linalg.norm(p[sel] - o, axis=1)
                else:
                    reach = np.full(sel.size, camera.ortho_height / camera.height)
                lim = 2.0 * (self.ldc.h + reach)
                _refine(sel, o, d, prim, sc.tri_p, sc.tri_n, sc.tri_ng, lim, p, ng, ns)
        if (~from_ldc).any():
            q = pix[~from_ldc]
            j = np.searchsorted(rc_pix, q)
            if rc_surf is None or np.any(j >= rc_pix.size) or np.any(rc_pix[np.minimum(j, rc_pix.size - 1)] != q):
                raise AssertionError("covered pixel without a surface record")  # pragma: no cover
            rp, rng_, rns, rmat, rbits = rc_surf
            p[~from_ldc], ng[~from_ldc], ns[~from_ldc], mat[~from_ldc] = rp[j], rng_[j], rns[j], rmat[j]
            if bits.shape[1]:
                bits[~from_ldc] = rbits[j]
        return p, ng, ns, mat, bits

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

    def _trace_mirrors(self, pix, p, ng, ns, wo, mat, k, radiance, counts, force) -> np.ndarray:
        """k generations of image-based mirror rays ending in the cone gather (module docstring).
        Adds kr x (traced radiance) to ``radiance[pix]``; returns the pixels that traced."""
        from engine.ibrt import trace

        sc, ldc = self.scene, self.ldc
        mt = sc.materials
        bg = np.asarray(ldc.background, np.float64)
        # generation 0: the pixels' own mirror rays
        c = np.einsum("ij,ij->i", ns, wo)
        d = 2.0 * c[:, None] * ns - wo
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        live = (self._has_kr[mat] & (np.einsum("ij,ij->i", ng, d) > 0.0)) | force
        out_pix = pix[live]
        thr = mt.kr[mat[live]].astype(np.float64)
        o, d, ng_o = p[live], d[live], ng[live]
        owner = np.arange(out_pix.size)
        acc = np.zeros((out_pix.size, 3))
        for gen in range(1, k + 1):
            if not owner.size:
                break
            hits = trace(ldc, self.accel, o, d, origin_normals=ng_o)  # leaves the surface it starts on
            counts["traced_rays"] += int(owner.size)
            counts["ibrt_steps"] += hits.n_steps
            miss = ~hits.hit
            if miss.any():
                np.add.at(acc, owner[miss], thr[miss] * bg)
            h = np.flatnonzero(hits.hit)
            if not h.size:
                break
            hp, hng, hns, hmat, _, hdiff, hbits = self._sample_surface(hits.axis[h], hits.sample[h], hits.side[h])
            hp = hits.point[h]  # where the ray meets the sample's patch
            hwo = -d[h]
            local = hdiff + highlights(sc, hp, hng, hns, hwo, hmat, hbits, area_light_samples=self.area_light_samples,
                                       seed=self.seed, force=force)
            last = gen == k
            if self.llf is not None:
                g_refl, n_look = gather_reflections(sc, self.llf, hp, hng, hns, hwo, hmat, mirror=last, glossy=True,
                                                    force=force)
                local += g_refl
                counts["gather_lookups"] += n_look
            np.add.at(acc, owner[h], thr[h] * local)
            if last:
                break
            # next generation: mirror rays of the hits that are mirrors
            c = np.einsum("ij,ij->i", hns, hwo)
            nd = 2.0 * c[:, None] * hns - hwo
            nd /= np.linalg.norm(nd, axis=1, keepdims=True)
            cont = (self._has_kr[hmat] & (np.einsum("ij,ij->i", hng, nd) > 0.0)) | force
            owner = owner[h][cont]
            thr = thr[h][cont] * mt.kr[hmat[cont]]
            o, d, ng_o = hp[cont], nd[cont], hng[cont]
        radiance[out_pix] += acc
        return out_pix


__all__ = ["FILLS", "LDCRenderResult", "LDCViewRenderer", "MAX_IBRT_GENERATIONS", "METHODS", "PROV_FILLED",
           "PROV_GATHERED", "PROV_NONE", "PROV_TRACED", "PROV_WARPED", "parse_method"]
