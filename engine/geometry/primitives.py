"""Tessellated primitives with smooth vertex normals, in object-local space.

Every function returns a :class:`~engine.geometry.mesh.TriMesh` whose triangles wind
counter-clockwise seen from outside (right-hand-rule normal points outward) and whose
vertex normals are analytic where the surface is smooth:

=========  ==========================================  ====================  ==========
function   vertices                                     faces                 closed
=========  ==========================================  ====================  ==========
sphere     ``10 * 4**L + 2``                            ``20 * 4**L``         yes
box        24 (4 per face, flat normals)                12                    yes [#]_
cylinder   ``2 s`` (+ ``2 (s + 1)`` with caps)          ``2 s`` (+ ``2 s``)   when capped [#]_
plane      ``(s + 1)**2``                               ``2 s**2``            no
disk       ``s + 1``                                    ``s``                 no
=========  ==========================================  ====================  ==========

.. [#] Closed once coincident positions are merged: faces keep separate vertices so
   the shading normals stay flat.
.. [#] The side shares no vertices with the caps (flat cap normals), but the cap rings
   are bit-identical to the side rings, so the surface is watertight by position.

Sizes must stay resolvable in float32 relative to the centre (Embree intersects in
float32): a radius below ``1e-5 * max|center|`` is rejected; model small objects near
the origin and place them with a transform instead.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from numbers import Integral, Real

import numpy as np

from engine.errors import InvalidInputError
from engine.geometry.mesh import TriMesh

__all__ = ["sphere", "box", "cylinder", "plane", "disk", "MAX_SPHERE_SUBDIVISIONS", "MAX_SEGMENTS"]

MAX_SPHERE_SUBDIVISIONS = 8  # 655362 vertices, 1310720 faces
MAX_SEGMENTS = 65536
MAX_PLANE_SEGMENTS = 2048  # 8.4M triangles
_MAX_COORD = 1e18  # Embree silently ignores primitives beyond this
_MIN_RELATIVE_SIZE = 1e-5  # a few float32 ulps per edge at the finest default tessellation


# --------------------------------------------------------------------------- validation


def _as_point(value: object, name: str) -> np.ndarray:
    try:
        p = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name} must be 3 finite numbers, got {value!r}") from exc
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise InvalidInputError(f"{name} must be 3 finite numbers, got {value!r}")
    if np.any(np.abs(p) > _MAX_COORD):
        raise InvalidInputError(f"{name} coordinates must be within +-{_MAX_COORD:g}, got {value!r}")
    return p


def _as_positive(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, Real | np.floating | np.integer):
        raise InvalidInputError(f"{name} must be a finite number > 0, got {value!r}")
    x = float(value)
    if not math.isfinite(x) or x <= 0.0:
        raise InvalidInputError(f"{name} must be a finite number > 0, got {value!r}")
    return x


def _as_sizes(value: object, name: str, n: int) -> np.ndarray:
    """A positive scalar (used for every axis) or ``n`` positive numbers."""
    if isinstance(value, Real | np.floating | np.integer) and not isinstance(value, bool):
        return np.full(n, _as_positive(value, name))
    if not isinstance(value, Sequence | np.ndarray):
        raise InvalidInputError(f"{name} must be a number or {n} numbers > 0, got {value!r}")
    try:
        s = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name} must be {n} finite numbers > 0, got {value!r}") from exc
    if s.shape != (n,) or not np.all(np.isfinite(s)) or np.any(s <= 0.0):
        raise InvalidInputError(f"{name} must be {n} finite numbers > 0, got {value!r}")
    return s


def _as_count(value: object, name: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, Integral):
        raise InvalidInputError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    k = int(value)
    if not lo <= k <= hi:
        raise InvalidInputError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return k


def _check_extent(center: np.ndarray, half_extent: float, name: str) -> None:
    """Reject sizes that overflow Embree's range or vanish next to the centre in float32."""
    if np.max(np.abs(center)) + half_extent > _MAX_COORD:
        raise InvalidInputError(f"{name} too large: the shape would extend beyond +-{_MAX_COORD:g}")
    if half_extent < _MIN_RELATIVE_SIZE * float(np.max(np.abs(center))):
        raise InvalidInputError(
            f"{name} {half_extent:g} is too small for center {center.tolist()} to be resolved in "
            f"float32; build the shape at the origin and move it with a transform"
        )


def _mesh(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> TriMesh:
    return TriMesh(
        np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(faces, dtype=np.int32),
        np.ascontiguousarray(normals, dtype=np.float64),
    )


# --------------------------------------------------------------------------- sphere


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    """Unit icosahedron, 12 vertices and 20 outward CCW faces."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array(
        [
            [-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0],
            [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
            [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1],
        ],
        dtype=np.float64,
    )  # fmt: skip
    f = np.array(
        [
            [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
            [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
            [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
            [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
        ],
        dtype=np.int64,
    )  # fmt: skip
    return v / np.linalg.norm(v, axis=1, keepdims=True), f


def _subdivide(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split every triangle in 4; one new vertex per undirected edge, projected onto the sphere."""
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    edges = np.stack([np.stack([a, b], 1), np.stack([b, c], 1), np.stack([c, a], 1)], 0)  # (3, m, 2)
    keys = np.sort(edges.reshape(-1, 2), axis=1)
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    mid = v[unique[:, 0]] + v[unique[:, 1]]
    mid /= np.linalg.norm(mid, axis=1, keepdims=True)
    m = f.shape[0]
    ab, bc, ca = (v.shape[0] + inverse.reshape(3, m)).astype(np.int64)
    faces = np.concatenate(
        [
            np.stack([a, ab, ca], 1),
            np.stack([b, bc, ab], 1),
            np.stack([c, ca, bc], 1),
            np.stack([ab, bc, ca], 1),
        ]
    )
    return np.concatenate([v, mid]), faces


def sphere(center: Sequence[float] = (0.0, 0.0, 0.0), radius: float = 1.0, subdivisions: int = 5) -> TriMesh:
    """Icosphere: a subdivided icosahedron with vertices on the sphere.

    Level ``L`` has ``10 * 4**L + 2`` vertices and ``20 * 4**L`` faces; L5 (10242 vertices)
    shades round and its volume is within 0.2 % of ``4/3 pi r**3``. Normals are the
    exact radial directions ``(v - center) / radius``.
    """
    c = _as_point(center, "center")
    r = _as_positive(radius, "radius")
    level = _as_count(subdivisions, "subdivisions", 0, MAX_SPHERE_SUBDIVISIONS)
    _check_extent(c, r, "radius")
    unit, faces = _icosahedron()
    for _ in range(level):
        unit, faces = _subdivide(unit, faces)
    return _mesh(c + r * unit, faces, unit)


# --------------------------------------------------------------------------- box


def box(center: Sequence[float] = (0.0, 0.0, 0.0), size: float | Sequence[float] = 1.0) -> TriMesh:
    """Axis-aligned box of edge lengths ``size = (sx, sy, sz)`` (or one number for a cube).

    6 faces x 4 vertices with flat normals, 12 triangles.
    """
    c = _as_point(center, "center")
    s = _as_sizes(size, "size", 3)
    _check_extent(c, float(np.min(s)) / 2.0, "size")
    _check_extent(c, float(np.max(s)) / 2.0, "size")
    h = s / 2.0
    verts, norms, faces = [], [], []
    for axis in range(3):
        u, w = (axis + 1) % 3, (axis + 2) % 3  # (u, w, axis) is a right-handed frame
        for sign in (1.0, -1.0):
            n = np.zeros(3)
            n[axis] = sign
            # corners in the (u, w) plane, counter-clockwise seen from +axis
            uv = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
            if sign < 0:
                uv = uv[::-1]
            quad = np.zeros((4, 3))
            quad[:, axis] = sign * h[axis]
            quad[:, u] = uv[:, 0] * h[u]
            quad[:, w] = uv[:, 1] * h[w]
            base = 4 * len(verts)
            verts.append(c + quad)
            norms.append(np.repeat(n[None], 4, axis=0))
            faces.append(base + np.array([[0, 1, 2], [0, 2, 3]]))
    return _mesh(np.concatenate(verts), np.concatenate(faces), np.concatenate(norms))


# --------------------------------------------------------------------------- cylinder, disk


def _ring(c: np.ndarray, r: float, y: float, segments: int) -> np.ndarray:
    """``segments`` points on a circle in the plane ``y``; angle increases from +x towards +z."""
    theta = 2.0 * np.pi * np.arange(segments) / segments
    ring = np.empty((segments, 3))
    ring[:, 0] = c[0] + r * np.cos(theta)
    ring[:, 1] = y
    ring[:, 2] = c[2] + r * np.sin(theta)
    return ring


def _fan(center_vertex: np.ndarray, ring: np.ndarray, up: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle fan around ``center_vertex`` (index 0) with flat +-y normals."""
    s = ring.shape[0]
    k = np.arange(s)
    nxt = (k + 1) % s
    # the ring turns from +x to +z, i.e. clockwise seen from +y: reverse it for an upward face
    faces = (
        np.stack([np.zeros(s, dtype=np.int64), 1 + nxt, 1 + k], 1)
        if up
        else np.stack([np.zeros(s, dtype=np.int64), 1 + k, 1 + nxt], 1)
    )
    verts = np.concatenate([center_vertex[None], ring])
    normals = np.zeros_like(verts)
    normals[:, 1] = 1.0 if up else -1.0
    return verts, faces, normals


def cylinder(
    center: Sequence[float] = (0.0, 0.0, 0.0),
    radius: float = 1.0,
    height: float = 2.0,
    segments: int = 64,
    capped: bool = True,
) -> TriMesh:
    """Cylinder along y from ``center.y - height/2`` to ``center.y + height/2``.

    The side has ``2 * segments`` vertices (no duplicated seam) with radial normals; each cap
    is a fan with its own ``segments + 1`` vertices (centre first) and a flat +-y normal.
    """
    c = _as_point(center, "center")
    r = _as_positive(radius, "radius")
    h = _as_positive(height, "height")
    s = _as_count(segments, "segments", 3, MAX_SEGMENTS)
    if not isinstance(capped, bool | np.bool_):
        raise InvalidInputError(f"capped must be a bool, got {capped!r}")
    _check_extent(c, r, "radius")
    _check_extent(c, h / 2.0, "height")
    y0, y1 = c[1] - h / 2.0, c[1] + h / 2.0
    bottom, top = _ring(c, r, y0, s), _ring(c, r, y1, s)
    radial = (bottom - np.array([c[0], y0, c[2]])) / r
    radial[:, 1] = 0.0
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    k = np.arange(s)
    nxt = (k + 1) % s
    b0, b1, t0, t1 = k, nxt, s + k, s + nxt
    side_faces = np.concatenate([np.stack([b0, t0, b1], 1), np.stack([b1, t0, t1], 1)])
    verts, faces, normals = [np.concatenate([bottom, top])], [side_faces], [np.concatenate([radial, radial])]
    if capped:
        offset = 2 * s
        for y, ring, up in ((y1, top, True), (y0, bottom, False)):
            cv, cf, cn = _fan(np.array([c[0], y, c[2]]), ring, up)
            verts.append(cv)
            faces.append(cf + offset)
            normals.append(cn)
            offset += cv.shape[0]
    return _mesh(np.concatenate(verts), np.concatenate(faces), np.concatenate(normals))


def disk(center: Sequence[float] = (0.0, 0.0, 0.0), radius: float = 1.0, segments: int = 64) -> TriMesh:
    """Disk in the xz plane through ``center``, normal +y: a fan of ``segments`` triangles."""
    c = _as_point(center, "center")
    r = _as_positive(radius, "radius")
    s = _as_count(segments, "segments", 3, MAX_SEGMENTS)
    _check_extent(c, r, "radius")
    v, f, n = _fan(c, _ring(c, r, c[1], s), up=True)
    return _mesh(v, f, n)


# --------------------------------------------------------------------------- plane


def plane(
    center: Sequence[float] = (0.0, 0.0, 0.0),
    size: float | Sequence[float] = (1.0, 1.0),
    segments: int = 1,
) -> TriMesh:
    """Rectangle in the xz plane through ``center``, normal +y, ``size = (sx, sz)``.

    A grid of ``segments x segments`` quads (two triangles each), ``(segments + 1)**2`` vertices.
    """
    c = _as_point(center, "center")
    sx, sz = _as_sizes(size, "size", 2)
    n = _as_count(segments, "segments", 1, MAX_PLANE_SEGMENTS)
    _check_extent(c, min(sx, sz) / 2.0, "size")
    _check_extent(c, max(sx, sz) / 2.0, "size")
    xs = c[0] + sx * (np.arange(n + 1) / n - 0.5)
    zs = c[2] + sz * (np.arange(n + 1) / n - 0.5)
    gx, gz = np.meshgrid(xs, zs, indexing="ij")  # vertex (i, j) -> index i * (n + 1) + j
    verts = np.stack([gx.ravel(), np.full(gx.size, c[1]), gz.ravel()], 1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    p00 = (i * (n + 1) + j).ravel()
    p01, p10, p11 = p00 + 1, p00 + (n + 1), p00 + (n + 2)
    # z cross x = +y: go to the +z neighbour first, then the +x one
    faces = np.concatenate([np.stack([p00, p01, p10], 1), np.stack([p10, p01, p11], 1)])
    normals = np.zeros_like(verts)
    normals[:, 1] = 1.0
    return _mesh(verts, faces, normals)
