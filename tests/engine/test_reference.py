"""Reference renderer against closed-form answers, and HARD_CASES 7, 8, 12, 13."""

from __future__ import annotations

import math

import numpy as np
import pytest

from engine.errors import InvalidInputError, NonFiniteOutputError
from engine.geometry.mesh import TriMesh
from engine.reference import ReferenceParams, render_reference
from engine.scene import CameraParams
from tests.engine.scenes import mat, quad, scene, sphere_mesh

DOWN = CameraParams("orthographic", (0, 5, 0), (0, 0, 0), (0, 0, -1), 16, 16, ortho_height=1.0)


def test_directional_light_on_diffuse_plane_is_exact():
    kd = (0.2, 0.5, 0.8)
    E = np.array([1.0, 2.0, 3.0])
    d = np.array([0.3, -1.0, 0.2])
    sc = scene([(quad((0, 0, 0), 4.0), mat(kd=kd))],
               [dict(type="directional", direction=tuple(d), irradiance=tuple(E))])
    out = render_reference(sc, DOWN, ReferenceParams(spp=1))
    cos = 1.0 / np.linalg.norm(d)
    want = np.array(kd) / math.pi * E * cos
    np.testing.assert_allclose(out.radiance.reshape(-1, 3), np.tile(want, (256, 1)), rtol=1e-5)
    assert out.coverage.all()
    np.testing.assert_allclose(out.depth, 5.0, rtol=1e-6)
    np.testing.assert_allclose(out.normal[..., 1], 1.0, rtol=1e-6)


def test_point_light_inverse_square_and_cosine():
    I, h = 7.0, 0.8
    cam = CameraParams("orthographic", (0, 5, 0), (0, 0, 0), (0, 0, -1), 64, 64, ortho_height=2.0)
    sc = scene([(quad((0, 0, 0), 4.0), mat(kd=(1, 1, 1)))],
               [dict(type="point", position=(0.0, h, 0.0), intensity=(I, I, I))])
    out = render_reference(sc, cam, ReferenceParams(spp=16))
    # analytic radiance averaged over each pixel footprint (8x8 sub-samples)
    px = (np.arange(64 * 8) + 0.5) / (64 * 8) * 2.0 - 1.0
    X, Z = np.meshgrid(px, px)
    d2 = X ** 2 + Z ** 2 + h ** 2
    L = I / math.pi * h / d2 ** 1.5
    want = L.reshape(64, 8, 64, 8).mean(axis=(1, 3))
    np.testing.assert_allclose(out.radiance[..., 0], want, rtol=5e-3)


def test_unjittered_samples_are_stratum_centres():
    """pixel_jitter=False: one sample is the pixel centre exactly (the point-sampled image the
    image-based methods make); 4 spp are the centres of the 2 x 2 strata; the seed plays no part."""
    I, h = 7.0, 0.8
    cam = CameraParams("orthographic", (0, 5, 0), (0, 0, 0), (0, 0, -1), 16, 16, ortho_height=2.0)
    sc = scene([(quad((0, 0, 0), 4.0), mat(kd=(1, 1, 1)))],
               [dict(type="point", position=(0.0, h, 0.0), intensity=(I, I, I))])

    def analytic(sub):
        px = (np.arange(16 * sub) + 0.5) / (16 * sub) * 2.0 - 1.0
        X, Z = np.meshgrid(px, px)
        L = I / math.pi * h / (X ** 2 + Z ** 2 + h ** 2) ** 1.5
        return L.reshape(16, sub, 16, sub).mean(axis=(1, 3))

    one = render_reference(sc, cam, ReferenceParams(spp=1, pixel_jitter=False, seed=1))
    np.testing.assert_allclose(one.radiance[..., 0], analytic(1), rtol=5e-5)  # float32 ray origins
    assert np.array_equal(one.radiance, render_reference(sc, cam, ReferenceParams(spp=1, pixel_jitter=False,
                                                                                    seed=9)).radiance)
    four = render_reference(sc, cam, ReferenceParams(spp=4, pixel_jitter=False))
    np.testing.assert_allclose(four.radiance[..., 0], analytic(2), rtol=5e-5)
    jittered = render_reference(sc, cam, ReferenceParams(spp=1))
    assert not np.allclose(jittered.radiance, one.radiance, rtol=1e-5)
    with pytest.raises(InvalidInputError, match="pixel_jitter"):
        ReferenceParams(pixel_jitter="no")


# 4 x 4 pixels of 1 x 1 world units looking down -y: pixel (row r, column c) covers
# x in [c - 2, c - 1], z in [r - 2, r - 1]; a pixel's top is its smallest z, its left its smallest x.
EDGE_CAM = CameraParams("orthographic", (0, 5, 0), (0, 0, 0), (0, 0, -1), 4, 4, ortho_height=4.0)
EDGE_SPP = [*range(1, 65), 128, 512]


def _half_plane(axis: str, h: float):
    """A floor of radiance exactly 1 (kd 1, irradiance pi from straight above) over x < -2 + h
    (axis "x": the left fraction h of column 0) or z < -2 + h (axis "z": the top fraction h of
    row 0), nothing elsewhere: a pixel's value is the fraction of its samples on the floor.
    The floor reaches just past the image, so the scene's centre (the origin of Embree's float32
    frame) is near the edge and a sample is told from it to ~1e-7 of a pixel."""
    e = -2.0 + h
    xe, ze = (e, 2.5) if axis == "x" else (2.5, e)
    v = np.array([[-2.5, 0.0, -2.5], [xe, 0.0, -2.5], [xe, 0.0, ze], [-2.5, 0.0, ze]])
    mesh = TriMesh(v, np.array([[0, 1, 2], [0, 2, 3]], np.int32), np.tile([0.0, 1.0, 0.0], (4, 1)))
    return scene([(mesh, mat(kd=(1, 1, 1)))],
                 [dict(type="directional", direction=(0.0, -1.0, 0.0), irradiance=(math.pi,) * 3)])


def _edge_pixels(img: np.ndarray, axis: str) -> np.ndarray:
    return img[:, 0, 0] if axis == "x" else img[0, :, 0]


@pytest.mark.parametrize("axis", ["z", "x"])
def test_every_spp_covers_each_pixel_evenly(axis):
    """Whatever spp, half of every pixel's samples fall in its top (left) half: exactly for even
    spp, within one sample for odd spp (a stratified pattern, not one that leaves part of a row
    of its grid empty)."""
    sc = _half_plane(axis, 0.5)
    for spp in EDGE_SPP:
        img = render_reference(sc, EDGE_CAM, ReferenceParams(spp=spp, seed=spp)).radiance
        frac = _edge_pixels(img, axis)
        tol = (0.5 if spp % 2 else 0.0) / spp + 1e-6
        assert np.all(np.abs(frac - 0.5) <= tol), (spp, frac)
        rest = img[:, 1:, 0] if axis == "x" else img[1:, :, 0]
        assert rest.max() == 0.0


@pytest.mark.parametrize("spp", [2, 3, 8, 32, 128])
@pytest.mark.parametrize("axis", ["z", "x"])
def test_edge_pixel_mean_over_seeds_is_its_coverage(spp, axis):
    """A pixel crossed by an edge at 0.3 of its height (width) averages to coverage 0.3 over
    seeds: the samples are uniform over the pixel (their mean position is its centre)."""
    h = 0.3
    sc = _half_plane(axis, h)
    vals = np.array([_edge_pixels(render_reference(sc, EDGE_CAM, ReferenceParams(spp=spp, seed=s)).radiance,
                                  axis) for s in range(64)], np.float64)
    se = vals.std(ddof=1) / math.sqrt(vals.size)
    assert abs(vals.mean() - h) <= 4.0 * se + 1e-5, (vals.mean(), se)


def test_unjittered_cells_tile_the_pixel_for_every_spp():
    """pixel_jitter=False: spp equal-area cells in rows; their centres average to the pixel
    centre for every spp (the g x g grid's centres for squares)."""
    from engine.reference import _cell_centre

    for spp in range(1, 700):
        gx = math.ceil(math.sqrt(spp))
        c = np.array([_cell_centre(j, spp, gx) for j in range(spp)])
        np.testing.assert_allclose(c.mean(axis=0), 0.5, atol=1e-12)
        assert c.min() > 0 and c.max() < 1 and np.unique(c, axis=0).shape[0] == spp
        rows, counts = np.unique(c[:, 1], return_counts=True)
        assert counts.max() - counts.min() <= 1 and counts.max() <= gx
        # each row is as tall as its share of the cells: every cell has area 1 / spp
        edges = np.concatenate([[0.0], np.cumsum(counts) / spp])
        np.testing.assert_allclose(rows, 0.5 * (edges[:-1] + edges[1:]), atol=1e-12)
        if gx * gx == spp:
            g = (np.arange(gx) + 0.5) / gx
            np.testing.assert_allclose(np.sort(c[:, 0]), np.sort(np.tile(g, gx)), atol=1e-12)


def _corner_factor(a, b, c):
    """Form factor from a point to an a x b rectangle above one corner at height c (parallel)."""
    A, B = a / math.hypot(a, c), b / math.hypot(b, c)
    return (A * math.atan(b / math.hypot(a, c)) + B * math.atan(a / math.hypot(b, c))) / (2 * math.pi)


@pytest.mark.parametrize("two_sided", [False, True])
def test_rect_light_matches_form_factor(two_sided):
    Le, a, b, h = 3.0, 1.0, 0.6, 0.5
    # the camera looks down from under the light (camera rays that meet a light's emitting side show it)
    cam = CameraParams("orthographic", (0, 0.25, 0), (0, 0, 0), (0, 0, -1), 8, 8, ortho_height=0.01)
    # edges chosen so cross(edge_u, edge_v) points down (-y): the light faces the floor
    light = dict(type="rect", corner=(-a / 2, h, -b / 2), edge_u=(a, 0.0, 0.0), edge_v=(0.0, 0.0, b),
                 radiance=(Le, Le, Le), two_sided=two_sided)
    sc = scene([(quad((0, 0, 0), 4.0), mat(kd=(1, 1, 1)))], [light])
    out = render_reference(sc, cam, ReferenceParams(spp=16, area_light_samples=64))
    E = math.pi * Le * 4 * _corner_factor(a / 2, b / 2, h)
    assert out.radiance[..., 0].mean() == pytest.approx(E / math.pi, rel=1e-2)
    # the back of a one-sided light emits nothing
    flipped = dict(light, edge_u=light["edge_v"], edge_v=light["edge_u"])
    sc2 = scene([(quad((0, 0, 0), 4.0), mat(kd=(1, 1, 1)))], [flipped])
    out2 = render_reference(sc2, cam, ReferenceParams(spp=4, area_light_samples=16))
    if two_sided:
        assert out2.radiance.mean() > 0
    else:
        assert out2.radiance.max() == 0.0


@pytest.mark.parametrize("n", [1.0, 50.0, 1e4, 1e6])
def test_phong_peak_is_normalised_for_any_exponent(n):
    """HARD_CASES 8: peak = ks (n+2)/(2 pi) E, finite even for n = 1e6."""
    sc = scene([(quad((0, 0, 0), 4.0), mat(kd=(0, 0, 0), ks=(1, 1, 1), shininess=n))],
               [dict(type="directional", direction=(0.0, -1.0, 0.0), irradiance=(1.0, 1.0, 1.0))])
    out = render_reference(sc, DOWN, ReferenceParams(spp=1))
    assert np.all(np.isfinite(out.radiance))
    np.testing.assert_allclose(out.radiance, (n + 2) / (2 * math.pi), rtol=1e-5)
    # tilted light: far off the lobe the highlight vanishes without NaN
    sc2 = scene([(quad((0, 0, 0), 4.0), mat(kd=(0, 0, 0), ks=(1, 1, 1), shininess=n))],
                [dict(type="directional", direction=(1.0, -1.0, 0.0), irradiance=(1.0, 1.0, 1.0))])
    out2 = render_reference(sc2, DOWN, ReferenceParams(spp=1))
    assert np.all(np.isfinite(out2.radiance))
    expect = (n + 2) / (2 * math.pi) * math.cos(math.pi / 4) ** n * math.cos(math.pi / 4)
    np.testing.assert_allclose(out2.radiance, expect, rtol=1e-5, atol=1e-300)


def _mirror_setup(**floor):
    """A lit diffuse wall seen in a reflecting floor."""
    wall = quad((0.0, 0.0, -1.0), 20.0, normal_axis=2)
    floor_mesh = quad((0.0, -0.5, 0.0), 20.0)
    lights = [dict(type="directional", direction=(0.0, 0.0, -1.0), irradiance=(2.0, 2.0, 2.0))]
    return scene([(wall, mat("w", kd=(0.8, 0.4, 0.2))), (floor_mesh, mat("f", kd=(0, 0, 0), **floor))],
                 lights)


def test_glossy_with_huge_exponent_converges_to_mirror():
    cam = CameraParams("perspective", (0.0, 0.0, 2.0), (0.0, -0.5, 0.0), (0, 1, 0), 24, 24, fov_y_deg=20)
    mirror = render_reference(_mirror_setup(kr=(0.9, 0.9, 0.9)), cam, ReferenceParams(spp=1))
    glossy = render_reference(_mirror_setup(kg=(0.9, 0.9, 0.9), gloss_exponent=1e6), cam,
                              ReferenceParams(spp=1, glossy_samples=4))
    assert np.all(np.isfinite(glossy.radiance))
    floor_px = mirror.object_id == 1
    assert floor_px.sum() > 50
    # glossy weight carries cos(theta_i); the ideal mirror doesn't (ALGORITHMS.md material model)
    d = glossy.radiance[floor_px] / np.maximum(mirror.radiance[floor_px], 1e-12)
    assert np.all(d > 0.1) and np.all(d <= 1.0 + 1e-3)


def test_mirror_facing_mirror_stops_at_depth_and_stays_bounded():
    """HARD_CASES 7: two parallel mirrors; energy grows with depth but never past the limit."""
    kr = 0.8
    m = mat("mir", kd=(0.1, 0.1, 0.1), kr=(kr, kr, kr))
    a = quad((0.0, 0.0, -1.0), 50.0, normal_axis=2)
    b = quad((0.0, 0.0, 1.0), 50.0, normal_axis=2, flip=True)
    lights = [dict(type="point", position=(0.0, 0.0, 0.0), intensity=(1.0, 1.0, 1.0))]
    sc = scene([(a, m), (b, m)], lights)
    cam = CameraParams("perspective", (0.0, 0.3, 0.5), (0.2, 0.3, -1.0), (0, 1, 0), 8, 8, fov_y_deg=30)
    prev = None
    l0 = None
    for depth in (0, 1, 2, 4, 8, 16):
        out = render_reference(sc, cam, ReferenceParams(spp=1, max_depth=depth))
        assert np.all(np.isfinite(out.radiance))
        assert out.counts["reflection"] <= depth * 64
        if l0 is None:
            l0 = out.radiance.max()
        if prev is not None:
            assert np.all(out.radiance >= prev - 1e-7)
        # every bounce picks up at most kr^k of the brightest directly lit radiance
        assert out.radiance.max() <= l0 / (1 - kr) + 1e-6
        prev = out.radiance


def test_empty_scene_is_background():
    sc = scene([], background=(0.1, 0.2, 0.3))
    out = render_reference(sc, DOWN, ReferenceParams(spp=2))
    np.testing.assert_allclose(out.radiance.reshape(-1, 3), np.tile([0.1, 0.2, 0.3], (256, 1)), rtol=1e-6)
    assert not out.coverage.any()
    assert (out.depth == 0).all()


def test_no_lights_gives_ambient_only_and_zero_light_gives_black():
    sc = scene([(quad((0, 0, 0), 4.0), mat(kd=(0.5, 0.25, 1.0)))], [], ambient=(0.2, 0.2, 0.2))
    out = render_reference(sc, DOWN, ReferenceParams(spp=1, indirect_samples=2))
    np.testing.assert_allclose(out.radiance[..., 0], 0.1, rtol=1e-6)
    np.testing.assert_allclose(out.radiance[..., 2], 0.2, rtol=1e-6)
    sc0 = scene([(quad((0, 0, 0), 4.0), mat())], [dict(type="point", position=(0, 1, 0), intensity=(0, 0, 0))])
    assert render_reference(sc0, DOWN, ReferenceParams(spp=1)).radiance.max() == 0.0


def test_non_finite_result_fails_the_render():
    """HARD_CASES 13: an overflowing light makes the render fail loudly, never an Inf image."""
    sc = scene([(quad((0, 0, 0), 4.0), mat(kd=(1, 1, 1)))],
               [dict(type="point", position=(0, 1e-3, 0), intensity=(1e307, 1e307, 1e307))])
    with pytest.raises(NonFiniteOutputError):
        render_reference(sc, DOWN, ReferenceParams(spp=1))


def test_deterministic_for_a_seed():
    lights = [dict(type="rect", corner=(-0.5, 1.0, -0.5), edge_u=(1.0, 0, 0), edge_v=(0, 0, 1.0),
                   radiance=(2, 2, 2))]
    sc = scene([(quad((0, 0, 0), 4.0), mat()), (sphere_mesh((0, 0.3, 0), 0.2, 2), mat())], lights)
    p = ReferenceParams(spp=2, area_light_samples=4, indirect_samples=2, seed=3)
    a = render_reference(sc, DOWN, p).radiance
    b = render_reference(sc, DOWN, p).radiance
    c = render_reference(sc, DOWN, ReferenceParams(spp=2, area_light_samples=4, indirect_samples=2, seed=4))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c.radiance)


def test_embree_and_reference_backends_render_the_same_image():
    lights = [dict(type="point", position=(1.0, 2.0, 1.0), intensity=(3, 3, 3))]
    sc = scene([(quad((0, 0, 0), 4.0), mat(kr=(0.3, 0.3, 0.3))),
                (sphere_mesh((0, 0.3, 0), 0.3, 2), mat("s", kd=(0.6, 0.2, 0.2), ks=(0.3, 0.3, 0.3),
                                                        shininess=20))], lights)
    cam = CameraParams("perspective", (0, 1, 2), (0, 0.2, 0), (0, 1, 0), 12, 12, fov_y_deg=40)
    p = ReferenceParams(spp=1)
    a = render_reference(sc, cam, p, backend="embree")
    b = render_reference(sc, cam, p, backend="reference")
    np.testing.assert_allclose(a.radiance, b.radiance, rtol=1e-4, atol=1e-6)
    assert np.array_equal(a.object_id, b.object_id)


@pytest.mark.parametrize("bounces", [1, 3])
def test_indirect_light_inside_a_sphere_matches_the_series(bounces):
    """Inside a closed diffuse sphere of albedo a with a point light at its centre, every
    bounce adds a^k of the direct radiance: L_B = a/pi * I/R^2 * sum_{k=0..B} a^k."""
    a, I, R = 0.5, 1.0, 1.0
    sc = scene([(sphere_mesh(radius=R, subdivisions=5), mat(kd=(a, a, a)))],
               [dict(type="point", position=(0, 0, 0), intensity=(I, I, I))])
    cam = CameraParams("perspective", (0, 0, 0.2), (0, 0, -1), (0, 1, 0), 8, 8, fov_y_deg=60)
    out = render_reference(sc, cam, ReferenceParams(spp=4, indirect_samples=256, indirect_bounces=bounces))
    want = a / math.pi * I / R ** 2 * sum(a ** k for k in range(bounces + 1))
    assert out.radiance.mean() == pytest.approx(want, rel=0.02)


def test_image_does_not_depend_on_pipelines():
    lights = [dict(type="rect", corner=(-0.5, 1.0, -0.5), edge_u=(1.0, 0, 0), edge_v=(0, 0, 1.0),
                   radiance=(2, 2, 2))]
    sc = scene([(quad((0, 0, 0), 4.0), mat(kg=(0.3, 0.3, 0.3), gloss_exponent=20)),
                (sphere_mesh((0, 0.3, 0), 0.2, 2), mat("s", kr=(0.5, 0.5, 0.5), kd=(0.3, 0.3, 0.3)))], lights)
    cam = CameraParams("perspective", (0, 1, 2), (0, 0.2, 0), (0, 1, 0), 64, 48, fov_y_deg=40)
    imgs = [render_reference(sc, cam, ReferenceParams(spp=2, area_light_samples=4, indirect_samples=2,
                                                      glossy_samples=4, pipelines=k)).radiance
            for k in (1, 2, 3)]
    assert np.array_equal(imgs[0], imgs[1]) and np.array_equal(imgs[0], imgs[2])


def test_progress_is_reported_and_cancellation_stops_the_render():
    sc = scene([(quad((0, 0, 0), 4.0), mat())], [dict(type="point", position=(0, 1, 0), intensity=(1, 1, 1))])
    cam = CameraParams("perspective", (0, 1, 2), (0, 0, 0), (0, 1, 0), 128, 128, fov_y_deg=40)
    seen = []
    render_reference(sc, cam, ReferenceParams(spp=1), progress=lambda f, s: seen.append(f))
    assert seen[-1] == 1.0 and all(a <= b for a, b in zip(seen, seen[1:], strict=False)) and len(seen) >= 8

    class Cancelled(Exception):
        pass

    def cancel(frac, stage):
        if frac > 0.2:
            raise Cancelled

    for pipelines in (1, 2):
        with pytest.raises(Cancelled):
            render_reference(sc, cam, ReferenceParams(spp=1, pipelines=pipelines), progress=cancel)


def test_the_glossy_rays_of_a_first_bounce_share_their_hits_indirect_paths():
    # A chain hit plans K' indirect paths; the M glossy rays of a first glossy bounce would give the
    # surfaces they reach M K' between them, M times a diffuse pixel's. Their hits share K' instead:
    # ceil(K' / M) each, while a mirror ray's hit (one ray, no split) keeps K'.
    from engine.reference import KIND_CHAIN, _plan

    kd = np.array([[0.5, 0.5, 0.5]])
    zero = np.zeros((1, 3))
    n = 3
    split = np.array([True, False, True])
    k_per_hit, m_glossy = 64, 8
    out = [np.zeros(n, np.int64) for _ in range(4)]
    _plan(0, n, np.zeros(n, np.int32), np.ones((n, 3)), np.full(n, KIND_CHAIN, np.int8), np.ones(n, np.int32),
          np.full(n, 2, np.int32), split, kd, zero, zero, 4, m_glossy, k_per_hit, False, *out)
    n_ind = out[2]
    assert list(n_ind) == [8, 64, 8]
    _plan(0, n, np.zeros(n, np.int32), np.ones((n, 3)), np.full(n, KIND_CHAIN, np.int8), np.ones(n, np.int32),
          np.full(n, 2, np.int32), split, kd, zero, zero, 4, 5, 12, False, *out)
    assert list(out[2]) == [3, 12, 3]  # rounded up: no hit goes without a path
