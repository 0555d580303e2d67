"""Triangle adjacency against a slow edge dictionary, and the edge walk against Embree's hits."""

from __future__ import annotations

import numpy as np

from engine.geometry.adjacency import locate_on_mesh, triangle_neighbours
from engine.raycast import EmbreeCaster
from tests.engine.scenes import mat, quad, scene, sphere_mesh


def _slow_neighbours(tri_p):
    edges: dict = {}
    for t in range(tri_p.shape[0]):
        for k in range(3):
            a, b = tuple(tri_p[t, (k + 1) % 3]), tuple(tri_p[t, (k + 2) % 3])
            edges.setdefault(frozenset((a, b)), []).append((t, k))
    out = np.full((tri_p.shape[0], 3), -1, np.int32)
    for users in edges.values():
        if len(users) == 2:
            (t0, k0), (t1, k1) = users
            out[t0, k0], out[t1, k1] = t1, t0
    return out


def test_neighbours_match_the_slow_dictionary_with_borders_and_non_manifold_edges():
    sc = scene([(sphere_mesh((0, 0, 0), 1.0, subdivisions=3), mat("a")), (quad((0, -2, 0), 2.0), mat("b"))])
    tri_p = sc.tri_p
    # a third triangle on one sphere edge: that edge becomes non-manifold (no neighbour)
    extra = np.array([[tri_p[0, 1], tri_p[0, 2], tri_p[0, 1] * 1.5]])
    tri_p = np.concatenate([tri_p, extra])
    got = triangle_neighbours(tri_p)
    assert np.array_equal(got, _slow_neighbours(tri_p))
    n_sphere = sc.tri_p.shape[0] - 2
    assert got[0, 0] == -1 and (got[1:n_sphere] >= 0).sum() >= 3 * (n_sphere - 1) - 2
    assert (got[n_sphere:n_sphere + 2] == -1).sum() == 4  # the quad: one shared diagonal, four borders
    assert triangle_neighbours(np.zeros((0, 3, 3))).shape == (0, 3)


def test_walk_finds_the_triangle_embree_hits():
    sc = scene([(sphere_mesh((0, 0, 0), 1.0, subdivisions=4, jitter=0.02, seed=3), mat("a"))])
    nbr = triangle_neighbours(sc.tri_p)
    caster = EmbreeCaster(sc)
    rng = np.random.default_rng(5)
    n = 400
    o = rng.normal(size=(n, 3))
    o = 4.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
    target = rng.normal(size=(n, 3)) * 0.3
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hits = caster.intersect(o, d)
    ok_rays = np.flatnonzero(hits.prim >= 0)
    assert ok_rays.size > 300
    found = refused = 0
    for i in ok_rays:
        true_t = int(hits.prim[i])
        start = int(nbr[nbr[true_t, 0], 1])  # two edges away
        ok, t, s, bw, bu, bv = locate_on_mesh(*o[i], *d[i], start, sc.tri_p, sc.tri_ng, nbr, 8)
        if not ok or min(bw, bu, bv) < -1e-9:  # grazing rays: the planes' crossings disagree, no walk
            refused += 1
            continue
        assert abs(bw + bu + bv - 1.0) < 1e-12
        q = o[i] + s * d[i]
        assert np.allclose(q, bw * sc.tri_p[t, 0] + bu * sc.tri_p[t, 1] + bv * sc.tri_p[t, 2], atol=1e-9)
        found += t == true_t
    # the same triangle except where the hit is on a shared edge (either side is right there)
    assert refused <= ok_rays.size // 100 and found >= ok_rays.size - refused - 2


def test_walk_stops_at_a_border_and_reports_rays_behind_or_parallel():
    sc = scene([(quad((0, 0, 0), 2.0), mat("a"))])  # two triangles, y = 0 plane
    nbr = triangle_neighbours(sc.tri_p)
    ok, t, s, *_ = locate_on_mesh(5.0, 1.0, 0.0, 0.0, -1.0, 0.0, 0, sc.tri_p, sc.tri_ng, nbr, 8)
    assert ok and 0 <= t < 2 and s == 1.0  # outside the quad: the walk ends at the border triangle
    assert not locate_on_mesh(0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0, sc.tri_p, sc.tri_ng, nbr, 8)[0]  # behind
    assert not locate_on_mesh(0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0, sc.tri_p, sc.tri_ng, nbr, 8)[0]  # parallel
