"""Caustic photon map (engine/caustics.py): its irradiance against a closed form, the indirect pass
with it against the closed form and against paths alone, determinism, and no map where a scene
has no caustics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from engine.caustics import build_caustic_map, has_caustics
from engine.errors import InvalidInputError
from engine.newviews.indirect import IndirectParams, trace_indirect_points
from engine.newviews.ldc import bake_ldc_axis, indirect_chunk
from engine.raycast import EmbreeCaster
from engine.reference import ReferenceRenderer
from engine.sampler import sample_key
from tests.engine.scenes import box_room, mat, quad, scene
from tests.engine.test_reference_caustics import _corner_factor, _up_light

KD, KR, LE, SIZE, H_LIGHT, H_MIRROR = 0.5, 0.8, 3.0, 4.0, 1.0, 2.0
ROOM = 12.0


def _floor_under_a_mirror(ceiling: dict | None = None):
    """A diffuse floor lit only through a mirror ceiling: the light at height H_LIGHT faces up,
    away from the floor; the floor sees its mirror image, a downward light of radiance kr Le at
    height 2 H_MIRROR - H_LIGHT."""
    ceiling = ceiling or mat("mirror", kd=(0, 0, 0), kr=(KR,) * 3)
    return scene([(quad((0, 0, 0), ROOM), mat("floor", kd=(KD,) * 3)),
                  (quad((0, H_MIRROR, 0), ROOM, flip=True), ceiling)], [_up_light(SIZE, H_LIGHT, LE)])


def _image_irradiance(p: np.ndarray) -> np.ndarray:
    """Irradiance at floor points p (n, 3) from the light's mirror image: pi kr Le times the form
    factor to the image's rectangle, four corner rectangles added with signs."""
    c = 2 * H_MIRROR - H_LIGHT

    def corner(x: np.ndarray, z: np.ndarray) -> np.ndarray:
        return np.sign(x) * np.sign(z) * np.array([_corner_factor(abs(a), abs(b), c) if a and b else 0.0
                                                   for a, b in zip(x, z, strict=True)])

    x1, x2 = -SIZE / 2 - p[:, 0], SIZE / 2 - p[:, 0]
    z1, z2 = -SIZE / 2 - p[:, 2], SIZE / 2 - p[:, 2]
    return math.pi * KR * LE * (corner(x2, z2) - corner(x1, z2) - corner(x2, z1) + corner(x1, z1))


def _floor_points(n: int = 64, spread: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """n points on the floor within ``spread`` of its centre, and the floor's normal."""
    rng = np.random.default_rng(5)
    p = np.column_stack([rng.uniform(-spread, spread, n), np.zeros(n), rng.uniform(-spread, spread, n)])
    return p, np.tile([0.0, 1.0, 0.0], (n, 1))


def test_irradiance_through_a_mirror_is_the_mirror_images():
    sc = _floor_under_a_mirror()
    assert has_caustics(sc)
    cmap = build_caustic_map(sc, EmbreeCaster(sc), 1 << 20, 0.02, 4)
    p, n = _floor_points()
    e = cmap.irradiance(p, n)
    want = _image_irradiance(p)
    assert _image_irradiance(np.zeros((1, 3)))[0] == pytest.approx(
        math.pi * KR * LE * 4 * _corner_factor(SIZE / 2, SIZE / 2, 2 * H_MIRROR - H_LIGHT))
    # ~200 photons within the kernel's radius (0.02 of the diagonal: 0.34) of each point, ~7 %
    # noise each; ~20 independent disks over the points' square: ~1.5 % for the mean. The kernel's
    # blur of this smooth caustic is second order (0.3 % at the centre)
    assert e[:, 0].mean() == pytest.approx(want.mean(), rel=0.04)
    # the other side of the floor gets nothing, and neither does the mirror (no diffuse lobe)
    assert np.all(cmap.irradiance(p, -n) == 0.0)
    assert cmap.stats["stored"] > 0 and np.all(np.abs(cmap.pos[:, 1]) < 1e-9)
    # the cells' piecewise-constant irradiance, what path vertices get, has the same level
    assert cmap.cell_irradiance(p, n)[:, 0].mean() == pytest.approx(want.mean(), rel=0.05)


def test_indirect_pass_with_photons_gets_the_closed_form():
    """The floor's indirect light with 2 bounces is its light through the mirror (floor -> mirror ->
    floor -> mirror -> light would be a third bounce): kd/pi times the image's irradiance, from
    the map at the points themselves and nothing from the paths (they meet the light through the
    mirror no more)."""
    sc = _floor_under_a_mirror()
    ren = ReferenceRenderer(sc)
    p, n = _floor_points(32)
    base = np.zeros((p.shape[0], 3))
    got = {}
    for caustics in ("photons", "paths"):
        ip = IndirectParams(bounces=2, min_paths=1024, max_paths=1024, caustics=caustics, caustic_radius=0.02)
        res = trace_indirect_points(ren, p, n, n, np.zeros(p.shape[0], np.int32), base, ip,
                                    key=sample_key(0, 3, 0), brightness=1.0)
        got[caustics] = res
    want = KD / math.pi * _image_irradiance(p).mean()
    assert got["photons"].radiance[:, 0].mean() == pytest.approx(want, rel=0.03)
    assert got["paths"].radiance[:, 0].mean() == pytest.approx(want, rel=0.03)
    assert got["photons"].stats["caustics"]["method"] == "photons"
    assert got["paths"].stats["caustics"] == {"method": "paths"}


@pytest.mark.parametrize("g", [8.0, 60.0])
def test_light_through_a_glossy_ceiling_agrees_with_paths(g):
    """Under a glossy ceiling (kg, cos^g lobe) the floor's light has no closed form: the photon
    map's and the paths' (next-event estimation of the glossy lobe and its rays meeting the light,
    weighted by multiple importance sampling, tests/engine/test_reference_caustics.py) must agree,
    2 bounces, with the map's light at the points and at the paths' vertices."""
    sc = _floor_under_a_mirror(mat("glossy", kd=(0, 0, 0), kg=(KR,) * 3, gloss_exponent=g))
    ren = ReferenceRenderer(sc)
    p, n = _floor_points(32)
    base = np.zeros((p.shape[0], 3))
    means = {}
    for caustics, paths in (("photons", 256), ("paths", 8192)):
        ip = IndirectParams(bounces=3, min_paths=paths, max_paths=paths, caustics=caustics, caustic_radius=0.02)
        res = trace_indirect_points(ren, p, n, n, np.zeros(p.shape[0], np.int32), base, ip,
                                    key=sample_key(0, 3, 0), brightness=1.0)
        means[caustics] = float(res.radiance[:, 0].mean())
    assert means["photons"] == pytest.approx(means["paths"], rel=0.03), means


def test_photon_map_is_deterministic_whatever_the_threads():
    sc = _floor_under_a_mirror()
    caster = EmbreeCaster(sc)
    a = build_caustic_map(sc, caster, 1 << 15, 0.02, 4, seed=3, serial=True)
    b = build_caustic_map(sc, caster, 1 << 15, 0.02, 4, seed=3, serial=False)
    c = build_caustic_map(sc, caster, 1 << 15, 0.02, 4, seed=4)
    for name in ("keys", "pos", "nrm", "power", "okeys", "irr"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.pos, c.pos)


def test_chunks_with_a_photon_map_give_the_same_bits_as_one_pass():
    """Every chunk job builds the same map (one seed), so an axis split over jobs, each with its
    own renderer, bakes what one pass bakes."""
    from engine.newviews.ldc import with_indirect

    sc = _floor_under_a_mirror()
    caster = EmbreeCaster(sc)
    ax = bake_ldc_axis(sc, caster, 1, 12)
    params = IndirectParams(min_paths=16, max_paths=16, bounces=2, seed=7, caustic_photons=1 << 14,
                            caustic_radius=0.02)
    n = ax.n_samples
    whole = with_indirect(ax, [indirect_chunk(sc, caster, ax, 0, n, params)], params)
    k = n // 3
    parts = [indirect_chunk(sc, caster, ax, a, b, params, renderer=ReferenceRenderer(sc, caster))
             for a, b in ((k, n), (0, k))]
    assert np.array_equal(whole.diffuse, with_indirect(ax, parts, params).diffuse)
    assert parts[0].stats["caustics"]["method"] == "photons"


def test_scene_without_caustics_has_no_map_and_the_same_bake():
    """No mirror or glossy surface (or no rect light): nothing to map, and the photon setting
    bakes exactly what paths alone bake."""
    sc = box_room()
    caster = EmbreeCaster(sc)
    assert not has_caustics(sc) and build_caustic_map(sc, caster, 4096, 0.01, 4) is None
    no_light = scene([(quad((0, 0, 0), 2.0), mat("m", kd=(0.5,) * 3, kr=(0.3,) * 3))],
                     [dict(type="point", position=(0.0, 1.0, 0.0), intensity=(1.0,) * 3)])
    assert not has_caustics(no_light)
    ax = bake_ldc_axis(sc, caster, 2, 8)
    a = indirect_chunk(sc, caster, ax, 0, ax.n_samples, IndirectParams(min_paths=16, max_paths=16))
    b = indirect_chunk(sc, caster, ax, 0, ax.n_samples, IndirectParams(min_paths=16, max_paths=16, caustics="paths"))
    np.testing.assert_array_equal(a.radiance, b.radiance)
    assert a.stats["caustics"] == {"method": "paths"}


@pytest.mark.parametrize("kw", [{"caustics": "light"}, {"caustic_photons": 10}, {"caustic_radius": 0.5},
                                {"caustic_radius": 0.0}])
def test_bad_caustic_settings_are_refused(kw):
    with pytest.raises(InvalidInputError):
        IndirectParams(**kw)
