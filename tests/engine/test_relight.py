"""Relighting engine : exactness, limits, linearity, docs/hard-cases.md #10 (and #9), naive cross-check."""

from __future__ import annotations

import numpy as np
import pytest

from engine.errors import InvalidInputError
from engine.relighting.bake import bake_dataset
from engine.relighting.dataset import IlluminationDataset, points_from_depth
from engine.relighting.grid import locate_directions
from engine.relighting.lights import DirectionalLight, EnvironmentLight, PointLight, RectLight, light_from_dict
from engine.relighting.relight import relight
from engine.scene import CameraParams
from tests.engine.relight_naive import (
    ALBEDO,
    lambert_directional,
    lambert_point,
    lat_long_lights,
    naive_relight,
    sphere_points,
)

R = 5.0
H = 40


def make_ds(spacing=20.0, h=H, radius=R, intensity=1.0, **kw):
    pts, mask = sphere_points(h)
    lights = lat_long_lights(spacing, radius, **kw)
    imgs = np.stack([lambert_point(pts, mask, lt, intensity) for lt in lights])
    return IlluminationDataset(imgs, lights, np.full((len(lights), 3), intensity), pts, mask), pts, mask


@pytest.fixture(scope="module")
def full20():
    ds, pts, mask = make_ds(20.0)
    return ds, bake_dataset(ds, sphere_center=[0, 0, 0], half=False), pts, mask


@pytest.fixture(scope="module")
def hemi():
    ds, pts, mask = make_ds(15.0, lat_min=0.0, lat_max=90.0)
    return ds, bake_dataset(ds, sphere_center=[0, 0, 0], half=False), pts, mask


def rel_err(img, gt, mask):
    return float(np.abs(img - gt)[mask].mean() / gt[mask].mean())


# ---------------------------------------------------------------- exactness, limits, linearity


def test_light_at_dataset_light_is_bit_exact(full20):
    ds, b, pts, mask = full20
    for k in (0, 7, len(ds.light_positions) - 1):
        r = relight(b, PointLight(ds.light_positions[k], 1.0))
        assert r.exact and r.n_outside == 0
        assert np.array_equal(r.image, ds.images[k])
        r2 = relight(b, PointLight(ds.light_positions[k], (2.0, 3.0, 0.5)))
        assert np.array_equal(r2.image, ds.images[k] * np.float32([2.0, 3.0, 0.5]))
        # the interpolating kernel agrees at the vertex (weights (1, 0, 0))
        r3 = relight(b, PointLight(ds.light_positions[k], 1.0), exact_fast_path=False)
        np.testing.assert_allclose(r3.image, ds.images[k], rtol=1e-5, atol=1e-9)


def test_exact_match_superposition_is_bit_exact(full20):
    """Lights exactly at dataset lights: the stored images' superposition, no interpolation, and only
    those lights are read."""
    ds, b, pts, mask = full20
    a, c = 4, 17
    r = relight(b, [PointLight(ds.light_positions[a], 2.0), PointLight(ds.light_positions[c], (0.5, 1.0, 3.0))])
    assert r.exact and r.n_triangles_used == 0 and r.lights_used.tolist() == [a, c]
    want = np.zeros_like(ds.images[a])
    want += ds.images[a] * np.float32(2.0)
    want += ds.images[c] * np.float32([0.5, 1.0, 3.0])
    assert np.array_equal(r.image, want)
    # one light off the dataset: the interpolating kernel for all (never a mixed answer)
    two = [PointLight(ds.light_positions[a], 2.0), PointLight((0.3, 1.0, 4.0), 1.0)]
    mixed = relight(b, two)
    assert not mixed.exact and mixed.n_triangles_used > 0
    assert np.array_equal(mixed.image, relight(b, two, exact_fast_path=False).image)
    # the kernel at the vertex (weights (1, 0, 0)) plus the other light: their sum (linearity)
    parts = relight(b, two[0], exact_fast_path=False).image + relight(b, two[1]).image
    np.testing.assert_allclose(mixed.image, parts, rtol=1e-6, atol=1e-9)


def test_relight_reads_only_the_triangles_the_lights_need(full20):
    """``lights_used`` / ``n_triangles_used`` are the triangles the per-pixel sphere points fall in
    (computed here independently with locate_directions), a small part of the dataset."""
    ds, b, pts, mask = full20
    lpos = np.array([0.7, 1.9, 4.1])
    r = relight(b, PointLight(lpos, 1.0))
    p = b.points
    u = (lpos - p) / np.linalg.norm(lpos - p, axis=1, keepdims=True)
    o = p - b.sphere_center
    bb = np.sum(o * u, axis=1)
    t = -bb + np.sqrt(bb * bb - (np.sum(o * o, axis=1) - b.sphere_radius ** 2))
    tri, _ = locate_directions(b, o + t[:, None] * u)
    assert np.all(tri >= 0)
    assert r.n_triangles_used == np.unique(tri).size
    assert r.lights_used.tolist() == np.unique(b.triangles[np.unique(tri)]).tolist()
    assert r.lights_used.size < 0.25 * len(b.light_positions)


def test_exact_hit_half_store_returns_stored_values():
    ds, pts, mask = make_ds(30.0)
    b = bake_dataset(ds, sphere_center=[0, 0, 0], half=True)
    assert b.report["dtype"] == "float16"
    r = relight(b, PointLight(ds.light_positions[3], 1.0))
    np.testing.assert_allclose(r.image, ds.images[3], rtol=2 ** -11, atol=0)


def test_directional_is_far_limit_of_point(full20):
    _, b, pts, mask = full20
    toward = np.array([0.3, 0.5, 0.8])
    toward /= np.linalg.norm(toward)
    e = np.array([1.0, 2.0, 0.5])
    dirl = relight(b, DirectionalLight(-toward, e)).image
    for d in (1e6, 1e15):  # the kernel's float32 weights carry the light's intensity: in range at any distance
        far = relight(b, PointLight(toward * d, e * d * d)).image
        np.testing.assert_allclose(far, dirl, rtol=1e-4, atol=1e-7)
    assert rel_err(dirl, lambert_directional(pts, mask, toward, e), mask) < 0.05


def test_superposition_is_linear(full20):
    _, b, _, mask = full20
    a = PointLight((1.0, 2.0, 3.5), (1.0, 0.5, 2.0))
    c = PointLight((-2.0, 0.5, 2.0), 3.0)
    d = DirectionalLight((0.2, -0.3, -1.0), 0.7)
    both = relight(b, [a, c, d]).image
    parts = relight(b, a).image + relight(b, c).image + relight(b, d).image
    np.testing.assert_allclose(both, parts, rtol=1e-5, atol=1e-8)
    double = relight(b, PointLight(a.position, 2 * np.asarray(a.intensity))).image
    np.testing.assert_allclose(double, 2 * relight(b, a).image, rtol=1e-6)


@pytest.mark.parametrize("layout", ["pixel_major", "tiled"])
def test_kernel_matches_naive_reference(full20, layout):
    ds, _, _, _ = full20
    small, pts, mask = make_ds(20.0, h=12)
    b = bake_dataset(small, sphere_center=[0, 0, 0], half=False, layout=layout)
    assert b.layout == layout
    pl = [((1.0, 2.0, 3.5), (1.0, 0.5, 2.0)), ((0.3, -0.2, 1.8), (1.0, 1.0, 1.0)),
          ((400.0, 30.0, -20.0), (1e4, 1e4, 1e4)), (tuple(ds.light_positions[5]), (1.0, 1.0, 1.0))]
    tl = [((0.1, 0.9, 0.4), (0.5, 0.5, 0.5))]
    want, w_out = naive_relight(b, pl, tl)
    got = relight(b, [PointLight(p, i) for p, i in pl] + [DirectionalLight(-np.asarray(d), e) for d, e in tl])
    np.testing.assert_allclose(got.image, want, rtol=1e-5, atol=1e-9)
    assert np.array_equal(got.outside_mask, w_out)


@pytest.mark.parametrize("layout", ["tiled", "pixel_major"])
def test_simd_kernel_matches_naive_on_a_multi_chunk_half_store(layout):
    """The chunked kernel (per 256-row chunk: one triangle tested for all rows at once, scalar
    search for the rest, float16 decoded by bit operations, units of 8 chunks per thread group)
    against the per-pixel reference on a float16 store of many chunks: lights on an edge, at a
    vertex, across the coverage boundary (some pixels outside), near and far, and directional."""
    ds, pts, mask = make_ds(15.0, h=88, lat_min=0.0, lat_max=90.0)
    b = bake_dataset(ds, sphere_center=[0, 0, 0], layout=layout)
    assert b.report["dtype"] == "float16" and b.layout == layout
    n = b.pixel_index.size
    assert n > 2 * 8 * 256  # more than two units of chunks
    lp = b.light_positions
    edge = lp[b.triangles[7, 0]] + lp[b.triangles[7, 1]]
    edge = edge / np.linalg.norm(edge) * 7.0
    vertex = lp[b.triangles[11, 2]] * 1.5
    pl = [(edge, (1.0, 1.0, 1.0)), (vertex, (0.5, 1.0, 2.0)), ((0.0, 0.2, 4.0), (1.0, 1.0, 1.0)),
          ((1.0, 2.0, 3.5), (1.0, 0.5, 2.0)), ((400.0, 300.0, -20.0), (1e4, 1e4, 1e4))]
    tl = [((0.1, 0.9, 0.4), (0.5, 0.5, 0.5))]
    got = relight(b, [PointLight(p, i) for p, i in pl] + [DirectionalLight(-np.asarray(d), e) for d, e in tl])
    assert 0 < got.n_outside < n
    rows = np.unique(np.concatenate([np.arange(0, n, 37), np.arange(96), np.arange(n - 96, n)]))
    want, w_out = naive_relight(b, pl, tl, rows=rows)
    sel = b.pixel_index[rows]
    np.testing.assert_allclose(got.image.reshape(-1, 3)[sel], want.reshape(-1, 3)[sel], rtol=1e-5, atol=1e-9)
    assert np.array_equal(got.outside_mask.ravel()[sel], w_out.ravel()[sel])
    assert got.outside_mask.ravel()[sel].any()
    # threads and the serial compilation give the same image bit for bit
    for kw in ({"serial": True}, {"threads": 1}):
        again = relight(b, [PointLight(p, i) for p, i in pl] + [DirectionalLight(-np.asarray(d), e) for d, e in tl],
                        **kw)
        assert np.array_equal(again.image, got.image) and np.array_equal(again.outside_mask, got.outside_mask)


@pytest.mark.parametrize("half", [False, True])
def test_float32_geometry_border_rows_get_the_float64_answer(half):
    """The tiled store's point lights take the float32 sphere direction and cone test; a row whose float32
    cone coordinates are within their error bound of 0 is re-tested in float64 (docs/hard-cases.md #10). A light ON
    the sphere sends every row's direction to the light itself: at an edge midpoint of the coverage
    boundary (latitude 0 of a hemisphere: the triangle on one side, nothing on the other), at an interior
    edge midpoint and at a vertex (the exact path off), every row lies on an edge or a vertex up to
    rounding; 1e-9 rad outside the boundary every row is outside coverage for float64, but float32 rounding
    would take about half of them for inside (without the re-test, n_outside is about n / 2). Every row
    must get the float64 answer: the naive reference's values and outside mask, and the same outside
    mask and lights as the pixel-major store (float64 geometry throughout)."""
    ds, pts, mask = make_ds(15.0, h=48, lat_min=0.0, lat_max=90.0)
    bt = bake_dataset(ds, sphere_center=[0, 0, 0], sphere_radius=R, half=half)
    bp = bake_dataset(ds, sphere_center=[0, 0, 0], sphere_radius=R, half=half, layout="pixel_major")
    assert bt.layout == "tiled" and bt.pixel_index.size > 4 * 256
    lp, tri = bt.light_positions, bt.triangles
    boundary = [t for t in range(len(tri)) if np.sum(lp[tri[t], 1] == 0.0) == 2]
    assert boundary
    t = boundary[len(boundary) // 2]
    k0, k1 = [k for k in tri[t] if lp[k, 1] == 0.0]
    on_boundary = (lp[k0] + lp[k1]) / np.linalg.norm(lp[k0] + lp[k1]) * R
    assert abs(on_boundary[1]) < 1e-15
    interior = (lp[tri[5, 1]] + lp[tri[5, 2]]) / np.linalg.norm(lp[tri[5, 1]] + lp[tri[5, 2]]) * R
    vertex = lp[tri[9, 0]]
    # 1e-9 rad below / above the boundary: outside / inside for float64 (its tolerance is 1e-12 relative),
    # far below float32's resolution of the direction (~1e-7)
    below, above = (on_boundary + [0.0, -1e-9 * R, 0.0], on_boundary + [0.0, 1e-9 * R, 0.0])
    rows = np.arange(0, bt.pixel_index.size, 5)
    sel = bt.pixel_index[rows]
    n = bt.pixel_index.size
    for pos, n_out in ((on_boundary, 0), (interior, 0), (vertex, 0), (below, n), (above, 0)):
        light = PointLight(pos, 1.0)
        got = relight(bt, light, exact_fast_path=False)
        assert not got.exact and got.n_outside == n_out and got.n_singular == 0
        want, w_out = naive_relight(bt, [(pos, (1.0, 1.0, 1.0))], rows=rows)
        assert np.array_equal(got.outside_mask.ravel()[sel], w_out.ravel()[sel])
        np.testing.assert_allclose(got.image.reshape(-1, 3)[sel], want.reshape(-1, 3)[sel], rtol=1e-5, atol=1e-9)
        _assert_same_relight(got, relight(bp, light, exact_fast_path=False))


def test_float32_cone_test_never_accepts_rows_just_outside_coverage():
    """Rows whose sphere directions are within float32 rounding of the coverage boundary, in chunks whose
    first row is well inside the boundary triangle (so the SIMD pass tests them all against it): float64
    puts about half of them outside (the points, float32 numbers, are off the boundary plane by their
    rounding, ~1e-8 relative; float64's tolerance is 1e-12), and float32 rounding of the direction (~1e-7)
    would accept many of those as inside without the border re-test. Hemisphere lights rotated to a generic
    orientation (boundary = a generic plane through the centre), a light on that plane, the points on it up
    to their rounding, each 16 x 16 block's first pixel clearly on the covered side. The outside mask and
    the lights must be the float64 geometry's (the pixel-major store), the values the naive reference's."""
    q, _ = np.linalg.qr(np.random.default_rng(5).normal(size=(3, 3)))
    up = q @ [0.0, 1.0, 0.0]  # the covered side: up . x >= 0
    flat = lat_long_lights(15.0, R, lat_min=0.0, lat_max=90.0)
    lights = flat @ q.T
    ring = np.nonzero(flat[:, 1] == 0.0)[0]
    m = lights[ring[3]] + lights[ring[4]]
    m /= np.linalg.norm(m)
    side = np.cross(up, m)
    light = 0.5 * R * m
    h = 32
    ys, xs = np.mgrid[0:h, 0:h]
    pts = (-0.2 * R + (ys / h - 0.5) * 0.1 * R)[..., None] * m + ((xs / h - 0.5) * 0.2 * R)[..., None] * side
    pts[0::16, 0::16] -= 1e-3 * R * up  # below the plane: the ray through the light leaves above it
    pts = pts.astype(np.float32).astype(np.float64)  # the kernel's float32 points are these exactly
    rng = np.random.default_rng(3)
    imgs = rng.uniform(0.5, 1.0, (len(lights), h, h, 3)).astype(np.float32)
    ds = IlluminationDataset(imgs, lights, np.ones((len(lights), 3)), pts)
    bt = bake_dataset(ds, sphere_center=[0, 0, 0], sphere_radius=R)
    bp = bake_dataset(ds, sphere_center=[0, 0, 0], sphere_radius=R, layout="pixel_major")
    assert bt.layout == "tiled" and bt.report["dtype"] == "float16"
    got = relight(bt, PointLight(light, 1.0))
    _assert_same_relight(got, relight(bp, PointLight(light, 1.0)))
    assert 0.2 < got.n_outside / h ** 2 < 0.8
    assert not got.outside_mask[0::16, 0::16].any()
    want, w_out = naive_relight(bt, [(light, (1.0, 1.0, 1.0))])
    agree = w_out == got.outside_mask  # the naive formula's own rounding decides a few rows on the plane
    assert agree.mean() > 0.97
    np.testing.assert_allclose(got.image[agree], want[agree], rtol=1e-5, atol=1e-9)


def test_float16_bit_decode_matches_numpy():
    """The kernels decode float16 bits without a lookup table, by F16C (hosts that have it) or by
    integer operations: every finite value, subnormals and -0 included, equals numpy's float16 ->
    float32 conversion bit for bit, for both implementations."""
    import numba as nb

    from engine.relighting.kernel import HOST_F16C, half_f16c, half_int

    @nb.njit
    def decode_bits(bits, out):
        for i in range(bits.size):
            out[i] = half_int(bits[i])

    @nb.njit
    def decode_hw(bits, out):
        for i in range(bits.size):
            out[i] = half_f16c(bits[i])

    bits = np.arange(65536, dtype=np.uint16)
    ref = bits.view(np.float16).astype(np.float32)
    finite = np.isfinite(ref)
    for decode in (decode_bits, decode_hw) if HOST_F16C else (decode_bits,):
        out = np.empty(bits.size, np.float32)
        decode(bits, out)
        assert np.array_equal(out[finite].view(np.uint32), ref[finite].view(np.uint32))


def test_error_decreases_with_light_density():
    errs = {}
    lights = [PointLight((1.3, 2.1, 3.7), 1.0), PointLight((-2.9, -1.1, 3.0), 1.0)]
    for spacing in (20.0, 5.0):
        ds, pts, mask = make_ds(spacing, h=32)
        b = bake_dataset(ds, sphere_center=[0, 0, 0])
        gt = sum(lambert_point(pts, mask, lt.position) for lt in lights)
        errs[spacing] = rel_err(relight(b, lights).image, gt, mask)
    assert errs[5.0] < errs[20.0] / 4, errs
    assert errs[5.0] < 0.01, errs


def test_inside_and_far_outside_the_sphere(full20):
    _, b, pts, mask = full20
    for pos in [(0.5, 0.8, 2.0), (0.0, 0.0, 1.5), (300.0, 200.0, 900.0), (1e5, -3e4, 2e5)]:
        r = relight(b, PointLight(pos, 1.0))
        gt = lambert_point(pts, mask, pos)
        assert np.all(np.isfinite(r.image)) and r.n_outside == 0 and r.n_singular == 0
        lit = gt[..., 0] > 0.05 * gt.max()  # away from the terminator
        assert np.abs(r.image - gt)[lit].max() / gt.max() < 0.1, pos


def test_far_side_of_object(full20):
    _, b, pts, mask = full20
    pos = (0.3, 0.4, -4.0)  # behind the sphere, as seen from the camera
    r = relight(b, PointLight(pos, 1.0))
    gt = lambert_point(pts, mask, pos)
    assert r.n_outside == 0 and np.all(np.isfinite(r.image))
    assert np.abs(r.image - gt).max() < 0.1 * lambert_point(pts, mask, (0, 0, 4.0)).max()


def test_light_at_and_near_a_surface_point(full20):
    _, b, pts, mask = full20
    iy, ix = np.argwhere(mask)[len(np.argwhere(mask)) // 2]
    p0 = pts[iy, ix]
    for offset in (0.0, 1e-12):
        r = relight(b, PointLight(p0 + offset, 1.0))
        assert np.all(np.isfinite(r.image))
        assert r.singular_mask[iy, ix] and r.n_singular == 1
        assert np.all(r.image[iy, ix] == 0)
    r = relight(b, PointLight(p0, 1.0), min_light_distance=0.0)  # a zero cutoff still catches d = 0
    assert np.all(np.isfinite(r.image)) and r.n_singular == 1
    with pytest.raises(InvalidInputError, match="directional"):
        relight(b, PointLight((1e200, 0, 0), 1.0))
    # just beyond the cutoff the value is large but finite
    r = relight(b, PointLight(p0 + np.array([0, 0, 1e-3]), 1.0))
    assert r.n_singular == 0 and np.all(np.isfinite(r.image))


def test_directions_outside_coverage_are_masked_and_counted(hemi):
    ds, b, pts, mask = hemi
    assert b.report["n_uncovered_faces"] > 0
    below = relight(b, PointLight((0.0, -4.0, 0.5), 1.0))
    assert below.n_outside == int(mask.sum()) and np.all(below.image == 0)
    assert np.array_equal(below.outside_mask, mask)
    above = relight(b, PointLight((0.5, 3.0, 2.0), 1.0))
    assert above.n_outside == 0
    # a light near the horizon: only some pixels see it inside the covered half
    side = relight(b, PointLight((0.0, 0.2, 4.0), 1.0))
    assert 0 < side.n_outside < mask.sum()
    assert np.all(side.image[side.outside_mask & (side.image[..., 0] > 0)] >= 0)


def test_coverage_threshold_parameter(hemi):
    ds, b, pts, mask = hemi
    strict = bake_dataset(ds, sphere_center=[0, 0, 0], max_face_radius_deg=89.0)
    assert strict.report["n_uncovered_faces"] == b.report["n_uncovered_faces"]  # cover faces are at 90 deg
    assert relight(strict, PointLight((0.0, -4.0, 0.5), 1.0)).n_outside == int(mask.sum())
    for bad in (0.0, 90.0, 120.0):
        with pytest.raises(InvalidInputError, match="max_face_radius_deg"):
            bake_dataset(ds, sphere_center=[0, 0, 0], max_face_radius_deg=bad)


def test_upper_front_quarter_coverage():
    ds, pts, mask = make_ds(10.0, lat_min=0.0, lat_max=80.0, lon_min=0.0, lon_max=180.0)
    b = bake_dataset(ds, sphere_center=[0, 0, 0])
    assert b.report["n_uncovered_faces"] > 0
    assert relight(b, PointLight((0.5, 2.0, 3.0), 1.0)).n_outside == 0
    assert relight(b, PointLight((0.5, 2.0, -3.0), 1.0)).n_outside == int(mask.sum())


# ---------------------------------------------------------------- barycentrics and point location


def test_barycentric_weights(full20):
    _, b, _, _ = full20
    rng = np.random.default_rng(1)
    d = rng.normal(size=(20000, 3))
    tri, w = locate_directions(b, d)
    assert np.all(tri >= 0)
    assert np.all(w >= 0) and np.all(np.abs(w.sum(axis=1) - 1) < 1e-6)
    tri2, w2 = locate_directions(b, d)
    assert np.array_equal(tri, tri2) and np.array_equal(w, w2)
    # the located triangle really contains the direction (no missed candidates)
    v = b.directions[b.triangles[tri]]  # (n, 3, 3)
    recon = np.einsum("ni,nij->nj", w, v)
    cosang = np.einsum("nj,nj->n", recon / np.linalg.norm(recon, axis=1, keepdims=True),
                       d / np.linalg.norm(d, axis=1, keepdims=True))
    assert np.all(cosang > 1 - 1e-9)


def test_vertex_and_edge_hits(full20):
    _, b, _, _ = full20
    tri, w = locate_directions(b, b.directions)
    for k in range(len(b.directions)):
        q = list(b.triangles[tri[k]]).index(k)
        assert abs(w[k, q] - 1) < 1e-9
    t0 = b.triangles[:50]
    mids = b.directions[t0[:, 0]] + b.directions[t0[:, 1]]
    tri, w = locate_directions(b, mids)
    for i in range(50):
        got = dict(zip(b.triangles[tri[i]], w[i], strict=True))
        assert abs(got.get(t0[i, 0], 0) - 0.5) < 1e-9 and abs(got.get(t0[i, 1], 0) - 0.5) < 1e-9
    # a light on an edge and at a vertex, through the whole pipeline, against the naive reference
    small, pts, mask = make_ds(20.0, h=10)
    bs = bake_dataset(small, sphere_center=[0, 0, 0], half=False)
    e = bs.light_positions[bs.triangles[0, 0]] + bs.light_positions[bs.triangles[0, 1]]
    e = e / np.linalg.norm(e) * 7.0
    v = bs.light_positions[bs.triangles[3, 2]] * 1.5
    want, _ = naive_relight(bs, [(e, (1, 1, 1)), (v, (1, 1, 1))])
    got = relight(bs, [PointLight(e, 1.0), PointLight(v, 1.0)]).image
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-9)


# ---------------------------------------------------------------- dataset problems


def test_duplicate_lights_are_removed_and_counted():
    ds, pts, mask = make_ds(30.0)
    lp = ds.light_positions
    near = lp[4] + np.array([1e-7, 0, 0])
    pos = np.concatenate([lp, lp[2:3], near[None]])
    imgs = np.concatenate([ds.images, ds.images[2:3], ds.images[4:5]])
    dup = IlluminationDataset(imgs, pos, np.ones((len(pos), 3)), pts, mask)
    # the same sphere for both bakes (the default radius is the mean distance of the input lights, which
    # the near duplicate changes by 2e-10 relative: a last-bit difference in a few pixels)
    b = bake_dataset(dup, sphere_center=[0, 0, 0], sphere_radius=R)
    assert b.report["n_exact_duplicates"] == 1 and b.report["n_near_duplicates"] == 1
    assert b.report["n_lights"] == len(lp)
    ref = bake_dataset(ds, sphere_center=[0, 0, 0], sphere_radius=R)
    lt = PointLight((1.0, 2.0, 3.0), 1.0)
    assert np.array_equal(relight(b, lt).image, relight(ref, lt).image)


@pytest.mark.parametrize("lights, match", [
    (np.array([[np.cos(a), 0, np.sin(a)] for a in np.linspace(0, 6, 12)]) * R, "great circle"),
    (np.array([[np.cos(a), 0.5, np.sin(a)] for a in np.linspace(0, 6, 12)]) * R, "coplanar"),
    (np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0]]) * R, "great circle"),
    (np.array([[1, 0, 0]] * 5) * R, "distinct"),
])
def test_degenerate_light_sets_give_clear_errors(lights, match):
    pts, mask = sphere_points(8)
    imgs = np.zeros((len(lights), 8, 8, 3), np.float32)
    ds = IlluminationDataset(imgs, lights, np.ones((len(lights), 3)), pts, mask)
    with pytest.raises(InvalidInputError, match=match):
        bake_dataset(ds, sphere_center=[0, 0, 0])


def test_three_lights_make_one_triangle():
    pts, mask = sphere_points(8)
    lights = np.array([[1, 1, 1], [-1, 1, 1], [0, -1, 1.0]]) * 3
    imgs = np.stack([lambert_point(pts, mask, lt) for lt in lights])
    b = bake_dataset(IlluminationDataset(imgs, lights, np.ones((3, 3)), pts, mask), sphere_center=[0, 0, 0])
    assert b.triangles.shape == (1, 3)
    r = relight(b, [PointLight((0, 0, 5.0), 1.0), PointLight((0, 0, -5.0), 1.0)])
    assert r.n_outside == int(mask.sum())  # the back light is outside the single triangle
    assert np.all(np.isfinite(r.image)) and r.image.max() > 0


def test_random_light_sets_never_leak_qhull_errors():
    rng = np.random.default_rng(3)
    pts, mask = sphere_points(6)
    for trial in range(30):
        k = int(rng.integers(3, 9))
        lights = rng.normal(size=(k, 3))
        if trial % 3 == 0:
            lights[:, 2] = 0.0  # coplanar through the centre
        if trial % 5 == 0:
            lights[1:] = lights[0]  # all the same
        lights = lights / np.linalg.norm(lights, axis=1, keepdims=True) * R
        ds = IlluminationDataset(np.zeros((k, 6, 6, 3), np.float32), lights, np.ones((k, 3)), pts, mask)
        try:
            b = bake_dataset(ds, sphere_center=[0, 0, 0])
        except InvalidInputError:
            continue
        assert np.all(np.isfinite(relight(b, PointLight((0, 0, 3.0), 1.0)).image))


def test_validation_names_the_field():
    pts, mask = sphere_points(8)
    imgs = np.zeros((4, 8, 8, 3), np.float32)
    lights = lat_long_lights(90, R)[:4]
    ones = np.ones((4, 3))
    with pytest.raises(InvalidInputError, match=r"images\[2\].*differs"):
        IlluminationDataset([imgs[0], imgs[1], np.zeros((8, 7, 3)), imgs[3]], lights, ones, pts, mask)
    with pytest.raises(InvalidInputError, match="light count 3 does not match image count 4"):
        IlluminationDataset(imgs, lights[:3], ones, pts, mask)
    bad = lights.copy()
    bad[1, 0] = np.nan
    with pytest.raises(InvalidInputError, match=r"light_positions: NaN/Inf in light\(s\) \[1\]"):
        IlluminationDataset(imgs, bad, ones, pts, mask)
    with pytest.raises(InvalidInputError, match="points: .*do not match the image size"):
        IlluminationDataset(imgs, lights, ones, pts[:, :7], mask)
    with pytest.raises(InvalidInputError, match="mask: shape"):
        IlluminationDataset(imgs, lights, ones, pts, mask[:7])
    with pytest.raises(InvalidInputError, match="points: .*NaN/Inf"):
        IlluminationDataset(imgs, lights, ones, pts, None)
    with pytest.raises(InvalidInputError, match="intensities"):
        IlluminationDataset(imgs, lights, -ones, pts, mask)
    cam = CameraParams("orthographic", (0, 0, 5), (0, 0, 0), (0, 1, 0), 8, 8, ortho_height=2.4)
    with pytest.raises(InvalidInputError, match="depth: depth map is 8x9 but the camera is 8x8"):
        points_from_depth(np.ones((8, 9)), cam)
    ds = IlluminationDataset(imgs, lights, ones, pts, mask)
    with pytest.raises(InvalidInputError, match="does not enclose"):
        bake_dataset(ds, sphere_center=[0, 0, 0], sphere_radius=0.5)
    with pytest.raises(InvalidInputError, match="layout"):
        bake_dataset(ds, layout="tiles")
    with pytest.raises(InvalidInputError, match="light type"):
        light_from_dict({"type": "spot"})


# ---------------------------------------------------------------- storage (docs/hard-cases.md #9)


def test_float16_only_where_safe():
    ds, pts, mask = make_ds(45.0, h=12)
    hdr = IlluminationDataset(ds.images * 1e7, ds.light_positions, ds.intensities, ds.points, ds.mask)
    b = bake_dataset(hdr, sphere_center=[0, 0, 0])  # 1e7 > float16 max, but a power-of-two scale fits it
    assert b.report["dtype"] == "float16"
    k = 2
    out = relight(b, PointLight(ds.light_positions[k], 1.0)).image
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(out, hdr.images[k], rtol=2 ** -11)
    # values 1e-8 .. 1 survive float16 thanks to the per-light power-of-two scale
    imgs = ds.images.copy()
    imgs[:, mask] = np.where(imgs[:, mask] > 0, np.clip(imgs[:, mask], 1e-8, None), 0)
    (y0, x0), (y1, x1) = np.argwhere(mask)[:2]
    imgs[:, y0, x0] = 1e-8
    tiny = IlluminationDataset(imgs, ds.light_positions, ds.intensities, ds.points, ds.mask)
    b = bake_dataset(tiny, sphere_center=[0, 0, 0])
    assert b.report["dtype"] == "float16"
    out = relight(b, PointLight(ds.light_positions[k], 1.0)).image
    np.testing.assert_allclose(out[mask], imgs[k][mask], rtol=2 ** -10)
    # 1e-8 next to 1e6 in one light: float32
    imgs[:, y1, x1] = 1e6
    mixed = IlluminationDataset(imgs, ds.light_positions, ds.intensities, ds.points, ds.mask)
    b = bake_dataset(mixed, sphere_center=[0, 0, 0])
    assert b.report["dtype"] == "float32" and "1e-08" in b.report["dtype_reason"]
    assert np.array_equal(relight(b, PointLight(ds.light_positions[k], 1.0)).image, imgs[k])
    # the knob: values below 1e-8 x the light's max (here 1e-2) may lose precision -> float16 again
    assert bake_dataset(mixed, sphere_center=[0, 0, 0], half_rel_floor=1e-8).report["dtype"] == "float16"


# ---------------------------------------------------------------- light kinds, geometry, scale


def test_rect_and_environment_lights(full20):
    _, b, pts, mask = full20
    tiny = RectLight(corner=(0.99, 1.99, 3.99), edge_u=(0.02, 0, 0), edge_v=(0, 0.02, 0), radiance=1.0 / 4e-4,
                     samples=4)  # area 4e-4, facing -z: away from the sphere
    assert relight(b, tiny).image.max() == 0
    tiny2 = RectLight(corner=(0.99, 1.99, 3.99), edge_u=(0, 0.02, 0), edge_v=(0.02, 0, 0), radiance=1.0 / 4e-4,
                      samples=4)  # normal -z: facing the sphere
    two = RectLight(corner=(0.99, 1.99, 3.99), edge_u=(0.02, 0, 0), edge_v=(0, 0.02, 0), radiance=1.0 / 4e-4,
                    samples=4, two_sided=True)
    pt = relight(b, PointLight((1.0, 2.0, 3.99), 1.0)).image
    lit = pt[..., 0] > 0.1 * pt.max()
    for rl in (tiny2, two):
        img = relight(b, rl).image
        # intensity L A cos(theta_emitter): close to a point light with I = cos(theta) ~ 0.9
        ratio = img[lit, 0] / pt[lit, 0]
        assert 0.6 < ratio.min() and ratio.max() <= 1.0 + 1e-5
    env = np.ones((16, 32, 3), np.float32)
    for method, n in (("downsample", 64), ("importance", 256)):
        img = relight(b, EnvironmentLight(env, n_lights=n, method=method, seed=2)).image
        # uniform radiance L=1 on an unoccluded convex Lambertian surface: albedo x L
        assert abs(np.median(img[mask, 1]) - ALBEDO) < 0.08 * ALBEDO, method
    a = relight(b, light_from_dict({"type": "environment", "image": env, "n_lights": 32, "method": "importance",
                                    "seed": 5})).image
    c = relight(b, EnvironmentLight(env, n_lights=32, method="importance", seed=5)).image
    assert np.array_equal(a, c)


def test_distant_dataset():
    pts, mask = sphere_points(24)
    toward = lat_long_lights(15.0, 1.0, lat_min=-90, lat_max=90)
    e = np.full((len(toward), 3), 2.0)
    imgs = np.stack([lambert_directional(pts, mask, t, 2.0) for t in toward])
    b = bake_dataset(IlluminationDataset(imgs, toward * 3.0, e, pts, mask, distant=True))
    assert b.distant
    t = np.array([0.2, 0.4, 0.9])
    r = relight(b, DirectionalLight(-t, 1.0))
    assert rel_err(r.image, lambert_directional(pts, mask, t), mask) < 0.03
    k = 11
    ex = relight(b, DirectionalLight(-b.light_positions[k], 2.0))
    assert ex.exact and np.array_equal(ex.image, imgs[b.kept_from[k]])
    ex = relight(b, DirectionalLight(-3.7 * toward[k], 2.0))  # renormalised: may differ in the last bit
    assert ex.exact


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_scale_invariance(scale):
    ds, pts, mask = make_ds(30.0, h=12)
    # jitter the lights: a lat-long grid has cocircular quads whose diagonal Qhull picks by rounding
    lp = ds.light_positions + np.random.default_rng(0).normal(scale=0.05, size=ds.light_positions.shape)
    ds = IlluminationDataset(np.stack([lambert_point(pts, mask, p) for p in lp]), lp, ds.intensities, pts, mask)
    s = IlluminationDataset(ds.images, ds.light_positions * scale, ds.intensities * scale ** 2,
                            ds.points * scale, ds.mask)
    b0 = bake_dataset(ds, sphere_center=[0, 0, 0])
    b1 = bake_dataset(s, sphere_center=[0, 0, 0])
    lt = np.array([0.7, 1.9, 3.1])
    np.testing.assert_allclose(relight(b1, PointLight(lt * scale, scale ** 2)).image,
                               relight(b0, PointLight(lt, 1.0)).image, rtol=1e-4, atol=1e-9)


def test_points_from_depth_cameras():
    ortho = CameraParams("orthographic", (0, 0, 5), (0, 0, 0), (0, 1, 0), 6, 4, ortho_height=2.0)
    p, ok = points_from_depth(np.full((4, 6), 5.0), ortho)
    assert ok.all() and np.allclose(p[..., 2], 0.0)
    persp = CameraParams("perspective", (0, 0, 5), (0, 0, 0), (0, 1, 0), 6, 4, fov_y_deg=40)
    p, _ = points_from_depth(np.full((4, 6), 5.0), persp, depth_kind="z")
    assert np.allclose(p[..., 2], 0.0)
    pd, _ = points_from_depth(np.full((4, 6), 5.0), persp, depth_kind="distance")
    assert np.allclose(np.linalg.norm(pd - np.array([0, 0, 5.0]), axis=-1), 5.0)
    k = np.array([[10.0, 0, 3.0], [0, 10.0, 2.0], [0, 0, 1]])
    depth = np.full((4, 6), 2.0)
    depth[0, 0] = np.nan
    depth[1, 1] = -1
    p, ok = points_from_depth(depth, intrinsics=k, world_from_camera=np.eye(4))
    assert not ok[0, 0] and not ok[1, 1] and ok.sum() == 22
    assert np.allclose(p[ok][:, 2], 2.0)
    np.testing.assert_allclose(p[2, 3], [(3.5 - 3.0) / 10 * 2, (2.5 - 2.0) / 10 * 2, 2.0])


def test_scene_far_from_the_origin():
    """The kernel keeps the surface points as float32 offsets from the sphere centre (distant dataset: the
    points' bounding-box centre): a dataset translated far from the origin relights like the original
    (float32 world coordinates at 1e4 would be off by ~1e-3, i.e. relative errors ~1e-3)."""
    ds, pts, mask = make_ds(20.0, h=24)
    shift = np.array([1e4, -3e3, 7e3])
    moved = IlluminationDataset(ds.images, ds.light_positions + shift, ds.intensities, pts + shift, mask)
    b0 = bake_dataset(ds, sphere_center=[0, 0, 0], sphere_radius=R, half=False)
    b1 = bake_dataset(moved, sphere_center=shift, sphere_radius=R, half=False)
    lt = np.array([1.0, 2.0, 3.5])
    a, c = relight(b0, PointLight(lt, 1.0)), relight(b1, PointLight(lt + shift, 1.0))
    np.testing.assert_allclose(c.image, a.image, rtol=1e-5, atol=1e-9)
    assert np.array_equal(c.outside_mask, a.outside_mask)
    # a distant dataset far from the origin, against the per-pixel reference
    toward = lat_long_lights(20.0, 1.0)
    imgs = np.stack([lambert_directional(pts, mask, t) for t in toward])
    dd = IlluminationDataset(imgs, toward, np.ones((len(toward), 3)), pts + shift, mask, distant=True)
    bd = bake_dataset(dd, half=False)
    near = shift + np.array([0.5, 1.5, 3.0])
    got = relight(bd, [PointLight(near, 2.0), DirectionalLight((-0.2, -0.9, -0.4), 0.5)])
    want, w_out = naive_relight(bd, [(near, (2.0, 2.0, 2.0))], [((0.2, 0.9, 0.4), (0.5, 0.5, 0.5))])
    np.testing.assert_allclose(got.image, want, rtol=1e-5, atol=1e-9)
    assert np.array_equal(got.outside_mask, w_out)


def test_aligned_output_runs_match_naive():
    """A frame whose rows are multiples of 16 pixels: the kernel writes each 16-pixel block row with
    non-temporal vector stores (64-byte aligned image); values against the per-pixel reference,
    pixels without a surface point exactly 0."""
    ds, pts, mask = make_ds(20.0, h=64)
    b = bake_dataset(ds, sphere_center=[0, 0, 0], half=False)
    geom = b.kernel_geometry
    # a round mask: 16-row groups that are whole block rows (written as vector runs) and others
    assert 0 < geom.runs.mean() < 1
    pl = [((1.0, 2.0, 3.5), (1.0, 0.5, 2.0))]
    got = relight(b, [PointLight(p, i) for p, i in pl])
    assert got.image.ctypes.data % 64 == 0
    rows = np.arange(0, b.pixel_index.size, 7)
    want, _ = naive_relight(b, pl, rows=rows)
    sel = b.pixel_index[rows]
    np.testing.assert_allclose(got.image.reshape(-1, 3)[sel], want.reshape(-1, 3)[sel], rtol=1e-5, atol=1e-9)
    assert np.all(got.image[~mask] == 0)
    pm = bake_dataset(ds, sphere_center=[0, 0, 0], half=False, layout="pixel_major")
    _assert_same_relight(got, relight(pm, PointLight(*pl[0])))


def _assert_same_relight(a, b, tol=1e-6):
    """A tiled store's point lights take the float32 geometry (pass A and the cone test in float32, the
    border rows in float64), a pixel-major store the float64 one: the images agree to ``tol`` of their
    maximum, the masks and the lights read exactly."""
    assert np.max(np.abs(a.image.astype(np.float64) - b.image)) <= tol * np.max(np.abs(b.image))
    assert np.array_equal(a.outside_mask, b.outside_mask) and np.array_equal(a.singular_mask, b.singular_mask)
    assert np.array_equal(a.lights_used, b.lights_used)


def test_serial_kernel_and_threads_agree(full20):
    _, b, _, _ = full20
    lt = [PointLight((1.0, 2.0, 3.5), 1.0), DirectionalLight((0, 0, -1), 1.0)]
    a = relight(b, lt).image
    assert np.array_equal(a, relight(b, lt, serial=True).image)
    assert np.array_equal(a, relight(b, lt, threads=1).image)


# ---------------------------------------------------------------- end to end with the reference renderer


def test_reference_rendered_dataset_with_cast_shadows():
    """A sphere on a floor rendered by engine.reference under 53 lights on the upper cap (a partly
    covered sphere), points from the renderer's depth map; novel light vs a ground-truth render."""
    from engine.reference import ReferenceParams, render_reference
    from tests.engine.scenes import mat, quad, scene, sphere_mesh

    cam = CameraParams("perspective", (0, 3.0, 3.0), (0, 0.3, 0), (0, 1, 0), 24, 24, fov_y_deg=40)
    centre = np.array([0, 0.3, 0])
    lights = lat_long_lights(20.0, 6.0, lat_min=10.0, lat_max=90.0) + centre
    parts = [(sphere_mesh((0, 0.5, 0), 0.5, subdivisions=3), mat(kd=(0.6, 0.6, 0.6))),
             (quad((0, 0, 0), 3.0), mat(name="floor", kd=(0.5, 0.4, 0.3)))]

    def render(pos):
        sc = scene(parts, [dict(type="point", position=tuple(pos), intensity=(30.0, 30.0, 30.0))])
        return render_reference(sc, cam, ReferenceParams(spp=1))

    outs = [render(p) for p in lights]
    pts, valid = points_from_depth(outs[0].depth, cam, depth_kind="distance")
    mask = valid & outs[0].coverage
    ds = IlluminationDataset(np.stack([o.radiance for o in outs]), lights, np.full((len(lights), 3), 30.0), pts,
                             mask)
    b = bake_dataset(ds, sphere_center=centre, sphere_radius=6.0, half=False)
    assert b.report["n_uncovered_faces"] > 0
    assert np.array_equal(relight(b, PointLight(lights[7], 30.0)).image[mask], outs[7].radiance[mask])
    novel = centre + np.array([1.7, 3.9, 2.3])
    gt = render(novel).radiance
    got = relight(b, PointLight(novel, 30.0))
    assert got.n_outside == 0 and got.n_singular == 0
    err = rel_err(got.image, gt, mask)
    print(f"reference scene: mean abs error / mean = {err:.4f}")
    assert err < 0.1
    # the cast shadow on the floor is reproduced: dark where the ground truth is dark
    floor = mask & (np.abs(pts[..., 1]) < 1e-3)
    lum = gt[..., 1]
    shadow = floor & (lum < 0.2 * np.median(lum[floor]))
    lit = floor & (lum > 0.8 * np.median(lum[floor]))
    assert shadow.sum() >= 3
    assert got.image[shadow, 1].mean() < 0.5 * got.image[lit, 1].mean()


def test_store_layout_and_half_rounding_match_numpy():
    ds, pts, mask = make_ds(30.0, h=16)
    imgs = ds.images * np.float32(3.7)
    imgs[:, mask] += np.random.default_rng(4).random(imgs[:, mask].shape).astype(np.float32) * 1e-3
    ds = IlluminationDataset(imgs, ds.light_positions, ds.intensities, pts, mask)
    b = bake_dataset(ds, sphere_center=[0, 0, 0], half=True, layout="pixel_major")
    assert b.report["dtype"] == "float16" and b.report["layout"] == "pixel_major"
    assert bake_dataset(ds, sphere_center=[0, 0, 0]).layout == "tiled"  # the default (faster to gather)
    flat = imgs.reshape(len(imgs), -1, 3)[b.kept_from][:, b.pixel_index]  # (K, n, 3)
    want = (flat * b.store_scale[:, None, None].astype(np.float32)).astype(np.float16).transpose(1, 0, 2)
    assert np.array_equal(b.store.view(np.uint16), want.view(np.uint16))
    b32 = bake_dataset(ds, sphere_center=[0, 0, 0], half=False, layout="pixel_major")
    assert np.array_equal(b32.store, flat.transpose(1, 0, 2))
    # stored pixels: every masked pixel once, in 16 x 16 image blocks
    assert np.array_equal(np.sort(b.pixel_index), np.nonzero(mask.ravel())[0])
    assert np.array_equal(b.points, pts.reshape(-1, 3)[b.pixel_index])


@pytest.mark.parametrize("half", [True, False])
def test_tiled_layout_equals_pixel_major(full20, half):
    ds, _, _, mask = full20
    bp = bake_dataset(ds, sphere_center=[0, 0, 0], half=half)
    bt = bake_dataset(ds, sphere_center=[0, 0, 0], half=half, layout="tiled")
    assert bt.store.shape[2] == 256 and bt.store.shape[0] == -(-int(mask.sum()) // 256)
    for k in (0, 5, len(bp.light_positions) - 1):
        assert np.array_equal(bt.light_values(k), bp.light_values(k))
    lights = [PointLight((1.0, 2.0, 3.5), 1.0), DirectionalLight((0.3, -0.2, -1.0), 0.5)]
    _assert_same_relight(relight(bt, lights), relight(bp, lights))
    assert np.array_equal(relight(bt, PointLight(ds.light_positions[4], 1.0)).image,
                          relight(bp, PointLight(ds.light_positions[4], 1.0)).image)
