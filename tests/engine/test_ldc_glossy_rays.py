"""LDC views with the glossy lobe traced (``glossy_rays``) and image-based rays that see the rect
lights: a glossy floor shows a light seen in a mirror, as the reference renderer does, where the
light field's gather cannot (the light field holds surfaces, never a light)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from engine.errors import InvalidInputError
from engine.newviews.effects import analyze
from engine.newviews.ldc import bake_ldc
from engine.newviews.llf import bake_llf
from engine.newviews.renderer import PROV_TRACED, LDCViewRenderer
from engine.raycast import EmbreeCaster
from engine.reference import ReferenceParams, render_reference
from engine.scene import CameraParams
from tests.engine.scenes import mat, quad, scene

# a rect light facing down, a mirror wall behind it facing +z, a purely glossy floor: the floor's
# radiance is its glossy lobe's alone, the light's reflection seen straight (a highlight) and in
# the mirror (light -> mirror -> floor -> eye), nothing else
LIGHT = dict(type="rect", corner=(-0.2, 2.0, -0.7), edge_u=(0.4, 0.0, 0.0), edge_v=(0.0, 0.0, 0.4),
             radiance=(20.0, 20.0, 20.0))
KR = 0.9
CAM = CameraParams("perspective", (0.0, 1.2, 2.5), (0.0, 0.0, -0.5), (0, 1, 0), 64, 64, 50.0)
MIRROR_CAM = CameraParams("perspective", (0.0, 0.6, 2.5), (0.0, 1.5, -1.5), (0, 1, 0), 64, 64, 50.0)
REF = ReferenceParams(spp=16, max_depth=3, glossy_samples=64)


def _scene(mirror: bool = True):
    floor = (quad((0.0, 0.0, -0.25), 4.0, normal_axis=1), mat("floor", kd=(0, 0, 0), kg=(0.5, 0.5, 0.5),
                                                               gloss_exponent=60.0))
    wall = (quad((0.0, 1.0, -1.5), 3.0, normal_axis=2), mat("mirror", kd=(0, 0, 0), kr=(KR, KR, KR)))
    return scene([floor, wall] if mirror else [floor], [LIGHT])


@pytest.fixture(scope="module")
def mirrored_light():
    sc = _scene()
    caster = EmbreeCaster(sc)
    plan = analyze(sc)
    ldc = bake_ldc(sc, caster, 64, plan=plan)
    llf = bake_llf(sc, caster, 2, 16, params=ReferenceParams(max_depth=2, glossy_samples=4))
    ref = render_reference(sc, CAM, REF)
    return sc, plan, ldc, llf, ref


def _floor_spot(ref, floor):
    """The floor's pixels lit by the light's image in the mirror: bright in the reference, dark
    without the mirror (where the light's direct highlight is negligible)."""
    no_mirror = render_reference(_scene(mirror=False), CAM, REF).radiance.mean(axis=2)
    y = ref.radiance.mean(axis=2)
    return floor & (no_mirror < 0.01) & (y > 0.1)


def test_glossy_rays_show_a_light_seen_in_a_mirror(mirrored_light):
    sc, plan, ldc, llf, ref = mirrored_light
    r = LDCViewRenderer(sc, ldc, llf, plan)
    floor = binary_erosion(ref.object_id == 0, iterations=2)
    spot = _floor_spot(ref, floor)
    assert spot.sum() >= 50
    y_ref = ref.radiance.mean(axis=2)
    gathered = r.render(CAM, "ldc+ibrt:1", glossy_rays=0)
    traced = r.render(CAM, "ldc+ibrt:1", glossy_rays=64)
    y_g, y_t = gathered.radiance.mean(axis=2), traced.radiance.mean(axis=2)
    print(f"spot mean: reference {y_ref[spot].mean():.4f}, gathered {y_g[spot].mean():.4f}, "
          f"traced {y_t[spot].mean():.4f}; floor mean {y_ref[floor].mean():.4f} / {y_g[floor].mean():.4f} / "
          f"{y_t[floor].mean():.4f}")
    # the light field cannot show the light's image: the gathered spot is dark
    assert y_g[spot].mean() < 0.05 * y_ref[spot].mean()
    # the traced lobe finds it through the mirror, with the reference's brightness
    assert y_t[spot].mean() == pytest.approx(y_ref[spot].mean(), rel=0.1)
    assert y_t[floor].mean() == pytest.approx(y_ref[floor].mean(), rel=0.05)
    assert (traced.provenance[floor] == PROV_TRACED).all()
    assert traced.counts["glossy_rays"] > 0 and traced.plan["passes"]["ibrt"]["glossy_rays"] == 64
    assert not traced.plan["passes"]["gather"]["ran"]
    # deterministic
    again = r.render(CAM, "ldc+ibrt:1", glossy_rays=64)
    assert np.array_equal(again.radiance, traced.radiance)


def test_mirror_rays_show_the_light(mirrored_light):
    """A traced mirror ray that meets a rect light shows the light's radiance (times kr), as the
    reference renderer's mirror chain does; before that it showed what lay behind the light."""
    sc, plan, ldc, llf, ref = mirrored_light
    res = LDCViewRenderer(sc, ldc, llf, plan).render(MIRROR_CAM, "ldc+ibrt:1")
    ref = render_reference(sc, MIRROR_CAM, REF)
    mirror = res.object_id == 1
    # the reference's pixels wholly on the light's image (the light seen straight, 20, is not the LDC's to show)
    lit = mirror & (np.abs(ref.radiance.mean(axis=2) - KR * 20.0) < 0.01 * KR * 20.0)
    assert lit.sum() >= 4
    np.testing.assert_allclose(res.radiance[lit], KR * 20.0, rtol=1e-5)


def test_glossy_rays_need_traced_methods(mirrored_light):
    sc, plan, ldc, llf, _ = mirrored_light
    r = LDCViewRenderer(sc, ldc, llf, plan)
    for method in ("ldc", "ldc+llf", "ldc+ibrt:0"):
        with pytest.raises(InvalidInputError, match="glossy_rays"):
            r.render(CAM, method, glossy_rays=4)
    for bad in (-1, 257, 2.5, True):
        with pytest.raises(InvalidInputError, match="glossy_rays"):
            r.render(CAM, "ldc+ibrt:1", glossy_rays=bad)


def _filter_slow(has, term, normal, depth, mat, w, h, radius, min_cos, rel_depth):
    out = term.copy()
    for i in np.flatnonzero(has):
        y, x = divmod(int(i), w)
        pick = [j for yy in range(max(0, y - radius), min(h, y + radius + 1))
                for xx in range(max(0, x - radius), min(w, x + radius + 1))
                for j in [yy * w + xx]
                if has[j] and mat[j] == mat[i] and float(normal[i] @ normal[j]) >= min_cos
                and abs(depth[j] - depth[i]) <= rel_depth * depth[i]]
        if pick:
            out[i] = term[pick].mean(axis=0)
    return out


def test_glossy_filter_is_the_plain_same_surface_average():
    from engine.newviews.renderer import _filter_glossy

    rng = np.random.default_rng(3)
    w, h = 23, 17
    n = w * h
    has = rng.random(n) < 0.7
    term = rng.random((n, 3))
    normal = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (n, 1))
    normal[rng.random(n) < 0.2] = (0.0, 0.6, 0.8)  # a crease: another surface by the normal test
    normal[5] = 0.0  # degenerate: fails its own test, keeps its own term
    has[5] = True
    depth = (1.0 + 0.1 * rng.random(n)).astype(np.float32)
    depth[rng.random(n) < 0.1] *= 2.0  # a depth step
    mat = rng.integers(0, 2, n).astype(np.int32)
    for radius in (0, 1, 3):
        out = np.zeros_like(term)
        _filter_glossy(has, term, normal, depth, mat, w, h, radius, 0.95, 0.05, out)
        want = _filter_slow(has, term, normal, depth, mat, w, h, radius, 0.95, 0.05)
        np.testing.assert_allclose(out[has], want[has], rtol=1e-12)
    assert np.array_equal(out[5], term[5])


def test_auto_traces_only_where_a_lobe_may_see_a_light_in_a_mirror(mirrored_light):
    """glossy_rays="auto" (the default) traces GLOSSY_RAYS_AUTO rays on the glossy floor under the
    mirror and the rect light, and nothing without the mirror: that image is the gathered one, bit
    for bit, and the plan says why."""
    from engine.methods import GLOSSY_RAYS_AUTO

    sc, plan, ldc, llf, _ = mirrored_light
    r = LDCViewRenderer(sc, ldc, llf, plan)
    auto = r.render(CAM, "ldc+ibrt:1")
    assert np.array_equal(auto.radiance, r.render(CAM, "ldc+ibrt:1", glossy_rays=GLOSSY_RAYS_AUTO).radiance)
    assert auto.plan["passes"]["ibrt"]["glossy_rays"] == GLOSSY_RAYS_AUTO
    assert "mirrors" in auto.plan["passes"]["ibrt"]["glossy_why"]
    assert r.render(CAM, "ldc+llf").counts["glossy_rays"] == 0  # no traced method: nothing to trace

    sc2 = _scene(mirror=False)
    caster = EmbreeCaster(sc2)
    plan2 = analyze(sc2)
    r2 = LDCViewRenderer(sc2, bake_ldc(sc2, caster, 32, plan=plan2),
                         bake_llf(sc2, caster, 2, 8, params=ReferenceParams(max_depth=2, glossy_samples=4)), plan2)
    a, g = r2.render(CAM, "ldc+ibrt:1"), r2.render(CAM, "ldc+ibrt:1", glossy_rays=0)
    assert a.counts["glossy_rays"] == 0 and np.array_equal(a.radiance, g.radiance)
    assert a.plan["passes"]["ibrt"]["glossy_why"] == "auto: no mirror"
