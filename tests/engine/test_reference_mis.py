"""Multiple importance sampling of rect lights at glossy (kg) lobes and Russian roulette on path
vertices: each strategy alone, both weighted (power and balance heuristics) and roulette on or off
estimate the same radiance, the closed form's or an independent quadrature's, within the standard
error measured over seeds; MIS has less variance than either strategy alone where each is poor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from engine.errors import InvalidInputError
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.scene import CameraParams
from tests.engine.scenes import mat, quad, scene, sphere_mesh

# an orthographic footprint of 8 x 2 pixels straddling x = 0 (left half x < 0, right half x > 0),
# looking straight down from above the floor: every pixel's mirror direction is +y
CAM = CameraParams("orthographic", (0, 0.5, 0), (0, 0, 0), (0, 0, -1), 8, 2, ortho_height=0.005)

ROUGH, SHARP = 1.0, 1000.0  # Phong exponents of the two floor halves
# a small, bright light off to the side, and a big, dim one straight above; no ray from the
# pixels meets one light in front of the other (a ray ends at the first light it meets, a shadow
# ray passes through lights: such a pair would not be one integral for the two strategies)
SMALL = dict(size=0.1, h=0.5, x=1.0, Le=200.0)
BIG = dict(size=2.0, h=1.0, x=0.0, Le=1.0)


def _light(size: float, h: float, x: float, Le: float) -> dict:
    """A one-sided size x size rect light at height h centred over (x, 0), emitting down."""
    return dict(type="rect", corner=(x - size / 2, h, -size / 2), edge_u=(size, 0.0, 0.0), edge_v=(0.0, 0.0, size),
                radiance=(Le, Le, Le))


def _quadrature(g: float, size: float, h: float, x: float, Le: float, n: int = 1500) -> float:
    """Radiance toward +y of a floor point at the origin with BRDF (g + 2) / (2 pi) cos^g(alpha)
    about +y, from a downward-facing light: midpoint rule over the light, where
    cos(theta) = cos(alpha) = cos(theta') = h / d."""
    t = (np.arange(n) + 0.5) / n * size - size / 2
    X, Z = np.meshgrid(t + x, t)
    d = np.sqrt(X ** 2 + Z ** 2 + h ** 2)
    c = h / d
    return float(np.sum((g + 2) / (2 * math.pi) * c ** g * Le * c * c / d ** 2) * (size / n) ** 2)


def _floor_scene(rho: float):
    left = quad((-20.0, 0, 0), 40.0)
    right = quad((20.0, 0, 0), 40.0)
    return scene([(left, mat("rough", kd=(0, 0, 0), kg=(rho,) * 3, gloss_exponent=ROUGH)),
                  (right, mat("sharp", kd=(0, 0, 0), kg=(rho,) * 3, gloss_exponent=SHARP))],
                 [_light(**SMALL), _light(**BIG)])


def _seeds(renderer: ReferenceRenderer, params: ReferenceParams, n: int) -> np.ndarray:
    """(n, h, w) green channel of n renders with seeds 0 .. n - 1."""
    from dataclasses import replace
    return np.stack([renderer.render(CAM, replace(params, seed=s)).radiance[..., 1] for s in range(n)])


def test_mis_and_each_strategy_alone_agree_with_the_quadrature_and_mis_has_the_least_variance():
    """Left half: a rough lobe under a small bright light (the lobe's rays rarely find it: BSDF
    sampling alone is poor). Right half: a sharp lobe under a big light (its light samples rarely
    fall in the lobe: light sampling alone is poor). All four modes must give the quadrature in
    the mean (within 4 standard errors over seeds), and MIS must have less variance over the
    whole image than either strategy alone."""
    rho, n_seeds = 0.8, 40
    sc = _floor_scene(rho)
    want_rough = rho * (_quadrature(ROUGH, **SMALL) + _quadrature(ROUGH, **BIG))
    want_sharp = rho * (_quadrature(SHARP, **SMALL) + _quadrature(SHARP, **BIG))
    params = ReferenceParams(spp=1, glossy_samples=16, area_light_samples=4, max_depth=1)
    var = {}
    for mode in ("power", "balance", "light", "bsdf"):
        img = _seeds(ReferenceRenderer(sc, glossy_mis=mode), params, n_seeds)
        for half, want in ((img[:, :, :4], want_rough), (img[:, :, 4:], want_sharp)):
            per_seed = half.reshape(n_seeds, -1).mean(axis=1)
            se = per_seed.std(ddof=1) / math.sqrt(n_seeds)
            assert abs(per_seed.mean() - want) < 4 * se + 2e-3 * want, (mode, per_seed.mean(), want, se)
        # relative variance of a pixel, averaged over each half, then summed over the halves
        var[mode] = float(img[:, :, :4].var(axis=0, ddof=1).mean() / want_rough ** 2
                          + img[:, :, 4:].var(axis=0, ddof=1).mean() / want_sharp ** 2)
    assert var["power"] < 0.5 * min(var["light"], var["bsdf"]), var
    assert var["balance"] < 0.5 * min(var["light"], var["bsdf"]), var


def test_mis_weights_a_glossy_lobe_at_path_vertices_too():
    """A diffuse floor under a glossy ceiling (kg, rough), lit only through the ceiling: the
    light faces up, away from the floor, toward the ceiling. The floor's indirect light reaches it
    through the ceiling's glossy lobe at a path vertex, where both strategies exist (next-event
    estimation from the ceiling point and the lobe's ray); MIS, light-only and BSDF-only agree in
    the mean within 4 standard errors."""
    kd, rho, g = 0.7, 0.6, 4.0
    floor = quad((0, 0, 0), 60.0)
    ceiling = quad((0, 2.0, 0), 60.0, flip=True)
    up_light = dict(type="rect", corner=(-0.5, 1.0, -0.5), edge_u=(0.0, 0.0, 1.0), edge_v=(1.0, 0.0, 0.0),
                    radiance=(5.0, 5.0, 5.0))
    sc = scene([(floor, mat("floor", kd=(kd,) * 3)), (ceiling, mat("ceil", kd=(0, 0, 0), kg=(rho,) * 3,
                                                                    gloss_exponent=g))], [up_light])
    cam = CameraParams("orthographic", (0, 0.5, 0), (0, 0, 0), (0, 0, -1), 4, 4, ortho_height=0.01)
    params = ReferenceParams(spp=4, indirect_samples=64, indirect_bounces=2, area_light_samples=4, max_depth=0)
    means = {}
    for mode in ("power", "light", "bsdf"):
        r = ReferenceRenderer(sc, glossy_mis=mode)
        from dataclasses import replace
        per_seed = np.array([r.render(cam, replace(params, seed=s)).radiance[..., 1].mean() for s in range(16)])
        means[mode] = (per_seed.mean(), per_seed.std(ddof=1) / 4.0)
    for a in means:
        for b in means:
            (ma, sa), (mb, sb) = means[a], means[b]
            assert abs(ma - mb) < 4 * math.hypot(sa, sb), means
    assert means["power"][0] > 0.0


@pytest.mark.parametrize("albedo", [0.5, 0.8])
def test_russian_roulette_keeps_the_sphere_series_and_saves_rays(albedo):
    """Inside a closed diffuse sphere of albedo a with a point light at its centre, B bounces add
    up to L = a/pi I/R^2 sum_{k=0..B} a^k. With roulette (from the third bounce on) and without,
    the mean over seeds is that closed form within 4 standard errors (plus the tessellation's
    0.5 %), and roulette traces fewer indirect rays."""
    a, intensity, bounces, n_seeds = albedo, 1.0, 8, 8
    sc = scene([(sphere_mesh(radius=1.0, subdivisions=5), mat(kd=(a, a, a)))],
               [dict(type="point", position=(0, 0, 0), intensity=(intensity,) * 3)])
    cam = CameraParams("perspective", (0, 0, 0.2), (0, 0, -1), (0, 1, 0), 8, 8, fov_y_deg=60)
    want = a / math.pi * intensity * sum(a ** k for k in range(bounces + 1))
    rays = {}
    for roulette in (True, False):
        r = ReferenceRenderer(sc, roulette=roulette)
        vals, n_ind = [], 0
        for s in range(n_seeds):
            out = r.render(cam, ReferenceParams(spp=4, indirect_samples=64, indirect_bounces=bounces, seed=s))
            vals.append(out.radiance.mean())
            n_ind += out.counts["indirect"]
        v = np.array(vals)
        se = v.std(ddof=1) / math.sqrt(n_seeds)
        assert abs(v.mean() - want) < 4 * se + 5e-3 * want, (roulette, v.mean(), want, se)
        rays[roulette] = n_ind
    assert rays[True] < 0.9 * rays[False], rays


def test_unknown_mis_mode_is_refused():
    sc = _floor_scene(0.5)
    with pytest.raises(InvalidInputError, match="glossy_mis"):
        ReferenceRenderer(sc, glossy_mis="max")
