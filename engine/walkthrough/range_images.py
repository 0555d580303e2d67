"""360-degree range images (cube maps) at a base viewpoint and time.

A cube range image holds, for the 6 faces of a cube around ``eye`` (each a 90-degree
perspective view of ``res x res`` pixels, face order +x, -x, +y, -y, +z, -z, the up vectors of
the usual cube-map layout), the radiance split into **direct** and **indirect** parts, the
distance along each pixel-centre ray to the first hit (``depth``, 0 where the ray leaves the
scene) and the object id seen there (-1 for none).

Both radiance parts are the reference renderer's (``engine/reference.py``), which the
walkthrough reconstruction is measured against:

- direct = a render with ``indirect_samples = 0`` (emission, ambient, direct light with
  shadows, mirror / glossy chains);
- indirect, as the walkthrough bake computes it (``trace_cube_indirect``): the reference
  renderer's indirect paths from the first hit of every pixel-centre ray, traced per pixel until
  the estimated standard error reaches a requested noise level
  (``engine.newviews.indirect.trace_indirect_points``);
- or, with ``render_cube(..., indirect=True)``, a fixed-sample split: (a render with path-traced
  indirect light) - direct, for the same seed. The camera jitter and the first-hit light samples
  of both renders come from the same counter-based random streams, so on diffuse surfaces the
  difference is exactly the path-traced part; behind mirror / glossy chains it also carries the
  (zero-mean) difference between two samplings of the direct light there.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import InvalidInputError
from engine.metrics import REC709_WEIGHTS
from engine.newviews.indirect import IndirectParams, trace_indirect_points
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.scene import CameraParams

__all__ = ["CUBE_FACES", "CubeIndirect", "CubeRangeImage", "cube_directions", "cube_surface_points",
           "direction_to_cube", "face_camera", "render_cube", "seen_fraction", "surface_points",
           "trace_cube_indirect"]

# (forward, up) per face; right = forward x up
CUBE_FACES: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = (
    ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    ((-1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    ((0.0, 1.0, 0.0), (0.0, 0.0, -1.0)),
    ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
    ((0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
)


def face_basis() -> np.ndarray:
    """(6, 3, 3) float64: rows right, up, forward of every face."""
    out = np.empty((6, 3, 3))
    for k, (f, u) in enumerate(CUBE_FACES):
        fw = np.asarray(f, dtype=np.float64)
        up = np.asarray(u, dtype=np.float64)
        out[k, 0] = np.cross(fw, up)
        out[k, 1] = up
        out[k, 2] = fw
    return out


_BASIS = face_basis()


def face_camera(eye: np.ndarray | tuple[float, float, float], face: int, res: int) -> CameraParams:
    """The 90-degree perspective camera of cube face ``face`` at ``eye``."""
    e = tuple(float(c) for c in np.asarray(eye, dtype=np.float64))
    f, u = CUBE_FACES[face]
    return CameraParams("perspective", e, (e[0] + f[0], e[1] + f[1], e[2] + f[2]), u, res, res, fov_y_deg=90.0)


def cube_directions(res: int) -> np.ndarray:
    """(6, res, res, 3) float64 unit directions through every pixel centre (camera.py conventions)."""
    c = (np.arange(res) + 0.5) * (2.0 / res) - 1.0
    sx = c[None, :]
    sy = -c[:, None]
    d = (_BASIS[:, None, None, 2, :] + sx[None, :, :, None] * _BASIS[:, None, None, 0, :]
         + sy[None, :, :, None] * _BASIS[:, None, None, 1, :])
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def direction_to_cube(dx, dy, dz, res):
    """(face, column, row) of the cube pixel a direction falls in."""
    ax, ay, az = abs(dx), abs(dy), abs(dz)
    if ax >= ay and ax >= az:
        face = 0 if dx > 0 else 1
        m = ax
    elif ay >= az:
        face = 2 if dy > 0 else 3
        m = ay
    else:
        face = 4 if dz > 0 else 5
        m = az
    b = _BASIS
    s = (dx * b[face, 0, 0] + dy * b[face, 0, 1] + dz * b[face, 0, 2]) / m
    t = (dx * b[face, 1, 0] + dy * b[face, 1, 1] + dz * b[face, 1, 2]) / m
    col = int((s + 1.0) * 0.5 * res)
    row = int((1.0 - t) * 0.5 * res)
    col = min(max(col, 0), res - 1)
    row = min(max(row, 0), res - 1)
    return face, col, row


@nb.njit(cache=True, nogil=True, error_model="numpy")
def seen_fraction(eye_a, depth_a, oid_a, eye_b, depth_b, oid_b, res, basis, tol):
    """Fraction of a's hit pixels whose surface point b sees (same object, distance within tol).
    Lives here, next to ``direction_to_cube``: numba's cache does not notice edits to a callee in
    another file."""
    total = 0
    seen = 0
    for f in range(6):
        for r in range(res):
            for c in range(res):
                d = depth_a[f, r, c]
                if d <= 0.0:
                    continue
                total += 1
                sx = (c + 0.5) * 2.0 / res - 1.0
                sy = 1.0 - (r + 0.5) * 2.0 / res
                dx = basis[f, 2, 0] + sx * basis[f, 0, 0] + sy * basis[f, 1, 0]
                dy = basis[f, 2, 1] + sx * basis[f, 0, 1] + sy * basis[f, 1, 1]
                dz = basis[f, 2, 2] + sx * basis[f, 0, 2] + sy * basis[f, 1, 2]
                ln = math.sqrt(dx * dx + dy * dy + dz * dz)
                qx = eye_a[0] + dx / ln * d - eye_b[0]
                qy = eye_a[1] + dy / ln * d - eye_b[1]
                qz = eye_a[2] + dz / ln * d - eye_b[2]
                dist = math.sqrt(qx * qx + qy * qy + qz * qz)
                if dist == 0.0:
                    seen += 1
                    continue
                fb, cb, rb = direction_to_cube(qx, qy, qz, res)
                if oid_b[fb, rb, cb] == oid_a[f, r, c] and abs(depth_b[fb, rb, cb] - dist) <= tol * dist:
                    seen += 1
    if total == 0:
        return 1.0
    return seen / total


@dataclass
class CubeRangeImage:
    """One base image: eye (3,) float64, time, res; direct / indirect (6, res, res, 3) float32
    (indirect is all zero when it was not computed); depth (6, res, res) float32 (0: no hit);
    object_id (6, res, res) int32 (-1: no hit); timings in seconds."""

    eye: np.ndarray
    time: float
    res: int
    direct: np.ndarray
    indirect: np.ndarray
    depth: np.ndarray
    object_id: np.ndarray
    has_indirect: bool = False
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def radiance(self) -> np.ndarray:
        return self.direct + self.indirect


def render_cube(renderer: ReferenceRenderer, eye: np.ndarray | tuple[float, float, float], res: int,
                params: ReferenceParams, *, time_value: float = 0.0, indirect: bool = False,
                direct: bool = True) -> CubeRangeImage:
    """Render the 6 faces at ``eye``. ``params.indirect_samples`` sets the path-traced part
    when ``indirect`` (it must then be > 0); the direct part uses the same params with
    ``indirect_samples = 0``. With ``direct=False`` only depth and object ids are filled
    (one ray per pixel, no shading): the cheap view used by the decompositions."""
    if not isinstance(res, int) or not 1 <= res <= 8192:
        raise InvalidInputError(f"res must be an integer in [1, 8192], got {res!r}")
    e = np.asarray(eye, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(e)):
        raise InvalidInputError("eye must be finite")
    if indirect and params.indirect_samples <= 0:
        raise InvalidInputError("indirect=True needs params.indirect_samples > 0")
    t0 = time.perf_counter()
    d_par = replace(params, indirect_samples=0)
    direct_img = np.zeros((6, res, res, 3), np.float32)
    ind_img = np.zeros((6, res, res, 3), np.float32)
    depth = np.zeros((6, res, res), np.float32)
    oid = np.full((6, res, res), -1, np.int32)
    timings = {"direct": 0.0, "indirect": 0.0, "geometry": 0.0}
    if not direct:
        dirs = cube_directions(res).reshape(-1, 3)
        hits = renderer.caster.intersect(np.broadcast_to(e, dirs.shape).copy(), dirs)
        hit = hits.prim >= 0
        sc = renderer.scene
        prim = np.where(hit, hits.prim, 0)
        depth = np.where(hit, hits.t, 0.0).astype(np.float32).reshape(6, res, res)
        if sc.n_triangles:
            oid = np.where(hit, sc.tri_object[prim], -1).astype(np.int32).reshape(6, res, res)
        timings["geometry"] = time.perf_counter() - t0
        return CubeRangeImage(e, float(time_value), res, direct_img, ind_img, depth, oid, False, timings)
    for k in range(6):
        cam = face_camera(e, k, res)
        t1 = time.perf_counter()
        out = renderer.render(cam, d_par)
        timings["direct"] += time.perf_counter() - t1
        direct_img[k] = out.radiance
        depth[k] = out.depth
        oid[k] = out.object_id
        if indirect:
            t1 = time.perf_counter()
            full = renderer.render(cam, params)
            timings["indirect"] += time.perf_counter() - t1
            ind_img[k] = full.radiance - out.radiance
    timings["total"] = time.perf_counter() - t0
    return CubeRangeImage(e, float(time_value), res, direct_img, ind_img, depth, oid, indirect, timings)


@dataclass
class CubeIndirect:
    """Converged indirect light of one base cube (``trace_cube_indirect``): radiance (6, res, res, 3)
    float32 (0 where the pixel's ray leaves the scene); stderr (6, res, res) float32, the estimated
    standard error of each pixel's luminance; paths (6, res, res) int32 paths traced per pixel;
    stats: ``engine.newviews.indirect.summarize`` of the achieved noise plus timings."""

    radiance: np.ndarray
    stderr: np.ndarray
    paths: np.ndarray
    stats: dict


def surface_points(renderer: ReferenceRenderer, origins: np.ndarray,
                   directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """First hits of rays (n, 3): (index of every ray that hits, hit point, geometric normal,
    shading normal, material id), the normals on the side the ray arrives on (a shading normal
    on the wrong side of the geometric one falls back to it), as the reference renderer shades a
    camera hit."""
    sc = renderer.scene
    dirs = np.ascontiguousarray(directions, np.float64).reshape(-1, 3)
    hits = renderer.caster.intersect(np.ascontiguousarray(origins, np.float64).reshape(-1, 3), dirs)
    idx = np.flatnonzero(hits.prim >= 0)
    t = hits.prim[idx]
    u = hits.u[idx].astype(np.float32).astype(np.float64)[:, None]
    v = hits.v[idx].astype(np.float32).astype(np.float64)[:, None]
    w0 = 1.0 - u - v
    p = w0 * sc.tri_p[t, 0] + u * sc.tri_p[t, 1] + v * sc.tri_p[t, 2]
    g = sc.tri_ng[t].astype(np.float64)
    s = w0 * sc.tri_n[t, 0] + u * sc.tri_n[t, 1] + v * sc.tri_n[t, 2]
    ls = np.linalg.norm(s, axis=1, keepdims=True)
    s = np.where(ls > 1e-12, s / np.maximum(ls, 1e-300), g)
    back = np.einsum("ij,ij->i", g, dirs[idx]) > 0.0
    g[back] *= -1.0
    s[back] *= -1.0
    wrong = np.einsum("ij,ij->i", s, g) <= 0.0
    s[wrong] = g[wrong]
    return idx, p, g, s, sc.tri_material[t].astype(np.int32)


def cube_surface_points(renderer: ReferenceRenderer, eye: np.ndarray,
                        res: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``surface_points`` of the pixel-centre rays of a cube at ``eye``; the index is into the
    flattened (6, res, res) cube."""
    dirs = cube_directions(res).reshape(-1, 3)
    e = np.asarray(eye, dtype=np.float64).reshape(3)
    return surface_points(renderer, np.broadcast_to(e, dirs.shape), dirs)


def trace_cube_indirect(renderer: ReferenceRenderer, eye: np.ndarray | tuple[float, float, float], res: int,
                        direct: np.ndarray, params: IndirectParams, *, key: np.uint64,
                        progress: Callable[[float], None] | None = None) -> CubeIndirect:
    """Indirect diffuse light of every pixel of a cube at ``eye`` (``res`` pixels per face edge),
    path traced per pixel until its estimated relative standard error reaches ``params.noise``.

    One surface point per pixel: the first hit of the pixel-centre ray, on the side the ray
    arrives on (``cube_surface_points``). Its paths are the reference renderer's indirect paths
    (``ReferenceRenderer.trace_diffuse_paths``, via ``engine.newviews.indirect.trace_indirect_points``):
    adaptive, the error measured against the pixel's total brightness, ``direct`` (6, res, res, 3)
    plus the indirect estimate, never less than ``params.floor`` times the cube's mean direct
    luminance over the surfaces that receive indirect light. Hit j (in pixel order) draws its
    paths as pixel j of the sampler stream ``key``: equal keys give identical cubes."""
    t0 = time.perf_counter()
    if direct.shape != (6, res, res, 3):
        raise InvalidInputError(f"direct must have shape (6, {res}, {res}, 3), got {direct.shape}")
    pix, p, g, s, mat = cube_surface_points(renderer, np.asarray(eye, np.float64), res)
    base = direct.reshape(-1, 3)[pix].astype(np.float64)
    receives = np.any(renderer.scene.materials.kd[mat] > 0.0, axis=1) if pix.size else np.zeros(0, np.bool_)
    brightness = float((base[receives] @ np.asarray(REC709_WEIGHTS, np.float64)).mean()) if receives.any() else 0.0
    res_pts = trace_indirect_points(renderer, p, g, s, mat, base, params, key=key, pixel_base=0,
                                    brightness=brightness, progress=progress)
    n = 6 * res * res
    rad = np.zeros((n, 3), np.float32)
    se = np.zeros(n, np.float32)
    paths = np.zeros(n, np.int32)
    rad[pix], se[pix], paths[pix] = res_pts.radiance, res_pts.stderr, res_pts.paths
    stats = dict(res_pts.stats)
    stats["time"] = time.perf_counter() - t0
    return CubeIndirect(rad.reshape(6, res, res, 3), se.reshape(6, res, res), paths.reshape(6, res, res), stats)
