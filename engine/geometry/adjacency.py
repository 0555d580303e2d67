"""Triangle adjacency and point location on a triangle soup by walking across edges.

The LDC renderer knows, per pixel, the triangle of the LDC sample it shows; the pixel's own
surface point usually lies on a neighbouring triangle (a sample stands for an ``h x h`` cell,
often several triangles wide on tessellated curved surfaces). Extrapolating the sample
triangle's normals across its edges tilts the shading normal by several degrees there, which
moves Phong highlights (teapot_glossy: LRMS 0.172 -> 0.116 with the walk at LDC 256). The walk
below crosses edges toward the pixel ray's crossing, using only the mesh (no ray casting).

``triangle_neighbours`` matches edges by exact corner positions (the runtime scene stores
corners per triangle; meshes share vertex positions along their edges). An edge shared by
more than two triangles (non-manifold) or by one (a border) has no neighbour (-1).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)

__all__ = ["locate_on_mesh", "triangle_neighbours"]


def triangle_neighbours(tri_p: np.ndarray) -> np.ndarray:
    """(nt, 3) int32: the triangle across the edge opposite corner k of each triangle, -1 where
    there is none (border) or the edge is shared by more than two triangles."""
    tri_p = np.asarray(tri_p, dtype=np.float64)
    nt = tri_p.shape[0]
    out = np.full((nt, 3), -1, np.int32)
    if nt == 0:
        return out
    _, vid = np.unique(tri_p.reshape(-1, 3), axis=0, return_inverse=True)
    vid = vid.reshape(nt, 3).astype(np.int64)
    # edge opposite corner k joins corners k+1 and k+2
    a = np.concatenate([vid[:, 1], vid[:, 2], vid[:, 0]])
    b = np.concatenate([vid[:, 2], vid[:, 0], vid[:, 1]])
    key = np.minimum(a, b) * (int(vid.max()) + 1) + np.maximum(a, b)
    tri = np.tile(np.arange(nt, dtype=np.int64), 3)
    corner = np.repeat(np.arange(3, dtype=np.int64), nt)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    lengths = np.diff(np.r_[starts, ks.size])
    pairs = starts[lengths == 2]
    i0, i1 = order[pairs], order[pairs + 1]
    out[tri[i0], corner[i0]] = tri[i1]
    out[tri[i1], corner[i1]] = tri[i0]
    return out


@nb.njit(cache=True, nogil=True, error_model="numpy")
def locate_on_mesh(ox, oy, oz, dx, dy, dz, t, tri_p, tri_ng, nbr, max_steps):
    """Walk from triangle ``t`` toward the crossing of the ray ``o + s d`` with the mesh: at each
    step intersect the ray with the current triangle's plane, take the barycentrics of that
    point, and cross the edge opposite the most negative one (to ``nbr``, never straight back to
    the triangle just left) until all are >= 0 (to 1e-9), no edge is left to cross, or
    ``max_steps`` edges were crossed.

    Returns ``(ok, t, s, bw, bu, bv)``: ``ok`` False when the ray is parallel to a plane or
    the crossing is behind the origin (nothing moved); else the last triangle, the ray
    parameter of its plane crossing and the (unclamped) barycentrics of corners 0, 1, 2."""
    prev = -1
    for step in range(max_steps + 1):
        g0, g1, g2 = tri_ng[t, 0], tri_ng[t, 1], tri_ng[t, 2]
        den = dx * g0 + dy * g1 + dz * g2
        if abs(den) < 1e-12:
            return False, t, 0.0, 0.0, 0.0, 0.0
        ax, ay, az = tri_p[t, 0, 0], tri_p[t, 0, 1], tri_p[t, 0, 2]
        s = ((ax - ox) * g0 + (ay - oy) * g1 + (az - oz) * g2) / den
        if not s > 0.0:
            return False, t, 0.0, 0.0, 0.0, 0.0
        vx, vy, vz = ox + s * dx - ax, oy + s * dy - ay, oz + s * dz - az
        e1x, e1y, e1z = tri_p[t, 1, 0] - ax, tri_p[t, 1, 1] - ay, tri_p[t, 1, 2] - az
        e2x, e2y, e2z = tri_p[t, 2, 0] - ax, tri_p[t, 2, 1] - ay, tri_p[t, 2, 2] - az
        d00 = e1x * e1x + e1y * e1y + e1z * e1z
        d01 = e1x * e2x + e1y * e2y + e1z * e2z
        d11 = e2x * e2x + e2y * e2y + e2z * e2z
        d20 = vx * e1x + vy * e1y + vz * e1z
        d21 = vx * e2x + vy * e2y + vz * e2z
        dd = d00 * d11 - d01 * d01
        if not dd > 0.0:
            return False, t, 0.0, 0.0, 0.0, 0.0
        bu = (d11 * d20 - d01 * d21) / dd
        bv = (d00 * d21 - d01 * d20) / dd
        bw = 1.0 - bu - bv
        mn = min(bw, min(bu, bv))
        if mn >= -1e-9 or step == max_steps:
            return True, t, s, bw, bu, bv
        # cross the edge of the most negative barycentric, but never straight back: the planes
        # differ per triangle, so two neighbours can each place the crossing inside the other
        k = -1
        best = -1e-9
        for c in range(3):
            bc = bw if c == 0 else (bu if c == 1 else bv)
            if bc < best and nbr[t, c] >= 0 and nbr[t, c] != prev:
                best = bc
                k = c
        if k < 0:
            return True, t, s, bw, bu, bv
        prev = t
        t = nbr[t, k]
    return True, t, 0.0, 0.0, 0.0, 0.0  # pragma: no cover - the loop always returns
