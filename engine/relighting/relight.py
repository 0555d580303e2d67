"""Relighting from an illumination dataset (docs/relighting.md; the paper's section 2): :func:`relight`.

A fixed camera sees an object lit, image by image, by K point lights (or K distant
lights). With the 3-D surface point ``P`` of every pixel known, the pixel under a new
light is interpolated from the three dataset images whose lights form the triangle that
the ray from ``P`` through the new light crosses on the light sphere (paper eq. 1).

This module owns the public entry point: :func:`relight` checks its arguments, expands the lights
(``engine.relighting.lights``), prepares the kernel frame and runs the relight kernel
(``engine.relighting.kernel``) or, for lights exactly at dataset lights, the exact path; and
:class:`RelightResult`. The package's other modules: ``dataset`` (:class:`IlluminationDataset`,
``points_from_depth``), ``grid`` (direction triangulation and lookup, ``locate_directions``),
``bake`` (``bake_dataset``, :class:`BakedDataset`), ``compress`` (the low-rank store).

Radiometric normalisation (decision, docs/relighting.md "Math"): the stored images are the
raw dataset images ``V_k``; the kernel interpolates the *distance- and intensity-normalised*
responses ``R_k(p) = V_k(p) |P - s_k|^2 / I_k`` (per channel; ``V_k / E_k`` for a distant
dataset), which depend on the light direction only, and multiplies by the new light's
irradiance factor ``I / |P - l|^2`` (``E`` for a directional light). At a vertex this is
exactly eq. 1; inside a triangle it interpolates the smoother quantity, and lights that
are not exactly on the fitted sphere are handled without a second approximation.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import InvalidInputError
from engine.relighting.bake import BakedDataset
from engine.relighting.kernel import exact_kernel, relight_kernel, zero_pixels
from engine.relighting.lights import K_DIRECTIONAL, K_POINT, expand_lights


@dataclass(frozen=True)
class RelightResult:
    """image (h, w, 3) float32 (0 outside the dataset mask); outside_mask (h, w) bool: some light
    direction fell outside the covered part of the sphere (that light contributes 0 there);
    singular_mask (h, w) bool: a point light closer than ``min_light_distance`` to the surface
    point (contributes 0, see docs/relighting.md); timings in seconds; ``exact`` True when the
    exact-hit path (stored images, no interpolation) produced the image. ``lights_used``: the
    kept dataset lights whose values were read (sorted indices into ``baked.light_positions``),
    ``n_triangles_used``: the triangles the lights needed (0 on the exact path)."""

    image: np.ndarray
    outside_mask: np.ndarray
    n_outside: int
    singular_mask: np.ndarray
    n_singular: int
    timings: dict
    exact: bool = False
    n_lights: int = 0
    lights_used: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    n_triangles_used: int = 0


def _exact_indices(baked: BakedDataset, kinds, lp) -> np.ndarray | None:
    """Dataset light index of every expanded light when all match dataset lights exactly."""
    want = K_DIRECTIONAL if baked.distant else K_POINT
    if kinds.size == 0 or np.any(kinds != want):
        return None
    out = np.empty(kinds.size, np.int64)
    for j in range(kinds.size):
        if baked.distant:  # unit directions: allow the last-bit difference of renormalising
            hit = np.nonzero(np.all(np.abs(baked.light_positions - lp[j]) <= 1e-15, axis=1))[0]
        else:
            hit = np.nonzero(np.all(baked.light_positions == lp[j], axis=1))[0]
        if hit.size == 0:
            return None
        out[j] = hit[0]
    return out


def relight(baked: BakedDataset, lights, *, threads: int | None = None, serial: bool = False,
            min_light_distance: float | None = None, exact_fast_path: bool = True) -> RelightResult:
    """Relight a baked dataset with any number of lights (superposed).

    lights: a light spec or a list of them (:class:`PointLight`, :class:`DirectionalLight`,
        :class:`RectLight`, :class:`EnvironmentLight`, or their ``{"type": ...}`` dicts).
    threads: threads the kernel runs on (None = numba's current setting, ``nb.get_num_threads()``);
        serial=True runs it in the calling thread only (for callers with their own threads).
    min_light_distance: a point light nearer than this to a surface point contributes 0 there
        and the pixel is marked singular; default 1e-6 x the sphere radius (x the scene extent
        for distant datasets).
    """
    if not isinstance(baked, BakedDataset):
        raise InvalidInputError("relight: expected a BakedDataset (see bake_dataset)")
    t0 = time.perf_counter()
    kinds, lp, li, ln = expand_lights(lights)
    h, w = baked.shape
    if min_light_distance is None:
        scale = baked.sphere_radius if math.isfinite(baked.sphere_radius) else float(
            np.max(np.ptp(baked.points, axis=0)) or 1.0)
        min_light_distance = 1e-6 * scale
    if not (min_light_distance >= 0 and math.isfinite(min_light_distance)):
        raise InvalidInputError("min_light_distance must be finite and >= 0")
    t1 = time.perf_counter()
    timings = {"expand_lights_s": t1 - t0}
    geom = baked.kernel_geometry
    # every store row is written by the kernels; 64-byte aligned for the non-temporal output runs
    buf = np.empty(h * w * 3 + 16, np.float32)
    off = (-buf.ctypes.data % 64) // 4
    img = buf[off:off + h * w * 3].reshape(h * w, 3)
    zero_pixels(img, geom.unused_pixels)  # numpy's fancy assignment took 0.7 ms at 1 MP
    outside = np.zeros(h * w, bool)
    singular = np.zeros(h * w, bool)
    exact = _exact_indices(baked, kinds, lp) if exact_fast_path else None
    if exact is not None:
        # light(s) exactly at dataset lights: the stored images, scaled, no interpolation; float32
        # arithmetic in the order of ``sum_j light_values(k_j) * ratio_j`` (bit-identical to it)
        ratios = np.ascontiguousarray((li / baked.intensities[exact]).astype(np.float32))
        exact_kernel(baked.kernel_store(), geom.pixel_index, exact, baked.store_scale[exact].astype(np.float32),
                     ratios, img, serial=serial)
        timings["kernel_s"] = time.perf_counter() - t1
        used = np.unique(exact)
        n_tri_used = 0
        count = False  # the exact path sets no flags
    else:
        touched = np.zeros(baked.triangles.shape[0], np.uint8)
        flagged = np.zeros(1, np.uint8)
        inv_int = np.ascontiguousarray(1.0 / (baked.intensities * baked.store_scale[:, None]))
        radius = baked.sphere_radius if math.isfinite(baked.sphere_radius) else 1.0
        prev = nb.get_num_threads()
        if threads is not None and not serial:
            if not (1 <= int(threads) <= nb.config.NUMBA_NUM_THREADS):
                raise InvalidInputError(f"threads must be in [1, {nb.config.NUMBA_NUM_THREADS}]")
            nb.set_num_threads(int(threads))
        # the kernel frame: positions relative to geom.origin; directions toward directional lights unit
        lp_k = lp.copy()
        pos = kinds != K_DIRECTIONAL
        lp_k[pos] -= geom.origin
        if np.any(~pos):
            lp_k[~pos] /= np.linalg.norm(lp_k[~pos], axis=1, keepdims=True)
        lpos_k = baked.light_positions - (0.0 if baked.distant else geom.origin)
        lpos_k = np.ascontiguousarray(lpos_k.astype(np.float32))
        near2 = (float(min_light_distance) + 4.0 * geom.rounding) ** 2
        # the power of two that brings the radius into [1, 2) for the float32 geometry (exact scaling)
        fscale = math.ldexp(1.0, -math.frexp(radius)[1] + 1)
        try:
            relight_kernel(geom.points, baked.points, geom.origin, baked.kernel_store(), lpos_k, inv_int,
                           baked.distant, radius, fscale, baked.triangles, baked.tri_inverse, baked.grid_n,
                           baked.grid_start, baked.grid_items, kinds, lp_k, li, ln, float(min_light_distance) ** 2,
                           near2, geom.pixel_index, geom.runs, geom.run_pixels, img, outside, singular, touched,
                           flagged, serial=serial)
        finally:
            if threads is not None and not serial:
                nb.set_num_threads(prev)
        timings["kernel_s"] = time.perf_counter() - t1
        tri_used = np.nonzero(touched)[0]
        used = np.unique(baked.triangles[tri_used])
        n_tri_used = int(tri_used.size)
        count = bool(flagged[0])
    timings["total_s"] = time.perf_counter() - t0
    return RelightResult(image=img.reshape(h, w, 3), outside_mask=outside.reshape(h, w),
                         n_outside=int(np.count_nonzero(outside)) if count else 0,
                         singular_mask=singular.reshape(h, w),
                         n_singular=int(np.count_nonzero(singular)) if count else 0, timings=timings,
                         exact=exact is not None,
                         n_lights=int(kinds.size), lights_used=used.astype(np.int64), n_triangles_used=n_tri_used)
