"""The view's diffuse radiance read between an LDC's samples (``diffuse_filter="bilinear"``,
engine/newviews/renderer.py ``_bilinear_diffuse``) instead of from the nearest sample."""

from __future__ import annotations

import numpy as np
import pytest

from engine.camera import camera_rays, pixel_centers
from engine.errors import InvalidInputError
from engine.newviews.effects import analyze
from engine.newviews.ldc import bake_ldc, surface_attributes
from engine.newviews.renderer import LDCViewRenderer
from engine.raycast import EmbreeCaster
from engine.scene import CameraParams
from tests.engine.scenes import mat, quad, scene


def _paint(sc, ldc, f) -> None:
    """Every sample's diffuse radiance (both sides, every channel) set to f(its point)."""
    for ax in ldc.axes:
        p, _, _ = surface_attributes(sc, ax.ldi.prim, ax.ldi.u, ax.ldi.v)
        ax.diffuse[:] = f(p)[:, None, None].astype(np.float32)


def _ramp_scene():
    """A floor and a wall tilted by 30 degrees about z (so its samples sit at varying depths)."""
    wall = quad((0, 0, 0), 1.6, 0)
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    v = wall.vertices @ rot.T + np.array([-0.6, 0.9, 0.0])
    n = wall.normals @ rot.T
    tilted = type(wall)(np.ascontiguousarray(v), wall.faces, np.ascontiguousarray(n))
    return scene([(quad((0, 0, 0), 2.0, 1), mat("floor")), (tilted, mat("wall"))],
                 [dict(type="point", position=(0.0, 1.5, 0.3), intensity=(3.0, 3.0, 3.0))])


def _camera(eye, look_at, fov: float, width: int, height: int) -> CameraParams:
    return CameraParams(kind="perspective", eye=eye, look_at=look_at, up=(0.0, 1.0, 0.0), width=width,
                        height=height, fov_y_deg=fov)


def _ray_plane(cam: CameraParams, point, normal):
    o, d = camera_rays(cam, *pixel_centers(cam))
    t = ((np.asarray(point) - o) @ normal) / (d @ normal)
    return o + t[:, None] * d


def test_a_linear_field_on_a_plane_is_reproduced_at_every_pixel_centre():
    sc = _ramp_scene()
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, 24, plan=analyze(sc))

    def field(p):
        return 1.0 + 0.3 * p[:, 0] + 0.2 * p[:, 2]

    _paint(sc, ldc, field)
    cam = _camera((0.3, 1.4, 2.2), (0.1, 0.0, 0.0), 40.0, 96, 72)
    want = field(_ray_plane(cam, (0, 0, 0), np.array([0.0, 1.0, 0.0]))).reshape(72, 96)
    out = {}
    for filt in ("bilinear", "nearest"):
        r = LDCViewRenderer(sc, ldc, None, caster=caster, diffuse_filter=filt).render(cam, "ldc")
        # where the 2 x 2 samples around a point are all on the floor: more than two sample
        # spacings from its border and from the wall (whose foot is at x = -0.6 - 0.8 sin 30)
        q = _ray_plane(cam, (0, 0, 0), np.array([0.0, 1.0, 0.0]))
        inner = (r.object_id == 0).ravel() & np.all(np.abs(q[:, [0, 2]]) < 1.0 - 2 * ldc.h, axis=1) & \
            (q[:, 0] > -1.0 + 2 * ldc.h)
        out[filt] = np.abs(r.radiance[..., 1].ravel() - want.ravel())[inner]
        if filt == "bilinear":
            assert r.counts["diffuse_interpolated"] > 0.5 * r.object_id.size
            assert "diffuse" in r.timings
    assert out["bilinear"].size > 1500
    assert out["bilinear"].max() < 2e-5, out["bilinear"].max()
    # the nearest sample is off by up to half a sample spacing times the slope
    assert out["nearest"].max() > 0.01


def test_a_tilted_plane_interpolates_between_samples_at_different_depths():
    sc = _ramp_scene()
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, 24, plan=analyze(sc))

    def field(p):
        return 2.0 + 0.5 * p[:, 1] - 0.25 * p[:, 2]

    _paint(sc, ldc, field)
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    normal = np.array([c, s, 0.0])  # the wall's, rotated
    cam = _camera((1.6, 1.2, 1.2), (-0.6, 0.9, 0.0), 35.0, 80, 80)
    q = _ray_plane(cam, (-0.6, 0.9, 0.0), normal)
    want = field(q).reshape(80, 80)
    r = LDCViewRenderer(sc, ldc, None, caster=caster).render(cam, "ldc")
    # where the 2 x 2 samples around a point are all on the wall: more than two sample
    # spacings from its border (in the wall's own axes: along z, and in-plane across it)
    local = q - np.array([-0.6, 0.9, 0.0])
    across = local @ np.array([-s, c, 0.0])
    inner = (r.object_id == 1).ravel() & (np.abs(local[:, 2]) < 0.8 - 2 * ldc.h) & \
        (np.abs(across) < 0.8 - 2 * ldc.h)
    err = np.abs(r.radiance[..., 0].ravel() - want.ravel())[inner]
    assert err.size > 800
    assert err.max() < 2e-5, err.max()


def test_nothing_bleeds_across_objects_or_creases():
    # one value per surface: interpolation must give back exactly the nearest sample's
    sc = scene([(quad((0, 0, 0), 2.0, 1), mat("floor")), (quad((-1, 1, 0), 2.0, 0), mat("left")),
                (quad((0, 1, -1), 2.0, 2), mat("back"))],
               [dict(type="point", position=(0.0, 1.5, 0.3), intensity=(3.0, 3.0, 3.0))])
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, 20, plan=analyze(sc))
    for ax in ldc.axes:
        ax.diffuse[:] = (1.0 + ax.object.astype(np.float32))[:, None, None]
    cam = _camera((0.8, 1.3, 2.0), (-0.3, 0.5, -0.4), 50.0, 64, 64)
    a = LDCViewRenderer(sc, ldc, None, caster=caster).render(cam, "ldc")
    b = LDCViewRenderer(sc, ldc, None, caster=caster, diffuse_filter="nearest").render(cam, "ldc")
    assert a.counts["diffuse_interpolated"] > 1000
    np.testing.assert_array_equal(a.radiance, b.radiance)


def test_edge_supersampling_interpolates_its_sub_pixels_too():
    sc = _ramp_scene()
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, 24, plan=analyze(sc))
    _paint(sc, ldc, lambda p: 1.0 + 0.3 * p[:, 0] + 0.2 * p[:, 2])
    cam = _camera((0.3, 1.4, 2.2), (0.1, 0.0, 0.0), 40.0, 48, 36)
    r = LDCViewRenderer(sc, ldc, None, caster=caster).render(cam, "ldc", supersample=2, antialias="edges")
    assert "edge_diffuse" in r.timings
    assert r.counts["edge_pixels"] > 0


def test_an_unknown_filter_is_refused():
    sc = _ramp_scene()
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, 8, plan=analyze(sc))
    with pytest.raises(InvalidInputError, match="diffuse_filter"):
        LDCViewRenderer(sc, ldc, None, caster=caster, diffuse_filter="cubic")
