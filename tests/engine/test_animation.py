"""Scene schema additions for walkthroughs (view space) and the keyframe animation engine."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from api_schemas.errors import format_validation_error
from api_schemas.scene import canonical_scene_json, load_scene_file, load_scene_json, scene_hash
from engine.errors import InvalidInputError
from engine.scene import LightTable, MaterialTable, SceneObjectPart
from engine.walkthrough.animation import AnimatedScene, LightTrack, TransformTrack, decompose_affine
from workers.scene_loader import directory_resolver, load_animated_scene

SAMPLES = Path(__file__).resolve().parents[2] / "samples"


def base_doc() -> dict:
    return {
        "camera": {"type": "perspective", "eye": [0, 1, 5], "look_at": [0, 1, 0], "width": 8, "height": 8},
        "materials": [{"name": "m"}],
        "objects": [{"type": "sphere", "name": "ball", "material": "m", "radius": 1}],
        "lights": [{"type": "point", "name": "key", "position": [0, 5, 0], "intensity": [10, 10, 10]}],
    }


def errors_of(doc: dict) -> list[dict]:
    with pytest.raises(ValidationError) as ei:
        load_scene_json(json.dumps(doc))
    return format_validation_error(ei.value)


# --------------------------------------------------------------------------- schema


def test_samples_keep_their_scene_hash() -> None:
    # hashes of the committed samples before the view_space field existed: adding an optional
    # field must not change the cache key of any existing scene
    before = {
        "cornell_box": "0b538b5fe1200a39a3646e98088817e73adbc2e49b3837a5c1fa6cc141b6e07a",
        "mirror_box": "9429eb9ea28bd1a95890b8ff673c355e263a6d065551425af3e8f8e3a2cefcfa",
        "teapot_glossy": "d9e75642f7902987e68f0bcdea29f63cfc0ec89f1eeb8ffb588bf7e3fbb65184",
    }
    for name, h in before.items():
        scene = load_scene_file(SAMPLES / "scenes" / f"{name}.json")
        assert scene_hash(scene) == h
        assert "view_space" not in canonical_scene_json(scene)


def test_view_space_types_parse_and_change_the_hash() -> None:
    plain = scene_hash(load_scene_json(json.dumps(base_doc())))
    for vs in ({"type": "path", "points": [[0, 1, 3], [1, 1, 3]]},
               {"type": "box", "min": [-1, 1.6, 2], "max": [1, 1.6, 4]},
               {"type": "polygon", "vertices": [[0, 0], [2, 0], [2, 2], [0, 2]], "eye_height": 1.6}):
        doc = base_doc()
        doc["view_space"] = vs
        scene = load_scene_json(json.dumps(doc))
        assert scene.view_space is not None and scene.view_space.type == vs["type"]
        assert scene_hash(scene) != plain
        assert scene_hash(load_scene_json(canonical_scene_json(scene))) == scene_hash(scene)


@pytest.mark.parametrize(
    ("view_space", "field", "words"),
    [
        ({"type": "box", "min": [0, 0, 0], "max": [1, -1, 1]}, "view_space.max", "y: max -1 < min 0"),
        ({"type": "box", "min": [1, 2, 3], "max": [1, 2, 3]}, "view_space.max", "no room"),
        ({"type": "path", "points": [[1, 1, 1], [1, 1, 1]]}, "view_space.points", "no room"),
        ({"type": "polygon", "vertices": [[0, 0], [1, 1], [2, 2]], "eye_height": 1}, "view_space.vertices",
         "zero area"),
        ({"type": "polygon", "vertices": [[0, 0], [4, 0], [0, 2], [3, 3]], "eye_height": 1},
         "view_space.vertices", "intersects itself"),
        ({"type": "sphere"}, "view_space.type", ""),
    ],
)
def test_view_space_errors_name_field(view_space: dict, field: str, words: str) -> None:
    doc = base_doc()
    doc["view_space"] = view_space
    errs = errors_of(doc)
    assert any(e["field"] == field and words in e["message"] for e in errs), errs


def test_keyframe_errors_name_field_and_range() -> None:
    doc = base_doc()
    doc["animation"] = {"start": 0, "end": 2, "objects": {"ball": [{"time": 1, "transform": {}},
                                                                   {"time": 0.5, "transform": {}},
                                                                   {"time": 3, "transform": {}}]}}
    errs = errors_of(doc)
    fields = {e["field"]: e["message"] for e in errs}
    assert "increase strictly" in fields["animation.objects.ball.1.time"]
    assert "[start, end] = [0, 2]" in fields["animation.objects.ball.2.time"]


# --------------------------------------------------------------------------- interpolation


def _trs(t=(0, 0, 0), q=(0, 0, 0, 1), s=(1, 1, 1)) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(q).as_matrix() * np.asarray(s, float)[None, :]
    m[:3, 3] = t
    return m


def test_transform_track_exact_at_keys_and_lerp_slerp_between() -> None:
    q1 = Rotation.from_euler("y", 120, degrees=True).as_quat()
    m0 = _trs((0, 0, 0), (0, 0, 0, 1), (1, 1, 1))
    m1 = _trs((4, 2, 0), q1, (2, 1, 1))
    tr = TransformTrack.from_matrices(0, [1.0, 3.0], [m0, m1])
    np.testing.assert_allclose(tr.matrix_at(1.0), m0, atol=1e-12)
    np.testing.assert_allclose(tr.matrix_at(3.0), m1, atol=1e-12)
    np.testing.assert_allclose(tr.matrix_at(-5.0), m0, atol=1e-12)  # held before the first key
    np.testing.assert_allclose(tr.matrix_at(9.0), m1, atol=1e-12)  # and after the last
    mid = tr.matrix_at(2.0)
    # slow obvious expectation: rotation by 60 degrees about y, translation / scale halfway
    want = _trs((2, 1, 0), Rotation.from_euler("y", 60, degrees=True).as_quat(), (1.5, 1, 1))
    np.testing.assert_allclose(mid, want, atol=1e-9)
    assert tr.changes_within(0.0, 1.5) and not tr.changes_within(3.0, 5.0) and not tr.changes_within(-2, 1.0)


def test_slerp_takes_the_short_arc_and_matrix_keyframes_decompose() -> None:
    qa = Rotation.from_euler("z", 170, degrees=True).as_quat()
    qb = -Rotation.from_euler("z", -170, degrees=True).as_quat()  # same rotation family, far hemisphere
    tr = TransformTrack.from_matrices(0, [0, 1], [_trs(q=qa), _trs(q=qb)])
    ang = Rotation.from_matrix(tr.matrix_at(0.5)[:3, :3]).as_euler("xyz", degrees=True)[2]
    assert abs(abs(ang) - 180) < 1e-6  # through 180, not through 0
    mirror = _trs((1, 2, 3), Rotation.from_euler("x", 30, degrees=True).as_quat(), (-2, 1, 0.5))
    t, q, p = decompose_affine(mirror)
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix() @ p, mirror[:3, :3], atol=1e-12)
    np.testing.assert_allclose(t, (1, 2, 3))


def _two_part_scene(**kw) -> AnimatedScene:
    from tests.engine.scenes import quad

    mats = MaterialTable.from_rows([dict(name="m", kd=(0.5, 0.5, 0.5), ks=(0, 0, 0), shininess=0.0, kr=(0, 0, 0),
                                         kg=(0, 0, 0), gloss_exponent=0.0, emission=(0, 0, 0))])
    floor = quad((0, 0, 0), 4.0)
    tile = quad((0, 0, 0), 1.0)
    parts = [SceneObjectPart("floor", floor, 0), SceneObjectPart("tile", tile.transformed(_trs((0, 1, 0))), 0)]
    rows = [dict(type="point", name="key", position=(0, 3, 0), intensity=(5, 5, 5))]
    return AnimatedScene(parts, mats, rows, local_meshes={1: tile}, **kw)


def test_scene_at_moves_only_animated_objects_and_lights() -> None:
    tr = TransformTrack.from_matrices(1, [0, 2], [_trs((0, 1, 0)), _trs((2, 1, 0))])
    lt = LightTrack(0, np.array([0.0, 2.0]), np.array([[0, 3, 0], [4, 3, 0]], float), np.array([1.0]),
                    np.array([[7.0, 7.0, 7.0]]))
    an = _two_part_scene(start=0, end=2, object_tracks=[tr], light_tracks=[lt])
    s1 = an.scene_at(1.0)
    tile = s1.tri_p[s1.tri_object == 1].reshape(-1, 3)
    np.testing.assert_allclose(tile.mean(axis=0), (1, 1, 0), atol=1e-12)
    floor0 = an.scene_at(0.0).tri_p[an.scene_at(0.0).tri_object == 0]
    np.testing.assert_array_equal(s1.tri_p[s1.tri_object == 0], floor0)
    np.testing.assert_allclose(s1.lights.point_position[0], (2, 3, 0))
    np.testing.assert_allclose(s1.lights.point_intensity[0], (7, 7, 7))  # single key: held
    assert an.moving_objects(0, 2) == [1] and an.changing_lights(0, 2) == [0]
    assert not an.is_static
    with pytest.raises(InvalidInputError, match=r"frame_times\.3: 2\.5 is outside the animation interval \[0, 2\]"):
        an.check_time(2.5, "frame_times.3")


def test_static_scene_is_built_once() -> None:
    an = _two_part_scene()
    assert an.is_static and an.scene_at(0.0) is an.scene_at(5.0)
    assert isinstance(an.lights_at(0.0), LightTable)


def test_loader_animates_the_sample() -> None:
    scene = load_scene_file(SAMPLES / "scenes" / "cornell_animated.json")
    an = load_animated_scene(scene, directory_resolver(SAMPLES))
    names = an.object_names
    ball = names.index("ball")
    for t, centre in ((0.0, (120, 55, 200)), (1.0, (170, 55, 170)), (4.0, (150, 55, 60))):
        sc = an.scene_at(t)
        pts = sc.tri_p[sc.tri_object == ball].reshape(-1, 3)
        np.testing.assert_allclose(0.5 * (pts.min(0) + pts.max(0)), centre, atol=1e-6)
    lamp = an.scene_at(2.0).lights
    np.testing.assert_allclose(lamp.point_position[0], (275, 420, 200))
    np.testing.assert_allclose(lamp.point_intensity[0], (6500, 6250, 7750))
    cube = names.index("cube")
    sc = an.scene_at(4.0)
    pts = sc.tri_p[sc.tri_object == cube].reshape(-1, 3)
    np.testing.assert_allclose(pts.max(0) - pts.min(0), (90, 117, 90), atol=1e-6)  # rotated 90 deg, scaled in y
    assert math.isclose(an.start, 0.0) and math.isclose(an.end, 4.0)


def test_loader_without_animation_is_static() -> None:
    doc = copy.deepcopy(base_doc())
    an = load_animated_scene(load_scene_json(json.dumps(doc)))
    assert an.is_static and an.start == an.end == 0.0


def test_schema_and_engine_view_space_distances_agree() -> None:
    # the API checks eyes with the schema models, the engine with its own types: they must agree
    from api_schemas.scene import BoxViewSpace, PathViewSpace, PolygonViewSpace
    from engine.walkthrough.viewspace import BoxSpace, PathSpace, PolygonSpace

    rng = np.random.default_rng(3)
    pts = [[0.0, 1.0, 0.0], [2.0, 1.0, 1.0], [3.0, 1.5, -1.0]]
    poly = [[0.0, 0.0], [4.0, 0.0], [4.0, 1.0], [1.0, 1.0], [1.0, 3.0], [0.0, 3.0]]
    pairs = [
        (PathViewSpace(points=pts, radius=0.25), PathSpace(np.array(pts), 0.25)),
        (BoxViewSpace(min=(0, 1, 0), max=(2, 1, 3)), BoxSpace(np.array([0.0, 1, 0]), np.array([2.0, 1, 3]))),
        (PolygonViewSpace(vertices=poly, eye_height=1.6), PolygonSpace(np.array(poly), 1.6)),
    ]
    for schema_vs, engine_vs in pairs:
        for p in rng.uniform(-1, 4, size=(200, 3)):
            ds = schema_vs.distance(tuple(p))
            de = max(0.0, engine_vs.distance(p) - getattr(engine_vs, "radius", 0.0))
            assert math.isclose(ds, de, rel_tol=1e-9, abs_tol=1e-12), (schema_vs.type, p, ds, de)
            assert (ds <= 1e-9) == engine_vs.contains(p, 1e-9)
