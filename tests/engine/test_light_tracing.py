"""Light-traced caustics in the reference renderer (engine/light_tracing.py): paths light ->
mirror / glossy ... -> diffuse -> camera traced from the lights and joined to the camera, which the
camera's own paths then leave out. Checked against a closed form, against the camera's paths alone
(the same integral, a different estimator) and for determinism."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from engine.errors import InvalidInputError
from engine.light_tracing import applies
from engine.metrics import REC709_WEIGHTS
from engine.raycast import EmbreeCaster
from engine.reference import ReferenceParams, ReferenceRenderer, render_reference
from engine.scene import CameraParams
from tests.engine.scenes import mat, quad, sample_scene, scene
from tests.engine.test_reference_caustics import _corner_factor, _up_light

# looking down at the floor from just below the light, a wide view (the light paths spread over
# every floor point the mirror lights, so the view must hold many of them)
LOOK_DOWN = CameraParams("perspective", (0, 0.9, 0), (0, 0, 0), (0, 0, -1), 16, 16, fov_y_deg=90.0)


def _rect_factor(x: float, z: float, x1: float, x2: float, z1: float, z2: float, c: float) -> float:
    """Form factor from a floor point (x, 0, z) facing up to the rectangle [x1, x2] x [z1, z2] at
    height c facing down: four corner rectangles, added and taken away."""
    def f(a: float, b: float) -> float:
        return math.copysign(1.0, a) * math.copysign(1.0, b) * _corner_factor(abs(a), abs(b), c)
    return f(x2 - x, z2 - z) - f(x1 - x, z2 - z) - f(x2 - x, z1 - z) + f(x1 - x, z1 - z)


def _mirror_room():
    """test_reference_caustics' mirror room with a 4 x 4 mirror (so that more of the light's paths
    land in LOOK_DOWN's view), and the green channel of LOOK_DOWN's image in closed form at the
    pixel centres (every floor point in view sees the whole mirror image of the light)."""
    kd, kr, Le, size, h, H = 0.7, 0.9, 5.0, 4.0, 1.0, 2.0
    floor = quad((0, 0, 0), 60.0)
    mirror = quad((0, H, 0), 4.0, flip=True)
    sc = scene([(floor, mat("floor", kd=(kd, kd, kd))), (mirror, mat("mirror", kd=(0, 0, 0), kr=(kr, kr, kr)))],
               [_up_light(size, h, Le)])
    cam = LOOK_DOWN
    right, up, fwd = cam.basis()
    t = math.tan(math.radians(cam.fov_y_deg) / 2)
    want = np.empty((cam.height, cam.width))
    for y in range(cam.height):
        for x in range(cam.width):
            sx = (2 * (x + 0.5) / cam.width - 1) * t
            sy = (1 - 2 * (y + 0.5) / cam.height) * t
            d = fwd + sx * right + sy * up
            p = np.asarray(cam.eye) + d * (cam.eye[1] / -d[1])
            want[y, x] = kd * kr * Le * _rect_factor(p[0], p[2], -size / 2, size / 2, -size / 2, size / 2,
                                                     2 * H - h)
    return sc, want


def test_floor_lit_through_a_mirror_matches_the_closed_form_with_and_without_light_tracing():
    """The floor of test_reference_caustics' mirror room (a light facing up, away from the floor,
    under a mirror ceiling), seen by a pinhole camera: every floor point sees the light's mirror
    image, a downward light of radiance kr Le at height 2H - h, so L = kd kr Le F(point, image).
    Light-traced (the light's paths reflected by the mirror land on the floor and are joined to the
    camera) and path-traced (the floor's paths find the light in the mirror) both converge to it."""
    sc, want = _mirror_room()
    cam = LOOK_DOWN
    assert applies(sc, cam, 1)
    base = ReferenceParams(spp=64, indirect_samples=64, indirect_bounces=2, area_light_samples=1)
    ren = ReferenceRenderer(sc, EmbreeCaster(sc))
    traced = [ren.render(cam, dataclasses.replace(base, light_paths=64.0, seed=s)) for s in (1, 2)]
    assert traced[0].counts["light_paths"] == 64 * 64 * 256
    img = 0.5 * (traced[0].radiance[..., 1] + traced[1].radiance[..., 1])
    # the image's mean (noise about 0.5 %), and blocks of 4 x 4 pixels (noise about 2 %)
    assert img.mean() == pytest.approx(want.mean(), rel=0.02)
    blocks = img.reshape(4, 4, 4, 4).mean(axis=(1, 3))
    assert np.abs(blocks / want.reshape(4, 4, 4, 4).mean(axis=(1, 3)) - 1).max() < 0.1
    paths = render_reference(sc, cam, dataclasses.replace(base, light_paths=0.0, indirect_samples=1024))
    assert "light_paths" not in paths.counts
    assert paths.radiance[..., 1].mean() == pytest.approx(want.mean(), rel=0.02)


def test_light_tracing_changes_nothing_where_no_path_is_light_traced():
    """No mirror / glossy surface, an orthographic camera or no indirect paths: ``light_paths``
    makes no difference, bit for bit, and no light path is traced (only the effects a scene calls
    for)."""
    sc, _ = _mirror_room()
    ren = ReferenceRenderer(sc, EmbreeCaster(sc))
    ortho = CameraParams("orthographic", (0, 0.9, 0), (0, 0, 0), (0, 0, -1), 8, 8, ortho_height=1.0)
    p = ReferenceParams(spp=4, indirect_samples=4, indirect_bounces=2)
    a = ren.render(ortho, dataclasses.replace(p, light_paths=0.0))
    b = ren.render(ortho, dataclasses.replace(p, light_paths=4.0))
    assert np.array_equal(a.radiance, b.radiance) and "light_paths" not in b.counts
    direct = dataclasses.replace(p, indirect_samples=0)
    a = ren.render(LOOK_DOWN, dataclasses.replace(direct, light_paths=0.0))
    b = ren.render(LOOK_DOWN, dataclasses.replace(direct, light_paths=4.0))
    assert np.array_equal(a.radiance, b.radiance) and "light_paths" not in b.counts
    plain = sample_scene("cornell_box")
    assert not applies(plain.runtime, plain.camera, 4)
    cam = dataclasses.replace(plain.camera, width=24, height=24)
    ren = ReferenceRenderer(plain.runtime, EmbreeCaster(plain.runtime))
    a = ren.render(cam, dataclasses.replace(p, light_paths=0.0))
    b = ren.render(cam, dataclasses.replace(p, light_paths=4.0))
    assert np.array_equal(a.radiance, b.radiance)


def _object_means(img: np.ndarray, oid: np.ndarray) -> dict[int, float]:
    y = img.reshape(-1, 3).astype(np.float64) @ np.asarray(REC709_WEIGHTS)
    o = oid.reshape(-1)
    return {int(k): float(y[o == k].mean()) for k in np.unique(o) if k >= 0 and np.count_nonzero(o == k) >= 40}


def _mirror_glossy_box(size: int, spp: int) -> tuple[ReferenceRenderer, CameraParams, ReferenceParams]:
    """The mirror / glossy Cornell box's renderer, its camera at size x size, and path-traced settings
    of ``spp`` samples with one path and one rect-light sample each."""
    ld = sample_scene("cornell_mirror_glossy")
    cam = dataclasses.replace(ld.camera, width=size, height=size)
    params = ReferenceParams(spp=spp, indirect_samples=spp, indirect_bounces=4, max_depth=6, area_light_samples=1,
                             glossy_samples=1)
    return ReferenceRenderer(ld.runtime, EmbreeCaster(ld.runtime)), cam, params


def test_light_tracing_agrees_with_the_camera_paths_on_the_mirror_glossy_box():
    """The mirror / glossy Cornell box (a smooth-shaded mirror sphere, a glossy box, a rect light):
    the light-traced split and the camera's paths alone estimate the same image. Each object's mean
    brightness agrees within 4 standard errors of the two estimates (measured over seeds); the
    ceiling and the back wall, lit mostly through the sphere, hold most of the caustics."""
    ren, cam, base = _mirror_glossy_box(40, 128)
    runs: dict[float, list[dict[int, float]]] = {0.0: [], 1.0: []}
    for lp in runs:
        for seed in (1, 2, 3):
            out = ren.render(cam, dataclasses.replace(base, light_paths=lp, seed=seed))
            runs[lp].append(_object_means(out.radiance, out.object_id))
    assert len(runs[0.0][0]) >= 5
    for k in runs[0.0][0]:
        a = np.array([r[k] for r in runs[0.0]])
        b = np.array([r[k] for r in runs[1.0]])
        se = math.sqrt(a.var(ddof=1) / a.size + b.var(ddof=1) / b.size)
        assert abs(a.mean() - b.mean()) <= 4.0 * se + 0.003 * a.mean(), (ren.scene.object_names[k], a, b)


def test_light_tracing_lowers_the_noise_where_the_light_comes_through_the_mirror():
    """Seed to seed, the light-traced split is less noisy on the mirror / glossy box's walls (its
    caustics) than the camera's paths alone, at the same camera samples."""
    ren, cam, base = _mirror_glossy_box(32, 32)

    def noise(lp: float) -> float:
        outs = [ren.render(cam, dataclasses.replace(base, light_paths=lp, seed=s)) for s in (1, 2)]
        # the pixels errors are measured on (the luminaire's outline left out)
        sel = ren.error_region(cam, outs[0].object_id, outs[0].depth, base.max_depth).reshape(-1)
        y = [o.radiance.reshape(-1, 3)[sel] @ np.asarray(REC709_WEIGHTS) for o in outs]
        return float(np.sqrt(np.mean((y[0] - y[1]) ** 2) / np.mean(((y[0] + y[1]) / 2) ** 2)))

    with_light, paths_only = noise(1.0), noise(0.0)
    assert with_light < 0.6 * paths_only, (with_light, paths_only)


def test_light_traced_render_is_deterministic_whatever_the_pipelines():
    sc, _ = _mirror_room()
    ren = ReferenceRenderer(sc, EmbreeCaster(sc))
    p = ReferenceParams(spp=8, indirect_samples=8, indirect_bounces=2, light_paths=2.0, seed=3)
    a = ren.render(LOOK_DOWN, p)
    b = ren.render(LOOK_DOWN, dataclasses.replace(p, pipelines=1, chunk_pixels=64))
    assert np.array_equal(a.radiance, b.radiance)
    c = ren.render(LOOK_DOWN, dataclasses.replace(p, seed=4))
    assert not np.array_equal(a.radiance, c.radiance)


def test_progressive_render_adds_the_light_traced_part_to_both_halves():
    """An adaptive render of the mirror room, whose light is all light-traced: it stops at its error
    target, and its estimated error (half A against half B, light-traced parts included) is within
    a factor of two of its error against the closed form."""
    sc, want = _mirror_room()
    ren = ReferenceRenderer(sc, EmbreeCaster(sc))
    p = ReferenceParams(spp=1024, indirect_samples=256, indirect_bounces=2, area_light_samples=1, light_paths=64.0,
                        max_error=0.1)
    out = ren.render(LOOK_DOWN, p)
    assert out.counts["light_paths"] > 0
    assert out.adaptive is not None and out.adaptive["target_met"], out.adaptive
    y = out.radiance[..., 1]
    measured = float(np.sqrt(np.mean((y - want) ** 2)) / want.mean())
    assert 0.5 * measured <= out.adaptive["estimated_error"] <= 2.0 * measured, (out.adaptive, measured)


@pytest.mark.parametrize("bad", [-1.0, 65.0, float("nan"), True, "1"])
def test_light_paths_out_of_range_is_refused(bad):
    with pytest.raises(InvalidInputError, match="light_paths"):
        ReferenceParams(light_paths=bad)
