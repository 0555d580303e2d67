"""The bake: an illumination dataset reorganised for the relight kernel.

Owns :class:`BakedDataset` (the store, the kept lights, the triangulation and the cube-map grid: what a
relight reads, and what a dataset bake artifact holds), :class:`KernelGeometry` (the surface points in
the kernel's compact float32 form, derived on first use), :func:`bake_dataset` and the bake's numba
kernels (per-light statistics, the gather into the store with float32 -> float16 rounding) and the
storage choice (:func:`_choose_dtype`: float16 with per-light power-of-two scales when every value
that matters keeps float16's precision, else float32; or the low-rank store of
``engine.relighting.compress``). The direction work (deduplication, triangulation, grid) is
``engine.relighting.grid``'s.

Store layouts (docs/relighting.md "Storage"): ``pixel_major`` (n, K, 3) or ``tiled``
(ceil(n / TILE), K, TILE, 3), rows in 16 x 16 image blocks (``compress.block_order``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from functools import cached_property

import numba as nb
import numpy as np
from numba.extending import overload

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import InvalidInputError
from engine.relighting.compress import LowRankStore, block_order, compress_store
from engine.relighting.dataset import IlluminationDataset, checked_array
from engine.relighting.grid import build_grid, dedupe_directions, triangulate
from engine.sched import run_pieces_parallel

HALF_MAX = 65504.0
HALF_MIN_NORMAL = 6.103515625e-05
LAYOUTS = ("pixel_major", "tiled")
TILE = 256  # pixels per tile of the "tiled" layout (a power of two: the kernel shifts and masks)
TILE_SHIFT = 8
CHUNK = TILE
"""Store rows the relight kernel handles together (one tile of the tiled store); KernelGeometry's
points come in chunks of this many rows."""


@dataclass(frozen=True)
class BakedDataset:
    """A dataset ready for relighting. Arrays are read-only in spirit; do not mutate.

    store: float16 or float32; ``layout="pixel_major"``: (n_valid, K', 3), row r holds the K'
        kept lights' values of pixel ``pixel_index[r]``; ``layout="tiled"``: (ceil(n_valid / TILE),
        K', TILE, 3), each tile of TILE consecutive rows stored light-major (the last tile padded
        with zeros). Use :meth:`light_values` rather than indexing it directly.
    pixel_index: (n_valid,) int64 flat (row-major) pixel index of each store row.
    points: (n_valid, 3) float64 surface points.
    light_positions (K', 3), intensities (K', 3): the kept (deduplicated) lights;
    kept_from: (K',) int64 index of each kept light in the input dataset.
    store_scale: (K',) float64 power-of-two factor each light's values were multiplied by
        before storing (1 for float32).
    directions (K', 3): unit light directions from the sphere centre (the triangulated points).
    triangles: (T, 3) int64 covered triangles (indices into the kept lights), outward-wound.
    tri_inverse: (T, 3, 3) float64; ``tri_inverse[t] @ u`` gives the cone coordinates of a
        direction u with respect to the triangle's vertices.
    grid_*: cube-map point location (6 faces x n x n cells, CSR list of candidate triangles).
    report: counts and choices (duplicates, coverage, dtype, ...), JSON-serialisable.
    """

    shape: tuple[int, int]
    distant: bool
    store: np.ndarray
    pixel_index: np.ndarray
    points: np.ndarray
    light_positions: np.ndarray
    intensities: np.ndarray
    kept_from: np.ndarray
    directions: np.ndarray
    store_scale: np.ndarray
    sphere_center: np.ndarray
    sphere_radius: float
    triangles: np.ndarray
    tri_inverse: np.ndarray
    grid_n: int
    grid_start: np.ndarray
    grid_items: np.ndarray
    report: dict = field(default_factory=dict)
    lowrank: LowRankStore | None = None

    @property
    def layout(self) -> str:
        if self.lowrank is not None:
            return "lowrank"
        return "tiled" if self.store.ndim == 4 else "pixel_major"

    def light_values(self, k: int) -> np.ndarray:
        """(n_valid, 3) float32 stored values of kept light k, unscaled (as in the input; for a
        compressed store, reconstructed from the low-rank factors)."""
        if self.lowrank is not None:
            return self.lowrank.light_values(k)
        v = self.store[:, k].reshape(-1, 3)[: self.pixel_index.size].astype(np.float32)
        if self.store_scale[k] != 1.0:
            v /= np.float32(self.store_scale[k])  # a power of two: exact
        return v

    @property
    def nbytes(self) -> int:
        lr = self.lowrank.nbytes if self.lowrank is not None else 0
        # + the kernel's float32 points and int32 pixel index (derived on the first relight)
        return int(self.store.nbytes + lr + self.points.nbytes + self.pixel_index.nbytes
                   + self.pixel_index.size * 16)

    @cached_property
    def kernel_geometry(self) -> KernelGeometry:
        """The surface points and pixel index in the relight kernel's compact form, derived on first use
        and kept with this object (not a field: never serialised, artifacts are unchanged)."""
        return KernelGeometry.of(self)

    def kernel_store(self):
        """What the relight kernel reads: the store (float16 as uint16 bits) or the low-rank factors."""
        if self.lowrank is not None:
            return self.lowrank.kernel_args()
        return self.store.view(np.uint16) if self.store.dtype == np.float16 else self.store


@dataclass(frozen=True)
class KernelGeometry:
    """What the relight kernel reads per pixel besides the store, at 16 bytes a pixel instead of 32.

    origin (3,) float64: the kernel frame's origin, the sphere centre (distant dataset: the centre of
        the points' bounding box); every position the kernel sees is relative to it.
    points (n_chunks, 3, 256) float32: ``baked.points - origin`` rounded to float32, one contiguous
        row per axis and chunk of 256 store rows (the last chunk zero-padded).
    rounding: a bound on ``|points(float32) - (baked.points - origin)|`` for every point
        (2^-24 x the largest |point - origin| per rounded point, kept with a factor 2 margin). A light
        within ``min_light_distance + 4 x rounding`` of a float32 point is decided and computed from
        the float64 point (so the singular rule is the float64 one).
    pixel_index (n,) int32 (int64 for frames of 2^31 pixels or more): ``baked.pixel_index``.
    runs (ceil(n / 16),) uint8: 1 where store rows 16 g .. 16 g + 15 are 16 consecutive pixels;
    run_pixels = pixel_index[::16].
    unused_pixels: the flat pixels without a store row (zero in every relit image).
    """

    origin: np.ndarray
    points: np.ndarray
    rounding: float
    pixel_index: np.ndarray
    runs: np.ndarray
    run_pixels: np.ndarray
    unused_pixels: np.ndarray

    @staticmethod
    def of(baked: BakedDataset) -> KernelGeometry:
        p64 = baked.points
        if baked.distant:
            origin = 0.5 * (p64.min(axis=0) + p64.max(axis=0)) if p64.shape[0] else np.zeros(3)
        else:
            origin = np.asarray(baked.sphere_center, np.float64)
        o = p64 - origin
        n = o.shape[0]
        n_chunks = (n + CHUNK - 1) // CHUNK
        pad = np.zeros((n_chunks * CHUNK, 3), np.float32)
        pad[:n] = o
        pts = np.ascontiguousarray(pad.reshape(n_chunks, CHUNK, 3).transpose(0, 2, 1))
        far = float(np.sqrt(np.max(np.einsum("ij,ij->i", o, o)))) if n else 0.0
        h, w = baked.shape
        idx_t = np.int32 if h * w < 2 ** 31 else np.int64
        used = np.zeros(h * w, bool)
        used[baked.pixel_index] = True
        g = np.full((n + 15) // 16 * 16, -1, np.int64)
        g[:n] = baked.pixel_index
        g = g.reshape(-1, 16)
        runs = np.all(g[:, 1:] - g[:, :-1] == 1, axis=1).astype(np.uint8)
        return KernelGeometry(origin=origin, points=pts, rounding=2.0 ** -23 * far, runs=runs,
                              pixel_index=baked.pixel_index.astype(idx_t),
                              run_pixels=np.ascontiguousarray(baked.pixel_index[::16].astype(idx_t)),
                              unused_pixels=np.nonzero(~used)[0].astype(idx_t))

    @property
    def nbytes(self) -> int:
        return int(self.points.nbytes + self.pixel_index.nbytes + self.runs.nbytes + self.run_pixels.nbytes
                   + self.unused_pixels.nbytes)



@nb.njit(cache=True, nogil=True)
def _light_stats(images, keep, pix, rel_floor, vmax, vmin, j0, j1):
    """Per kept light j in j0 .. j1 - 1: max |v| and the smallest |v| > 0 that is >= rel_floor x max,
    over the stored pixels. images (K, h*w, 3) float32."""
    for j in range(j0, j1):
        k = keep[j]
        m = 0.0
        for r in range(pix.size):
            for c in range(3):
                m = max(m, abs(images[k, pix[r], c]))
        vmax[j] = m
        fl = rel_floor * m
        mn = np.inf
        for r in range(pix.size):
            for c in range(3):
                a = abs(images[k, pix[r], c])
                if a > 0.0 and a >= fl and a < mn:
                    mn = a
        vmin[j] = mn


@nb.njit(cache=True, inline="always")
def _f32_to_f16_bits(f):
    """float32 bits (uint32) -> float16 bits, round to nearest even (numpy's
    ``npy_floatbits_to_halfbits``); the caller guarantees no overflow (values <= 65504)."""
    h_sgn = np.uint16((f & np.uint32(0x80000000)) >> np.uint32(16))
    f_exp = f & np.uint32(0x7F800000)
    if f_exp <= np.uint32(0x38000000):
        if f_exp < np.uint32(0x33000000):
            return h_sgn
        e = f_exp >> np.uint32(23)
        f_sig = np.uint32(0x00800000) + (f & np.uint32(0x007FFFFF))
        f_sig = f_sig >> (np.uint32(113) - e)
        if (f_sig & np.uint32(0x3FFF)) != np.uint32(0x1000) or (f & np.uint32(0x7FF)) != np.uint32(0):
            f_sig += np.uint32(0x1000)
        return np.uint16(h_sgn + np.uint16(f_sig >> np.uint32(13)))
    h_exp = np.uint16((f_exp - np.uint32(0x38000000)) >> np.uint32(13))
    f_sig = f & np.uint32(0x007FFFFF)
    if (f_sig & np.uint32(0x3FFF)) != np.uint32(0x1000):
        f_sig += np.uint32(0x1000)
    return np.uint16(h_sgn + np.uint16(np.uint16(f_sig >> np.uint32(13)) + h_exp))


def _put(out, r, j, c, v):  # pragma: no cover - replaced by the overload in numba code
    raise NotImplementedError


@overload(_put, inline="always")
def _put_impl(out, r, j, c, v):
    """out[row r, light j, channel c] = v for a pixel-major (3-D) or tiled (4-D) store."""
    if out.ndim == 4:
        def put4(out, r, j, c, v):
            out[r >> TILE_SHIFT, j, r & (TILE - 1), c] = v
        return put4

    def put3(out, r, j, c, v):
        out[r, j, c] = v
    return put3


_BLOCK = 2048
_MIN_ITEMS = 4096  # values read per thread piece at least (engine.sched: a piece costs ~20-50 us to dispatch)


@nb.njit(cache=True, nogil=True)
def _gather_pixel_major(images, keep, pix, scale, out, out16, half, b0, b1):
    """Blocks b0 .. b1 - 1 of _BLOCK rows of the store: row r, light j = images[keep[j], pix[r], :] x
    scale[j], written as float32 (``out``) or as float16 bits (``out16``), pixel-major or tiled. Blocks
    of pixels keep the reads contiguous per light and the writes inside one L2-sized block."""
    n = pix.size
    for bi in range(b0, b1):
        r0 = bi * _BLOCK
        r1 = min(n, r0 + _BLOCK)
        for j in range(keep.size):
            k = keep[j]
            s = np.float32(scale[j])
            for r in range(r0, r1):
                p = pix[r]
                for c in range(3):
                    v = np.float32(images[k, p, c] * s)
                    if half:
                        _put(out16, r, j, c, _f32_to_f16_bits(np.uint32(v.view(np.uint32))))
                    else:
                        _put(out, r, j, c, v)


def _choose_dtype(vmax: np.ndarray, vmin: np.ndarray, half: bool, rel_floor: float
                  ) -> tuple[type, np.ndarray, str]:
    """Storage dtype and per-light power-of-two scales from per-light statistics.

    float16 is used when, after scaling light k by ``2^e_k`` (max near 2^15; a power of two,
    so the scaling is exact and reversible), no value overflows and no value that matters
    (``|v| >= rel_floor x`` that light's max) falls below float16's smallest normal.
    """
    k = vmax.shape[0]
    ones = np.ones(k)
    if not half:
        return np.float32, ones, "float32 requested"
    if not np.all(np.isfinite(vmax)):
        return np.float32, ones, "float32: non-finite values"
    scale = np.where(vmax > 0, np.exp2(np.floor(np.log2(32768.0 / np.where(vmax > 0, vmax, 1.0)))), 1.0)
    if np.any(vmax * scale > HALF_MAX):
        return np.float32, ones, "float32: a light overflows float16 even after scaling"
    small = np.isfinite(vmin) & (vmin * scale < HALF_MIN_NORMAL)
    if np.any(small):
        j = int(np.nonzero(small)[0][0])
        return np.float32, ones, (f"float32: light {j} has values down to {float(vmin[j]):.3g} "
                                  f"(>= {rel_floor:g} x its max {vmax[j]:.3g}) that float16 would not keep "
                                  "to 2^-11 relative precision")
    return np.float16, scale, (f"float16 with per-light power-of-two scales (every value >= {rel_floor:g} x its "
                               "light's max kept to 2^-11 relative precision)")


def bake_dataset(ds: IlluminationDataset, *, sphere_center=None, sphere_radius: float | None = None,
                 layout: str = "tiled", half: bool = True, dedupe_tol_deg: float = 1e-3,
                 max_face_radius_deg: float | None = None, half_rel_floor: float = 0.0,
                 compress: float | None = None) -> BakedDataset:
    """Deduplicate, triangulate and reorganise a dataset for relighting.

    sphere_center: default the dataset's ``sphere_center``, else the centroid of the masked
        surface points (ignored for distant datasets, whose sphere is at infinity).
    sphere_radius: default the mean distance of the lights from the centre; it must enclose
        every surface point.
    dedupe_tol_deg: lights whose directions from the centre are closer than this are
        duplicates; the first (in input order) is kept, the others are dropped and counted.
    max_face_radius_deg: coverage rule (docs/relighting.md); None = min(85, 3 x median).
    half: store float16 when every value fits (else float32; the choice is in ``report``);
        ``half_rel_floor``: values below this fraction of their light's max may lose precision
        (default 0: every non-zero value keeps float16's 2^-11 relative precision, docs/hard-cases.md #9).
    compress: None, or the requested relative RMS error (0 < compress < 1) of a low-rank store
        (``engine.relighting.compress``: rank per 256-pixel tile). It is used only when its measured
        error meets the request and it is smaller than the uncompressed store; otherwise the
        uncompressed store is built and ``report["compression_reason"]`` says why. The measured
        errors are in ``report["compression_report"]`` either way.
    """
    if not isinstance(ds, IlluminationDataset):
        raise InvalidInputError("bake_dataset: expected an IlluminationDataset")
    if layout not in LAYOUTS:
        raise InvalidInputError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    if not (dedupe_tol_deg >= 0 and math.isfinite(dedupe_tol_deg)):
        raise InvalidInputError("dedupe_tol_deg must be finite and >= 0")
    if max_face_radius_deg is not None and not (0 < max_face_radius_deg <= 89.0):
        # the cone test and the cube-map caps need every covered face's circumcap < 90 deg
        raise InvalidInputError("max_face_radius_deg must be in (0, 89]")
    if not (0 <= half_rel_floor < 1):
        raise InvalidInputError("half_rel_floor must be in [0, 1)")
    if compress is not None and not (isinstance(compress, (int, float)) and 0 < compress < 1):
        raise InvalidInputError(f"compress must be a relative RMS error in (0, 1) or None, got {compress!r}")
    t0 = time.perf_counter()
    h, w = ds.shape
    # stored pixels in 16 x 16 image blocks: neighbouring rows see the lights in nearly the same
    # direction, so a tile of the tiled or low-rank store reads few lights' runs (docs: Kernel)
    pix = block_order(ds.mask)
    pts = np.ascontiguousarray(ds.points.reshape(-1, 3)[pix])
    report: dict = {"n_lights_input": int(ds.light_positions.shape[0]), "n_pixels": int(pix.size)}
    if ds.distant:
        center = np.zeros(3)
        radius = math.inf
        dirs = ds.light_positions.copy()
    else:
        if sphere_center is None:
            sphere_center = ds.sphere_center
        center = pts.mean(axis=0) if sphere_center is None else checked_array("sphere_center", sphere_center,
                                                                          np.float64, 1)
        if center.shape != (3,) or not np.all(np.isfinite(center)):
            raise InvalidInputError("sphere_center: expected 3 finite numbers")
        off = ds.light_positions - center
        dist = np.linalg.norm(off, axis=1)
        if np.any(dist == 0):
            raise InvalidInputError(f"light_positions: light(s) {np.nonzero(dist == 0)[0][:10].tolist()} "
                                    "sit exactly at the sphere centre")
        radius = float(dist.mean()) if sphere_radius is None else float(sphere_radius)
        if not (math.isfinite(radius) and radius > 0):
            raise InvalidInputError("sphere_radius: must be finite and > 0")
        far = float(np.max(np.linalg.norm(pts - center, axis=1)))
        if far >= radius:
            raise InvalidInputError(f"sphere_radius: the light sphere (radius {radius:.6g}) does not enclose the "
                                    f"surface (farthest point at {far:.6g} from the centre)")
        dirs = off / dist[:, None]
        report["light_radius_deviation_max"] = float(np.max(np.abs(dist - radius)) / radius)
    keep, n_exact, n_near = dedupe_directions(dirs, ds.light_positions, math.radians(dedupe_tol_deg))
    report.update(n_exact_duplicates=n_exact, n_near_duplicates=n_near, n_lights=int(keep.size))
    if keep.size < 3:
        raise InvalidInputError(f"light_positions: only {keep.size} distinct light(s) after deduplication; "
                                "at least 3 are needed")
    dirs_k = np.ascontiguousarray(dirs[keep])
    tri, tri_report = triangulate(dirs_k, max_face_radius_deg)
    report.update(tri_report)
    report["n_triangles"] = int(tri.shape[0])
    mats = np.stack([dirs_k[tri[:, 0]], dirs_k[tri[:, 1]], dirs_k[tri[:, 2]]], axis=2)  # columns = vertices
    try:
        inv = np.linalg.inv(mats)
    except np.linalg.LinAlgError:
        raise InvalidInputError("light_positions: a degenerate light triangle (3 directions on a great "
                                "circle)") from None
    grid_n, grid_start, grid_items = build_grid(dirs_k, tri)
    report["grid_n"] = grid_n
    report["grid_mean_candidates"] = float(grid_items.size / max(grid_start.size - 1, 1))
    t1 = time.perf_counter()
    flat = ds.images.reshape(ds.images.shape[0], h * w, 3)
    vmax = np.empty(keep.size)
    vmin = np.empty(keep.size)
    run_pieces_parallel(lambda j0, j1: _light_stats(flat, keep, pix, float(half_rel_floor), vmax, vmin, j0, j1),
                        keep.size, max(1, _MIN_ITEMS // max(1, 3 * pix.size)))
    dt, scale, why = _choose_dtype(vmax, vmin, half, half_rel_floor)
    is_half = dt is np.float16
    n_rows_plain = ((pix.size + TILE - 1) // TILE) * TILE if layout == "tiled" else pix.size  # tiles are padded
    plain_bytes = n_rows_plain * keep.size * 3 * (2 if is_half else 4)
    if compress is not None:
        t2 = time.perf_counter()
        lowrank, crep = compress_store(flat, keep, pix, float(compress))
        crep["time_s"] = time.perf_counter() - t2
        crep["uncompressed_store_bytes"] = int(plain_bytes)
        report["compression_report"] = crep
        if crep["rel_rms_error"] > compress:
            report["compression_reason"] = (f"measured error {crep['rel_rms_error']:.3g} exceeds the requested "
                                            f"{compress:g} even at full rank (float32 factors)")
        elif lowrank.nbytes >= plain_bytes:
            report["compression_reason"] = (f"low-rank store ({lowrank.nbytes} bytes, mean rank "
                                            f"{crep['rank_mean']:.1f}) is not smaller than the {np.dtype(dt).name} "
                                            f"store ({plain_bytes} bytes)")
        else:
            report.update(dtype="float32", dtype_reason=f"low-rank factors (float32); the plain store would be "
                          f"{np.dtype(dt).name}: {why}", layout="lowrank", store_bytes=int(lowrank.nbytes),
                          compression="svd_per_tile",
                          compression_reason=f"meets the requested relative RMS error {compress:g} "
                                             f"(measured {crep['rel_rms_error']:.3g}) at "
                                             f"{lowrank.nbytes / plain_bytes:.1%} of the plain store")
            report["time_triangulate_s"] = t1 - t0
            report["time_store_s"] = time.perf_counter() - t1
            return BakedDataset(shape=(h, w), distant=ds.distant, store=np.zeros((0, keep.size, 3), np.float32),
                                pixel_index=pix, points=pts,
                                light_positions=np.ascontiguousarray(ds.light_positions[keep]),
                                intensities=np.ascontiguousarray(ds.intensities[keep]),
                                kept_from=keep.astype(np.int64), directions=dirs_k, store_scale=np.ones(keep.size),
                                sphere_center=center, sphere_radius=radius, triangles=np.ascontiguousarray(tri),
                                tri_inverse=np.ascontiguousarray(inv), grid_n=grid_n, grid_start=grid_start,
                                grid_items=grid_items, report=report, lowrank=lowrank)
    if layout == "tiled":
        n_tiles = (pix.size + TILE - 1) // TILE
        store = np.zeros((n_tiles, keep.size, TILE, 3), np.float16 if is_half else np.float32)
    else:
        store = np.empty((pix.size, keep.size, 3), np.float16 if is_half else np.float32)
    dummy32 = np.empty((1,) * (store.ndim - 1) + (3,), np.float32)
    dummy16 = np.empty((1,) * (store.ndim - 1) + (3,), np.uint16)
    out32, out16 = (dummy32, store.view(np.uint16)) if is_half else (store, dummy16)
    run_pieces_parallel(lambda b0, b1: _gather_pixel_major(flat, keep, pix, scale, out32, out16, is_half, b0, b1),
                        (pix.size + _BLOCK - 1) // _BLOCK, 1)
    report.update(dtype=np.dtype(dt).name, dtype_reason=why, layout=layout,
                  store_bytes=int(store.nbytes), compression="none")
    report.setdefault("compression_reason", "not requested")
    report["time_triangulate_s"] = t1 - t0
    report["time_store_s"] = time.perf_counter() - t1
    return BakedDataset(shape=(h, w), distant=ds.distant, store=store, pixel_index=pix, points=pts,
                        light_positions=np.ascontiguousarray(ds.light_positions[keep]),
                        intensities=np.ascontiguousarray(ds.intensities[keep]),
                        kept_from=keep.astype(np.int64), directions=dirs_k, store_scale=scale,
                        sphere_center=center, sphere_radius=radius, triangles=np.ascontiguousarray(tri),
                        tri_inverse=np.ascontiguousarray(inv), grid_n=grid_n, grid_start=grid_start,
                        grid_items=grid_items, report=report)
