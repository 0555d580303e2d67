"""Dataset generation from a scene: light placement, replacement of the scene's
lights, ground truth, and a generated dataset relit against its ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from engine.errors import InvalidInputError
from engine.reference import ReferenceParams
from engine.relighting.bake import bake_dataset
from engine.relighting.dataset import points_from_depth
from engine.relighting.generate import (
    LightPlacement,
    generate_dataset,
    object_mask,
    place_lights,
    render_ground_truth,
    scene_without_objects,
    surface_aovs,
)
from engine.relighting.grid import locate_directions
from engine.relighting.lights import DirectionalLight, PointLight
from engine.relighting.relight import relight
from engine.scene import CameraParams
from tests.engine.scenes import mat, quad, scene, sphere_mesh

REF = ReferenceParams(spp=1, max_depth=0, seed=0)
CAM = CameraParams("perspective", (0, 3.0, 3.0), (0, 0.3, 0), (0, 1, 0), 24, 24, fov_y_deg=40)


def ball_on_floor(ambient=(0.2, 0.2, 0.2), emission=(0, 0, 0)):
    parts = [(sphere_mesh((0, 0.5, 0), 0.5, subdivisions=3), mat(name="ball", kd=(0.6, 0.6, 0.6),
                                                                 ks=(0.3, 0.3, 0.3), shininess=40.0)),
             (quad((0, 0, 0), 3.0), mat(name="floor", kd=(0.5, 0.4, 0.3), emission=emission))]
    # the scene's own lights, ambient, background and emission must not reach the dataset
    return scene(parts, [dict(type="point", position=(2.0, 3.0, 1.0), intensity=(5.0, 5.0, 5.0)),
                         dict(type="directional", direction=(0, -1, 0), irradiance=(1.0, 1.0, 1.0))],
                 ambient=ambient, background=(0.3, 0.3, 0.3))


@pytest.fixture(scope="module")
def generated():
    sc = ball_on_floor(emission=(0.05, 0.0, 0.0))
    calls = []
    ds = generate_dataset(sc, CAM, LightPlacement(region="hemisphere", spacing_deg=15.0), REF,
                          progress=lambda f, s: calls.append(f))
    return sc, ds, calls


# ---------------------------------------------------------------- placement


def _nn_deg(d):
    dist, _ = cKDTree(d).query(d, k=2)
    return np.degrees(2 * np.arcsin(dist[:, 1] / 2))


@pytest.mark.parametrize("region", ["sphere", "hemisphere", "upper_front_quarter"])
@pytest.mark.parametrize("layout", ["grid", "geodesic"])
def test_placement_regions_and_spacing(region, layout):
    p = LightPlacement(region=region, layout=layout, spacing_deg=10.0, front=(0, 0, 1))
    d = p.directions()
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.array_equal(d, p.directions())  # deterministic
    assert len(np.unique(np.round(d, 9), axis=0)) == len(d)  # no duplicates
    if region != "sphere":
        assert d[:, 1].min() >= -1e-12  # upper half about +y
        assert np.isclose(d[:, 1].min(), 0.0, atol=1e-12)  # lights reach the horizon
    if region == "upper_front_quarter":
        assert d[:, 2].min() >= -1e-12  # front half (+z)
    nn = _nn_deg(d)
    if layout == "grid":
        assert abs(np.median(nn) - 10.0) < 0.3 and nn.max() < 10.5
    else:
        assert 0.5 * 10.0 < nn.min() and np.median(nn) < 1.2 * 10.0 and nn.max() < 1.3 * 10.0
    assert p.light_count() == len(d)


def test_geodesic_sphere_is_a_subdivided_icosahedron():
    for f in (1, 2, 3, 6):
        d = LightPlacement(region="sphere", layout="geodesic", spacing_deg=63.4349 / f).directions()
        assert len(d) == 10 * f * f + 2


@pytest.mark.parametrize("region", ["hemisphere", "upper_front_quarter"])
@pytest.mark.parametrize("layout", ["grid", "geodesic"])
def test_partial_regions_are_covered_to_their_edge(region, layout):
    """Directions inside the region (even close to its boundary) are covered by the baked
    triangulation; directions clearly outside are not (no extrapolation)."""
    from engine.relighting.dataset import IlluminationDataset

    p = LightPlacement(region=region, layout=layout, spacing_deg=10.0, front=(0, 0, 1))
    lights = place_lights(p, (0, 0, 0), 5.0)
    k = len(lights)
    pts = np.zeros((1, 1, 3))
    ds = IlluminationDataset(np.ones((k, 1, 1, 3), np.float32), lights, np.ones(k), pts)
    b = bake_dataset(ds, half=False)
    rng = np.random.default_rng(0)
    q = rng.normal(size=(4000, 3))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    margin = np.sin(np.radians(1.0))
    inside = q[:, 1] > margin
    outside = q[:, 1] < -np.sin(np.radians(10.0))
    if region == "upper_front_quarter":
        inside &= q[:, 2] > margin
        outside |= q[:, 2] < -np.sin(np.radians(10.0))
    tri, _ = locate_directions(b, q)
    assert np.all(tri[inside] >= 0)
    assert np.all(tri[outside] < 0)


def test_placement_dict_round_trip_and_errors():
    p = LightPlacement(region="sphere", layout="geodesic", spacing_deg=5, center=(1, 2, 3), radius=4,
                       intensity=(1, 2, 3), up=(0, 0, 2), front=(1, 0, 0))
    d = p.to_dict()
    assert d["up"] == [0.0, 0.0, 1.0] and d["intensity"] == [1.0, 2.0, 3.0]
    import json

    assert LightPlacement.from_dict(json.loads(json.dumps(d))) == p
    assert LightPlacement.from_dict({}) == LightPlacement()
    bad = [({"region": "cube"}, "placement.region"), ({"layout": "spiral"}, "placement.layout"),
           ({"spacing_deg": 0.1}, r"placement.spacing_deg must be a number in \[0.5, 90\]"),
           ({"spacing_deg": "5"}, "placement.spacing_deg"), ({"spacing_deg": float("nan")}, "spacing_deg"),
           ({"radius": -1}, "placement.radius"), ({"intensity": 0}, "placement.intensity"),
           ({"center": [1, 2]}, "placement.center"), ({"up": [0, 0, 0]}, "placement.up"),
           ({"front": [0, 1, 0]}, "placement.front"), ({"colour": 1}, r"unknown field\(s\) \['colour'\]")]
    for kw, match in bad:
        with pytest.raises(InvalidInputError, match=match):
            LightPlacement.from_dict(kw)
    with pytest.raises(InvalidInputError, match="placement: expected an object"):
        LightPlacement.from_dict([1])


def test_quarter_faces_the_camera():
    """Default front = toward the camera: the quarter's lights are on the camera's side."""
    sc = ball_on_floor()
    cam = CameraParams("perspective", (3.0, 2.0, 0.0), (0, 0.3, 0), (0, 1, 0), 8, 8, fov_y_deg=40)
    ds = generate_dataset(sc, cam, LightPlacement(spacing_deg=30.0), REF)
    rel = ds.light_positions - ds.sphere_center
    assert rel[:, 0].min() >= -1e-9 and rel[:, 1].min() >= -1e-9  # front = +x here, up = +y
    assert np.allclose(ds.meta["resolved_placement"]["front"], [1, 0, 0], atol=1e-6)
    top = CameraParams("perspective", (0, 5.0, 0), (0, 0, 0), (0, 0, -1), 8, 8)
    with pytest.raises(InvalidInputError, match="placement.front"):
        generate_dataset(sc, top, LightPlacement(spacing_deg=30.0), REF)


# ---------------------------------------------------------------- generation


def test_generated_dataset_format(generated):
    sc, ds, calls = generated
    k = ds.light_positions.shape[0]
    assert ds.images.shape == (k, 24, 24, 3) and ds.images.dtype == np.float32
    assert calls == pytest.approx([(j + 1) / k for j in range(k)])
    res = ds.meta["resolved_placement"]
    c, r = np.asarray(res["center"]), res["radius"]
    assert np.allclose(np.linalg.norm(ds.light_positions - c, axis=1), r)
    assert np.array_equal(ds.sphere_center, c)
    assert np.allclose(ds.intensities, r * r)  # default intensity: irradiance 1 at the centre
    assert ds.meta["n_lights"] == k == LightPlacement(region="hemisphere", spacing_deg=15.0).light_count()
    # geometry: the renderer's depth AOV through points_from_depth; mask = pixels hitting geometry
    depth, oid = surface_aovs(sc, CAM)
    pts, valid = points_from_depth(depth, CAM, depth_kind="distance")
    assert np.array_equal(ds.mask, valid & (oid >= 0))
    assert np.array_equal(ds.points[ds.mask], pts[ds.mask])
    assert 0 < ds.mask.sum() < ds.mask.size
    assert np.max(np.linalg.norm(ds.points[ds.mask] - c, axis=1)) < r / 1.5 + 1e-9
    # background 0: nothing where nothing is hit (jittered samples may hit geometry next to the mask)
    from scipy.ndimage import binary_dilation

    assert np.all(ds.images[:, ~binary_dilation(ds.mask)] == 0)


def test_dataset_images_are_lit_only_by_their_light(generated):
    """Image k == the ground truth under light k alone (bit-exact: same renderer, same seed); the
    scene's own lights, ambient, background and emission are gone, so images add like lights."""
    sc, ds, _ = generated
    for j in (0, 7):
        gt = render_ground_truth(sc, CAM, PointLight(tuple(ds.light_positions[j]), tuple(ds.intensities[j])), REF)
        assert np.array_equal(gt, ds.images[j])
    both = render_ground_truth(sc, CAM, [PointLight(tuple(ds.light_positions[j]), tuple(ds.intensities[j]))
                                         for j in (3, 11)], REF)
    assert np.allclose(both, ds.images[3] + ds.images[11], rtol=1e-5, atol=1e-7)
    dark = render_ground_truth(sc, CAM, PointLight((0, 50.0, 0), 0.0), REF)  # a zero light: all black
    assert np.all(dark == 0)


def test_generated_dataset_relights_to_ground_truth(generated):
    sc, ds, _ = generated
    b = bake_dataset(ds, half=False)
    assert b.report["light_radius_deviation_max"] < 1e-12  # the bake uses the generation sphere
    j = 9
    ex = relight(b, PointLight(tuple(ds.light_positions[j]), tuple(ds.intensities[j])))
    assert ex.exact and np.array_equal(ex.image[ds.mask], ds.images[j][ds.mask])
    c = ds.sphere_center
    for light in (PointLight(tuple(c + [1.0, 2.2, 1.2]), 20.0), PointLight(tuple(c + [-8.0, 20.0, 9.0]), 400.0),
                  DirectionalLight((-0.3, -1.0, -0.4), 1.5)):
        gt = render_ground_truth(sc, CAM, light, REF)
        got = relight(b, light)
        m = ds.mask & ~got.outside_mask
        assert m.sum() > 0.9 * ds.mask.sum()
        err = float(np.abs(got.image - gt)[m].mean() / gt[m].mean())
        assert err < 0.1, err


def test_generation_errors_and_cancel():
    sc = ball_on_floor()
    with pytest.raises(InvalidInputError, match=r"placement.radius: the light sphere \(radius 1\) does not enclose"):
        generate_dataset(sc, CAM, {"radius": 1.0, "spacing_deg": 30}, REF)
    away = CameraParams("perspective", (0, 3.0, 3.0), (0, 6.0, 6.0), (0, 1, 0), 8, 8)
    with pytest.raises(InvalidInputError, match="no pixel sees"):
        generate_dataset(sc, away, LightPlacement(spacing_deg=30.0), REF)
    with pytest.raises(InvalidInputError, match="placement: unknown field"):
        generate_dataset(sc, CAM, {"spacings": 5}, REF)

    class Stop(Exception):
        pass

    seen = []

    def cancel(f, stage):
        seen.append(f)
        if len(seen) == 2:
            raise Stop

    with pytest.raises(Stop):
        generate_dataset(sc, CAM, LightPlacement(spacing_deg=30.0), REF, progress=cancel)
    assert len(seen) == 2


def test_scene_without_objects_and_object_mask():
    sc = ball_on_floor()
    ball = object_mask(sc, CAM, ["o0"])
    assert 0 < ball.sum() < 0.5 * ball.size
    bg = scene_without_objects(sc, ["o0"])
    assert bg.n_triangles == int(np.sum(sc.tri_object == 1))
    _, oid = surface_aovs(bg, CAM)
    assert np.all(oid[ball] == 1)  # the floor behind the removed ball
    assert not object_mask(bg, CAM, ["o0"]).any()
    with pytest.raises(InvalidInputError, match=r"objects \['teapot'\] are not in the scene"):
        scene_without_objects(sc, ["teapot"])
