"""Layered light field: octahedron directions, lattice lookup, views baked by the reference
renderer, split bake + merge, storage round trips."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

from engine.errors import InvalidInputError
from engine.newviews.ldc import LDC, LDCAxis, bake_ldc, surface_attributes
from engine.newviews.ldi import build_ldi
from engine.newviews.llf import (
    LLF,
    LLFView,
    bake_llf,
    bake_llf_views,
    candidate_directions,
    direction_spacing,
    estimate_llf_bytes,
    lattice_index_table,
    llf_direction_count,
    merge_llf,
    octahedron_directions,
    view_frame,
)
from engine.raycast import EmbreeCaster
from engine.reference import ReferenceParams, ReferenceRenderer
from tests.engine.scenes import mat, quad, scene, sphere_mesh

PT = dict(type="point", position=(1.5, 2.5, 2.0), intensity=(4.0, 4.0, 4.0))


def _roundtrip(arrays: dict) -> dict:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    buf.seek(0)
    return dict(np.load(buf, allow_pickle=False))


@pytest.mark.parametrize("f,n", [(1, 6), (2, 18), (4, 66), (8, 258), (16, 1026), (5, 102)])
def test_direction_counts_unit_distinct_near_uniform(f, n):
    d = octahedron_directions(f)
    assert llf_direction_count(f) == n and d.shape == (n, 3) and d.dtype == np.float64
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert len(np.unique(np.round(d, 9), axis=0)) == n
    assert np.allclose(d.sum(axis=0), 0.0, atol=1e-9)  # symmetric set
    if f >= 2:
        dots = d @ d.T
        np.fill_diagonal(dots, -2.0)
        nn = np.arccos(np.clip(dots.max(axis=1), -1, 1))
        # equal-area lattice: nearest-neighbour angles within 1.4x of each other (measured 1.33)
        assert nn.max() / nn.min() < 1.4
        assert 0.8 < nn.mean() / direction_spacing(f) < 1.1
    if 2 <= f <= 8:
        # every direction's share of the sphere: Voronoi-like count of random directions
        rng = np.random.default_rng(0)
        q = rng.normal(size=(200 * n, 3))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        share = np.bincount(np.argmax(q @ d.T, axis=1), minlength=n) / q.shape[0] * n
        assert 0.5 < share.min() and share.max() < 1.6
    if f == 1:
        assert np.allclose(np.sort(np.abs(d), axis=0), np.sort(np.abs(np.eye(3).repeat(2, 0)), axis=0))


def test_bad_frequency():
    for f in (0, -1, 65, 2.5, True):
        with pytest.raises(InvalidInputError):
            octahedron_directions(f)


@pytest.mark.parametrize("f", [4, 8, 16])
def test_candidate_window_covers_nearby_directions(f):
    d = octahedron_directions(f)
    tab = lattice_index_table(f)
    assert set(tab[tab >= 0].tolist()) == set(range(len(d)))
    rng = np.random.default_rng(f)
    out = np.empty(len(d) + 8, np.int64)
    for _ in range(400):
        q = rng.normal(size=3)
        q /= np.linalg.norm(q)
        ang = np.arccos(np.clip(d @ q, -1, 1))
        for radius in (3, 5):
            k = candidate_directions(q[0], q[1], q[2], f, radius, tab, out)
            got = set(out[:k].tolist())
            assert len(got) == k  # no duplicates
            need = set(np.flatnonzero(ang <= (radius - 2) / (0.6 * f) + 1e-12).tolist())
            assert need <= got
            if radius == 3:
                assert set(np.argsort(ang)[:3].tolist()) <= got  # the mirror cone's 3 nearest


def _scene():
    return scene([(quad((0, -0.5, 0), 3.0, normal_axis=1), mat("floor", kd=(0.6, 0.6, 0.55), ks=(0.2, 0.2, 0.2),
                                                             shininess=30.0)),
                  (sphere_mesh((0.2, 0.1, 0.0), 0.5, 2), mat("ball", kd=(0.2, 0.3, 0.7), kr=(0.5, 0.5, 0.5)))],
                 [PT], ambient=(0.05, 0.05, 0.05), background=(0.1, 0.2, 0.3))


def test_views_are_ldis_shaded_by_the_reference():
    sc = _scene()
    caster = EmbreeCaster(sc)
    params = ReferenceParams(max_depth=2, glossy_samples=4)
    views = bake_llf_views(sc, caster, 2, 24, [0, 5, 17], params=params)
    dirs = octahedron_directions(2)
    ren = ReferenceRenderer(sc, caster)
    lo, hi = sc.bounds
    for v in views:
        fr = v.ldi.frame
        assert np.allclose(fr.w, dirs[v.index]) and fr.nu == fr.nv == 24
        # the frame covers the bounding sphere: every box corner projects inside, in front of the plane
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        rel = corners - fr.origin
        assert np.all(rel @ fr.w > 0) and np.all((rel @ fr.u > 0) & (rel @ fr.u < fr.nu * fr.h))
        ref_ldi = build_ldi(caster, view_frame(sc, dirs[v.index], 24), max_layers=32)
        assert np.array_equal(ref_ldi.offsets, v.ldi.offsets) and np.array_equal(ref_ldi.depth, v.ldi.depth)
        want = ren.shade_hits(v.ldi.prim, v.ldi.u, v.ldi.v, np.broadcast_to(fr.w, (v.n_samples, 3)), params,
                              stream_id=v.index)
        assert np.array_equal(v.radiance, want.astype(np.float32))
        assert v.radiance.dtype == np.float32 and np.all(np.isfinite(v.radiance)) and v.radiance.min() >= 0


def test_radiance_matches_a_naive_direct_light_computation():
    # one convex object, point light: no shadows, no reflections -> kd/pi I cos / d^2 + ambient
    sc = scene([(sphere_mesh((0, 0, 0), 1.0, 3), mat("ball", kd=(0.2, 0.3, 0.7)))], [PT], ambient=(0.05, 0.05, 0.05))
    caster = EmbreeCaster(sc)
    (v,) = bake_llf_views(sc, caster, 1, 32, [3], params=ReferenceParams(max_depth=0))
    p, ng, ns = surface_attributes(sc, v.ldi.prim, v.ldi.u, v.ldi.v)
    w = v.ldi.frame.w
    flip = np.where(ng @ w > 0, -1.0, 1.0)[:, None]  # the side the view's ray arrives on
    ng, ns = ng * flip, ns * flip
    ns = np.where((np.einsum("ij,ij->i", ns, ng) > 0)[:, None], ns, ng)
    to = np.asarray(PT["position"]) - p
    dist = np.linalg.norm(to, axis=1)
    lw = to / dist[:, None]
    lit = (np.einsum("ij,ij->i", ng, lw) > 0)
    cos = np.clip(np.einsum("ij,ij->i", ns, lw), 0, None) * lit
    want = np.array([0.2, 0.3, 0.7]) / np.pi * 4.0 * (cos / dist**2)[:, None] + 0.05 * np.array([0.2, 0.3, 0.7])
    # back faces (the inside of the sphere seen through it) are unlit: the sphere shadows them
    front = flip[:, 0] > 0
    assert front.sum() > 200
    assert np.allclose(v.radiance[front], want[front], rtol=2e-4, atol=1e-6)


def test_split_bake_merge_storage_and_progress():
    sc = _scene()
    caster = EmbreeCaster(sc)
    params = ReferenceParams(max_depth=1, glossy_samples=2)
    seen: list[float] = []
    whole = bake_llf(sc, caster, 2, 16, params=params, progress=seen.append)
    assert seen == sorted(seen) and seen[-1] == pytest.approx(1.0) and len(seen) >= 18
    n = llf_direction_count(2)
    a = bake_llf_views(sc, caster, 2, 16, range(0, n, 2), params=params)
    b = bake_llf_views(sc, caster, 2, 16, range(1, n, 2), params=params)
    merged = merge_llf(2, 16, b + a, whole.params)
    assert merged.n_directions == n and [v.index for v in merged.views] == list(range(n))
    assert np.array_equal(merged.pk_depth, whole.pk_depth) and np.array_equal(merged.pk_radiance, whole.pk_radiance)
    assert np.array_equal(merged.pk_offsets, whole.pk_offsets)
    assert whole.nbytes > 0 and whole.n_samples == sum(v.n_samples for v in whole.views)
    # storage: every view and the metadata through npz without pickle
    views2 = [LLFView.from_arrays(_roundtrip(v.to_arrays())) for v in whole.views]
    again = LLF.from_arrays(_roundtrip(whole.to_arrays()), views2)
    assert again.params == whole.params and again.f == 2 and again.resolution == 16
    assert np.array_equal(again.pk_radiance, whole.pk_radiance) and np.array_equal(again.pk_depth, whole.pk_depth)
    with pytest.raises(InvalidInputError, match="missing"):
        merge_llf(2, 16, a, whole.params)
    with pytest.raises(InvalidInputError):
        merge_llf(2, 16, a + a[:1] + b[1:], whole.params)
    with pytest.raises(InvalidInputError):
        merge_llf(2, 32, a + b, whole.params)
    broken = whole.views[0].to_arrays()
    del broken["radiance"]
    with pytest.raises(InvalidInputError, match="radiance"):
        LLFView.from_arrays(broken)
    bad = whole.views[0].to_arrays()
    bad["radiance"] = bad["radiance"][:-1]
    with pytest.raises(InvalidInputError):
        LLFView.from_arrays(bad)
    with pytest.raises(InvalidInputError):
        bake_llf_views(sc, caster, 2, 16, [0, 0], params=params)
    with pytest.raises(InvalidInputError):
        bake_llf_views(sc, caster, 2, 16, [n], params=params)
    with pytest.raises(InvalidInputError):
        bake_llf_views(sc, caster, 2, 3, [0], params=params)
    with pytest.raises(InvalidInputError, match="MiB"):
        bake_llf_views(sc, caster, 2, 64, [0, 1], params=params, max_bytes=estimate_llf_bytes(2, 64, n_views=2) - 1)


def test_ldc_storage_roundtrip():
    sc = _scene()
    ldc = bake_ldc(sc, EmbreeCaster(sc), 24)
    axes = [LDCAxis.from_arrays(_roundtrip(a.to_arrays())) for a in reversed(ldc.axes)]
    back = LDC.from_arrays(_roundtrip(ldc.to_arrays()), axes)
    assert back.h == ldc.h and back.resolution == 24 and back.plan == ldc.plan
    assert back.closed_objects == ldc.closed_objects and np.array_equal(back.background, ldc.background)
    for x, y in zip(back.axes, ldc.axes, strict=True):
        # stored: the counts of the bake's timings, not its wall-clock seconds (same bytes every bake)
        assert x.axis == y.axis and x.timings == {k: v for k, v in y.timings.items() if not isinstance(v, float)}
        assert "shadow_rays" in x.timings and not any(isinstance(v, float) for v in x.timings.values())
        for k in ("normal", "geo_normal", "facing", "material", "object", "diffuse", "visibility"):
            assert np.array_equal(getattr(x, k), getattr(y, k)) and getattr(x, k).dtype == getattr(y, k).dtype
        assert np.array_equal(x.ldi.depth, y.ldi.depth) and np.array_equal(x.ldi.offsets, y.ldi.offsets)
    d = ldc.axes[0].to_arrays()
    d["diffuse"] = d["diffuse"][:-1]
    with pytest.raises(InvalidInputError):
        LDCAxis.from_arrays(d)
    with pytest.raises(InvalidInputError):
        LDC.from_arrays(ldc.to_arrays(), axes[:2])
    assert math.isfinite(back.nbytes)
