"""Ray casting: Embree against the brute-force reference, and the numerics of docs/hard-cases.md #1, #2, #5, #6."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from engine.geometry.mesh import TriMesh
from engine.raycast import (
    EmbreeCaster,
    ReferenceCaster,
    all_hits,
    hit_points,
    make_caster,
    spawn_origins,
)
from tests.engine.scenes import from_trimesh, mat, quad, scene, sphere_mesh


def _random_rays(rng, n, lo, hi):
    """Rays from random points on a box around the scene toward random points inside it."""
    c = 0.5 * (lo + hi)
    r = np.linalg.norm(hi - lo)
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    o = c + dirs * r
    target = lo + rng.random((n, 3)) * (hi - lo)
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d


def _mixed_scene():
    box = trimesh.creation.box((2, 1, 3))
    box.apply_translation((2.5, 0, 0))
    cyl = trimesh.creation.cylinder(radius=0.5, height=2.0, sections=48)
    cyl.apply_translation((-2, 0, 0))
    return scene([(sphere_mesh(subdivisions=3), mat()), (from_trimesh(box, smooth=False), mat()),
                  (from_trimesh(cyl), mat()), (quad((0, -1.5, 0), 10.0), mat())])


def _agree(sc, o, d):
    e = EmbreeCaster(sc).intersect(o, d)
    r = ReferenceCaster(sc).intersect(o, d)
    assert np.array_equal(e.prim >= 0, r.prim >= 0)
    hit = r.prim >= 0
    rel = np.abs(e.t[hit] - r.t[hit]) / np.maximum(r.t[hit], 1e-30)
    assert rel.max() <= 1e-5
    same = e.prim[hit] == r.prim[hit]
    # a ray through a shared edge may legitimately pick either triangle at the same t
    assert same.mean() > 0.995
    return e, r


def test_embree_matches_reference_on_random_rays():
    sc = _mixed_scene()
    lo, hi = sc.bounds
    rng = np.random.default_rng(1)
    o, d = _random_rays(rng, 2000, lo, hi)
    e, _ = _agree(sc, o, d)
    assert 0.3 < e.hit.mean() <= 1.0


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
@pytest.mark.parametrize("offset", [0.0, 1e2, 1e4])
def test_embree_matches_reference_across_scales(scale, offset):
    m = sphere_mesh(subdivisions=2, radius=scale, center=(offset, offset * 0.5, -offset))
    sc = scene([(m, mat())])
    lo, hi = sc.bounds
    o, d = _random_rays(np.random.default_rng(2), 500, lo, hi)
    _agree(sc, o, d)


def test_hit_points_lie_on_triangles():
    sc = _mixed_scene()
    lo, hi = sc.bounds
    o, d = _random_rays(np.random.default_rng(3), 500, lo, hi)
    h = EmbreeCaster(sc).intersect(o, d)
    p = hit_points(sc, h)[h.hit]
    tri = sc.tri_p[h.prim[h.hit]]
    dist = np.abs(np.einsum("ij,ij->i", p - tri[:, 0], sc.tri_ng[h.prim[h.hit]]))
    assert dist.max() < 1e-9 * max(1.0, sc.extent)
    np.testing.assert_allclose(p, o[h.hit] + h.t[h.hit, None] * d[h.hit], atol=1e-5 * sc.extent)


# ------------------------------------------------------------------ docs/hard-cases.md #1: self-hits


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
@pytest.mark.parametrize("distance", [0.0, 1e2, 1e4])
def test_spawned_rays_never_self_hit(scale, distance):
    """Mitsuba test_ray_offset style sweep: rays leaving a sphere outward never re-hit it,
    rays leaving inward always reach the far side, and lights in view are never shadowed."""
    center = np.array([distance, -0.3 * distance, 0.7 * distance])
    m = sphere_mesh(center=center, radius=scale, subdivisions=4)
    sc = scene([(m, mat())])
    caster = EmbreeCaster(sc)
    rng = np.random.default_rng(4)
    n = 3000
    # hit the sphere from outside
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    o = center + dirs * 3 * scale
    d = -dirs + 0.1 * rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    h = caster.intersect(o, d)
    assert h.hit.mean() > 0.9
    o, d, h = o[h.hit], d[h.hit], type(h)(h.t[h.hit], h.prim[h.hit], h.u[h.hit], h.v[h.hit])
    p = hit_points(sc, h)
    ng = sc.tri_ng[h.prim]  # outward
    # outward directions in the hemisphere of ng, including grazing ones
    w = rng.normal(size=p.shape)
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    w = np.where(np.einsum("ij,ij->i", w, ng)[:, None] < 0, -w, w)
    w = w + 1e-3 * ng
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    out = caster.intersect(spawn_origins(sc, p, ng, w), w)
    # a convex mesh: an outward ray can only touch a neighbour at grazing angles
    assert out.hit.mean() < 0.005, f"self hits: {out.hit.sum()} of {len(w)}"
    # inward rays must hit the far side at a real distance (no self-hit at t ~ 0)
    win = -ng + 0.5 * w
    win /= np.linalg.norm(win, axis=1, keepdims=True)
    inn = caster.intersect(spawn_origins(sc, p, ng, win), win)
    assert inn.hit.all()
    assert (inn.t > 1e-3 * scale).all()
    # a light outside, in the outward hemisphere: never shadowed by the point's own triangle
    light = p + ng * 5 * scale
    ld = light - p
    dist = np.linalg.norm(ld, axis=1)
    occ = caster.occluded(spawn_origins(sc, p, ng, ld / dist[:, None]), ld / dist[:, None], dist * 0.999)
    assert not occ.any()


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_no_false_shadow_on_plane_far_from_origin(scale):
    """Points on a large plane far from the origin see a light just above them."""
    sc = scene([(quad((1e4, 0.0, -1e4), 100 * scale), mat())])
    caster = EmbreeCaster(sc)
    rng = np.random.default_rng(5)
    n = 2000
    xz = rng.uniform(-40 * scale, 40 * scale, (n, 2))
    o = np.stack([1e4 + xz[:, 0], np.full(n, scale), -1e4 + xz[:, 1]], 1)
    d = np.tile([0.0, -1.0, 0.0], (n, 1))
    h = caster.intersect(o, d)
    assert h.hit.all()
    p = hit_points(sc, h)
    ng = np.tile([0.0, 1.0, 0.0], (n, 1))
    for elev in (1e-3, 0.1, 1.0):
        ld = np.tile([1.0, elev, 0.3], (n, 1))
        ld /= np.linalg.norm(ld, axis=1, keepdims=True)
        occ = caster.occluded(spawn_origins(sc, p, ng, ld), ld, np.full(n, 10 * scale))
        assert not occ.any(), f"false shadows at elevation {elev}: {occ.sum()}"


# ------------------------------------------------------------------ docs/hard-cases.md #2: watertight


@pytest.mark.parametrize("backend", ["embree", "reference"])
def test_rays_from_inside_closed_jittered_sphere_always_hit(backend):
    m = sphere_mesh(subdivisions=3, jitter=0.05, seed=7)
    sc = scene([(m, mat())])
    caster = make_caster(sc, backend)
    rng = np.random.default_rng(6)
    n = 3000 if backend == "embree" else 600
    o = rng.uniform(-0.3, 0.3, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    assert caster.intersect(o, d).hit.all()


def test_rays_through_vertices_and_edges_never_fall_through():
    """pbrt-v4 Triangle.Watertight: aim exactly at shared vertices and edge points."""
    m = sphere_mesh(subdivisions=3, jitter=0.05, seed=8)
    sc = scene([(m, mat())])
    caster = EmbreeCaster(sc)
    v, f = m.vertices, m.faces
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    rng = np.random.default_rng(9)
    lam = rng.random((edges.shape[0], 1))
    targets = np.concatenate([v, v[edges[:, 0]] * lam + v[edges[:, 1]] * (1 - lam),
                              0.5 * (v[edges[:, 0]] + v[edges[:, 1]])])
    for origin in (np.zeros(3), np.array([0.1, -0.05, 0.02])):
        d = targets - origin
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        h = caster.intersect(np.broadcast_to(origin, d.shape), d)
        assert h.hit.all(), f"{(~h.hit).sum()} rays fell through"


# ------------------------------------------------------------------ all hits (LDI support)


def _brute_all_t(sc, o, d):
    """Every crossing distance of every triangle, by the reference caster one triangle at a time."""
    out = [[] for _ in range(o.shape[0])]
    for k in range(sc.n_triangles):
        one = scene([(TriMesh(sc.tri_p[k], np.array([[0, 1, 2]], np.int32), sc.tri_n[k]), mat())])
        h = ReferenceCaster(one).intersect(o, d)
        for i in np.nonzero(h.hit)[0]:
            out[i].append(h.t[i])
    return [sorted(x) for x in out]


def test_all_hits_nested_shells_keeps_every_layer():
    """docs/hard-cases.md #5: 18 nested spheres -> 36 crossings along a central ray, none lost."""
    shells = [(sphere_mesh(radius=1.0 + 0.05 * k, subdivisions=2), mat()) for k in range(18)]
    sc = scene(shells)
    rng = np.random.default_rng(10)
    n = 40
    o = np.tile([0.0, 0.0, 10.0], (n, 1)) + rng.uniform(-0.05, 0.05, (n, 3))
    d = np.tile([0.0, 0.0, -1.0], (n, 1))
    ah = all_hits(EmbreeCaster(sc), o, d, max_hits=64)
    assert (ah.counts == 36).all()
    assert not ah.truncated.any()
    ref = _brute_all_t(scene(shells[:3]), o[:5], d[:5])
    ah3 = all_hits(EmbreeCaster(scene(shells[:3])), o[:5], d[:5])
    for i in range(5):
        got = ah3.t[ah3.offsets[i]:ah3.offsets[i + 1]]
        np.testing.assert_allclose(got, ref[i], rtol=1e-6)
    # bounded memory: a cap truncates and flags
    capped = all_hits(EmbreeCaster(sc), o, d, max_hits=10)
    assert (capped.counts == 10).all() and capped.truncated.all()


def test_all_hits_close_layers_far_from_origin():
    """docs/hard-cases.md #6: two surfaces 1e-3 apart at depth 1e4 stay two layers."""
    a = quad((0.0, 0.0, -1e4), 1.0, normal_axis=2)
    b = quad((0.0, 0.0, -1e4 - 1e-3), 1.0, normal_axis=2)
    sc = scene([(a, mat()), (b, mat())])
    n = 50
    rng = np.random.default_rng(11)
    o = np.stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.4, 0.4, n), np.zeros(n)], 1)
    d = np.tile([0.0, 0.0, -1.0], (n, 1))
    ah = all_hits(EmbreeCaster(sc), o, d)
    assert (ah.counts == 2).all()
    gap = ah.t[1::2] - ah.t[0::2]
    np.testing.assert_allclose(gap, 1e-3, rtol=1e-3)


def test_empty_scene_misses_everything():
    sc = scene([])
    o = np.zeros((4, 3))
    d = np.tile([0.0, 0.0, 1.0], (4, 1))
    for backend in ("embree", "reference"):
        c = make_caster(sc, backend)
        assert not c.intersect(o, d).hit.any()
        assert not c.occluded(o, d, np.full(4, 1e9)).any()


def test_embree_caster_pickles_without_native_handle():
    import pickle

    sc = scene([(sphere_mesh(), mat())])
    c = EmbreeCaster(sc)
    c.intersect(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))
    c2 = pickle.loads(pickle.dumps(c))
    assert c2._embree is None
    assert c2.intersect(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])).hit.all()


def test_bad_rays_raise():
    sc = scene([(sphere_mesh(), mat())])
    c = EmbreeCaster(sc)
    with pytest.raises(ValueError):
        c.intersect(np.array([[np.nan, 0, 0]]), np.array([[0.0, 0, 1]]))
    with pytest.raises(ValueError):
        c.intersect(np.zeros((2, 3)), np.zeros((3, 3)))
