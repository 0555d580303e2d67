"""The pixels errors are measured on (engine/error_region.py): covered, not showing an emitter or
next to one, on an orthographic view where each pixel's footprint is known in closed form."""

from __future__ import annotations

import numpy as np
import pytest

from engine.error_region import emitter_pixels, error_region
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.scene import CameraParams
from tests.engine.scenes import mat, quad, scene

# 20 x 20 pixels over x, z in [-1, 1] (pixel size 0.1), looking down at a floor of side 1.6: the
# outer two pixel rings see nothing.
TOP = CameraParams("orthographic", (0, 5, 0), (0, 0, 0), (0, 0, -1), 20, 20, ortho_height=2.0)


def _aov(sc):
    out = ReferenceRenderer(sc).render(TOP, ReferenceParams(spp=1, max_depth=0, pixel_jitter=False))
    return out.object_id, out.depth


def _cells(x0: float, x1: float, z0: float, z1: float) -> np.ndarray:
    """(h, w) bool: the pixels whose centre lies in [x0, x1] x [z0, z1] (row 0 at z = -1: up is -z)."""
    c = -1.0 + 0.1 * (np.arange(20) + 0.5)
    zz, xx = np.meshgrid(c, c, indexing="ij")
    return (xx >= x0) & (xx <= x1) & (zz >= z0) & (zz <= z1)


def test_the_background_is_not_in_the_region():
    sc = scene([(quad((0, 0, 0), 1.6), mat())])
    oid, depth = _aov(sc)
    region = error_region(sc, TOP, oid, depth)
    assert np.array_equal(region, _cells(-0.8, 0.8, -0.8, 0.8))
    assert not emitter_pixels(sc, TOP, oid, depth).any()


def test_an_emissive_surface_and_its_neighbours_are_left_out():
    sc = scene([(quad((0, 0, 0), 1.6), mat()), (quad((0.3, 0.5, 0.3), 0.4), mat("lamp", kd=(0, 0, 0),
                                                                                 emission=(20, 20, 20)))])
    oid, depth = _aov(sc)
    lamp = _cells(0.1, 0.5, 0.1, 0.5)  # 4 x 4 pixels
    assert lamp.sum() == 16 and np.array_equal(emitter_pixels(sc, TOP, oid, depth), lamp)
    near = _cells(0.0, 0.6, 0.0, 0.6)  # and one pixel around them
    assert np.array_equal(error_region(sc, TOP, oid, depth), _cells(-0.8, 0.8, -0.8, 0.8) & ~near)


@pytest.mark.parametrize(("faces_up", "two_sided", "seen"), [(True, False, True), (False, False, False),
                                                             (False, True, True)])
def test_a_rect_light_counts_where_its_emitting_side_faces_the_camera(faces_up, two_sided, seen):
    """A 0.4-wide rect light above the floor facing up (toward the camera), down (away) or both."""
    corner, eu, ev = (-0.6, 0.5, -0.6), (0.4, 0, 0), (0, 0, 0.4)  # normal edge_u x edge_v: down
    if faces_up:
        eu, ev = ev, eu
    light = dict(type="rect", corner=corner, edge_u=eu, edge_v=ev, radiance=(5, 5, 5), two_sided=two_sided)
    sc = scene([(quad((0, 0, 0), 1.6), mat())], [light])
    oid, depth = _aov(sc)
    want = _cells(-0.6, -0.2, -0.6, -0.2) if seen else np.zeros((20, 20), bool)
    assert np.array_equal(emitter_pixels(sc, TOP, oid, depth), want)
    region = error_region(sc, TOP, oid, depth)
    assert region.sum() == 16 * 16 - (36 if seen else 0)


def test_a_light_smaller_than_a_pixel_between_pixel_centres_still_counts():
    # 0.03 x 0.03 inside pixel (row 10, col 10) = [0, 0.1]^2, away from its centre (0.05, 0.05):
    # no pixel-centre ray meets it, yet the pixel holds ~9 % of its radiance
    light = dict(type="rect", corner=(0.06, 0.5, 0.06), edge_u=(0, 0, 0.03), edge_v=(0.03, 0, 0),
                 radiance=(500, 500, 500))
    sc = scene([(quad((0, 0, 0), 1.6), mat())], [light])
    oid, depth = _aov(sc)
    want = np.zeros((20, 20), bool)
    want[10, 10] = True
    assert np.array_equal(emitter_pixels(sc, TOP, oid, depth), want)
    # hidden under the floor, it counts nowhere
    sc2 = scene([(quad((0, 0, 0), 1.6), mat())], [dict(light, corner=(0.06, -0.5, 0.06))])
    oid2, depth2 = _aov(sc2)
    assert not emitter_pixels(sc2, TOP, oid2, depth2).any()


def test_a_sliver_of_a_light_seen_at_a_grazing_angle_counts_wherever_it_covers_a_pixel():
    """Perspective, a long thin light tilted almost edge-on: every pixel that any of 16 x 16 rays
    through its square sees the light through is counted, and nothing farther than a pixel from one."""
    from engine.camera import camera_rays

    cam = CameraParams("perspective", (0.0, 0.3, 3.0), (0.0, 0.55, 0.0), (0, 1, 0), 64, 48, 30.0)
    light = dict(type="rect", corner=(-0.7, 0.6, -0.2), edge_u=(1.4, 0.0, 0.0), edge_v=(0.0, -0.01, 0.3),
                 radiance=(50, 50, 50), two_sided=True)
    sc = scene([(quad((0, 0, 0), 1.6), mat())], [light])
    out = ReferenceRenderer(sc).render(cam, ReferenceParams(spp=1, max_depth=0, pixel_jitter=False))
    got = emitter_pixels(sc, cam, out.object_id, out.depth)
    k = 16
    ys, xs, sy, sx = np.meshgrid(np.arange(48), np.arange(64), (np.arange(k) + 0.5) / k, (np.arange(k) + 0.5) / k,
                                 indexing="ij")
    o, d = camera_rays(cam, (xs + sx).ravel(), (ys + sy).ravel())
    lt = sc.lights
    u, v, c = lt.rect_edge_u[0], lt.rect_edge_v[0], lt.rect_corner[0]
    n = np.cross(u, v)
    t = ((c - o) @ n) / (d @ n)
    p = o + t[:, None] * d - c
    a = np.cross(p, v) @ n / (n @ n)
    b = np.cross(u, p) @ n / (n @ n)
    # the floor is below the light: nothing occludes it from this eye
    brute = ((t > 0) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)).reshape(48, 64, k * k).any(axis=2)
    assert brute.sum() > 20
    assert not (brute & ~got).any()
    from scipy.ndimage import binary_dilation
    assert not (got & ~binary_dilation(brute, np.ones((3, 3), bool))).any()


def test_an_emitter_seen_in_a_mirror_is_left_out_by_the_renderers_region():
    """A rect light facing down over a mirror floor: the camera above sees its back (nothing) and,
    in the mirror, its emitting side; the renderer's region leaves those pixels out (with their
    ring), the pure-NumPy region cannot see through mirrors."""
    light = dict(type="rect", corner=(-0.6, 0.5, -0.6), edge_u=(0.4, 0, 0), edge_v=(0, 0, 0.4), radiance=(5, 5, 5))
    sc = scene([(quad((0, 0, 0), 1.6), mat("mirror", kd=(0, 0, 0), kr=(0.9, 0.9, 0.9)))], [light])
    oid, depth = _aov(sc)
    ren = ReferenceRenderer(sc)
    floor = _cells(-0.8, 0.8, -0.8, 0.8)
    assert np.array_equal(error_region(sc, TOP, oid, depth), floor)
    in_mirror = ren.emitters_in_mirrors(TOP, max_depth=1)
    assert np.array_equal(in_mirror, _cells(-0.6, -0.2, -0.6, -0.2))
    assert np.array_equal(ren.error_region(TOP, oid, depth, max_depth=1), floor & ~_cells(-0.7, -0.1, -0.7, -0.1))
    # no reflection asked for, or no mirror: nothing more is left out
    assert not ren.emitters_in_mirrors(TOP, max_depth=0).any()
    matte = scene([(quad((0, 0, 0), 1.6), mat())], [light])
    assert not ReferenceRenderer(matte).emitters_in_mirrors(TOP, max_depth=4).any()
    # an adaptive render estimates its error over the same pixels
    out = ren.render(TOP, ReferenceParams(spp=16, max_depth=1, area_light_samples=1, max_error=0.5))
    assert out.adaptive["region_pixels"] == int((floor & ~_cells(-0.7, -0.1, -0.7, -0.1)).sum())
    assert out.error_region is not None and np.array_equal(out.error_region, floor & ~_cells(-0.7, -0.1, -0.7, -0.1))
    assert ren.render(TOP, ReferenceParams(spp=1, max_depth=1)).error_region is None  # a plain render has none
