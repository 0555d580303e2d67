"""The light-direction grid: which dataset lights a new light direction interpolates.

Owns the bake's direction work and the lookup the kernel does with it:

- :func:`dedupe_directions`: drop lights whose directions from the sphere centre coincide;
- :func:`triangulate`: the convex hull of the unit directions, minus the faces outside the
  coverage rule (docs/relighting.md "Coverage");
- :func:`build_grid`: a cube map over the direction sphere (6 faces x n x n cells), each cell
  listing the triangles whose circumcap overlaps it (CSR: ``grid_start``, ``grid_items``);
- :func:`locate` (numba, inlined into the relight kernel) and :func:`locate_directions` (its
  checked wrapper): the triangle containing a direction and the direction's weights in it.
"""

from __future__ import annotations

import math
from typing import Protocol

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import InvalidInputError
from engine.relighting.dataset import checked_array
from engine.sched import run_pieces_parallel


class LocatedGrid(Protocol):
    """What point location reads of a baked dataset (``engine.relighting.bake.BakedDataset`` has
    these fields): the triangles' inverse cone matrices and the cube-map grid over them."""

    tri_inverse: np.ndarray
    grid_n: int
    grid_start: np.ndarray
    grid_items: np.ndarray


CONE_EPS = 1e-12
"""A direction is inside a triangle when every cone coordinate is >= -CONE_EPS x their sum."""


def dedupe_directions(dirs: np.ndarray, pos: np.ndarray, tol_rad: float):
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


def triangulate(dirs: np.ndarray, max_face_radius_deg: float | None):
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




@nb.njit(cache=True)
def _cube_cell(x, y, z, n):
    """Index of the cube-map cell (face f, row j, column i of n x n) that direction (x, y, z) points into."""
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


def build_grid(dirs: np.ndarray, tri: np.ndarray):
    """(n, grid_start, grid_items): the cube map of n x n cells per face (n from the triangle count) and,
    per cell in ``_cube_cell`` order, the triangles whose circumcap overlaps the cell's cap, in index order
    (CSR: cell c's candidates are ``grid_items[grid_start[c]:grid_start[c + 1]]``)."""
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



@nb.njit(cache=True, nogil=True, inline="always")
def locate(x, y, z, inv, grid_n, grid_start, grid_items):
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
        if s > 0.0 and min(a0, min(a1, a2)) >= -CONE_EPS * s:
            a0 = max(a0, 0.0)
            a1 = max(a1, 0.0)
            a2 = max(a2, 0.0)
            s = a0 + a1 + a2
            return t, a0 / s, a1 / s, a2 / s
    return -1, 0.0, 0.0, 0.0


@nb.njit(cache=True, nogil=True)
def _locate_many(dirs, inv, grid_n, grid_start, grid_items, tri_out, w_out, i0, i1):
    for i in range(i0, i1):
        t, w0, w1, w2 = locate(dirs[i, 0], dirs[i, 1], dirs[i, 2], inv, grid_n, grid_start, grid_items)
        tri_out[i] = t
        w_out[i, 0], w_out[i, 1], w_out[i, 2] = w0, w1, w2



def locate_directions(baked: LocatedGrid, dirs) -> tuple[np.ndarray, np.ndarray]:
    """Triangle index (n,) int64 (-1 = outside coverage) and barycentric weights (n, 3)
    float64 for directions (n, 3) from the sphere centre (need not be unit)."""
    d = checked_array("dirs", dirs, np.float64, 2)
    if d.shape[1] != 3 or not np.all(np.isfinite(d)) or np.any(np.linalg.norm(d, axis=1) == 0):
        raise InvalidInputError("dirs: expected finite, non-zero (n, 3) directions")
    d = np.ascontiguousarray(d)
    tri = np.empty(d.shape[0], np.int64)
    w = np.zeros((d.shape[0], 3))
    run_pieces_parallel(lambda i0, i1: _locate_many(d, baked.tri_inverse, baked.grid_n, baked.grid_start,
                                                    baked.grid_items, tri, w, i0, i1), d.shape[0], 4096)
    return tri, w
