"""The LDC bake's direct light from rect lights: its rect-light points come from the stratified
sampler (engine/sampler.py), deterministic per seed and the same however the samples are sliced,
unbiased, and more accurate at equal samples than the jittered grid with independent jitter it
replaces (against the closed-form irradiance of a rectangle)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from engine.newviews.ldc import shade_samples
from engine.newviews.view_pass import highlights
from engine.raycast import EmbreeCaster
from tests.engine.scenes import mat, quad, scene

RADIANCE = 3.0
KD = 0.6
LIGHT = dict(type="rect", corner=(-0.5, 1.0, -0.5), edge_u=(1.0, 0.0, 0.0), edge_v=(0.0, 0.0, 1.0),
             radiance=(RADIANCE,) * 3)  # 1 x 1, one-sided, facing down (edge_u x edge_v = -y), 1 above the floor


def _corner_irradiance(a: np.ndarray, b: np.ndarray, h: float) -> np.ndarray:
    """Irradiance per unit radiance at a point under a corner of a parallel a x b rectangle at height
    h (the differential-area-to-parallel-rectangle form factor times pi)."""
    x, y = a / h, b / h
    sx, sy = np.sqrt(1 + x * x), np.sqrt(1 + y * y)
    return 0.5 * (x / sx * np.arctan(y / sx) + y / sy * np.arctan(x / sy))


def closed_form(pts: np.ndarray) -> np.ndarray:
    """kd / pi * E at floor points (y = 0) under the light (|x|, |z| < 0.5): four corner rectangles."""
    e = np.zeros(pts.shape[0])
    for dx in (-0.5, 0.5):
        for dz in (-0.5, 0.5):
            e += _corner_irradiance(np.abs(dx - pts[:, 0]), np.abs(dz - pts[:, 2]), 1.0)
    return KD / math.pi * RADIANCE * e


def jittered_grid(pts: np.ndarray, g: int, rng: np.random.Generator) -> np.ndarray:
    """kd / pi * E estimated on a g x g grid with one independent uniform jitter per cell (the
    estimator the bake used before the stratified sampler), unoccluded."""
    n = pts.shape[0]
    s = np.arange(g * g)
    u = (s[None, :] % g + rng.random((n, g * g))) / g
    v = (s[None, :] // g + rng.random((n, g * g))) / g
    lx, ly, lz = -0.5 + u - pts[:, :1], 1.0 - pts[:, 1:2], -0.5 + v - pts[:, 2:]
    d2 = lx * lx + ly * ly + lz * lz
    cos = ly / np.sqrt(d2)  # the same at the light (facing down) and at the floor (facing up)
    return KD / math.pi * RADIANCE * (cos * cos / d2).sum(axis=1) / (g * g)


@pytest.fixture(scope="module")
def floor():
    """The floor under the light, nothing between them (the closed form holds)."""
    sc = scene([(quad((0, 0, 0), 4.0, 1), mat("floor", kd=(KD,) * 3))], [LIGHT])
    return sc, EmbreeCaster(sc)


@pytest.fixture(scope="module")
def blocked():
    """The floor with a small blocker half way up: shadows and penumbrae."""
    sc = scene([(quad((0, 0, 0), 4.0, 1), mat("floor", kd=(KD,) * 3)),
                (quad((0.3, 0.5, 0.2), 0.3, 1), mat("blocker", kd=(0.2, 0.2, 0.2)))], [LIGHT])
    return sc, EmbreeCaster(sc)


def _points(n: int, seed: int, half: float = 0.45) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = np.zeros((n, 3))
    p[:, 0], p[:, 2] = rng.uniform(-half, half, n), rng.uniform(-half, half, n)
    return p


def _shade(sc, caster, p, n_light: int, seed: int, rows_per_slice: int = 1 << 21) -> np.ndarray:
    n = p.shape[0]
    up = np.tile([0.0, 1.0, 0.0], (n, 1))
    d, _, _ = shade_samples(sc, caster, p, up, up, np.zeros(n, np.int32), np.ones(1, np.bool_), store_bits=True,
                            area_light_samples=n_light, seed=seed, rows_per_slice=rows_per_slice)
    return d


def test_deterministic_per_seed_and_identical_however_sliced(blocked):
    sc, caster = blocked
    p = _points(3000, 1, half=0.8)  # some points in the blocker's shadow and penumbra
    whole = _shade(sc, caster, p, 16, seed=4)
    assert np.array_equal(whole, _shade(sc, caster, p, 16, seed=4))
    for rows in (16 * 7, 16 * 1000 + 5):  # slices of 7 samples, of 1000 samples (and a ragged end)
        assert np.array_equal(whole, _shade(sc, caster, p, 16, seed=4, rows_per_slice=rows))
    other = _shade(sc, caster, p, 16, seed=5)
    assert not np.array_equal(whole, other)
    assert np.isfinite(whole).all()


def test_unbiased_against_the_closed_form(floor):
    sc, caster = floor
    p = _points(400, 2)
    exact = closed_form(p)
    ratio = np.mean([_shade(sc, caster, p, 4, seed=s)[:, 0, 0] for s in range(32)], axis=0) / exact
    # 4 samples per point: ~6 % noise per point, ~1 % for the mean of 32 seeds, ~0.05 % over 400 points
    assert abs(ratio.mean() - 1.0) < 3e-3
    assert np.abs(ratio - 1.0).max() < 0.06
    converged = _shade(sc, caster, p, 4096, seed=0)[:, 0, 0] / exact
    assert np.abs(converged - 1.0).max() < 2e-4


@pytest.mark.parametrize("n_light", [16, 64])
def test_error_lower_than_the_jittered_grid_at_equal_samples(floor, n_light):
    sc, caster = floor
    p = _points(2000, 3, half=0.45)
    exact = closed_form(p)
    new = _shade(sc, caster, p, n_light, seed=0)[:, 0, 0]
    old = jittered_grid(p, int(round(math.sqrt(n_light))), np.random.default_rng(0))
    err_new = float(np.sqrt(np.mean(np.square(new - exact)))) / exact.mean()
    err_old = float(np.sqrt(np.mean(np.square(old - exact)))) / exact.mean()
    assert err_new < 0.5 * err_old, (err_new, err_old)


def test_highlights_deterministic_per_seed():
    sc = scene([(quad((0, 0, 0), 4.0, 1), mat("shiny", kd=(KD,) * 3, ks=(0.5,) * 3, shininess=20.0))], [LIGHT])
    n = 500
    p = _points(n, 4)
    up = np.tile([0.0, 1.0, 0.0], (n, 1))
    wo = np.tile([0.0, 0.6, 0.8], (n, 1))
    m = np.zeros(n, np.int32)
    a = highlights(sc, p, up, up, wo, m, seed=3)
    assert a.max() > 0
    assert np.array_equal(a, highlights(sc, p, up, up, wo, m, seed=3))
    assert not np.array_equal(a, highlights(sc, p, up, up, wo, m, seed=4))
