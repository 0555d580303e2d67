"""Relighting from an illumination dataset (ALGORITHMS.md part B; the paper's section 2).

A fixed camera sees an object lit, image by image, by K point lights (or K distant
lights). With the 3-D surface point ``P`` of every pixel known, the pixel under a new
light is interpolated from the three dataset images whose lights form the triangle that
the ray from ``P`` through the new light crosses on the light sphere (paper eq. 1).

Public, checked wrappers: :class:`IlluminationDataset`, :func:`points_from_depth`,
:func:`bake_dataset`, :func:`locate_directions`, :func:`relight`. The numba kernels
(``_locate``, ``_relight_kernel``) are private and do no validation (CONVENTIONS 6).
The math, the coverage rule and the storage layout are in ``docs/relighting.md``.

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
import types
from dataclasses import dataclass, field
from functools import cached_property

import numba as nb
import numpy as np
from llvmlite import binding as llvm_binding
from llvmlite import ir
from numba.core import cgutils
from numba.core import types as nbtypes
from numba.extending import intrinsic, overload

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import InvalidInputError
from engine.relighting.compress import LowRankStore, block_order, compress_store
from engine.scene import CameraParams
from engine.sched import next_block

HALF_MAX = 65504.0
HALF_MIN_NORMAL = 6.103515625e-05
LAYOUTS = ("pixel_major", "tiled")
TILE = 256  # pixels per tile of the "tiled" layout (a power of two: the kernel shifts and masks)
_TILE_SHIFT = 8

# light kinds inside the kernel
_K_POINT, _K_DIRECTIONAL, _K_ORIENTED, _K_TWO_SIDED = 0, 1, 2, 3

# ============================================================================ dataset


def _as_array(name: str, a, dtype, ndim: int | None = None) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=dtype)
    except (TypeError, ValueError) as e:
        raise InvalidInputError(f"{name}: not a numeric array ({e})") from None
    if ndim is not None and arr.ndim != ndim:
        raise InvalidInputError(f"{name}: expected {ndim} dimensions, got shape {arr.shape}")
    return arr


@dataclass(frozen=True)
class IlluminationDataset:
    """K images of one fixed view, image k lit only by light k, plus the surface points.

    images: (K, h, w, 3) float32 linear radiance.
    light_positions: (K, 3) float64; world positions of isotropic point lights, or, when
        ``distant`` is True, directions *toward* distant lights (normalised on entry).
    intensities: (K, 3) float64 > 0; W/sr for point lights, irradiance for distant lights.
    points: (h, w, 3) float64 surface point of every pixel, in the lights' frame.
    mask: (h, w) bool or None; pixels without a surface point (background) are False.
        Points of masked-out pixels are ignored (they may be NaN).
    distant: one flag for the whole dataset (a photometric-stereo rig has only distant
        lights, a light stage only near ones; mixed datasets are not supported).
    sphere_center: (3,) or None; the centre of the sphere the lights were placed on, when
        known (a light stage, a generated dataset); the bake's default centre.
    meta: JSON-serialisable facts about where the dataset came from (generation placement,
        render parameters, timings); not used by the bake.
    """

    images: np.ndarray
    light_positions: np.ndarray
    intensities: np.ndarray
    points: np.ndarray
    mask: np.ndarray | None = None
    distant: bool = False
    sphere_center: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if isinstance(self.images, (list, tuple)):
            shapes = [np.shape(a) for a in self.images]
            for i, sh in enumerate(shapes):
                if sh != shapes[0]:
                    raise InvalidInputError(f"images[{i}]: shape {sh} differs from images[0] {shapes[0]} "
                                            "(all images must have the same size)")
        imgs = _as_array("images", self.images, np.float32, 4)
        if imgs.shape[-1] != 3:
            raise InvalidInputError(f"images: expected (K, h, w, 3), got shape {imgs.shape}")
        k, h, w = imgs.shape[:3]
        if k < 3:
            raise InvalidInputError(f"images: at least 3 lit images are needed, got {k}")
        if h < 1 or w < 1:
            raise InvalidInputError(f"images: empty image size {h}x{w}")
        if not np.all(np.isfinite(imgs)):
            bad = np.unique(np.nonzero(~np.isfinite(imgs))[0])
            raise InvalidInputError(f"images: non-finite values in image(s) {bad[:10].tolist()}")
        pos = _as_array("light_positions", self.light_positions, np.float64, 2)
        if pos.shape != (k, 3):
            raise InvalidInputError(f"light_positions: light count {pos.shape[0] if pos.ndim else 0} "
                                    f"does not match image count {k} (shape {pos.shape}, expected ({k}, 3))")
        if not np.all(np.isfinite(pos)):
            bad = np.nonzero(~np.all(np.isfinite(pos), axis=1))[0]
            raise InvalidInputError(f"light_positions: NaN/Inf in light(s) {bad[:10].tolist()}")
        if self.distant:
            n = np.linalg.norm(pos, axis=1)
            if np.any(n == 0):
                raise InvalidInputError(f"light_positions: zero direction for distant light(s) "
                                        f"{np.nonzero(n == 0)[0][:10].tolist()}")
            pos = pos / n[:, None]
        inten = _as_array("intensities", self.intensities, np.float64)
        if inten.ndim == 1 and inten.shape == (k,):
            inten = np.repeat(inten[:, None], 3, axis=1)
        if inten.shape != (k, 3):
            raise InvalidInputError(f"intensities: expected ({k}, 3) or ({k},), got shape {inten.shape}")
        if not np.all(np.isfinite(inten)) or np.any(inten <= 0):
            raise InvalidInputError("intensities: must be finite and > 0 in every channel")
        pts = _as_array("points", self.points, np.float64, 3)
        if pts.shape != (h, w, 3):
            raise InvalidInputError(f"points: surface points of shape {pts.shape} do not match the "
                                    f"image size {h}x{w} (expected ({h}, {w}, 3))")
        if self.mask is None:
            m = np.ones((h, w), dtype=bool)
        else:
            m = np.asarray(self.mask)
            if m.shape != (h, w):
                raise InvalidInputError(f"mask: shape {m.shape} does not match the image size {h}x{w}")
            m = m.astype(bool)
        finite = np.all(np.isfinite(pts), axis=2)
        if np.any(m & ~finite):
            raise InvalidInputError(f"points: {int(np.sum(m & ~finite))} masked-in pixel(s) have NaN/Inf "
                                    "surface points (mask them out)")
        if not np.any(m):
            raise InvalidInputError("mask: no pixel has a surface point")
        pts = np.where(m[:, :, None], pts, 0.0)
        if self.sphere_center is not None:
            sc = _as_array("sphere_center", self.sphere_center, np.float64, 1)
            if sc.shape != (3,) or not np.all(np.isfinite(sc)):
                raise InvalidInputError("sphere_center: expected 3 finite numbers")
            object.__setattr__(self, "sphere_center", sc)
        object.__setattr__(self, "images", np.ascontiguousarray(imgs))
        object.__setattr__(self, "light_positions", np.ascontiguousarray(pos))
        object.__setattr__(self, "intensities", np.ascontiguousarray(inten))
        object.__setattr__(self, "points", np.ascontiguousarray(pts))
        object.__setattr__(self, "mask", m)
        object.__setattr__(self, "distant", bool(self.distant))

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.images.shape[1]), int(self.images.shape[2])


def points_from_depth(depth, camera: CameraParams | None = None, *, depth_kind: str = "z",
                      intrinsics=None, world_from_camera=None) -> tuple[np.ndarray, np.ndarray]:
    """Surface points (h, w, 3) float64 and validity (h, w) bool from a depth map (h, w).

    Either ``camera`` (this project's :class:`CameraParams`, perspective or orthographic;
    pixel centres as in ``engine.camera``) or ``intrinsics`` = 3x3 pinhole matrix K in the
    OpenCV camera frame (x right, y down, z forward) with optional ``world_from_camera``
    (4, 4). ``depth_kind``: ``"z"`` = distance along the optical axis, ``"distance"`` =
    distance along the pixel's ray. For an orthographic camera both are the same. Pixels
    whose depth is NaN, Inf or <= 0 are invalid (their point is NaN).
    """
    from engine.camera import camera_rays, pixel_centers

    d = _as_array("depth", depth, np.float64, 2)
    h, w = d.shape
    if depth_kind not in ("z", "distance"):
        raise InvalidInputError(f"depth_kind must be 'z' or 'distance', got {depth_kind!r}")
    if (camera is None) == (intrinsics is None):
        raise InvalidInputError("points_from_depth: give exactly one of camera or intrinsics")
    valid = np.isfinite(d) & (d > 0)
    dd = np.where(valid, d, np.nan)
    if camera is not None:
        if (camera.height, camera.width) != (h, w):
            raise InvalidInputError(f"depth: depth map is {h}x{w} but the camera is "
                                    f"{camera.height}x{camera.width}")
        px, py = pixel_centers(camera)
        o, dirs = camera_rays(camera, px, py)
        if camera.kind == "perspective" and depth_kind == "z":
            fwd = camera.basis()[2]
            t = dd.ravel() / (dirs @ fwd)
        else:
            t = dd.ravel()
        pts = o + dirs * t[:, None]
        return pts.reshape(h, w, 3), valid
    kmat = _as_array("intrinsics", intrinsics, np.float64, 2)
    if kmat.shape != (3, 3) or kmat[0, 0] == 0 or kmat[1, 1] == 0:
        raise InvalidInputError("intrinsics: expected a 3x3 pinhole matrix with fx, fy != 0")
    ys, xs = np.mgrid[0:h, 0:w]
    x = (xs + 0.5 - kmat[0, 2]) / kmat[0, 0]
    y = (ys + 0.5 - kmat[1, 2]) / kmat[1, 1]
    rays = np.stack([x, y, np.ones_like(x)], axis=-1)
    if depth_kind == "distance":
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    pts = rays * dd[:, :, None]
    if world_from_camera is not None:
        m = _as_array("world_from_camera", world_from_camera, np.float64, 2)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise InvalidInputError("world_from_camera: expected a finite (4, 4) matrix")
        pts = pts @ m[:3, :3].T + m[:3, 3]
    return pts, valid


# ============================================================================ bake


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
        n_chunks = (n + _CHUNK - 1) // _CHUNK
        pad = np.zeros((n_chunks * _CHUNK, 3), np.float32)
        pad[:n] = o
        pts = np.ascontiguousarray(pad.reshape(n_chunks, _CHUNK, 3).transpose(0, 2, 1))
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


def _dedupe(dirs: np.ndarray, pos: np.ndarray, tol_rad: float):
    """Keep the first of every group of lights whose direction is within ``tol_rad``."""
    k = dirs.shape[0]
    keep = np.ones(k, dtype=bool)
    n_exact = n_near = 0
    # exact duplicates by value (np.unique returns first occurrences)
    _, first = np.unique(pos, axis=0, return_index=True)
    exact_dup = np.ones(k, dtype=bool)
    exact_dup[first] = False
    n_exact = int(exact_dup.sum())
    keep &= ~exact_dup
    # near duplicates: pairs within the chord of tol_rad (k-d tree), greedily in input order
    from scipy.spatial import cKDTree

    idx = np.nonzero(keep)[0]
    if tol_rad > 0 and idx.size > 1:
        pairs = cKDTree(dirs[idx]).query_pairs(2.0 * math.sin(0.5 * tol_rad), output_type="ndarray")
        if pairs.size:
            pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
            for a, b in idx[pairs]:
                if keep[a] and keep[b]:
                    keep[b] = False
                    n_near += 1
    return np.nonzero(keep)[0], n_exact, n_near


def _triangulate(dirs: np.ndarray, max_face_radius_deg: float | None):
    """Convex hull of unit directions -> (covered triangles (T, 3), report dict)."""
    from scipy.spatial import ConvexHull, QhullError

    k = dirs.shape[0]
    _, sv, vt = np.linalg.svd(dirs - dirs.mean(axis=0), full_matrices=False)
    centroid_plane = abs(float(np.mean(dirs @ vt[2])))  # distance of the best-fit plane from the centre
    if k == 3 or sv[2] < 1e-9 * max(sv[0], 1e-300):
        # all directions in one plane: the hull is flat
        if k == 3:
            tri = np.array([[0, 1, 2]], dtype=np.int64)
            n = np.cross(dirs[1] - dirs[0], dirs[2] - dirs[0])
            if np.linalg.norm(n) < 1e-12 or abs(np.dot(n / np.linalg.norm(n), dirs[0])) < 1e-9:
                raise InvalidInputError("light_positions: the 3 light directions lie on one great circle "
                                        "of the light sphere (they enclose no area)")
            if np.dot(n, dirs[0]) < 0:
                tri = tri[:, ::-1].copy()
            return tri, {"n_hull_faces": 1, "n_uncovered_faces": 0, "max_face_radius_deg": None}
        where = "one great circle through the sphere centre" if centroid_plane < 1e-9 else "one circle"
        raise InvalidInputError(f"light_positions: the {k} light directions are coplanar (they lie on {where} "
                                "of the light sphere), so they do not span a triangulated area; add lights "
                                "off that circle")
    try:
        hull = ConvexHull(dirs)
    except (QhullError, ValueError) as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise InvalidInputError(f"light_positions: the light directions cannot be triangulated ({msg})") from None
    tri = hull.simplices.astype(np.int64)
    normals = hull.equations[:, :3]
    offsets = -hull.equations[:, 3]  # plane n.x = d, n outward
    # wind every triangle counter-clockwise seen from outside
    a, b, c = dirs[tri[:, 0]], dirs[tri[:, 1]], dirs[tri[:, 2]]
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), normals) < 0
    tri[flip] = tri[flip][:, ::-1]
    # coverage rule: a hull face's plane cuts the unit sphere in its circumcircle, of angular
    # radius acos(d). Spherical Delaunay faces have empty circumcircles, so a face with a large
    # circumcircle bridges a region with no lights: it is outside the coverage.
    radius_deg = np.degrees(np.arccos(np.clip(offsets, -1.0, 1.0)))
    auto = max_face_radius_deg is None
    thr = float(min(85.0, 3.0 * float(np.median(radius_deg)))) if auto else float(max_face_radius_deg)
    covered = radius_deg <= thr
    if not np.any(covered):
        raise InvalidInputError("light_positions: no triangle of the light triangulation is within the coverage "
                                f"rule (max circumradius {thr:.3g} deg); the lights are too sparse")
    return tri[covered], {"n_hull_faces": int(tri.shape[0]), "n_uncovered_faces": int((~covered).sum()),
                          "max_face_radius_deg": thr, "face_radius_rule": "auto" if auto else "given"}


def _unit(v):
    return v / np.linalg.norm(v)


@nb.njit(cache=True)
def _cube_cell(x, y, z, n):
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax >= ay and ax >= az:
        f = 0 if x > 0 else 1
        u, v = y / ax, z / ax
    elif ay >= az:
        f = 2 if y > 0 else 3
        u, v = x / ay, z / ay
    else:
        f = 4 if z > 0 else 5
        u, v = x / az, y / az
    i = int((u + 1.0) * 0.5 * n)
    j = int((v + 1.0) * 0.5 * n)
    i = min(max(i, 0), n - 1)
    j = min(max(j, 0), n - 1)
    return (f * n + j) * n + i


def _cell_caps(n: int):
    """Centre direction and angular radius (cos) of every cube-map cell, in _cube_cell order."""
    g = np.linspace(-1.0, 1.0, n + 1)
    centres = np.empty((6, n, n, 3))
    cosr = np.empty((6, n, n))
    for f in range(6):
        uu, vv = np.meshgrid(g, g)  # [j, i]
        axis, sign = f // 2, 1.0 if f % 2 == 0 else -1.0

        def dir_of(u, v, axis=axis, sign=sign):
            d = np.empty(u.shape + (3,))
            if axis == 0:
                d[..., 0], d[..., 1], d[..., 2] = sign, u, v
            elif axis == 1:
                d[..., 0], d[..., 1], d[..., 2] = u, sign, v
            else:
                d[..., 0], d[..., 1], d[..., 2] = u, v, sign
            return d / np.linalg.norm(d, axis=-1, keepdims=True)

        uc = 0.5 * (uu[:-1, :-1] + uu[1:, 1:])
        vc = 0.5 * (vv[:-1, :-1] + vv[1:, 1:])
        c = dir_of(uc, vc)
        corners = dir_of(uu, vv)
        cmin = np.minimum.reduce([np.einsum("jik,jik->ji", c, corners[dj:dj + n, di:di + n])
                                  for dj in (0, 1) for di in (0, 1)])
        centres[f], cosr[f] = c, cmin
    return centres.reshape(-1, 3), cosr.ravel()


def _build_grid(dirs: np.ndarray, tri: np.ndarray):
    t = tri.shape[0]
    n = int(np.clip(np.ceil(np.sqrt(t / 6.0)) * 2, 4, 128))
    centres, cos_cell = _cell_caps(n)
    a, b, c = dirs[tri[:, 0]], dirs[tri[:, 1]], dirs[tri[:, 2]]
    cc = _unit_rows(np.cross(b - a, c - a))  # circumcentre direction (outward: CCW winding)
    cos_tri = np.einsum("ij,ij->i", cc, a)
    ang_cell = np.arccos(np.clip(cos_cell, -1, 1))
    ang_tri = np.arccos(np.clip(cos_tri, -1, 1))
    pad = 1e-7
    # candidates by a k-d tree on the circumcentres (chord radius of the largest possible angle),
    # then the exact cap-overlap test per pair: O(cells x candidates), not O(cells x triangles)
    from scipy.spatial import cKDTree

    reach = np.minimum(ang_cell + ang_tri.max() + pad, np.pi)
    near = cKDTree(cc).query_ball_point(centres, r=2.0 * np.sin(0.5 * reach) + 1e-12)
    starts = [0]
    items: list[np.ndarray] = []
    for ci, cand in enumerate(near):
        cand = np.asarray(sorted(cand), dtype=np.int64)
        if cand.size:
            ang = np.arccos(np.clip(cc[cand] @ centres[ci], -1, 1))
            cand = cand[ang <= ang_cell[ci] + ang_tri[cand] + pad]
        items.append(cand)
        starts.append(starts[-1] + cand.size)
    grid_items = np.concatenate(items).astype(np.int64) if items else np.zeros(0, np.int64)
    return n, np.asarray(starts, dtype=np.int64), grid_items


def _unit_rows(v):
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@nb.njit(cache=True, parallel=True, nogil=True)
def _light_stats(images, keep, pix, rel_floor, vmax, vmin):
    """Per kept light j: max |v| and the smallest |v| > 0 that is >= rel_floor x max, over the
    stored pixels. images (K, h*w, 3) float32."""
    for j in nb.prange(keep.size):
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


_BLOCK = 2048


def _gather_kernel(images, keep, pix, scale, out, out16, half):
    """Pixel-major store: row r, light j = images[keep[j], pix[r], :] x scale[j], written as float32
    (``out``) or as float16 bits (``out16``). Blocks of pixels keep the reads contiguous per light
    and the writes inside one L2-sized block."""
    n = pix.size
    for bi in nb.prange((n + _BLOCK - 1) // _BLOCK):
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


_gather_pixel_major = nb.njit(cache=True, parallel=True, nogil=True)(_gather_kernel)


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
        (default 0: every non-zero value keeps float16's 2^-11 relative precision, HARD_CASES 9).
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
        center = pts.mean(axis=0) if sphere_center is None else _as_array("sphere_center", sphere_center,
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
    keep, n_exact, n_near = _dedupe(dirs, ds.light_positions, math.radians(dedupe_tol_deg))
    report.update(n_exact_duplicates=n_exact, n_near_duplicates=n_near, n_lights=int(keep.size))
    if keep.size < 3:
        raise InvalidInputError(f"light_positions: only {keep.size} distinct light(s) after deduplication; "
                                "at least 3 are needed")
    dirs_k = np.ascontiguousarray(dirs[keep])
    tri, tri_report = _triangulate(dirs_k, max_face_radius_deg)
    report.update(tri_report)
    report["n_triangles"] = int(tri.shape[0])
    mats = np.stack([dirs_k[tri[:, 0]], dirs_k[tri[:, 1]], dirs_k[tri[:, 2]]], axis=2)  # columns = vertices
    try:
        inv = np.linalg.inv(mats)
    except np.linalg.LinAlgError:
        raise InvalidInputError("light_positions: a degenerate light triangle (3 directions on a great "
                                "circle)") from None
    grid_n, grid_start, grid_items = _build_grid(dirs_k, tri)
    report["grid_n"] = grid_n
    report["grid_mean_candidates"] = float(grid_items.size / max(grid_start.size - 1, 1))
    t1 = time.perf_counter()
    flat = ds.images.reshape(ds.images.shape[0], h * w, 3)
    vmax = np.empty(keep.size)
    vmin = np.empty(keep.size)
    _light_stats(flat, keep, pix, float(half_rel_floor), vmax, vmin)
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
    _gather_pixel_major(flat, keep, pix, scale, dummy32 if is_half else store,
                        store.view(np.uint16) if is_half else dummy16, is_half)
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


# ============================================================================ kernels

_CONE_EPS = 1e-12
_CHUNK = 256  # rows per chunk = TILE: a chunk is one tile of the tiled store
_MAX_PASSES = 4  # triangles per chunk and light in the SIMD pass B (the rest: scalar pass B3)
_F32_BAND = 512.0  # the float32 cone test's border, in units of its error bound's 2^-24 N |s| (see the kernel)
_F32_WELL = 0.81  # the float32 geometry's points: |P - c| <= 0.9 R (nearer the sphere: the float64 test)
_F32_LIGHT_RANGE = 2.0 ** 20  # the float32 geometry's lights: within 2^20 sphere radii of the centre
_SIMD_MIN_ROWS = 32  # fewer rows left than this: the scalar pass B3 is cheaper than another SIMD pass
_UNIT = 8  # consecutive chunks one scratch group runs in a row (neighbouring 16 x 16 blocks: output rows,
#            points and pixel indices stay in the same pages and prefetch streams)


def _make_half(hardware: bool):
    @intrinsic
    def half(typingctx, bits):
        """float16 bits (uint16) -> float32, exact for zero, subnormal and normal values (the bake
        never stores Inf or NaN). numba has no CPU float16 type. ``hardware``: LLVM's half -> float
        extension (one F16C ``vcvtph2ps``); otherwise 32-bit integer operations (sign, exponent
        rebias 15 -> 127, mantissa widened 10 -> 23 bits; subnormals as mantissa x 2^-24). Both are
        vectorisable, unlike the 256 KiB lookup table used before."""
        if bits != nbtypes.uint16:
            return None

        def codegen(context, builder, sig, args):
            i32, f32 = ir.IntType(32), ir.FloatType()
            if hardware:
                return builder.fpext(builder.bitcast(args[0], ir.HalfType()), f32)
            x = builder.zext(args[0], i32)
            sign = builder.shl(builder.and_(x, ir.Constant(i32, 0x8000)), ir.Constant(i32, 16))
            em = builder.and_(x, ir.Constant(i32, 0x7FFF))  # exponent and mantissa
            normal = builder.add(builder.shl(em, ir.Constant(i32, 13)), ir.Constant(i32, 112 << 23))
            sub = builder.bitcast(builder.fmul(builder.uitofp(em, f32), ir.Constant(f32, 2.0 ** -24)), i32)
            mag = builder.select(builder.icmp_unsigned(">=", em, ir.Constant(i32, 0x400)), normal, sub)
            return builder.bitcast(builder.or_(mag, sign), f32)
        return nbtypes.float32(nbtypes.uint16), codegen
    return half


_half_bits = _make_half(False)
_half_hw = _make_half(True)
# numba compiles for the host CPU: with F16C the hardware conversion (without it LLVM would call a
# runtime helper the JIT may not provide, so the integer version is used)
_HOST_F16C = "+f16c" in llvm_binding.get_host_cpu_features().flatten().split(",")
_half = _half_hw if _HOST_F16C else _half_bits


def _make_prefetch(rw: int):
    @intrinsic
    def prefetch(typingctx, arr, idx):
        """Hint the cache line holding arr[idx] (1-D array) into L1; never faults (an index past the
        end is harmless), no effect on results."""
        if not (isinstance(arr, nbtypes.Array) and arr.ndim == 1 and isinstance(idx, nbtypes.Integer)):
            return None

        def codegen(context, builder, sig, args):
            aryty = sig.args[0]
            ary = context.make_array(aryty)(context, builder, args[0])
            ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1]], wraparound=False)
            i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
            fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]),
                                                "llvm.prefetch.p0")
            builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, rw), ir.Constant(i32, 3),
                              ir.Constant(i32, 1)])
            return context.get_dummy_value()
        return nbtypes.none(arr, idx), codegen
    return prefetch


@intrinsic
def _store_run48(typingctx, out, q, a0, a1, a2, r0):
    """out[q + 3 k + c] = (a0, a1, a2)[c][r0 + k] for k < 16: one 16-pixel RGB output run built from three
    float32 channel rows by vector shuffles. When &out[q] is 64-byte aligned the three cache lines are
    written with non-temporal stores (the frame is far larger than the caches: no read-for-ownership of
    lines that are overwritten whole, no eviction of the store runs); otherwise ordinary stores."""
    arr1 = (isinstance(out, nbtypes.Array) and out.ndim == 1 and out.dtype == nbtypes.float32)
    if not (arr1 and all(isinstance(a, nbtypes.Array) and a.ndim == 1 and a.dtype == nbtypes.float32
                         for a in (a0, a1, a2)) and isinstance(q, nbtypes.Integer)
            and isinstance(r0, nbtypes.Integer)):
        return None

    def codegen(context, builder, sig, args):
        f32 = ir.FloatType()
        i32, i64 = ir.IntType(32), ir.IntType(64)
        v16 = ir.VectorType(f32, 16)

        def ptr(k, idx):
            aryty = sig.args[k]
            ary = context.make_array(aryty)(context, builder, args[k])
            idx = context.cast(builder, idx, sig.args[1 if k == 0 else 5], nbtypes.intp)
            return cgutils.get_item_pointer(context, builder, aryty, ary, [idx], wraparound=False)

        dst = ptr(0, args[1])
        rows = [builder.load(builder.bitcast(ptr(k, args[5]), v16.as_pointer()), align=4) for k in (2, 3, 4)]
        ab = builder.shuffle_vector(rows[0], rows[1], ir.Constant(ir.VectorType(i32, 32), list(range(32))))
        cc = builder.shuffle_vector(rows[2], rows[2], ir.Constant(ir.VectorType(i32, 32), list(range(16)) * 2))
        mask = [(k // 3) + 16 * (k % 3) for k in range(48)]
        il = builder.shuffle_vector(ab, cc, ir.Constant(ir.VectorType(i32, 48), mask))
        parts = [builder.shuffle_vector(il, il, ir.Constant(ir.VectorType(i32, 16), list(range(16 * j, 16 * j + 16))))
                 for j in range(3)]
        aligned = builder.icmp_unsigned("==", builder.and_(builder.ptrtoint(dst, i64), ir.Constant(i64, 63)),
                                        ir.Constant(i64, 0))
        base = builder.bitcast(dst, v16.as_pointer())
        with builder.if_else(aligned) as (nt, plain):
            with nt:
                for j in range(3):
                    st = builder.store(parts[j], builder.gep(base, [ir.Constant(i32, j)]), align=64)
                    st.set_metadata("nontemporal", builder.module.add_metadata([ir.Constant(i32, 1)]))
            with plain:
                for j in range(3):
                    builder.store(parts[j], builder.gep(base, [ir.Constant(i32, j)]), align=4)
        return context.get_dummy_value()
    return nbtypes.none(out, q, a0, a1, a2, r0), codegen


@intrinsic
def _fence(typingctx):
    """Order the non-temporal stores before the kernel returns (a full fence: mfence on x86)."""
    def codegen(context, builder, sig, args):
        builder.fence("seq_cst")
        return context.get_dummy_value()
    return nbtypes.none(), codegen


_prefetch = _make_prefetch(0)  # for reading


@intrinsic
def _wide_vectors(typingctx):
    """Let LLVM's vectorisers use 512-bit vectors in the calling function (on AVX-512 hosts LLVM prefers
    256-bit ones by default; elsewhere the attribute changes nothing): the function attribute
    ``"prefer-vector-width"="512"``, which llvmlite's attribute set does not list (added as text)."""
    def codegen(context, builder, sig, args):
        set.add(builder.function.attributes, '"prefer-vector-width"="512"')
        return context.get_dummy_value()
    return nbtypes.none(), codegen


@nb.njit(cache=True, nogil=True)
def _lr_dot(u, b, u0, b0, r):
    """One value of a low-rank store: the dot product of a pixel-channel row and a light row."""
    s = np.float32(0.0)
    for j in range(r):
        s += u[u0 + j] * b[b0 + j]
    return s


def _fetch(store, i, k, c):  # pragma: no cover - replaced by the overload in numba code
    raise NotImplementedError


@overload(_fetch, inline="always")
def _fetch_impl(store, i, k, c):
    """Value (float32, stored scale) of store row i, kept light k, channel c, for every store kind."""
    if isinstance(store, nbtypes.BaseTuple):  # low-rank factors (u, b, u_off, b_off, rank)
        def lowrank(store, i, k, c):
            u, b, u_off, b_off, rank = store
            t = i >> _TILE_SHIFT
            r = rank[t]
            return _lr_dot(u, b, u_off[t] + ((i & (TILE - 1)) * 3 + c) * r, b_off[t] + k * r, r)
        return lowrank
    if store.ndim == 4:  # tiled: (tile, light, row in tile, channel)
        if store.dtype == nbtypes.uint16:
            return lambda store, i, k, c: _half(store[i >> _TILE_SHIFT, k, i & (TILE - 1), c])
        return lambda store, i, k, c: store[i >> _TILE_SHIFT, k, i & (TILE - 1), c]
    if store.dtype == nbtypes.uint16:
        return lambda store, i, k, c: _half(store[i, k, c])
    return lambda store, i, k, c: store[i, k, c]


def _flat(store):  # pragma: no cover - replaced by the overload in numba code
    raise NotImplementedError


@overload(_flat, inline="always")
def _flat_impl(store):
    """A tiled store as one flat array (hoisted out of the loops: reshape calls into the runtime)."""
    if not isinstance(store, nbtypes.BaseTuple) and store.ndim == 4:
        return lambda store: store.reshape(-1)
    return lambda store: np.zeros(1, np.float32)


def _run(flat, store, tile, k):  # pragma: no cover - replaced by the overload in numba code
    raise NotImplementedError


@overload(_run, inline="always")
def _run_impl(flat, store, tile, k):
    """The TILE x 3 values of light k in a tile, as a contiguous 1-D view (tiled store): row r,
    channel c is run[3 r + c], strides the loop vectoriser sees as constants."""
    if not isinstance(store, nbtypes.BaseTuple) and store.ndim == 4:
        def run(flat, store, tile, k):
            o = (tile * store.shape[1] + k) * (TILE * 3)
            return flat[o:o + TILE * 3]
        return run
    return lambda flat, store, tile, k: flat


def _run_value(run, store, i, r, k, c):  # pragma: no cover - replaced by the overload in numba code
    raise NotImplementedError


@overload(_run_value, inline="always")
def _run_value_impl(run, store, i, r, k, c):
    """_fetch(store, i, k, c) for row r of the chunk, through its light run when the store is tiled."""
    if not isinstance(store, nbtypes.BaseTuple) and store.ndim == 4:
        if store.dtype == nbtypes.uint16:
            return lambda run, store, i, r, k, c: _half(run[3 * r + c])
        return lambda run, store, i, r, k, c: run[3 * r + c]
    return lambda run, store, i, r, k, c: _fetch(store, i, k, c)


def _simd_store(store):  # pragma: no cover - replaced by the overload in numba code
    raise NotImplementedError


@overload(_simd_store, inline="always")
def _simd_store_impl(store):
    """True for a tiled float16/float32 store: its light runs are contiguous per tile, so pass B2
    (all rows against the chunk's triangle) reads them as vectors."""
    simd = not isinstance(store, nbtypes.BaseTuple) and store.ndim == 4
    return lambda store: simd


def _prefetch_runs(flat, store, tile, ka, kb, kc):  # pragma: no cover - replaced by the overload
    raise NotImplementedError


@overload(_prefetch_runs, inline="always")
def _prefetch_runs_impl(flat, store, tile, ka, kb, kc):
    """Prefetch three lights' runs of a tile (tiled store; nothing for the other kinds)."""
    if not isinstance(store, nbtypes.BaseTuple) and store.ndim == 4:
        step = 512 // store.dtype.bitwidth  # elements per 64-byte cache line

        def pf(flat, store, tile, ka, kb, kc):
            base = tile * store.shape[1]
            for k in (ka, kb, kc):
                o = (base + k) * (TILE * 3)
                for e in range(0, TILE * 3, step):
                    _prefetch(flat, o + e)
        return pf
    return lambda flat, store, tile, ka, kb, kc: None


def _put(out, r, j, c, v):  # pragma: no cover - replaced by the overload in numba code
    raise NotImplementedError


@overload(_put, inline="always")
def _put_impl(out, r, j, c, v):
    if out.ndim == 4:
        def put4(out, r, j, c, v):
            out[r >> _TILE_SHIFT, j, r & (TILE - 1), c] = v
        return put4

    def put3(out, r, j, c, v):
        out[r, j, c] = v
    return put3


@nb.njit(cache=True, nogil=True, inline="always")
def _locate(x, y, z, inv, grid_n, grid_start, grid_items):
    """(triangle, w0, w1, w2) for direction (x, y, z) (not necessarily unit); triangle -1 = none.

    Cone coordinates a = inv[t] @ u; u is inside when all are >= -eps. The first candidate
    in the cell's (fixed) list wins, so edge and vertex hits are deterministic. Weights are
    clamped to >= 0 and normalised: the barycentrics of the point where the ray along u
    meets the flat triangle (a gnomonic projection, exact at vertices and along edges).
    """
    cell = _cube_cell(x, y, z, grid_n)
    for q in range(grid_start[cell], grid_start[cell + 1]):
        t = grid_items[q]
        a0 = inv[t, 0, 0] * x + inv[t, 0, 1] * y + inv[t, 0, 2] * z
        a1 = inv[t, 1, 0] * x + inv[t, 1, 1] * y + inv[t, 1, 2] * z
        a2 = inv[t, 2, 0] * x + inv[t, 2, 1] * y + inv[t, 2, 2] * z
        s = a0 + a1 + a2
        # one combined test (branch mispredictions dominate the candidate loop)
        if s > 0.0 and min(a0, min(a1, a2)) >= -_CONE_EPS * s:
            a0 = max(a0, 0.0)
            a1 = max(a1, 0.0)
            a2 = max(a2, 0.0)
            s = a0 + a1 + a2
            return t, a0 / s, a1 / s, a2 / s
    return -1, 0.0, 0.0, 0.0


@nb.njit(cache=True, parallel=True, nogil=True)
def _locate_many(dirs, inv, grid_n, grid_start, grid_items, tri_out, w_out):
    for i in nb.prange(dirs.shape[0]):
        t, w0, w1, w2 = _locate(dirs[i, 0], dirs[i, 1], dirs[i, 2], inv, grid_n, grid_start, grid_items)
        tri_out[i] = t
        w_out[i, 0], w_out[i, 1], w_out[i, 2] = w0, w1, w2


@nb.njit(cache=True, nogil=True, inline="always")
def _f32(x):
    return np.float32(x)


@nb.njit(cache=True, nogil=True, inline="always")
def _sphere_point(kd, distant_ds, lx, ly, lz, nx, ny, nz, ox, oy, oz, r2):
    """Scalar pass A for one row and light in the kernel frame (origin = sphere centre): (d2, den, sx,
    sy, sz) with d2 = |l - P|^2 (inf for directional lights), den the irradiance denominator (the
    light's contribution is its intensity / den; den < 0 = an area sample facing away) and s a
    positive multiple of the direction from the centre to the sphere point (the cone test and the
    normalised weights do not depend on its length). The SIMD loops of pass A are the same
    operations per row."""
    if kd == 1:
        if distant_ds:
            return math.inf, 1.0, lx, ly, lz
        b = ox * lx + oy * ly + oz * lz
        cc = ox * ox + oy * oy + oz * oz - r2
        e = b * b - cc
        t = math.sqrt(e if e > 0.0 else 0.0) - b
        return math.inf, 1.0, ox + t * lx, oy + t * ly, oz + t * lz
    dx, dy, dz = lx - ox, ly - oy, lz - oz
    d2 = dx * dx + dy * dy + dz * dz
    den = d2
    if kd >= 2:
        c = -(dx * nx + dy * ny + dz * nz) / math.sqrt(d2)
        if kd == 3:
            c = abs(c)
        den = d2 / c if c > 0.0 else -1.0
    if distant_ds:
        return d2, den, dx, dy, dz
    b = ox * dx + oy * dy + oz * dz
    cc = ox * ox + oy * oy + oz * oz - r2
    e = b * b - cc * d2
    t = math.sqrt(e if e > 0.0 else 0.0) - b
    return d2, den, d2 * ox + t * dx, d2 * oy + t * dy, d2 * oz + t * dz


def _relight_kernel(workers, kpts, points64, origin, store, lpos32, inv_int, distant_ds, radius, fscale, tris, inv,
                    grid_n, grid_start, grid_items, kinds, lp, lint, lnorm, min_dist2, near2, pix, runs, run_pix, out,
                    outside, singular, touched, flagged):
    """Per store row (pixel): sum over lights of interpolated normalised response x irradiance.

    Kernel frame: every position relative to ``origin`` (the sphere centre; for a distant dataset the
    centre of the points' bounding box). kpts (n_chunks, 3, _CHUNK) float32: the surface points in that
    frame, one contiguous row per axis and chunk (zero padded); points64 (n, 3) float64 the baked
    points (world frame), used for the rows whose light is within ``near2`` (squared) of the float32
    point: whether the light is closer than ``min_dist2`` (singular) is decided, and the row computed,
    in float64 from the exact point. store (n, K, 3) or tiled (n_tiles, K, TILE, 3), f32 or f16 bits
    (uint16), or the low-rank factors; lpos32 (K, 3) float32 dataset light positions in the kernel frame; inv_int
    (K, 3) = 1 / (dataset intensity x store scale); kinds (M,) int64; lp (M, 3) light position (kernel
    frame) or direction toward the light; lint (M, 3) intensity (point, oriented) or irradiance
    (directional); lnorm (M, 3) emitter normal (oriented). pix (n,) flat pixel of each store row; out
    (h*w, 3) f32 written at ``pix[i]`` only; outside / singular (h*w,) bool, zeroed by the caller, set
    at ``pix[i]`` where true; touched (T,) uint8 set to 1 for every triangle whose three lights were
    read (racing writes all store 1); flagged (1,) uint8 set to 1 when any outside or singular flag was
    set (so the caller counts the masks only then).

    Fixed chunks of _CHUNK consecutive rows (one tile of the tiled store; the same chunks for any
    thread count and schedule, so results do not depend on them). ``workers`` scratch groups (one per
    thread) take units of _UNIT consecutive chunks from a shared counter (``engine.sched``: a thread
    that loses its core for a while takes fewer units instead of the other waiting for it).
    Light by light:
    - pass A (SIMD): every row's sphere direction s (a positive multiple of the sphere point: one
      sqrt, no division), |l - P|^2 and the irradiance denominator;
    - pass B1: the chunk's triangle = the one the first usable row falls in (cube-map search);
    - pass B2 (SIMD across rows, in simple loops the vectoriser takes): every row's cone test against
      that triangle, its weights times the squared distances to the three vertex lights times the
      irradiance factor (one division per row), the three lights' runs of the tile decoded, and the
      accumulation of the rows the triangle contains (most rows: a 16 x 16 block sees a light in
      nearly one direction);
    - pass B3 (scalar): the other rows, previous-row triangle first, then the cube-map search; the
      same operations per row as B2 (a tiled and a pixel-major store give the same image).
    While a chunk is processed, the next chunk's points (after the first light's pass A) and its runs of
    the current triangle's lights are prefetched.
    """
    counter = np.zeros(1, np.int64)
    for _ in nb.prange(workers):
        _relight_group(counter, kpts, points64, origin, store, lpos32, inv_int, distant_ds, radius, fscale, tris, inv,
                       grid_n, grid_start, grid_items, kinds, lp, lint, lnorm, min_dist2, near2, pix, runs,
                       run_pix, out, outside, singular, touched, flagged)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _relight_group(counter, kpts, points64, origin, store, lpos32, inv_int, distant_ds, radius, fscale, tris, inv,
                   grid_n, grid_start, grid_items, kinds, lp, lint, lnorm, min_dist2, near2, pix, runs, run_pix, out,
                   outside, singular, touched, flagged):
    """One scratch group of ``_relight_kernel`` (its units taken from ``counter``), in its own function:
    the parallel kernel is a thin prange over the groups, so numba's parfor passes see a few lines instead of the
    whole kernel (cold compile of a float32 / float16 store 36 / 33 s -> 32 / 27 s on the loaded
    machine; the images bit-identical, kernel time unchanged: bench.relight_speed --ab)."""
    _wide_vectors()
    n = points64.shape[0]
    m = kinds.shape[0]
    gx0, gy0, gz0 = origin[0], origin[1], origin[2]
    r2 = radius * radius
    n_chunks = (n + _CHUNK - 1) // _CHUNK
    n_units = (n_chunks + _UNIT - 1) // _UNIT
    flat = _flat(store)
    kflat = kpts.reshape(-1)
    oflat = out.reshape(-1)
    simd = _simd_store(store)
    sx = np.empty(_CHUNK)
    sy = np.empty(_CHUNK)
    sz = np.empty(_CHUNK)
    den = np.empty(_CHUNK)
    d2s = np.empty(_CHUNK)
    acc0 = np.empty(_CHUNK, np.float32)
    acc1 = np.empty(_CHUNK, np.float32)
    acc2 = np.empty(_CHUNK, np.float32)
    out_f = np.empty(_CHUNK, np.bool_)
    sing_f = np.empty(_CHUNK, np.bool_)
    todo = np.empty(_CHUNK, np.bool_)
    hit = np.empty(_CHUNK, np.bool_)
    wa = np.empty(_CHUNK)
    wb = np.empty(_CHUNK)
    wc = np.empty(_CHUNK)
    fa32 = np.empty(_CHUNK, np.float32)
    fb32 = np.empty(_CHUNK, np.float32)
    fc32 = np.empty(_CHUNK, np.float32)
    sx32 = np.empty(_CHUNK, np.float32)
    sy32 = np.empty(_CHUNK, np.float32)
    sz32 = np.empty(_CHUNK, np.float32)
    d2s32 = np.empty(_CHUNK, np.float32)
    bet32 = np.empty(_CHUNK, np.float32)
    bord = np.zeros(_CHUNK, np.bool_)
    bordw = bord.view(np.uint64)
    # float32 pass A: a light nearer than this (squared, float32) to a row's point sends the row to pass B3,
    # which decides with the float64 d2 against near2 (the float32 d2 is within 2^-20 of it; the 1e-12
    # radii floor keeps the float32 geometry away from underflow)
    rsc = radius * fscale
    nh32 = _f32(max(near2 * fscale * fscale * (1.0 + 2.0 ** -12), 1e-12 * rsc * rsc))
    va = np.empty((3, _CHUNK), np.float32)
    vb = np.empty((3, _CHUNK), np.float32)
    vc = np.empty((3, _CHUNK), np.float32)
    out_f[:] = False
    sing_f[:] = False
    # units of _UNIT consecutive chunks from the shared counter (engine.sched); the next unit is taken when
    # the current one's last chunk starts, so that chunk can prefetch its successor's points and runs
    unit = next_block(counter)
    unit_next = n_units
    ci = unit * _UNIT - 1
    while True:
        ci += 1
        if ci >= min((unit + 1) * _UNIT, n_chunks):
            unit = unit_next
            ci = unit * _UNIT
        if unit >= n_units:
            break
        i0 = ci * _CHUNK
        nc = min(n, i0 + _CHUNK) - i0
        # the group's next chunk: the next of this unit, else the first of the unit it takes now
        cn = ci + 1
        if cn >= min((unit + 1) * _UNIT, n_chunks):
            unit_next = next_block(counter)
            cn = unit_next * _UNIT
        n0 = cn * _CHUNK
        ncn = min(n, n0 + _CHUNK) - n0 if cn < n_chunks else 0
        # the chunk's points: three contiguous float32 rows
        qx = kflat[3 * i0:3 * i0 + _CHUNK]
        qy = kflat[3 * i0 + _CHUNK:3 * i0 + 2 * _CHUNK]
        qz = kflat[3 * i0 + 2 * _CHUNK:3 * i0 + 3 * _CHUNK]
        for r in range(_CHUNK):
            acc0[r] = np.float32(0.0)
            acc1[r] = np.float32(0.0)
            acc2[r] = np.float32(0.0)
        flags = False
        for j in range(m):
            kd = kinds[j]
            lx, ly, lz = lp[j, 0], lp[j, 1], lp[j, 2]
            nx, ny, nz = lnorm[j, 0], lnorm[j, 1], lnorm[j, 2]
            # the float32 geometry (one point light of a tiled store, the common case; the light within
            # 2^20 sphere radii: no float32 overflow or underflow in the scaled frame): pass A and the
            # cone test in float32, rows whose test is within its error bound re-tested in float64
            f32 = (simd and kd == 0 and not distant_ds
                   and max(abs(lx), max(abs(ly), abs(lz))) <= _F32_LIGHT_RANGE * radius)
            # ---- pass A: sphere direction, squared distance and irradiance denominator of every row
            if f32:
                # in the frame scaled by fscale (a power of two: exact) the radius is in [1, 2); the light
                # position as float32 hi + lo, so d = l - P is accurate to float32 rounding of d itself
                lsx, lsy, lsz = lx * fscale, ly * fscale, lz * fscale
                lxh, lyh, lzh = _f32(lsx), _f32(lsy), _f32(lsz)
                lxl, lyl, lzl = _f32(lsx - lxh), _f32(lsy - lyh), _f32(lsz - lzh)
                fs32 = _f32(fscale)
                rs2 = _f32(rsc * rsc)
                well = _f32(_F32_WELL * rsc * rsc)
                for r in range(_CHUNK):
                    ox, oy, oz = qx[r] * fs32, qy[r] * fs32, qz[r] * fs32
                    dx, dy, dz = (lxh - ox) + lxl, (lyh - oy) + lyl, (lzh - oz) + lzl
                    d2 = dx * dx + dy * dy + dz * dz
                    b = ox * dx + oy * dy + oz * dz
                    oo = ox * ox + oy * oy + oz * oz
                    e = b * b - (oo - rs2) * d2
                    t = math.sqrt(e if e > np.float32(0.0) else np.float32(0.0)) - b
                    sx32[r] = d2 * ox + t * dx
                    sy32[r] = d2 * oy + t * dy
                    sz32[r] = d2 * oz + t * dz
                    d2s32[r] = d2
                    # the cone test's error bound is proportional to d2 for points well inside the sphere;
                    # the others always take the float64 test
                    bet32[r] = d2 if oo <= well else np.float32(np.inf)
                n_todo = 0  # (a separate loop: an integer count in pass A halves its vector width)
                for r in range(_CHUNK):
                    u = (r < nc) & (d2s32[r] > nh32)
                    todo[r] = u
                    n_todo += u
            elif kd == 1:
                for r in range(_CHUNK):
                    den[r] = 1.0
                    d2s[r] = math.inf
                if distant_ds:
                    for r in range(_CHUNK):
                        sx[r], sy[r], sz[r] = lx, ly, lz
                else:
                    for r in range(_CHUNK):
                        ox, oy, oz = np.float64(qx[r]), np.float64(qy[r]), np.float64(qz[r])
                        b = ox * lx + oy * ly + oz * lz
                        cc = ox * ox + oy * oy + oz * oz - r2
                        e = b * b - cc
                        t = math.sqrt(e if e > 0.0 else 0.0) - b
                        sx[r] = ox + t * lx
                        sy[r] = oy + t * ly
                        sz[r] = oz + t * lz
            elif kd == 0 and not distant_ds:  # the common case, branch-free
                for r in range(_CHUNK):
                    ox, oy, oz = np.float64(qx[r]), np.float64(qy[r]), np.float64(qz[r])
                    dx, dy, dz = lx - ox, ly - oy, lz - oz
                    d2 = dx * dx + dy * dy + dz * dz
                    d2s[r] = d2
                    den[r] = d2
                    b = ox * dx + oy * dy + oz * dz
                    cc = ox * ox + oy * oy + oz * oz - r2
                    e = b * b - cc * d2
                    t = math.sqrt(e if e > 0.0 else 0.0) - b
                    sx[r] = d2 * ox + t * dx
                    sy[r] = d2 * oy + t * dy
                    sz[r] = d2 * oz + t * dz
            else:
                for r in range(nc):
                    d2s[r], den[r], sx[r], sy[r], sz[r] = _sphere_point(
                        kd, distant_ds, lx, ly, lz, nx, ny, nz, np.float64(qx[r]), np.float64(qy[r]),
                        np.float64(qz[r]), r2)
            if j == 0 and ncn > 0:
                # the next chunk's points, after this chunk's pass A rather than at its start (right after the
                # previous chunk's 48 non-temporal output lines, which hold the fill buffers the prefetches
                # wait for): bench A/B one point light 1.02-1.06x, bit-identical
                for e in range(0, 3 * _CHUNK, 16):
                    _prefetch(kflat, 3 * n0 + e)
            # the light's largest channel goes into the float64 factor (so the float32 weights are
            # in the range of the result, for any distance), the channel ratios into the constants
            lmax = max(lint[j, 0], max(lint[j, 1], lint[j, 2]))
            lmax = lmax if lmax > 0.0 else 1.0
            l0, l1, l2 = lint[j, 0] / lmax, lint[j, 1] / lmax, lint[j, 2] / lmax
            # rows to do: usable (not within near2 of the light, not an area sample facing away) and
            # not yet accumulated; the unusable rows (rare) go to pass B3
            if not f32:
                n_todo = 0
                for r in range(_CHUNK):
                    u = (r < nc) & (d2s[r] > near2) & (den[r] > 0.0)
                    todo[r] = u
                    n_todo += u
            n_rest = nc - n_todo  # unusable rows
            # ---- pass B (SIMD, tiled stores; pixel-major and low-rank rows are gathers either way:
            # all rows go to B3): a triangle = the one the first row to do falls in (cube-map search),
            # tested against every row of the chunk; then the next one, while >= _SIMD_MIN_ROWS rows
            # are left (a 16 x 16 block mostly needs one or two triangles)
            for _ in range(_MAX_PASSES if simd else 0):
                t0 = -1
                for r in range(nc):
                    if todo[r]:
                        if f32:  # the float64 direction (as the float64 kernel locates it)
                            _, _, x, y, z = _sphere_point(kd, distant_ds, lx, ly, lz, nx, ny, nz, np.float64(qx[r]),
                                                          np.float64(qy[r]), np.float64(qz[r]), r2)
                        else:
                            x, y, z = sx[r], sy[r], sz[r]
                        t0, w0, w1, w2 = _locate(x, y, z, inv, grid_n, grid_start, grid_items)
                        break
                if t0 < 0:  # outside coverage: pass B3 marks it
                    break
                touched[t0] = 1
                m00, m01, m02 = inv[t0, 0, 0], inv[t0, 0, 1], inv[t0, 0, 2]
                m10, m11, m12 = inv[t0, 1, 0], inv[t0, 1, 1], inv[t0, 1, 2]
                m20, m21, m22 = inv[t0, 2, 0], inv[t0, 2, 1], inv[t0, 2, 2]
                ka, kb, kc = tris[t0, 0], tris[t0, 1], tris[t0, 2]
                if ncn > 0:  # neighbouring blocks mostly see the same triangle
                    _prefetch_runs(flat, store, cn, ka, kb, kc)
                ax, ay, az = lpos32[ka, 0], lpos32[ka, 1], lpos32[ka, 2]
                bx, by, bz = lpos32[kb, 0], lpos32[kb, 1], lpos32[kb, 2]
                cx, cy, cz = lpos32[kc, 0], lpos32[kc, 1], lpos32[kc, 2]
                ia0, ia1, ia2 = _f32(inv_int[ka, 0] * l0), _f32(inv_int[ka, 1] * l1), _f32(inv_int[ka, 2] * l2)
                ib0, ib1, ib2 = _f32(inv_int[kb, 0] * l0), _f32(inv_int[kb, 1] * l1), _f32(inv_int[kb, 2] * l2)
                ic0, ic1, ic2 = _f32(inv_int[kc, 0] * l0), _f32(inv_int[kc, 1] * l1), _f32(inv_int[kc, 2] * l2)
                if f32:
                    # the cone test in float32: a row is inside t0 for sure when every cone coordinate is
                    # >= the bound of its float32 error, outside when one is below -bound, else on the
                    # border (re-tested below). Bound: |a32 - a64| <= 175 u N |s| (u = 2^-24, N the largest
                    # row sum of |inv[t0]|, |s| <= 3.42 d2 R in the scaled frame, points with |o|^2 <=
                    # _F32_WELL R^2), used with a factor ~3 margin
                    n00, n01, n02 = _f32(m00), _f32(m01), _f32(m02)
                    n10, n11, n12 = _f32(m10), _f32(m11), _f32(m12)
                    n20, n21, n22 = _f32(m20), _f32(m21), _f32(m22)
                    nrm = max(abs(m00) + abs(m01) + abs(m02), max(abs(m10) + abs(m11) + abs(m12),
                                                                  abs(m20) + abs(m21) + abs(m22)))
                    cb = _f32(_F32_BAND * 2.0 ** -24 * nrm * rsc)
                    lm32 = _f32(lmax * fscale * fscale)
                    for r in range(_CHUNK):
                        x, y, z = sx32[r], sy32[r], sz32[r]
                        a0 = n00 * x + n01 * y + n02 * z
                        a1 = n10 * x + n11 * y + n12 * z
                        a2 = n20 * x + n21 * y + n22 * z
                        mn = min(a0, min(a1, a2))
                        bb = cb * bet32[r]
                        tr = todo[r]
                        sure = mn >= bb
                        hit[r] = sure & tr
                        bd = (mn >= -bb) & (not sure) & tr
                        bord[r] = bd
                        a0 = max(a0, np.float32(0.0))
                        a1 = max(a1, np.float32(0.0))
                        a2 = max(a2, np.float32(0.0))
                        g = lm32 / ((a0 + a1 + a2) * d2s32[r])
                        px, py, pz = qx[r], qy[r], qz[r]
                        ex, ey, ez = ax - px, ay - py, az - pz
                        fa32[r] = (a0 * g) * (ex * ex + ey * ey + ez * ez)
                        ex, ey, ez = bx - px, by - py, bz - pz
                        fb32[r] = (a1 * g) * (ex * ex + ey * ey + ez * ez)
                        ex, ey, ez = cx - px, cy - py, cz - pz
                        fc32[r] = (a2 * g) * (ex * ex + ey * ey + ez * ez)
                    # the rows within the float32 test's error bound: _locate's float64 test and float64
                    # weights, exactly as the float64 pass below computes them
                    for w in range(_CHUNK // 8):  # 8 flags a word: the border rows are rare
                        if bordw[w] == 0:
                            continue
                        for r in range(8 * w, 8 * w + 8):
                            if not bord[r]:
                                continue
                            _, dn, x, y, z = _sphere_point(kd, distant_ds, lx, ly, lz, nx, ny, nz, np.float64(qx[r]),
                                                           np.float64(qy[r]), np.float64(qz[r]), r2)
                            a0 = m00 * x + m01 * y + m02 * z
                            a1 = m10 * x + m11 * y + m12 * z
                            a2 = m20 * x + m21 * y + m22 * z
                            s = a0 + a1 + a2
                            if s > 0.0 and min(a0, min(a1, a2)) >= -_CONE_EPS * s:
                                hit[r] = True
                                a0 = max(a0, 0.0)
                                a1 = max(a1, 0.0)
                                a2 = max(a2, 0.0)
                                g = lmax / ((a0 + a1 + a2) * dn)
                                px, py, pz = qx[r], qy[r], qz[r]
                                ex, ey, ez = ax - px, ay - py, az - pz
                                fa32[r] = _f32(a0 * g) * (ex * ex + ey * ey + ez * ez)
                                ex, ey, ez = bx - px, by - py, bz - pz
                                fb32[r] = _f32(a1 * g) * (ex * ex + ey * ey + ez * ez)
                                ex, ey, ez = cx - px, cy - py, cz - pz
                                fc32[r] = _f32(a2 * g) * (ex * ex + ey * ey + ez * ez)
                            bord[r] = False
                else:
                    # _locate's test against t0, weights x irradiance factor ...
                    for r in range(_CHUNK):
                        x, y, z = sx[r], sy[r], sz[r]
                        a0 = m00 * x + m01 * y + m02 * z
                        a1 = m10 * x + m11 * y + m12 * z
                        a2 = m20 * x + m21 * y + m22 * z
                        s = a0 + a1 + a2
                        hit[r] = (s > 0.0) & (min(a0, min(a1, a2)) >= -_CONE_EPS * s) & todo[r]
                        a0 = max(a0, 0.0)
                        a1 = max(a1, 0.0)
                        a2 = max(a2, 0.0)
                        g = lmax / ((a0 + a1 + a2) * den[r])  # rows outside t0: unused (masked)
                        wa[r], wb[r], wc[r] = a0 * g, a1 * g, a2 * g
                # ... times the squared distances to the three vertex lights (float32: relative
                # rounding 2^-24 per operation, the positions are scene-sized) ...
                if f32:
                    pass
                elif distant_ds:
                    for r in range(_CHUNK):
                        fa32[r], fb32[r], fc32[r] = wa[r], wb[r], wc[r]
                else:
                    for r in range(_CHUNK):
                        px, py, pz = qx[r], qy[r], qz[r]
                        ex, ey, ez = ax - px, ay - py, az - pz
                        fa32[r] = _f32(wa[r]) * (ex * ex + ey * ey + ez * ez)
                        ex, ey, ez = bx - px, by - py, bz - pz
                        fb32[r] = _f32(wb[r]) * (ex * ex + ey * ey + ez * ez)
                        ex, ey, ez = cx - px, cy - py, cz - pz
                        fc32[r] = _f32(wc[r]) * (ex * ex + ey * ey + ez * ez)
                # ... the three lights' values of the rows ...
                run_a, run_b = _run(flat, store, ci, ka), _run(flat, store, ci, kb)
                run_c = _run(flat, store, ci, kc)
                for r in range(_CHUNK):
                    i = i0 + r
                    va[0, r] = _run_value(run_a, store, i, r, ka, 0)
                    va[1, r] = _run_value(run_a, store, i, r, ka, 1)
                    va[2, r] = _run_value(run_a, store, i, r, ka, 2)
                    vb[0, r] = _run_value(run_b, store, i, r, kb, 0)
                    vb[1, r] = _run_value(run_b, store, i, r, kb, 1)
                    vb[2, r] = _run_value(run_b, store, i, r, kb, 2)
                    vc[0, r] = _run_value(run_c, store, i, r, kc, 0)
                    vc[1, r] = _run_value(run_c, store, i, r, kc, 1)
                    vc[2, r] = _run_value(run_c, store, i, r, kc, 2)
                # ... and the accumulation of the rows t0 contains (a select, not a branch; float32:
                # the values are float16 or float32, the weights' rounding is 2^-24)
                for r in range(_CHUNK):
                    ua, ub, uc = fa32[r], fb32[r], fc32[r]
                    v0 = ua * ia0 * va[0, r] + ub * ib0 * vb[0, r] + uc * ic0 * vc[0, r]
                    v1 = ua * ia1 * va[1, r] + ub * ib1 * vb[1, r] + uc * ic1 * vc[1, r]
                    v2 = ua * ia2 * va[2, r] + ub * ib2 * vb[2, r] + uc * ic2 * vc[2, r]
                    ok = hit[r]
                    c0, c1, c2 = acc0[r], acc1[r], acc2[r]
                    acc0[r] = c0 + v0 if ok else c0
                    acc1[r] = c1 + v1 if ok else c1
                    acc2[r] = c2 + v2 if ok else c2
                # the rows still to do: how many, and their range
                n_todo = 0
                for r in range(_CHUNK):
                    t = todo[r] > hit[r]  # still to do: not hit by this triangle
                    todo[r] = t
                    n_todo += t
                if n_todo < _SIMD_MIN_ROWS:
                    break
            # ---- pass B3 (scalar): the rows t0 does not contain. The current triangle's search
            # matrix, vertex lights, their positions and 1/intensity live in locals.
            last = -1
            ka = kb = kc = 0
            m00 = m01 = m02 = m10 = m11 = m12 = m20 = m21 = m22 = 0.0
            ax = ay = az = bx = by = bz = cx = cy = cz = np.float32(0.0)
            ia0 = ia1 = ia2 = ib0 = ib1 = ib2 = ic0 = ic1 = ic2 = np.float32(0.0)
            if n_todo + n_rest == 0:
                continue
            for r in range(nc):
                i = i0 + r
                px, py, pz = np.float64(qx[r]), np.float64(qy[r]), np.float64(qz[r])
                if f32:
                    if not todo[r] and d2s32[r] > nh32:  # accumulated in pass B
                        continue
                    d2, dn, x, y, z = _sphere_point(kd, distant_ds, lx, ly, lz, nx, ny, nz, px, py, pz, r2)
                else:
                    if not todo[r] and d2s[r] > near2 and den[r] > 0.0:  # accumulated in pass B
                        continue
                    d2, dn, x, y, z = d2s[r], den[r], sx[r], sy[r], sz[r]
                if d2 <= near2:  # the light is at the float32 point's rounding scale: exact point
                    px, py, pz = points64[i, 0] - gx0, points64[i, 1] - gy0, points64[i, 2] - gz0
                    d2, dn, x, y, z = _sphere_point(kd, distant_ds, lx, ly, lz, nx, ny, nz, px, py, pz, r2)
                    if d2 <= min_dist2:  # <=: a cutoff of 0 still catches d = 0
                        sing_f[r] = True
                        flags = True
                        continue
                if dn <= 0.0:  # area-light sample facing away
                    continue
                tri = -1
                if last >= 0:  # the previous such row's triangle first (_locate's test)
                    a0 = m00 * x + m01 * y + m02 * z
                    a1 = m10 * x + m11 * y + m12 * z
                    a2 = m20 * x + m21 * y + m22 * z
                    s = a0 + a1 + a2
                    if s > 0.0 and min(a0, min(a1, a2)) >= -_CONE_EPS * s:
                        tri = last
                if tri < 0:
                    tri, w0, w1, w2 = _locate(x, y, z, inv, grid_n, grid_start, grid_items)
                    if tri < 0:
                        out_f[r] = True
                        flags = True
                        continue
                if tri != last:
                    touched[tri] = 1
                    last = tri
                    m00, m01, m02 = inv[tri, 0, 0], inv[tri, 0, 1], inv[tri, 0, 2]
                    m10, m11, m12 = inv[tri, 1, 0], inv[tri, 1, 1], inv[tri, 1, 2]
                    m20, m21, m22 = inv[tri, 2, 0], inv[tri, 2, 1], inv[tri, 2, 2]
                    ka, kb, kc = tris[tri, 0], tris[tri, 1], tris[tri, 2]
                    ax, ay, az = lpos32[ka, 0], lpos32[ka, 1], lpos32[ka, 2]
                    bx, by, bz = lpos32[kb, 0], lpos32[kb, 1], lpos32[kb, 2]
                    cx, cy, cz = lpos32[kc, 0], lpos32[kc, 1], lpos32[kc, 2]
                    ia0, ia1, ia2 = _f32(inv_int[ka, 0] * l0), _f32(inv_int[ka, 1] * l1), _f32(inv_int[ka, 2] * l2)
                    ib0, ib1, ib2 = _f32(inv_int[kb, 0] * l0), _f32(inv_int[kb, 1] * l1), _f32(inv_int[kb, 2] * l2)
                    ic0, ic1, ic2 = _f32(inv_int[kc, 0] * l0), _f32(inv_int[kc, 1] * l1), _f32(inv_int[kc, 2] * l2)
                # the weights exactly as pass B2 computes them
                a0 = m00 * x + m01 * y + m02 * z
                a1 = m10 * x + m11 * y + m12 * z
                a2 = m20 * x + m21 * y + m22 * z
                a0 = max(a0, 0.0)
                a1 = max(a1, 0.0)
                a2 = max(a2, 0.0)
                g = lmax / ((a0 + a1 + a2) * dn)
                ua, ub, uc = _f32(a0 * g), _f32(a1 * g), _f32(a2 * g)  # float32 from here, as in pass B
                if not distant_ds:
                    p32x, p32y, p32z = _f32(px), _f32(py), _f32(pz)
                    ex, ey, ez = ax - p32x, ay - p32y, az - p32z
                    ua = ua * (ex * ex + ey * ey + ez * ez)
                    ex, ey, ez = bx - p32x, by - p32y, bz - p32z
                    ub = ub * (ex * ex + ey * ey + ez * ez)
                    ex, ey, ez = cx - p32x, cy - p32y, cz - p32z
                    uc = uc * (ex * ex + ey * ey + ez * ez)
                v0 = (ua * ia0 * _fetch(store, i, ka, 0)
                      + ub * ib0 * _fetch(store, i, kb, 0)
                      + uc * ic0 * _fetch(store, i, kc, 0))
                v1 = (ua * ia1 * _fetch(store, i, ka, 1)
                      + ub * ib1 * _fetch(store, i, kb, 1)
                      + uc * ic1 * _fetch(store, i, kc, 1))
                v2 = (ua * ia2 * _fetch(store, i, ka, 2)
                      + ub * ib2 * _fetch(store, i, kb, 2)
                      + uc * ic2 * _fetch(store, i, kc, 2))
                acc0[r] += v0
                acc1[r] += v1
                acc2[r] += v2
        for r0 in range(0, nc, 16):
            if runs[(i0 + r0) >> 4]:  # 16 rows = 16 consecutive pixels (a block row): 48 floats
                _store_run48(oflat, 3 * run_pix[(i0 + r0) >> 4], acc0, acc1, acc2, r0)
            else:
                for r in range(r0, min(nc, r0 + 16)):
                    q = 3 * pix[i0 + r]
                    oflat[q] = acc0[r]
                    oflat[q + 1] = acc1[r]
                    oflat[q + 2] = acc2[r]
        if flags:  # outside / singular flags (rare); the arrays arrive zeroed
            flagged[0] = 1
            for r in range(nc):
                if out_f[r]:
                    outside[pix[i0 + r]] = True
                if sing_f[r]:
                    singular[pix[i0 + r]] = True
                out_f[r] = False
                sing_f[r] = False
    # once per group, not per chunk: the non-temporal stores drain while the next chunks compute (a fence
    # per chunk waited for every chunk's 3 KiB to reach memory: 7.5 % of the serial kernel's samples)
    _fence()


class _DualKernel:
    """Parallel and serial compilations of one kernel source (as in ``engine.reference``):
    ``ser`` for callers that run several relights in Python threads (both release the GIL;
    the workqueue threading layer must not be entered from two threads at once)."""

    def __init__(self, fn):
        self.par = nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")(fn)
        ser = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__ + "_serial", fn.__defaults__,
                                 fn.__closure__)
        ser.__qualname__ = fn.__qualname__ + "_serial"
        ser.__module__ = fn.__module__
        self.ser = nb.njit(cache=True, nogil=True, error_model="numpy")(ser)

    def pick(self, serial: bool):
        return self.ser if serial else self.par


_RELIGHT = _DualKernel(_relight_kernel)


def _exact_kernel(store, pix, ks, scales, ratios, out):
    """out[pix[i]] = sum_j (stored value of light ks[j] / scales[j]) x ratios[j], in float32; a ratio
    of exactly 1 adds the value unscaled (so one light at its own intensity is the stored image)."""
    n = pix.size
    for ci in nb.prange((n + _CHUNK - 1) // _CHUNK):
        for i in range(ci * _CHUNK, min(n, (ci + 1) * _CHUNK)):
            q = pix[i]
            for c in range(3):
                acc = np.float32(0.0)
                for j in range(ks.size):
                    v = _fetch(store, i, ks[j], c)
                    if scales[j] != 1.0:
                        v = v / scales[j]
                    r = ratios[j, c]
                    acc += v if r == 1.0 else v * r
                out[q, c] = acc


_EXACT = _DualKernel(_exact_kernel)


@nb.njit(cache=True, nogil=True)
def _zero_pixels(img, pixels):
    """img[pixels] = 0 for an (h*w, 3) image."""
    for i in range(pixels.size):
        q = pixels[i]
        img[q, 0] = 0.0
        img[q, 1] = 0.0
        img[q, 2] = 0.0


def locate_directions(baked: BakedDataset, dirs) -> tuple[np.ndarray, np.ndarray]:
    """Triangle index (n,) int64 (-1 = outside coverage) and barycentric weights (n, 3)
    float64 for directions (n, 3) from the sphere centre (need not be unit)."""
    d = _as_array("dirs", dirs, np.float64, 2)
    if d.shape[1] != 3 or not np.all(np.isfinite(d)) or np.any(np.linalg.norm(d, axis=1) == 0):
        raise InvalidInputError("dirs: expected finite, non-zero (n, 3) directions")
    d = np.ascontiguousarray(d)
    tri = np.empty(d.shape[0], np.int64)
    w = np.zeros((d.shape[0], 3))
    _locate_many(d, baked.tri_inverse, baked.grid_n, baked.grid_start, baked.grid_items, tri, w)
    return tri, w


# ============================================================================ lights


def _vec3(name, v, *, positive=False, nonzero=False) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim == 0:
        a = np.full(3, float(a))
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InvalidInputError(f"{name}: expected 3 finite numbers, got {v!r}")
    if positive and np.any(a < 0):
        raise InvalidInputError(f"{name}: must be >= 0")
    if nonzero and np.linalg.norm(a) == 0:
        raise InvalidInputError(f"{name}: must be non-zero")
    return a


@dataclass(frozen=True)
class PointLight:
    """Isotropic point light: position (3,), intensity (3,) W/sr (or a scalar)."""

    position: tuple
    intensity: tuple = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class DirectionalLight:
    """Distant light: ``direction`` (3,) the way the light travels (as in the scene format),
    ``irradiance`` (3,) on a surface facing it."""

    direction: tuple
    irradiance: tuple = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class RectLight:
    """One-sided rectangle ``corner + a edge_u + b edge_v``, (a, b) in [0, 1]^2, emitting radiance
    ``radiance`` toward ``cross(edge_u, edge_v)`` (both ways if ``two_sided``); sampled with
    ``samples`` stratified, seeded points, each a point light of intensity L A / N cos(theta)."""

    corner: tuple
    edge_u: tuple
    edge_v: tuple
    radiance: tuple = (1.0, 1.0, 1.0)
    two_sided: bool = False
    samples: int = 16
    seed: int = 0


@dataclass(frozen=True)
class EnvironmentLight:
    """Equirectangular radiance map (H, W, 3) (row 0 = +y, the zenith; column u at azimuth
    phi = 2 pi (u + 0.5) / W, direction (sin th cos phi, cos th, sin th sin phi)), turned into
    ``n_lights`` directional lights: ``method="downsample"`` (blocks of equal angular size,
    energy-weighted direction; deterministic) or ``"importance"`` (pixels drawn with probability
    ~ luminance x solid angle, seeded)."""

    image: np.ndarray
    n_lights: int = 64
    method: str = "downsample"
    seed: int = 0
    scale: float = 1.0


LIGHT_TYPES = {"point": PointLight, "directional": DirectionalLight, "rect": RectLight,
               "environment": EnvironmentLight}


def light_from_dict(d: dict):
    """``{"type": "point", "position": [...], ...}`` -> light spec (unknown fields are errors)."""
    d = dict(d)
    kind = d.pop("type", None)
    cls = LIGHT_TYPES.get(kind)
    if cls is None:
        raise InvalidInputError(f"light type must be one of {sorted(LIGHT_TYPES)}, got {kind!r}")
    try:
        return cls(**d)
    except TypeError as e:
        raise InvalidInputError(f"{kind} light: {e}") from None


def _env_to_directional(env: EnvironmentLight):
    img = np.asarray(env.image, dtype=np.float64)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise InvalidInputError(f"environment image: expected (H, W, 3), got {img.shape}")
    if not np.all(np.isfinite(img)) or np.any(img < 0):
        raise InvalidInputError("environment image: values must be finite and >= 0")
    n = int(env.n_lights)
    if n < 1:
        raise InvalidInputError("environment n_lights must be >= 1")
    hh, ww = img.shape[:2]
    th = np.pi * (np.arange(hh) + 0.5) / hh
    ph = 2 * np.pi * (np.arange(ww) + 0.5) / ww
    st = np.sin(th)
    dirs = np.stack([st[:, None] * np.cos(ph)[None, :], np.repeat(np.cos(th)[:, None], ww, 1),
                     st[:, None] * np.sin(ph)[None, :]], axis=-1)  # (H, W, 3)
    domega = (np.pi / hh) * (2 * np.pi / ww) * st  # (H,)
    e_pix = img * domega[:, None, None] * env.scale  # irradiance contribution of each pixel
    if env.method == "downsample":
        n_lat = max(1, int(round(math.sqrt(n / 2.0))))
        n_lon = max(1, n // n_lat)
        rows = np.array_split(np.arange(hh), n_lat)
        cols = np.array_split(np.arange(ww), n_lon)
        out_d, out_e = [], []
        for r in rows:
            for c in cols:
                if r.size == 0 or c.size == 0:
                    continue
                e = e_pix[np.ix_(r, c)].reshape(-1, 3)
                dd = dirs[np.ix_(r, c)].reshape(-1, 3)
                wgt = e.sum(axis=1)
                tot = e.sum(axis=0)
                if wgt.sum() <= 0:
                    continue
                v = (dd * wgt[:, None]).sum(axis=0)
                nv = np.linalg.norm(v)
                v = v / nv if nv > 0 else dd[len(dd) // 2]
                out_d.append(v)
                out_e.append(tot)
        return np.array(out_d).reshape(-1, 3), np.array(out_e).reshape(-1, 3)
    if env.method == "importance":
        lum = (0.2126 * e_pix[..., 0] + 0.7152 * e_pix[..., 1] + 0.0722 * e_pix[..., 2]).ravel()
        if lum.sum() <= 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        p = lum / lum.sum()
        rng = np.random.default_rng(env.seed)
        idx = rng.choice(p.size, size=n, p=p)
        e = e_pix.reshape(-1, 3)[idx] / (p[idx, None] * n)
        return dirs.reshape(-1, 3)[idx], e
    raise InvalidInputError(f"environment method must be 'downsample' or 'importance', got {env.method!r}")


def _rect_samples(r: RectLight):
    c = _vec3("rect corner", r.corner)
    eu, ev = _vec3("rect edge_u", r.edge_u, nonzero=True), _vec3("rect edge_v", r.edge_v, nonzero=True)
    rad = _vec3("rect radiance", r.radiance, positive=True)
    ns = int(r.samples)
    if ns < 1:
        raise InvalidInputError("rect samples must be >= 1")
    nrm = np.cross(eu, ev)
    area = float(np.linalg.norm(nrm))
    if area == 0:
        raise InvalidInputError("rect: edge_u and edge_v are parallel")
    nrm /= area
    gx = int(math.ceil(math.sqrt(ns)))
    gy = int(math.ceil(ns / gx))
    j = np.arange(ns)
    jit = np.random.default_rng(r.seed).random((ns, 2))
    a = ((j % gx) + jit[:, 0]) / gx
    b = ((j // gx) + jit[:, 1]) / gy
    pos = c + a[:, None] * eu + b[:, None] * ev
    inten = np.broadcast_to(rad * area / ns, (ns, 3))  # I(theta) = L A/N cos(theta)
    return pos, inten, np.broadcast_to(nrm, (ns, 3))


def _expand_lights(lights) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    kinds, lp, li, ln = [], [], [], []
    if isinstance(lights, (PointLight, DirectionalLight, RectLight, EnvironmentLight, dict)):
        lights = [lights]
    for idx, spec in enumerate(lights):
        if isinstance(spec, dict):
            spec = light_from_dict(spec)
        if isinstance(spec, PointLight):
            pos = _vec3(f"lights[{idx}].position", spec.position)
            if np.max(np.abs(pos)) > 1e100:  # |l - P|^2 would overflow; the limit is a directional light
                raise InvalidInputError(f"lights[{idx}].position: farther than 1e100; use a directional light")
            kinds.append([_K_POINT])
            lp.append(pos[None])
            li.append(_vec3(f"lights[{idx}].intensity", spec.intensity, positive=True)[None])
            ln.append(np.zeros((1, 3)))
        elif isinstance(spec, DirectionalLight):
            d = _vec3(f"lights[{idx}].direction", spec.direction, nonzero=True)
            kinds.append([_K_DIRECTIONAL])
            lp.append((-d / np.linalg.norm(d))[None])  # the kernel wants the direction toward the light
            li.append(_vec3(f"lights[{idx}].irradiance", spec.irradiance, positive=True)[None])
            ln.append(np.zeros((1, 3)))
        elif isinstance(spec, RectLight):
            p, i, n = _rect_samples(spec)
            kinds.append([_K_TWO_SIDED if spec.two_sided else _K_ORIENTED] * p.shape[0])
            lp.append(p)
            li.append(i)
            ln.append(n)
        elif isinstance(spec, EnvironmentLight):
            d, e = _env_to_directional(spec)
            kinds.append([_K_DIRECTIONAL] * d.shape[0])
            lp.append(d)
            li.append(e)
            ln.append(np.zeros_like(d))
        else:
            raise InvalidInputError(f"lights[{idx}]: unsupported light spec {type(spec).__name__}")
    if not kinds:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))
    return (np.concatenate([np.asarray(k, np.int64) for k in kinds]), np.ascontiguousarray(np.concatenate(lp)),
            np.ascontiguousarray(np.concatenate(li)), np.ascontiguousarray(np.concatenate(ln)))


# ============================================================================ relight


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
    want = _K_DIRECTIONAL if baked.distant else _K_POINT
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
    threads: numba threads for the parallel kernel (None = numba's current setting);
        serial=True runs the serial nogil kernel (for callers with their own threads).
    min_light_distance: a point light nearer than this to a surface point contributes 0 there
        and the pixel is marked singular; default 1e-6 x the sphere radius (x the scene extent
        for distant datasets).
    """
    if not isinstance(baked, BakedDataset):
        raise InvalidInputError("relight: expected a BakedDataset (see bake_dataset)")
    t0 = time.perf_counter()
    kinds, lp, li, ln = _expand_lights(lights)
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
    _zero_pixels(img, geom.unused_pixels)  # numpy's fancy assignment took 0.7 ms at 1 MP
    outside = np.zeros(h * w, bool)
    singular = np.zeros(h * w, bool)
    exact = _exact_indices(baked, kinds, lp) if exact_fast_path else None
    if exact is not None:
        # light(s) exactly at dataset lights: the stored images, scaled, no interpolation; float32
        # arithmetic in the order of ``sum_j light_values(k_j) * ratio_j`` (bit-identical to it)
        ratios = np.ascontiguousarray((li / baked.intensities[exact]).astype(np.float32))
        _EXACT.pick(serial)(baked.kernel_store(), geom.pixel_index, exact,
                            baked.store_scale[exact].astype(np.float32), ratios, img)
        timings["kernel_s"] = time.perf_counter() - t1
        used = np.unique(exact)
        n_tri_used = 0
        count = False  # the exact path sets no flags
    else:
        touched = np.zeros(baked.triangles.shape[0], np.uint8)
        flagged = np.zeros(1, np.uint8)
        inv_int = np.ascontiguousarray(1.0 / (baked.intensities * baked.store_scale[:, None]))
        radius = baked.sphere_radius if math.isfinite(baked.sphere_radius) else 1.0
        kern = _RELIGHT.pick(serial)
        prev = nb.get_num_threads()
        if threads is not None and not serial:
            if not (1 <= int(threads) <= nb.config.NUMBA_NUM_THREADS):
                raise InvalidInputError(f"threads must be in [1, {nb.config.NUMBA_NUM_THREADS}]")
            nb.set_num_threads(int(threads))
        # the kernel frame: positions relative to geom.origin; directions toward directional lights unit
        lp_k = lp.copy()
        pos = kinds != _K_DIRECTIONAL
        lp_k[pos] -= geom.origin
        if np.any(~pos):
            lp_k[~pos] /= np.linalg.norm(lp_k[~pos], axis=1, keepdims=True)
        lpos_k = baked.light_positions - (0.0 if baked.distant else geom.origin)
        lpos_k = np.ascontiguousarray(lpos_k.astype(np.float32))
        near2 = (float(min_light_distance) + 4.0 * geom.rounding) ** 2
        # the power of two that brings the radius into [1, 2) for the float32 geometry (exact scaling)
        fscale = math.ldexp(1.0, -math.frexp(radius)[1] + 1)
        workers = 1 if serial else max(1, nb.get_num_threads())  # after set_num_threads
        try:
            kern(workers, geom.points, baked.points, geom.origin, baked.kernel_store(), lpos_k, inv_int,
                 baked.distant, radius, fscale, baked.triangles, baked.tri_inverse, baked.grid_n, baked.grid_start,
                 baked.grid_items, kinds, lp_k, li, ln, float(min_light_distance) ** 2, near2, geom.pixel_index,
                 geom.runs, geom.run_pixels, img, outside, singular, touched, flagged)
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
