"""Rect lights seen by the rays that next-event estimation does not cover: camera rays and rays
leaving mirror (kr) or glossy (kg) lobes, at camera-chain hits and at path vertices (caustic
paths such as diffuse -> mirror -> light). Checked against closed forms and an independent
quadrature, never against the renderer's own outputs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from engine.reference import ReferenceParams, ReferenceRenderer, render_reference
from engine.scene import CameraParams
from tests.engine.scenes import mat, quad, scene

# a tiny orthographic footprint at the origin, looking down from below every light used here
LOOK_DOWN = CameraParams("orthographic", (0, 0.5, 0), (0, 0, 0), (0, 0, -1), 4, 4, ortho_height=0.01)


def _corner_factor(a: float, b: float, c: float) -> float:
    """Form factor from a point to an a x b rectangle parallel to its plane at distance c, with
    a corner straight above the point."""
    A, B = a / math.hypot(a, c), b / math.hypot(b, c)
    return (A * math.atan(b / math.hypot(a, c)) + B * math.atan(a / math.hypot(b, c))) / (2 * math.pi)


def _up_light(size: float, h: float, Le: float, **kw) -> dict:
    """A size x size one-sided rect light centred above the origin at height h, emitting up (+y)."""
    return dict(type="rect", corner=(-size / 2, h, -size / 2), edge_u=(0.0, 0.0, size), edge_v=(size, 0.0, 0.0),
                radiance=(Le, Le, Le), **kw)


def _down_light(size: float, h: float, Le: float, **kw) -> dict:
    """The same light emitting down (-y)."""
    return dict(type="rect", corner=(-size / 2, h, -size / 2), edge_u=(size, 0.0, 0.0), edge_v=(0.0, 0.0, size),
                radiance=(Le, Le, Le), **kw)


def test_diffuse_floor_lit_only_through_a_mirror_gets_the_mirror_image_of_the_light():
    """A light at height h faces up, away from the floor (next-event estimation from the floor
    finds its back side: nothing), under a mirror ceiling (kr) at height H. The floor sees the
    light's mirror image, a downward-facing light of radiance kr Le at height 2H - h:
    L = kd/pi * pi kr Le * 4 F(size/2, size/2, 2H - h) (paths floor -> mirror -> light only: two
    bounces, the second being the mirror's)."""
    kd, kr, Le, size, h, H = 0.7, 0.9, 5.0, 4.0, 1.0, 2.0
    floor = quad((0, 0, 0), 60.0)
    mirror = quad((0, H, 0), 60.0, flip=True)
    sc = scene([(floor, mat("floor", kd=(kd, kd, kd))), (mirror, mat("mirror", kd=(0, 0, 0), kr=(kr, kr, kr)))],
               [_up_light(size, h, Le)])
    out = render_reference(sc, LOOK_DOWN, ReferenceParams(spp=4, indirect_samples=4096, indirect_bounces=2,
                                                          area_light_samples=4))
    want = kd * kr * Le * 4 * _corner_factor(size / 2, size / 2, 2 * H - h)
    assert out.radiance[..., 1].mean() == pytest.approx(want, rel=0.01)
    # one bounce is enough: the mirror vertex, the path's last, still looks for lights through its
    # mirror lobe (the segment Mitsuba's path with max_depth = 1 + 2 counts as well)
    one = render_reference(sc, LOOK_DOWN, ReferenceParams(spp=4, indirect_samples=4096, indirect_bounces=1,
                                                          area_light_samples=4))
    assert one.radiance[..., 1].mean() == pytest.approx(want, rel=0.01)
    # and it only looks for lights: the floor it meets instead is not shaded (that would be a path
    # of 4 segments); with a point light at height hp the floor gets its direct light, plus the same
    I, hp = 2.0, 1.5
    with_point = scene([(floor, mat("floor", kd=(kd, kd, kd))),
                        (mirror, mat("mirror", kd=(0, 0, 0), kr=(kr, kr, kr)))],
                       [_up_light(size, h, Le), dict(type="point", position=(0.0, hp, 0.0), intensity=(I, I, I))])
    both = render_reference(with_point, LOOK_DOWN, ReferenceParams(spp=4, indirect_samples=4096, indirect_bounces=1,
                                                                   area_light_samples=4))
    assert both.radiance[..., 1].mean() == pytest.approx(want + kd / math.pi * I / hp ** 2, rel=0.01)


def test_light_through_a_mirror_reaches_trace_diffuse_paths_too():
    """The public path entry point (used by the bakes) starts the same diffuse paths: the floor
    point under the light gets the same closed form."""
    kd, kr, Le, size, h, H = 0.5, 0.8, 3.0, 4.0, 1.0, 2.0
    sc = scene([(quad((0, 0, 0), 60.0), mat("floor", kd=(kd, kd, kd))),
                (quad((0, H, 0), 60.0, flip=True), mat("mirror", kd=(0, 0, 0), kr=(kr, kr, kr)))],
               [_up_light(size, h, Le)])
    r = ReferenceRenderer(sc)
    n = 8192
    acc = np.zeros((1, 3))
    r.trace_diffuse_paths(np.zeros((n, 3)), np.tile([0.0, 1.0, 0.0], (n, 1)), np.tile([0.0, 1.0, 0.0], (n, 1)),
                          np.zeros(n, np.int32), np.zeros(n, np.int64), np.arange(n, dtype=np.int64),
                          np.uint64(7), 2, acc, params=ReferenceParams(area_light_samples=4))
    # each path adds its estimate of the radiance kd/pi x the light it brings back
    want = kd * kr * Le * 4 * _corner_factor(size / 2, size / 2, 2 * H - h)
    assert acc[0, 0] / n == pytest.approx(want, rel=0.01)


def _glossy_quadrature(g: float, size: float, h: float, Le: float, n: int = 1200) -> float:
    """Radiance toward +y of a floor point at the origin whose BRDF is the normalised Phong lobe
    (g + 2) / (2 pi) cos^g(alpha) around the mirror direction (+y, the viewer is straight above),
    under a downward-facing size x size light of radiance Le at height h: midpoint rule over the
    light, with cos(theta) = cos(alpha) = cos(theta') = h / d."""
    x = (np.arange(n) + 0.5) / n * size - size / 2
    X, Z = np.meshgrid(x, x)
    d = np.sqrt(X ** 2 + Z ** 2 + h ** 2)
    c = h / d
    f = (g + 2) / (2 * math.pi) * c ** g
    return float(np.sum(f * Le * c * c / d ** 2) * (size / n) ** 2)


@pytest.mark.parametrize("g", [1.0, 20.0])
def test_glossy_lobe_sees_the_light_and_agrees_with_next_event_estimation(g):
    """The same Phong lobe as a highlight (ks, sampled by next-event estimation only) and as a
    glossy lobe (kg: its rays meet the light, and next-event estimation evaluates it too, the two
    weighted by multiple importance sampling) must give the same radiance, the quadrature's; half
    ks + half kg must give the full value again (not 1.5 x or 0.5 x of it: nothing counted twice
    or lost)."""
    Le, size, h, rho = 2.0, 2.0, 1.0, 0.8
    want = rho * _glossy_quadrature(g, size, h, Le)
    light = [_down_light(size, h, Le)]
    p = ReferenceParams(spp=16, glossy_samples=256, area_light_samples=64)
    got = {}
    for name, m in {"ks": mat("f", kd=(0, 0, 0), ks=(rho,) * 3, shininess=g),
                    "kg": mat("f", kd=(0, 0, 0), kg=(rho,) * 3, gloss_exponent=g),
                    "half": mat("f", kd=(0, 0, 0), ks=(rho / 2,) * 3, shininess=g, kg=(rho / 2,) * 3,
                                gloss_exponent=g)}.items():
        sc = scene([(quad((0, 0, 0), 40.0), m)], light)
        got[name] = float(render_reference(sc, LOOK_DOWN, p).radiance[..., 0].mean())
    for name, v in got.items():
        assert v == pytest.approx(want, rel=0.01), (name, got, want)


def test_camera_sees_the_emitting_side_of_a_rect_light_once():
    """Camera rays show a rect light's radiance where they meet its emitting side before any
    surface (Mitsuba's area emitters are visible too); the back of a one-sided light is not
    there; a two-sided light shows both sides; an emissive surface modelled at the light's
    place (a visible luminaire) does not add to it; a surface in front hides it."""
    Le, e = 4.0, np.array([4.0, 4.0, 4.0])
    up = CameraParams("orthographic", (0, 0.2, 0), (0, 1, 0), (0, 0, -1), 4, 4, ortho_height=0.5)
    wall = quad((0, 3.0, 0), 40.0, flip=True)  # a dark ceiling behind the light
    dark = mat("ceiling", kd=(0, 0, 0))
    out = render_reference(scene([(wall, dark)], [_down_light(2.0, 1.0, Le)]), up, ReferenceParams(spp=1))
    np.testing.assert_allclose(out.radiance.reshape(-1, 3), np.tile(e, (16, 1)), rtol=1e-6)
    # back side of a one-sided light: the ceiling behind it (black) shows
    out = render_reference(scene([(wall, dark)], [_up_light(2.0, 1.0, Le)]), up, ReferenceParams(spp=1))
    assert out.radiance.max() == 0.0
    out = render_reference(scene([(wall, dark)], [_up_light(2.0, 1.0, Le, two_sided=True)]), up,
                           ReferenceParams(spp=1))
    np.testing.assert_allclose(out.radiance.reshape(-1, 3), np.tile(e, (16, 1)), rtol=1e-6)
    # an emissive luminaire at the light's plane: seen once, not twice
    lum = quad((0, 1.0, 0), 2.0, flip=True)
    out = render_reference(scene([(wall, dark), (lum, mat("lum", kd=(0, 0, 0), emission=tuple(e)))],
                                 [_down_light(2.0, 1.0, Le)]), up, ReferenceParams(spp=1))
    np.testing.assert_allclose(out.radiance.reshape(-1, 3), np.tile(e, (16, 1)), rtol=1e-6)
    # a surface in front of the light hides it
    blocker = quad((0, 0.6, 0), 2.0, flip=True)
    out = render_reference(scene([(wall, dark), (blocker, mat("b", kd=(0, 0, 0)))], [_down_light(2.0, 1.0, Le)]),
                           up, ReferenceParams(spp=1))
    assert out.radiance.max() == 0.0


def test_mirror_shows_the_light_at_camera_chain_hits():
    """Camera -> mirror floor (kr) -> light: kr Le, where the mirror direction meets the light."""
    kr, Le = 0.6, 3.0
    sc = scene([(quad((0, 0, 0), 40.0), mat("m", kd=(0, 0, 0), kr=(kr, kr, kr)))], [_down_light(2.0, 1.0, Le)])
    out = render_reference(sc, LOOK_DOWN, ReferenceParams(spp=1, max_depth=1))
    np.testing.assert_allclose(out.radiance, kr * Le, rtol=1e-6)
    assert render_reference(sc, LOOK_DOWN, ReferenceParams(spp=1, max_depth=0)).radiance.max() == 0.0

