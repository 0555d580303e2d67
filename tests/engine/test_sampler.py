"""engine/sampler.py: stratification, determinism, uniformity and convergence of the sample values."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from engine.camera import camera_rays, pixel_centers
from engine.reference import ReferenceParams, ReferenceRenderer, render_reference
from engine.sampler import _reverse32, _sobol1_reversed, points, sample_key
from engine.scene import CameraParams
from tests.engine.scenes import mat, quad, scene, sphere_mesh


def _is_net(p: np.ndarray) -> bool:
    """Whether the 2^m points p form a (0, m, 2)-net in base 2: every elementary interval of
    area 2^-m (2^a columns x 2^(m-a) rows) holds exactly one point."""
    n = p.shape[0]
    m = int(round(math.log2(n)))
    assert 1 << m == n
    for a in range(m + 1):
        cx = np.floor(p[:, 0] * (1 << a)).astype(np.int64)
        cy = np.floor(p[:, 1] * (1 << (m - a))).astype(np.int64)
        cells = cx * (1 << (m - a)) + cy
        if np.unique(cells).size != n:
            return False
    return True


def test_unscrambled_sequence_is_sobol():
    """The generator of the second coordinate (a superset-xor transform of the index bits)
    equals Sobol's direction numbers v_0 = 2^31, v_k = v_(k-1) xor v_(k-1) >> 1."""
    rng = np.random.default_rng(0)
    for i in [*range(4096), *rng.integers(0, 1 << 32, 2000).tolist()]:
        want, v, k = 0, 1 << 31, i
        while k:
            if k & 1:
                want ^= v
            k >>= 1
            v ^= v >> 1
        assert int(_reverse32(_sobol1_reversed(np.uint64(i)))) == want, i


@pytest.mark.parametrize("seed,pixel", [(0, 0), (1, 7), (12345, 1 << 20), (7, 4095)])
def test_power_of_two_prefixes_and_aligned_blocks_are_nets(seed, pixel):
    key = sample_key(seed, 3)
    p = points(key, pixel, 4096)
    assert p.min() >= 0.0 and p.max() < 1.0
    for m in range(13):
        assert _is_net(p[: 1 << m]), m
    # every aligned block of 2^m samples is a net too (a pixel's samples split among its paths)
    for m in (2, 4, 6):
        for b in range(0, 4096, 1 << m):
            assert _is_net(p[b:b + (1 << m)]), (m, b)
    # indices beyond 2^32 (deep branching) keep the property
    far = points(key, pixel, 256, offset=(5 << 32) + 1024)
    assert _is_net(far)


def test_any_even_count_puts_half_of_the_samples_in_each_half():
    key = sample_key(0, 1)
    for n in range(1, 65):
        p = points(key, 3, n)
        for c in range(2):
            k = int(np.count_nonzero(p[:, c] < 0.5))
            assert abs(k - n / 2) <= 0.5, (n, c, k)


def test_values_are_a_pure_function_of_key_pixel_index():
    key = sample_key(4, 2)
    a = points(key, 11, 300)
    # any sub-range computed on its own gives the same values (a render split in chunks)
    np.testing.assert_array_equal(a[100:200], points(key, 11, 100, offset=100))
    np.testing.assert_array_equal(a, points(np.uint64(key), 11, 300))
    assert not np.array_equal(a, points(key, 12, 300))
    assert not np.array_equal(a, points(sample_key(4, 3), 11, 300))
    assert not np.array_equal(a, points(sample_key(5, 2), 11, 300))


def test_each_value_is_uniform_and_pixels_and_pairs_are_uncorrelated():
    """Owen scrambling makes every single sample uniform: sample i over many pixels (its own
    scramble each) is a uniform variable, whatever i; and two pairs, or two pixels, are
    independent of each other."""
    n = 4000
    for i in (0, 1, 5, 1000):
        vals = np.array([points(sample_key(0, 9), q, 1, offset=i)[0] for q in range(n)])
        for c in range(2):
            assert stats.kstest(vals[:, c], "uniform").pvalue > 1e-3, (i, c)
        assert abs(np.corrcoef(vals.T)[0, 1]) < 0.06
    a = points(sample_key(1, 0), 5, n)
    b = points(sample_key(1, 1), 5, n)
    c = points(sample_key(1, 0), 6, n)
    for x, y in ((a, b), (a, c)):
        cc = np.corrcoef(np.hstack([x, y]).T)[:2, 2:]
        assert np.all(np.abs(cc) < 0.06)


def _rms_error(f, exact, n, seeds, sampler):
    errs = [sampler(s, n) for s in range(seeds)]
    est = np.array([f(p).mean() for p in errs])
    return float(np.sqrt(np.mean((est - exact) ** 2))), float(est.mean())


def _ours(s, n):
    return points(sample_key(s, 0), 0, n)


def _independent(s, n):
    return np.random.default_rng(s).random((n, 2))


@pytest.mark.parametrize("name", ["smooth", "disc"])
def test_error_falls_faster_than_with_independent_samples(name):
    """RMS error over seeds of the estimate of a 2-D integral against n: slope ~ -0.5 for
    independent samples; for scrambled nets -1.5 on a smooth integrand and -0.75 on one with a
    discontinuity across the square (Owen: n^(-1/2 - 1/(2d)), d = 2); measured -1.47 and -0.78.
    Bounds are generous (-0.9 and -0.65): the point is the rate class, not its last digit."""
    if name == "smooth":
        def f(p):
            return np.exp(p[:, 0]) * np.cos(p[:, 1])
        exact = (math.e - 1.0) * math.sin(1.0)
        bound, ratio = -0.9, 0.02  # measured 0.0014 at n = 1024
    else:
        r = 0.4

        def f(p):
            return ((p[:, 0] - 0.5) ** 2 + (p[:, 1] - 0.5) ** 2 < r * r).astype(np.float64)
        exact = math.pi * r * r
        bound, ratio = -0.65, 0.35  # measured 0.18 at n = 1024
    ns = np.array([16, 64, 256, 1024])
    ours = [_rms_error(f, exact, int(n), 200, _ours) for n in ns]
    ind = [_rms_error(f, exact, int(n), 200, _independent) for n in ns]
    slope_ours = np.polyfit(np.log(ns), np.log([e for e, _ in ours]), 1)[0]
    slope_ind = np.polyfit(np.log(ns), np.log([e for e, _ in ind]), 1)[0]
    assert -0.7 < slope_ind < -0.3  # the yardstick behaves as theory says
    assert slope_ours < bound, (slope_ours, ours)
    assert ours[-1][0] < ratio * ind[-1][0]
    # unbiased: the mean over seeds is the integral within its standard error
    for (err, mean), n in zip(ours, ns, strict=True):
        assert abs(mean - exact) < 5 * err / math.sqrt(200) + 1e-12, n


# ---------------------------------------------------------------- in the reference renderer


def _busy_scene():
    lights = [dict(type="rect", corner=(-0.5, 1.0, -0.5), edge_u=(1.0, 0, 0), edge_v=(0, 0, 1.0),
                   radiance=(2, 2, 2)),
              dict(type="point", position=(0.5, 1.5, 0.5), intensity=(0.5, 0.5, 0.5))]
    return scene([(quad((0, 0, 0), 4.0), mat(kg=(0.3, 0.3, 0.3), gloss_exponent=20, kd=(0.4, 0.4, 0.4))),
                  (sphere_mesh((0, 0.3, 0), 0.2, 2), mat("s", kr=(0.5, 0.5, 0.5), kd=(0.3, 0.3, 0.3)))], lights)


def test_render_is_identical_for_any_chunk_split():
    """Every sample value is keyed by (seed, pixel, sample index, dimension), never by a ray's
    place in a batch: splitting the image in other chunks, or shading hits in other slices,
    gives the same bits."""
    sc = _busy_scene()
    ren = ReferenceRenderer(sc)
    cam = CameraParams("perspective", (0, 1, 2), (0, 0.2, 0), (0, 1, 0), 40, 30, fov_y_deg=40)
    base = dict(spp=3, area_light_samples=4, indirect_samples=5, glossy_samples=3, indirect_bounces=2, seed=5)
    ref = ren.render(cam, ReferenceParams(**base)).radiance  # 1200 pixels: chunks of 1024
    assert ref.max() > 0
    for chunk_pixels, pipelines in ((1, 2), (77, 1), (500, 3)):
        img = ren.render(cam, ReferenceParams(**base, chunk_pixels=chunk_pixels, pipelines=pipelines)).radiance
        assert np.array_equal(img, ref), (chunk_pixels, pipelines)
    assert not np.array_equal(ref, ren.render(cam, ReferenceParams(**dict(base, seed=6))).radiance)

    out = ren.render(cam, ReferenceParams(spp=1, pixel_jitter=False))
    hit = out.object_id.reshape(-1) >= 0
    o, d = camera_rays(cam, *pixel_centers(cam))
    hits = ren.caster.intersect(o[hit], d[hit])
    p = ReferenceParams(**base)
    a = ren.shade_hits(hits.prim, hits.u, hits.v, d[hit], p, stream_id=2)
    b = ren.shade_hits(hits.prim, hits.u, hits.v, d[hit], p, stream_id=2, chunk=101)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, ren.shade_hits(hits.prim, hits.u, hits.v, d[hit], p, stream_id=3))


def _corner_factor(a, b, c):
    A, B = a / math.hypot(a, c), b / math.hypot(b, c)
    return (A * math.atan(b / math.hypot(a, c)) + B * math.atan(a / math.hypot(b, c))) / (2 * math.pi)


def test_rect_light_estimate_is_unbiased_and_stratified_over_the_pixel():
    """A pixel that sees one point under a rect light: its value over seeds averages to the
    closed-form irradiance with few light samples, and the pixel's spp x 4 light samples are
    stratified across its camera samples: the error per seed falls faster than 1/sqrt(spp)."""
    Le, a, b, h = 3.0, 1.0, 0.6, 0.5
    cam = CameraParams("orthographic", (0, 5, 0), (0, 0, 0), (0, 0, -1), 2, 2, ortho_height=1e-6)
    light = dict(type="rect", corner=(-a / 2, h, -b / 2), edge_u=(a, 0.0, 0.0), edge_v=(0.0, 0.0, b),
                 radiance=(Le, Le, Le))
    sc = scene([(quad((0, 0, 0), 4.0), mat(kd=(1, 1, 1)))], [light])
    want = Le * 4 * _corner_factor(a / 2, b / 2, h)
    rms = {}
    for spp in (1, 16):
        vals = np.array([render_reference(sc, cam, ReferenceParams(spp=spp, area_light_samples=4, seed=s))
                         .radiance[..., 0].ravel() for s in range(100)], np.float64)
        se = vals.std(ddof=1) / math.sqrt(vals.size)
        assert abs(vals.mean() - want) <= 4 * se + 1e-6 * want, (spp, vals.mean(), want, se)
        rms[spp] = float(np.sqrt(np.mean((vals - want) ** 2)))
    # independent samples: rms[16] = rms[1] / 4; stratified over the pixel: much less
    assert rms[16] < rms[1] / 8, rms


@pytest.mark.parametrize("bounces", [1, 2])
def test_indirect_estimate_is_unbiased(bounces):
    """Inside a closed diffuse sphere with a point light at its centre (the closed form of
    tests/engine/test_reference.py), few indirect paths per pixel average to the series."""
    al, intensity, radius = 0.5, 1.0, 1.0
    sc = scene([(sphere_mesh(radius=radius, subdivisions=5), mat(kd=(al, al, al)))],
               [dict(type="point", position=(0, 0, 0), intensity=(intensity,) * 3)])
    cam = CameraParams("perspective", (0, 0, 0.2), (0, 0, -1), (0, 1, 0), 4, 4, fov_y_deg=60)
    vals = np.array([render_reference(sc, cam, ReferenceParams(spp=1, indirect_samples=2, indirect_bounces=bounces,
                                                                seed=s)).radiance[..., 0].ravel()
                     for s in range(40)], np.float64)
    want = al / math.pi * intensity / radius ** 2 * sum(al ** k for k in range(bounces + 1))
    se = vals.std(ddof=1) / math.sqrt(vals.size)
    # the tessellated sphere (subdivision 5) is within 0.3 % of the sphere's closed form
    assert abs(vals.mean() - want) <= 4 * se + 3e-3 * want, (vals.mean(), want, se)
