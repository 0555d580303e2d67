"""Layered depth cube (LDC): three LDIs along +x, +y, +z with per-sample attributes.

Per sample (CSR order of its LDI): shading normal (interpolated, unflipped, float32),
geometric normal (float32), ``facing`` (+1 when the geometric normal faces the LDI's
reference plane, i.e. n_g . w < 0, else -1), material id, object id, diffuse radiance for
BOTH sides of the surface (``diffuse`` (n, 2, 3) float32; side 0 is the side the geometric
normal points to, side 1 the other; surfaces are two-sided as in the reference renderer)
and a light-visibility bitmask per side (``visibility`` (n, 2, W) uint64, W =
ceil(n_lights / 64) words, bit i of word i // 64 set when light i lies in front of that
side and is unoccluded from it; for a rect light: when any of its samples is). When the
effect plan finds no occludable light, W = 0: no bits are stored and no shadow rays cast.

``diffuse`` holds everything view-independent the reference renderer shows at a camera
hit: direct diffuse ``kd/pi sum E cos`` over the lights (point and directional exact, rect
lights at g x g points, g = round(sqrt(area_light_samples)), each sample's points the first g*g
of its own Owen-scrambled Sobol sequence over the light, ``rect_net_point``: deterministic per seed,
the same however the bake is sliced or chunked) + ``kd * ambient`` + ``emission``. Light conventions
(offset origins, shadow shortening, shading-normal fallback) copy ``engine/reference.py``.

With ``indirect`` settings, ``diffuse`` also holds the indirect diffuse light (interreflections
up to a bounce limit, path-traced per sample side to a requested noise level:
``engine/newviews/indirect.py``), unless the effect plan finds that no indirect light can reach a
diffuse surface (``EffectPlan.indirect_skip``).

Baking is split per axis (``bake_ldc_axis``) so a job can run the axes separately, and the
indirect pass of an axis can be split further into runs of samples (``indirect_chunk``, then
``with_indirect``); ``merge_ldc`` puts three axes together.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import InvalidInputError
from engine.lights import directional_light_sample, point_light_sample, rect_light_sample
from engine.newviews.effects import EffectPlan, analyze
from engine.newviews.indirect import (
    IndirectParams,
    IndirectResult,
    axis_brightness,
    content_stats,
    merge_summaries,
    trace_indirect,
)
from engine.newviews.ldi import DEFAULT_MAX_BYTES, LDI, LDI_SAMPLE_BYTES, axis_frame, build_ldi, estimate_ldi_bytes
from engine.newviews.sparse_indirect import interpolate_untraced, traced_samples
from engine.raycast import OFFSET_EXTENT, OFFSET_REL, RayCaster
from engine.reference import ReferenceRenderer
from engine.sampler import derive_key, sample_2d, sample_key
from engine.scene import RuntimeScene

INV_PI = 1.0 / math.pi
MAX_RESOLUTION = 8192
# bytes per sample of the LDC attributes on top of the LDI (normals 24, facing 1, ids 8, diffuse 24)
LDC_ATTR_BYTES = 57
_DIRECT_STREAM = 7
"""The sampler stream of the direct light's rect-light positions: sample_key(seed, 7, stream_id)
(the indirect paths use ``engine.newviews.indirect``'s stream)."""


@dataclass(frozen=True)
class LDCAxis:
    axis: int
    ldi: LDI
    normal: np.ndarray  # (n, 3) float32 shading normal, unflipped
    geo_normal: np.ndarray  # (n, 3) float32
    facing: np.ndarray  # (n,) int8
    material: np.ndarray  # (n,) int32
    object: np.ndarray  # (n,) int32
    diffuse: np.ndarray  # (n, 2, 3) float32
    visibility: np.ndarray  # (n, 2, W) uint64
    timings: dict = field(default_factory=dict)

    @property
    def n_samples(self) -> int:
        return self.ldi.n_samples

    @property
    def nbytes(self) -> int:
        return int(self.ldi.nbytes + sum(a.nbytes for a in (self.normal, self.geo_normal, self.facing, self.material,
                                                             self.object, self.diffuse, self.visibility)))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays for storage (``np.savez``, no pickle): the LDI under ``ldi_``, the per-sample
        attributes, ``axis`` and, as a JSON string under ``timings``, what of the bake's
        ``timings`` does not measure wall-clock time (the counts, the indirect light's noise
        summary): the same axis baked twice stores the same bytes."""
        out = self.ldi.to_arrays("ldi_")
        kept = {k: (content_stats(v) if isinstance(v, dict) else v) for k, v in self.timings.items()
                if not isinstance(v, float)}  # floats are seconds (ldi, shade, shadow, total)
        out.update(axis=np.int64(self.axis), normal=self.normal, geo_normal=self.geo_normal, facing=self.facing,
                   material=self.material, object=self.object, diffuse=self.diffuse, visibility=self.visibility,
                   timings=np.array(json.dumps(kept, sort_keys=True)))
        return out

    @classmethod
    def from_arrays(cls, d) -> LDCAxis:
        """Inverse of ``to_arrays``; checks every attribute has one row per sample."""
        ldi = LDI.from_arrays(d, "ldi_")
        n = ldi.n_samples
        try:
            ax = cls(axis=int(np.asarray(d["axis"])), ldi=ldi,
                     normal=np.ascontiguousarray(d["normal"], dtype=np.float32),
                     geo_normal=np.ascontiguousarray(d["geo_normal"], dtype=np.float32),
                     facing=np.ascontiguousarray(d["facing"], dtype=np.int8),
                     material=np.ascontiguousarray(d["material"], dtype=np.int32),
                     object=np.ascontiguousarray(d["object"], dtype=np.int32),
                     diffuse=np.ascontiguousarray(d["diffuse"], dtype=np.float32),
                     visibility=np.ascontiguousarray(d["visibility"], dtype=np.uint64),
                     timings=json.loads(str(np.asarray(d["timings"]))) if "timings" in d else {})
        except KeyError as e:
            raise InvalidInputError(f"stored LDC axis lacks array {e.args[0]!r}") from None
        if ax.axis not in (0, 1, 2):
            raise InvalidInputError(f"stored LDC axis has axis {ax.axis}")
        if (ax.normal.shape != (n, 3) or ax.geo_normal.shape != (n, 3) or ax.facing.shape != (n,)
                or ax.material.shape != (n,) or ax.object.shape != (n,) or ax.diffuse.shape != (n, 2, 3)
                or ax.visibility.ndim != 3 or ax.visibility.shape[:2] != (n, 2)):
            raise InvalidInputError("stored LDC axis attributes don't match its sample count")
        return ax


@dataclass(frozen=True)
class LDC:
    axes: tuple[LDCAxis, LDCAxis, LDCAxis]
    h: float
    resolution: int
    n_lights: int
    background: np.ndarray
    closed_objects: tuple[bool, ...]
    plan: dict

    @property
    def n_samples(self) -> int:
        return sum(a.n_samples for a in self.axes)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.axes)

    @property
    def visibility_words(self) -> int:
        return int(self.axes[0].visibility.shape[2])

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The LDC's small metadata as plain arrays (the axes are stored on their own with
        ``LDCAxis.to_arrays``): h, resolution, n_lights, background, closed_objects, plan (JSON)."""
        return {"h": np.float64(self.h), "resolution": np.int64(self.resolution), "n_lights": np.int64(self.n_lights),
                "background": np.asarray(self.background, np.float64),
                "closed_objects": np.asarray(self.closed_objects, np.bool_), "plan": np.array(json.dumps(self.plan))}

    @classmethod
    def from_arrays(cls, meta, axes) -> LDC:
        """Rebuild an LDC from ``to_arrays()`` metadata and its three axes (any order)."""
        by_axis = {a.axis: a for a in axes}
        if sorted(by_axis) != [0, 1, 2] or len(axes) != 3:
            raise InvalidInputError(f"an LDC needs one axis each of 0, 1, 2; got {[a.axis for a in axes]}")
        try:
            h = float(np.asarray(meta["h"]))
            ldc = cls(axes=(by_axis[0], by_axis[1], by_axis[2]), h=h, resolution=int(np.asarray(meta["resolution"])),
                      n_lights=int(np.asarray(meta["n_lights"])),
                      background=np.asarray(meta["background"], np.float64).reshape(3),
                      closed_objects=tuple(bool(x) for x in np.asarray(meta["closed_objects"]).reshape(-1)),
                      plan=json.loads(str(np.asarray(meta["plan"]))))
        except KeyError as e:
            raise InvalidInputError(f"stored LDC metadata lacks {e.args[0]!r}") from None
        if len({a.visibility.shape[2] for a in axes}) != 1 or any(abs(a.ldi.frame.h - h) > 1e-12 * h for a in axes):
            raise InvalidInputError("stored LDC axes disagree with each other or with the metadata")
        return ldc


# ----------------------------------------------------------------------------- kernels


@nb.njit(cache=True, error_model="numpy")
def rect_net_point(key, light, owner, s):
    """The point (sx, sy) in [0, 1)^2 of rect light ``light`` (for ``engine.lights.rect_light_sample``)
    that is ``owner``'s sample ``s``: sample ``s`` of ``owner``'s stratified sequence over the light
    (engine/sampler.py, dimension derive_key(key, light, 0)). The g*g samples of one owner are the
    first g*g points of an Owen-scrambled Sobol sequence (a (0, m, 2)-net when g*g = 2^m), not one
    jittered point per grid cell."""
    return sample_2d(derive_key(key, light, 0), owner, s)


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _light_rows(p, ng, ns, mat, kd, occl, force_all, pt_pos, pt_int, dir_dir, dir_irr,
                rc, ru, rv, r_n, r_area, rL, r2s, r_g, key, first, center, extent,
                o_out, d_out, tmax_out, c_out, side_out, state):
    """One row per (sample, light sample). The light lies in front of at most one side of
    the surface (the side whose geometric normal has cos > 0 to it): the row belongs to that
    side. state: 0 = nothing, 1 = needs a shadow ray, 2 = visible without one.

    Rect-light positions: sample ``first + i``'s ``rect_net_point`` in the sampler stream ``key``, so
    a sample's light rows do not depend on the slice or chunk it is shaded in."""
    n = p.shape[0]
    npt = pt_pos.shape[0]
    ndir = dir_dir.shape[0]
    nrect = rc.shape[0]
    gg = r_g * r_g
    per = npt + ndir + nrect * gg
    for i in nb.prange(n):
        m = mat[i]
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        mx = max(abs(px - center[0]), abs(py - center[1]), abs(pz - center[2]))
        mag = OFFSET_REL * (mx + OFFSET_EXTENT * extent)
        for j in range(per):
            row = i * per + j
            state[row] = 0
            side_out[row] = 0
            c_out[row, 0] = c_out[row, 1] = c_out[row, 2] = 0.0
            # the scalar light functions, called with this row's light read out of the tables: a
            # function inlined with the table arrays as arguments would cost atomic reference counts
            # per row
            li = j
            q = 0
            sx = sy = 0.0
            if j >= npt + ndir:  # rect light q's sample s, stratified over the light
                q = (j - npt - ndir) // gg
                s = (j - npt - ndir) % gg
                sx, sy = rect_net_point(key, q, first + i, s)
                li = npt + ndir + q
            # the side the light is on, seen from the point itself
            if j < npt:
                ok, lx, ly, lz, e0, e1, e2, tmax = point_light_sample(
                    px, py, pz, 0.0, pt_pos[j, 0], pt_pos[j, 1], pt_pos[j, 2], pt_int[j, 0], pt_int[j, 1],
                    pt_int[j, 2])
            elif j < npt + ndir:  # the same from any origin: not sampled again below
                ok, lx, ly, lz, e0, e1, e2, tmax = directional_light_sample(
                    dir_dir[j - npt, 0], dir_dir[j - npt, 1], dir_dir[j - npt, 2], dir_irr[j - npt, 0],
                    dir_irr[j - npt, 1], dir_irr[j - npt, 2])
            else:
                ok, lx, ly, lz, e0, e1, e2, tmax = rect_light_sample(
                    px, py, pz, 0.0, sx, sy, rc[q, 0], rc[q, 1], rc[q, 2], ru[q, 0], ru[q, 1], ru[q, 2], rv[q, 0],
                    rv[q, 1], rv[q, 2], r_n[q, 0], r_n[q, 1], r_n[q, 2], r_area[q], rL[q, 0], rL[q, 1], rL[q, 2],
                    r2s[q], gg)
            if not ok:
                continue
            g0, g1, g2 = ng[i, 0], ng[i, 1], ng[i, 2]
            side = 0
            if g0 * lx + g1 * ly + g2 * lz < 0.0:
                side = 1
                g0, g1, g2 = -g0, -g1, -g2
            s0, s1, s2 = ns[i, 0], ns[i, 1], ns[i, 2]
            if side == 1:
                s0, s1, s2 = -s0, -s1, -s2
            if s0 * g0 + s1 * g1 + s2 * g2 <= 0.0:
                s0, s1, s2 = g0, g1, g2
            ox, oy, oz = px + mag * g0, py + mag * g1, pz + mag * g2
            if j < npt:
                ok, lx, ly, lz, e0, e1, e2, tmax = point_light_sample(
                    ox, oy, oz, mag, pt_pos[j, 0], pt_pos[j, 1], pt_pos[j, 2], pt_int[j, 0], pt_int[j, 1],
                    pt_int[j, 2])
            elif j >= npt + ndir:
                ok, lx, ly, lz, e0, e1, e2, tmax = rect_light_sample(
                    ox, oy, oz, mag, sx, sy, rc[q, 0], rc[q, 1], rc[q, 2], ru[q, 0], ru[q, 1], ru[q, 2], rv[q, 0],
                    rv[q, 1], rv[q, 2], r_n[q, 0], r_n[q, 1], r_n[q, 2], r_area[q], rL[q, 0], rL[q, 1], rL[q, 2],
                    r2s[q], gg)
            if not ok:
                continue
            cos_g = g0 * lx + g1 * ly + g2 * lz
            if cos_g <= 0.0 or tmax <= 0.0:
                continue
            cos_s = s0 * lx + s1 * ly + s2 * lz
            if cos_s < 0.0:
                cos_s = 0.0
            side_out[row] = side
            c_out[row, 0] = kd[m, 0] * INV_PI * e0 * cos_s
            c_out[row, 1] = kd[m, 1] * INV_PI * e1 * cos_s
            c_out[row, 2] = kd[m, 2] * INV_PI * e2 * cos_s
            if occl[li] or force_all:
                state[row] = 1
                o_out[row, 0] = ox - center[0]
                o_out[row, 1] = oy - center[1]
                o_out[row, 2] = oz - center[2]
                d_out[row, 0], d_out[row, 1], d_out[row, 2] = lx, ly, lz
                tmax_out[row] = min(tmax, 3.0e38)
            elif side == 0:  # occlusion-free light (convex closed scene): outer side sees it
                state[row] = 2


@nb.njit(cache=True, parallel=True, nogil=True)
def _accumulate(state, occ_rows, c, side, npt, ndir, gg, diffuse, vis, store_bits):
    n = diffuse.shape[0]
    per = c.shape[0] // max(n, 1)
    for i in nb.prange(n):
        for j in range(per):
            row = i * per + j
            st = state[row]
            if st == 0:
                continue
            if st == 1 and occ_rows[row]:
                continue
            s = side[row]
            diffuse[i, s, 0] += c[row, 0]
            diffuse[i, s, 1] += c[row, 1]
            diffuse[i, s, 2] += c[row, 2]
            if store_bits:
                if j < npt + ndir:
                    li = j
                else:
                    li = npt + ndir + (j - npt - ndir) // gg
                vis[i, s, li // 64] |= np.uint64(1) << np.uint64(li % 64)


def surface_attributes(scene: RuntimeScene, prim: np.ndarray, u: np.ndarray, v: np.ndarray):
    """(p float64, geometric normal float64, shading normal float64 unflipped) per hit."""
    pr = prim.astype(np.int64)
    uu = u.astype(np.float64)[:, None]
    vv = v.astype(np.float64)[:, None]
    w0 = 1.0 - uu - vv
    tp = scene.tri_p[pr]
    p = w0 * tp[:, 0] + uu * tp[:, 1] + vv * tp[:, 2]
    tn = scene.tri_n[pr]
    ns = w0 * tn[:, 0] + uu * tn[:, 1] + vv * tn[:, 2]
    ln = np.linalg.norm(ns, axis=1, keepdims=True)
    ng = scene.tri_ng[pr]
    ns = np.where(ln > 1e-12, ns / np.where(ln > 1e-12, ln, 1.0), ng)
    return np.ascontiguousarray(p), np.ascontiguousarray(ng), np.ascontiguousarray(ns)


def shade_samples(scene: RuntimeScene, caster: RayCaster, p: np.ndarray, ng: np.ndarray, ns: np.ndarray,
                  mat: np.ndarray, occludable: np.ndarray, *, store_bits: bool, force_all: bool = False,
                  area_light_samples: int = 16, seed: int = 0, stream_id: int = 0,
                  rows_per_slice: int = 1 << 21,
                  progress: Callable[[float], None] | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Two-sided view-independent radiance (n, 2, 3) float32 and visibility bits (n, 2, W).

    Shadow rays only for occludable lights (or every light with ``force_all``); work in
    slices of at most ``rows_per_slice`` light rows (bounded memory). ``progress(fraction)`` is
    called after every slice (fraction of the samples shaded); it may raise to cancel."""
    lt, mt = scene.lights, scene.materials
    n = p.shape[0]
    n_l = lt.count
    words = (n_l + 63) // 64 if store_bits else 0
    vis = np.zeros((n, 2, words), dtype=np.uint64)
    acc = np.zeros((n, 2, 3), dtype=np.float64)
    r_g = max(1, int(round(math.sqrt(area_light_samples))))
    gg = r_g * r_g
    per = lt.n_point + lt.n_directional + lt.n_rect * gg
    r_n, r_area = lt.rect_frames()
    occl = np.ascontiguousarray(np.asarray(occludable, dtype=np.bool_).reshape(-1))
    if occl.shape[0] != n_l:
        raise InvalidInputError(f"occludable must have one flag per light ({n_l}), got {occl.shape[0]}")
    key = sample_key(seed, _DIRECT_STREAM, stream_id)
    t_shade = t_shadow = 0.0
    n_shadow = 0
    if per and n:
        step = max(1, rows_per_slice // per)
        for s in range(0, n, step):
            t0 = time.perf_counter()
            sl = slice(s, min(n, s + step))
            k = sl.stop - sl.start
            rows = k * per
            so = np.empty((rows, 3), np.float32)
            sd = np.empty((rows, 3), np.float32)
            tm = np.empty(rows, np.float32)
            c = np.empty((rows, 3))
            side = np.empty(rows, np.int8)
            state = np.empty(rows, np.int8)
            _light_rows(p[sl], ng[sl], ns[sl], mat[sl], mt.kd, occl, force_all, lt.point_position,
                        lt.point_intensity, lt.dir_direction, lt.dir_irradiance, lt.rect_corner, lt.rect_edge_u,
                        lt.rect_edge_v, r_n, r_area, lt.rect_radiance, lt.rect_two_sided, r_g, key, s,
                        scene.center, scene.extent, so, sd, tm, c, side, state)
            live = np.flatnonzero(state == 1)
            t_shade += time.perf_counter() - t0
            t0 = time.perf_counter()
            occ_rows = np.zeros(rows, dtype=np.bool_)
            if live.size:
                occ_rows[live] = caster.occluded_local(np.ascontiguousarray(so[live]), np.ascontiguousarray(sd[live]),
                                                       np.ascontiguousarray(tm[live]))
            n_shadow += int(live.size)
            t_shadow += time.perf_counter() - t0
            t0 = time.perf_counter()
            _accumulate(state, occ_rows, c, side, lt.n_point, lt.n_directional, gg, acc[sl], vis[sl], store_bits)
            t_shade += time.perf_counter() - t0
            if progress is not None:
                progress(sl.stop / n)
    # view-independent constant terms (both sides)
    base = mt.kd[mat] * scene.ambient[None] + mt.emission[mat]
    acc += base[:, None, :]
    return acc.astype(np.float32), vis, {"shade": t_shade, "shadow": t_shadow, "shadow_rays": n_shadow}


# ----------------------------------------------------------------------------- bake


_CAST_SHARE = 0.15
"""Share of an axis bake given to multi-hit casting in progress reports (measured 5-12 % on the
samples at LDC 256; the rest is shading + shadow rays)."""
_INDIRECT_SHARE = 0.9
"""Share of an axis bake given to the indirect pass in progress reports when it runs (it traces
tens to hundreds of paths per sample side where direct light casts a few shadow rays)."""


def ldc_pixel_size(scene: RuntimeScene, resolution: int) -> float:
    lo, hi = scene.bounds
    ext = float(np.max(hi - lo))
    if not ext > 0:
        ext = max(scene.extent, 1e-6)
    return ext / resolution


def _check_resolution(resolution: int) -> None:
    if not isinstance(resolution, (int, np.integer)) or not (1 <= resolution <= MAX_RESOLUTION):
        raise InvalidInputError(f"LDC resolution must be an integer in [1, {MAX_RESOLUTION}], got {resolution!r}")


def estimate_ldc_bytes(scene: RuntimeScene, resolution: int, max_layers: int = 32) -> int:
    """Worst-case bytes of the three LDIs plus attributes (every pixel full to max_layers)."""
    _check_resolution(resolution)
    h = ldc_pixel_size(scene, resolution)
    lo, hi = scene.bounds
    words = (scene.lights.count + 63) // 64
    per = LDI_SAMPLE_BYTES + LDC_ATTR_BYTES + 16 * words
    return sum(estimate_ldi_bytes(f.n_pixels, max_layers, per)
               for f in (axis_frame(lo, hi, a, h) for a in range(3)))


def _resolve_visibility(plan: EffectPlan, n_lights: int, lights_visibility) -> tuple[np.ndarray, bool, bool]:
    """(occludable flags, store bits?, force shadow rays for every light?)."""
    if lights_visibility == "force":
        return np.ones(n_lights, dtype=np.bool_), n_lights > 0, True
    occl = np.asarray(plan.occludable_lights, dtype=np.bool_).reshape(-1)
    if lights_visibility is True or lights_visibility == "auto":
        return occl, bool(occl.any()), False
    if lights_visibility is False or lights_visibility == "none":
        return occl, False, False
    raise InvalidInputError(f"lights_visibility must be True, False or 'force', got {lights_visibility!r}")


def bake_ldc_axis(scene: RuntimeScene, caster: RayCaster, axis: int, resolution: int, *,
                  lights_visibility=True, plan: EffectPlan | None = None, area_light_samples: int = 16,
                  seed: int = 0, max_layers: int = 32, max_bytes: int = DEFAULT_MAX_BYTES,
                  indirect: IndirectParams | None = None,
                  progress: Callable[[float, str], None] | None = None) -> LDCAxis:
    """Bake one of the three LDIs of the LDC (axis 0, 1, 2 = +x, +y, +z) with its attributes.

    ``indirect``: also path-trace the indirect diffuse light of every sample side into ``diffuse``
    (skipped, at no cost, when the effect plan says none can arrive); None: direct light only.

    ``progress(fraction, stage)`` after the multi-hit casting (stage ``"cast"``), after every
    shading slice (``"shade"``) and every indirect round (``"indirect"``); the fraction weighs the
    stages by their usual share of the time; the callback may raise to cancel.

    ``lights_visibility``: True (store bits when the effect plan finds an occludable light),
    False (no bits; shadow rays still cast for occludable lights), 'force' (shadow rays and
    bits for every light, ignoring the plan; for tests of the plan)."""
    _check_resolution(resolution)
    if axis not in (0, 1, 2):
        raise InvalidInputError(f"axis must be 0, 1 or 2, got {axis!r}")
    if scene.n_triangles == 0:
        raise InvalidInputError("cannot bake an LDC of an empty scene")
    plan = plan if plan is not None else analyze(scene)
    n_l = scene.lights.count
    occl, store, force = _resolve_visibility(plan, n_l, lights_visibility)
    words = (n_l + 63) // 64 if store else 0
    h = ldc_pixel_size(scene, resolution)
    lo, hi = scene.bounds
    frame = axis_frame(lo, hi, axis, h)
    est = estimate_ldi_bytes(frame.n_pixels, max_layers, LDI_SAMPLE_BYTES + LDC_ATTR_BYTES + 16 * words)
    if est > max_bytes:
        raise InvalidInputError(f"LDC axis {axis} at resolution {resolution} x {max_layers} layers needs up to "
                                f"{est / 2**20:.1f} MiB, over the limit of {max_bytes / 2**20:.1f} MiB; "
                                "lower the resolution or max_layers")
    t0 = time.perf_counter()
    ldi = build_ldi(caster, frame, max_layers=max_layers, max_bytes=max_bytes)
    t_ldi = time.perf_counter() - t0
    if progress is not None:
        progress(_CAST_SHARE, "cast")
    p, ng, ns = surface_attributes(scene, ldi.prim, ldi.u, ldi.v)
    mat = scene.tri_material[ldi.prim].astype(np.int32)
    run_indirect = indirect is not None and not plan.indirect_skip
    direct_end = 1.0 - _INDIRECT_SHARE if run_indirect else 1.0
    diffuse, vis, st = shade_samples(scene, caster, p, ng, ns, mat, occl, store_bits=store, force_all=force,
                                     area_light_samples=area_light_samples, seed=seed, stream_id=axis,
                                     progress=None if progress is None else
                                     (lambda f: progress(_CAST_SHARE * direct_end
                                                         + (1.0 - _CAST_SHARE) * direct_end * f, "shade")))
    facing = np.where(ng @ frame.w < 0.0, 1, -1).astype(np.int8)
    out = LDCAxis(axis=axis, ldi=ldi, normal=ns.astype(np.float32), geo_normal=ng.astype(np.float32),
                  facing=facing, material=mat, object=scene.tri_object[ldi.prim].astype(np.int32),
                  diffuse=diffuse, visibility=vis,
                  timings={"ldi": t_ldi, "shade": st["shade"], "shadow": st["shadow"],
                           "total": time.perf_counter() - t0, "shadow_rays": st["shadow_rays"],
                           "truncated_pixels": ldi.n_truncated})
    if run_indirect:
        assert indirect is not None
        chunk = indirect_chunk(scene, caster, out, 0, out.n_samples, indirect,
                               progress=None if progress is None else
                               (lambda f: progress(direct_end + _INDIRECT_SHARE * f, "indirect")))
        out = with_indirect(out, [chunk], indirect)
        out.timings["total"] = time.perf_counter() - t0
    return out


def indirect_chunk(scene: RuntimeScene, caster: RayCaster, axis: LDCAxis, start: int, stop: int,
                   params: IndirectParams, *, renderer: ReferenceRenderer | None = None,
                   progress: Callable[[float], None] | None = None) -> IndirectResult:
    """Indirect diffuse light of samples ``start .. stop - 1`` of a direct-lit LDC axis (one job's
    share of an axis; ``with_indirect`` adds the chunks to the axis). The result does not depend
    on how the axis is split: each sample side draws its own sample sequence, and the noise floor
    comes from the whole axis. At ``params.stride`` > 1 only the traced samples
    (``engine.newviews.sparse_indirect``) get paths; the others stay 0 until ``with_indirect``
    interpolates them."""
    n = axis.n_samples
    if not (isinstance(start, (int, np.integer)) and isinstance(stop, (int, np.integer)) and 0 <= start <= stop <= n):
        raise InvalidInputError(f"indirect chunk [{start}, {stop}) is outside the axis's {n} samples")
    ldi = axis.ldi
    traced = traced_samples(ldi, axis.geo_normal, axis.object, axis.material, params.stride)
    rows = np.flatnonzero(traced[start:stop]) + int(start)
    p, ng, ns = surface_attributes(scene, ldi.prim[rows], ldi.u[rows], ldi.v[rows])
    receives = np.any(scene.materials.kd[axis.material] > 0.0, axis=1)
    brightness = axis_brightness(axis.diffuse, receives)
    renderer = renderer if renderer is not None else ReferenceRenderer(scene, caster)
    # the traced samples are numbered along the axis (each draws the sampler's sequence of its
    # number), so the result does not depend on the split
    got = trace_indirect(renderer, p, ng, ns, axis.material[rows], axis.diffuse[rows], params, stream_id=axis.axis,
                         first=int(np.count_nonzero(traced[:start])), brightness=brightness, progress=progress)
    m = int(stop - start)
    radiance, stderr, paths = np.zeros((m, 2, 3), np.float32), np.zeros((m, 2), np.float32), np.zeros((m, 2), np.int32)
    radiance[rows - start], stderr[rows - start], paths[rows - start] = got.radiance, got.stderr, got.paths
    return IndirectResult(first=int(start), radiance=radiance, stderr=stderr, paths=paths, stats=got.stats)


def with_indirect(axis: LDCAxis, chunks: list[IndirectResult], params: IndirectParams) -> LDCAxis:
    """The axis with the indirect light of ``chunks`` (which must tile its samples exactly, in any
    order) added to ``diffuse``; ``timings["indirect"]`` summarises the achieved noise level."""
    n = axis.n_samples
    order = sorted(chunks, key=lambda c: c.first)
    at = 0
    for c in order:
        if c.first != at:
            raise InvalidInputError(f"indirect chunks of axis {axis.axis} leave samples [{at}, {c.first}) out "
                                    "or overlap")
        at += c.radiance.shape[0]
    if at != n:
        raise InvalidInputError(f"indirect chunks of axis {axis.axis} cover {at} samples, the axis has {n}")
    radiance = np.concatenate([c.radiance for c in order]) if order else np.zeros((0, 2, 3), np.float32)
    if params.stride > 1:
        traced = traced_samples(axis.ldi, axis.geo_normal, axis.object, axis.material, params.stride)
        radiance = interpolate_untraced(axis.ldi, axis.geo_normal, axis.object, axis.material, params.stride,
                                        traced, radiance)
    diffuse = (axis.diffuse.astype(np.float64) + radiance).astype(np.float32)
    timings = dict(axis.timings)
    timings["indirect"] = merge_summaries([c.stats for c in order], params)
    if params.stride > 1:
        timings["indirect"]["stride"] = params.stride
        timings["indirect"]["interpolated_samples"] = int(n - np.count_nonzero(traced))
    if "time" in timings["indirect"]:
        timings["total"] = float(timings.get("total", 0.0)) + timings["indirect"]["time"]
    return LDCAxis(axis=axis.axis, ldi=axis.ldi, normal=axis.normal, geo_normal=axis.geo_normal, facing=axis.facing,
                   material=axis.material, object=axis.object, diffuse=diffuse, visibility=axis.visibility,
                   timings=timings)


def merge_ldc(scene: RuntimeScene, parts: list[LDCAxis], resolution: int, plan: EffectPlan | None = None) -> LDC:
    """Assemble three per-axis bakes (any order) into an LDC; checks they belong together."""
    by_axis = {p.axis: p for p in parts}
    if sorted(by_axis) != [0, 1, 2] or len(parts) != 3:
        raise InvalidInputError(f"merge_ldc needs exactly one part per axis 0, 1, 2; got {[p.axis for p in parts]}")
    h = ldc_pixel_size(scene, resolution)
    words = {p.visibility.shape[2] for p in parts}
    if len(words) != 1:
        raise InvalidInputError("LDC parts disagree on the visibility bitmask width")
    for p in parts:
        if abs(p.ldi.frame.h - h) > 1e-12 * h:
            raise InvalidInputError(f"LDC part for axis {p.axis} was baked at another resolution")
    plan = plan if plan is not None else analyze(scene)
    return LDC(axes=(by_axis[0], by_axis[1], by_axis[2]), h=h, resolution=int(resolution),
               n_lights=scene.lights.count, background=np.asarray(scene.background, dtype=np.float64),
               closed_objects=plan.closed_objects, plan=plan.to_dict() | {"indirect": indirect_state(parts, plan)})


def indirect_state(parts: list[LDCAxis], plan: EffectPlan) -> dict:
    """What the LDC holds of indirect light, for the plan: ``baked`` (with the achieved noise level
    per axis), ``skipped`` (none can arrive, with the effect plan's reason; whether it was asked for
    or not) or ``off`` (it could arrive, and the bake was not asked for it)."""
    summaries = [p.timings.get("indirect") for p in sorted(parts, key=lambda p: p.axis)]
    if all(isinstance(s, dict) for s in summaries):
        return {"state": "baked", "axes": summaries}
    if plan.indirect_skip:
        return {"state": "skipped", "reason": plan.indirect_skip}
    return {"state": "off", "reason": "the bake was not asked for indirect light"}


def bake_ldc(scene: RuntimeScene, caster: RayCaster, resolution: int, *, lights_visibility=True,
             plan: EffectPlan | None = None, area_light_samples: int = 16, seed: int = 0, max_layers: int = 32,
             max_bytes: int = DEFAULT_MAX_BYTES, indirect: IndirectParams | None = None) -> LDC:
    """Bake the whole LDC (three axes, then merge). ``max_bytes`` bounds the worst case of all three;
    ``indirect``: add indirect diffuse light (see ``bake_ldc_axis``)."""
    est = estimate_ldc_bytes(scene, resolution, max_layers)
    if est > max_bytes:
        raise InvalidInputError(f"LDC at resolution {resolution} x {max_layers} layers needs up to "
                                f"{est / 2**20:.1f} MiB, over the limit of {max_bytes / 2**20:.1f} MiB; "
                                "lower the resolution or max_layers")
    plan = plan if plan is not None else analyze(scene)
    parts = [bake_ldc_axis(scene, caster, a, resolution, lights_visibility=lights_visibility, plan=plan,
                           area_light_samples=area_light_samples, seed=seed, max_layers=max_layers,
                           max_bytes=max_bytes, indirect=indirect) for a in range(3)]
    return merge_ldc(scene, parts, resolution, plan)
