"""Scene schema: valid documents parse, each invalid one fails at the field to fix."""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import BaseModel, ValidationError

import api_schemas
from api_schemas import scene as scene_module
from api_schemas.errors import field_path, format_error_details, format_validation_error
from api_schemas.export import main as export_main
from api_schemas.export import render_schema
from api_schemas.scene import (
    InlineMeshObject,
    Material,
    PerspectiveCamera,
    Scene,
    SceneFileTooLargeError,
    Transform,
    canonical_scene_json,
    load_scene_file,
    load_scene_json,
    scene_hash,
    scene_json_schema,
)

REPO = Path(__file__).resolve().parents[2]
SCHEMA_FILE = REPO / "docs" / "scene.schema.json"

Doc = dict[str, Any]


def good_doc() -> Doc:
    """A scene using every object type, every light type and an animation."""
    return {
        "schema_version": 1,
        "name": "everything",
        "camera": {
            "type": "perspective",
            "eye": [0, 2, 8],
            "look_at": [0, 1, 0],
            "up": [0, 1, 0],
            "fov_y_deg": 40,
            "width": 320,
            "height": 240,
        },
        "materials": [
            {"name": "white", "kd": [0.7, 0.7, 0.7]},
            {"name": "plastic", "kd": [0.5, 0.1, 0.1], "ks": [0.3, 0.3, 0.3], "shininess": 50},
            {"name": "chrome", "kd": [0, 0, 0], "kr": [0.9, 0.9, 0.9]},
            {"name": "brushed", "kd": [0.2, 0.2, 0.2], "kg": [0.6, 0.6, 0.6], "gloss_exponent": 200},
            {"name": "lamp", "kd": [0, 0, 0], "emission": [5, 5, 4]},
        ],
        "objects": [
            {"type": "sphere", "name": "ball", "material": "plastic", "center": [0, 1, 0], "radius": 1},
            {"type": "plane", "name": "floor", "material": "white", "size": [20, 20], "segments": 4},
            {
                "type": "box",
                "material": "chrome",
                "size": [1, 2, 0.5],
                "transform": {"translate": [3, 1, 0], "rotate_deg": [0, 30, 0], "scale": [1, 1, 1]},
            },
            {
                "type": "cylinder",
                "material": "brushed",
                "radius": 0.3,
                "height": 2,
                "segments": 32,
                "capped": False,
                "transform": {"quaternion": [0, 0, 0, 1]},
            },
            {"type": "disk", "material": "lamp", "radius": 0.5, "center": [0, 4, 0]},
            {
                "type": "mesh",
                "name": "tri",
                "material": "white",
                "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]],
                "faces": [[0, 1, 2], [1, 3, 2]],
                "normals": [[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1]],
                "transform": {
                    "matrix": [[1, 0, 0, -3], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                },
            },
            {"type": "mesh_file", "material": "white", "path": "meshes/bunny.ply", "on_invalid": "clean"},
        ],
        "lights": [
            {"type": "point", "name": "key", "position": [4, 6, 4], "intensity": [100, 100, 90]},
            {"type": "directional", "name": "sun", "direction": [-1, -2, -1], "irradiance": [2, 2, 2]},
            {
                "type": "rect",
                "name": "panel",
                "corner": [-1, 5, -1],
                "edge_u": [2, 0, 0],
                "edge_v": [0, 0, 2],
                "radiance": [10, 10, 10],
                "two_sided": True,
            },
        ],
        "ambient": [0.01, 0.01, 0.01],
        "background": [0.1, 0.2, 0.3],
        "animation": {
            "start": 0,
            "end": 2,
            "objects": {
                "ball": [
                    {"time": 0, "transform": {}},
                    {"time": 2, "transform": {"translate": [0, 1, 0]}},
                ],
            },
            "lights": {
                "key": [{"time": 0, "position": [4, 6, 4]}, {"time": 1, "intensity": [50, 50, 50]}],
                "sun": [{"time": 1, "intensity": [1, 1, 1]}],
            },
        },
    }


def errors_of(doc: Doc) -> list[dict[str, str]]:
    with pytest.raises(ValidationError) as info:
        load_scene_json(json.dumps(doc))
    return [dict(e) for e in format_validation_error(info.value)]


def fields_of(doc: Doc) -> list[str]:
    return [e["field"] for e in errors_of(doc)]


# --------------------------------------------------------------------------- valid documents


def test_good_scene_parses() -> None:
    scene = load_scene_json(json.dumps(good_doc()))
    assert isinstance(scene.camera, PerspectiveCamera)
    assert scene.camera.fov_y_deg == 40.0
    assert [type(o).__name__ for o in scene.objects] == [
        "SphereObject",
        "PlaneObject",
        "BoxObject",
        "CylinderObject",
        "DiskObject",
        "InlineMeshObject",
        "MeshFileObject",
    ]
    assert [type(light).__name__ for light in scene.lights] == ["PointLight", "DirectionalLight", "RectLight"]
    assert scene.material_index() == {"white": 0, "plastic": 1, "chrome": 2, "brushed": 3, "lamp": 4}
    assert scene.animation is not None and set(scene.animation.objects) == {"ball"}
    # JSON integers become floats where floats are expected.
    assert scene.camera.eye == (0.0, 2.0, 8.0) and all(isinstance(c, float) for c in scene.camera.eye)


def test_empty_scene_is_valid() -> None:
    scene = load_scene_json(
        '{"camera": {"type": "orthographic", "eye": [0, 0, 1], "look_at": [0, 0, 0],'
        ' "ortho_height": 2, "width": 4, "height": 4}}'
    )
    assert scene.objects == [] and scene.lights == [] and scene.materials == []
    assert scene.name == "untitled" and scene.schema_version == 1 and scene.animation is None


def test_material_kind_helpers() -> None:
    by_name = {m.name: m for m in load_scene_json(json.dumps(good_doc())).materials}
    assert by_name["white"].is_diffuse and not by_name["white"].has_highlight
    assert by_name["lamp"].is_diffuse  # emission does not make a material view-dependent
    assert by_name["plastic"].has_highlight and not by_name["plastic"].is_diffuse
    assert by_name["chrome"].is_mirror and not by_name["chrome"].is_glossy
    assert by_name["brushed"].is_glossy and not by_name["brushed"].is_mirror
    # ks with shininess 0 is a valid (wide) lobe
    assert Material(name="wide", kd=(0.5, 0.5, 0.5), ks=(0.5, 0.5, 0.5)).has_highlight


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_checks_are_scale_free(scale: float) -> None:
    doc = good_doc()
    doc["camera"].update(eye=[0, 2 * scale, 8 * scale], look_at=[0, scale, 0])
    doc["lights"][2].update(edge_u=[2 * scale, 0, 0], edge_v=[0, 0, 2 * scale])
    doc["objects"][0]["transform"] = {"scale": [scale, scale, scale]}
    load_scene_json(json.dumps(doc))


def test_numpy_inputs_from_python() -> None:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    faces = np.array([[0, 1, 2]], dtype=np.int64)
    mesh = InlineMeshObject(vertices=vertices, faces=faces, material="m")
    assert mesh.faces == [(0, 1, 2)] and mesh.vertices[1] == (1.0, 0.0, 0.0)
    cam = PerspectiveCamera(eye=np.array([0.0, 0, 5]), look_at=(0, 0, 0), width=np.int64(64), height=48)
    assert cam.width == 64 and type(cam.width) is int


def test_models_are_frozen_and_forbid_extra() -> None:
    models = [
        obj
        for obj in vars(scene_module).values()
        if isinstance(obj, type) and issubclass(obj, BaseModel) and obj.__module__ == scene_module.__name__
    ]
    assert len(models) == 24  # + the three view-space models (walkthroughs), the three light bases
    for model in models:
        assert model.model_config.get("extra") == "forbid", model
        assert model.model_config.get("frozen") is True, model
    scene = load_scene_json(json.dumps(good_doc()))
    with pytest.raises(ValidationError):
        scene.camera.width = 10  # type: ignore[misc]


# --------------------------------------------------------------------------- invalid documents

Mutation = Callable[[Doc], None]


def _set(path: str, value: Any) -> Mutation:
    """Set a value at a dotted path (integers index lists)."""

    def mutate(doc: Doc) -> None:
        *parents, last = [int(p) if p.isdigit() else p for p in path.split(".")]
        node: Any = doc
        for p in parents:
            node = node[p]
        node[last] = value

    return mutate


def _pop(path: str) -> Mutation:
    def mutate(doc: Doc) -> None:
        *parents, last = [int(p) if p.isdigit() else p for p in path.split(".")]
        node: Any = doc
        for p in parents:
            node = node[p]
        del node[last]

    return mutate


def _append(path: str, value: Any) -> Mutation:
    def mutate(doc: Doc) -> None:
        node: Any = doc
        for p in [int(p) if p.isdigit() else p for p in path.split(".")]:
            node = node[p]
        node.append(value)

    return mutate


def _seq(*mutations: Mutation) -> Mutation:
    def mutate(doc: Doc) -> None:
        for m in mutations:
            m(doc)

    return mutate


SINGULAR = [[1, 0, 0, 0], [0, 1, 0, 0], [2, 0, 0, 0], [0, 0, 0, 1]]
MESH_FILE = 6  # index of the mesh_file object in good_doc()
MESH = 5

BAD_CASES: list[tuple[str, Mutation, str]] = [
    # numbers
    ("nan_in_eye", _set("camera.eye", [math.nan, 0, 0]), "camera.eye.0"),
    ("inf_in_look_at", _set("camera.look_at", [0, math.inf, 0]), "camera.look_at.1"),
    ("bool_as_number", _set("camera.eye", [0, True, 8]), "camera.eye.1"),
    ("string_as_number", _set("materials.1.shininess", "50"), "materials.1.shininess"),
    ("vec3_too_short", _set("camera.up", [0, 1]), "camera.up.2"),
    ("rgb_single_number", _set("background", 0.5), "background"),
    ("negative_kd", _set("materials.0.kd", [0.5, -0.1, 0.5]), "materials.0.kd.1"),
    ("negative_intensity", _set("lights.0.intensity", [-1, 1, 1]), "lights.0.intensity.0"),
    ("negative_ambient", _set("ambient", [0, 0, -1e-9]), "ambient.2"),
    # materials
    ("kd_plus_ks_above_one", _set("materials.1.ks", [0.3, 0.95, 0.3]), "materials.1"),
    ("kd_plus_kr_above_one", _set("materials.2.kd", [0.2, 0.2, 0.2]), "materials.2"),
    ("kg_needs_gloss_exponent", _pop("materials.3.gloss_exponent"), "materials.3.gloss_exponent"),
    ("shininess_too_large", _set("materials.1.shininess", 1e8), "materials.1.shininess"),
    ("bad_material_name", _set("materials.0.name", "white paint"), "materials.0.name"),
    ("duplicate_material_names", _append("materials", {"name": "white"}), "materials.5.name"),
    ("unknown_material_reference", _set("objects.3.material", "gold"), "objects.3.material"),
    # unknown fields anywhere
    ("extra_root", _set("colour", [1, 1, 1]), "colour"),
    ("extra_camera", _set("camera.fov", 40), "camera.fov"),
    ("extra_material", _set("materials.0.roughness", 0.5), "materials.0.roughness"),
    ("extra_object", _set("objects.0.radius_m", 1), "objects.0.radius_m"),
    ("extra_transform", _set("objects.2.transform.rotation", [0, 1, 0]), "objects.2.transform.rotation"),
    ("extra_light", _set("lights.1.angle", 0.5), "lights.1.angle"),
    ("extra_animation", _set("animation.loop", True), "animation.loop"),
    ("extra_keyframe", _set("animation.objects.ball.0.ease", "in"), "animation.objects.ball.0.ease"),
    # discriminators
    ("unknown_object_type", _set("objects.0.type", "cone"), "objects.0.type"),
    ("missing_object_type", _pop("objects.0.type"), "objects.0.type"),
    ("unknown_light_type", _set("lights.0.type", "spot"), "lights.0.type"),
    ("unknown_camera_type", _set("camera.type", "fisheye"), "camera.type"),
    ("wrong_schema_version", _set("schema_version", 2), "schema_version"),
    ("bool_schema_version", _set("schema_version", True), "schema_version"),
    # camera
    ("fov_zero", _set("camera.fov_y_deg", 0), "camera.fov_y_deg"),
    ("fov_180", _set("camera.fov_y_deg", 180), "camera.fov_y_deg"),
    ("eye_equals_look_at", _set("camera.look_at", [0, 2, 8]), "camera.look_at"),
    ("up_parallel", _set("camera.up", [0, 1, 8]), "camera.up"),
    ("up_antiparallel", _set("camera.up", [0, -2, -16]), "camera.up"),
    ("up_zero", _set("camera.up", [0, 0, 0]), "camera.up"),
    ("width_zero", _set("camera.width", 0), "camera.width"),
    ("width_too_large", _set("camera.width", 16385), "camera.width"),
    ("width_float", _set("camera.width", 320.0), "camera.width"),
    ("too_many_pixels", _seq(_set("camera.width", 16384), _set("camera.height", 4000)), "camera.height"),
    (
        "ortho_height_zero",
        _set(
            "camera",
            {
                "type": "orthographic",
                "eye": [0, 0, 1],
                "look_at": [0, 0, 0],
                "ortho_height": 0,
                "width": 4,
                "height": 4,
            },
        ),
        "camera.ortho_height",
    ),
    # objects
    ("radius_zero", _set("objects.0.radius", 0), "objects.0.radius"),
    ("subdivisions_9", _set("objects.0.subdivisions", 9), "objects.0.subdivisions"),
    ("box_size_zero", _set("objects.2.size", [1, 0, 1]), "objects.2.size.1"),
    ("cylinder_segments_2", _set("objects.3.segments", 2), "objects.3.segments"),
    ("capped_not_bool", _set("objects.3.capped", 1), "objects.3.capped"),
    ("plane_size_negative", _set("objects.1.size", [-1, 1]), "objects.1.size.0"),
    ("duplicate_object_names", _set("objects.1.name", "ball"), "objects.1.name"),
    ("face_index_too_large", _set(f"objects.{MESH}.faces", [[0, 1, 2], [1, 4, 2]]), f"objects.{MESH}.faces"),
    ("face_index_negative", _set(f"objects.{MESH}.faces", [[0, -1, 2]]), f"objects.{MESH}.faces"),
    ("face_index_huge", _set(f"objects.{MESH}.faces", [[0, 1, 2**70]]), f"objects.{MESH}.faces"),
    ("face_not_triangle", _set(f"objects.{MESH}.faces", [[0, 1, 2, 3]]), f"objects.{MESH}.faces.0"),
    ("no_faces", _set(f"objects.{MESH}.faces", []), f"objects.{MESH}.faces"),
    ("too_few_vertices", _set(f"objects.{MESH}.vertices", [[0, 0, 0]]), f"objects.{MESH}.vertices"),
    ("normals_count", _set(f"objects.{MESH}.normals", [[0, 0, 1]]), f"objects.{MESH}.normals"),
    ("zero_normal", _set(f"objects.{MESH}.normals.2", [0, 0, 0]), f"objects.{MESH}.normals"),
    ("path_dotdot", _set(f"objects.{MESH_FILE}.path", "../x"), f"objects.{MESH_FILE}.path"),
    ("path_inner_dotdot", _set(f"objects.{MESH_FILE}.path", "a/../../x"), f"objects.{MESH_FILE}.path"),
    ("path_absolute", _set(f"objects.{MESH_FILE}.path", "/abs"), f"objects.{MESH_FILE}.path"),
    ("path_backslash", _set(f"objects.{MESH_FILE}.path", "C:\\x"), f"objects.{MESH_FILE}.path"),
    ("path_drive", _set(f"objects.{MESH_FILE}.path", "C:/x"), f"objects.{MESH_FILE}.path"),
    ("path_nul", _set(f"objects.{MESH_FILE}.path", "a\x00b"), f"objects.{MESH_FILE}.path"),
    ("path_empty", _set(f"objects.{MESH_FILE}.path", ""), f"objects.{MESH_FILE}.path"),
    ("on_invalid_unknown", _set(f"objects.{MESH_FILE}.on_invalid", "fix"), f"objects.{MESH_FILE}.on_invalid"),
    # transforms
    (
        "zero_quaternion",
        _set("objects.3.transform.quaternion", [0, 0, 0, 0]),
        "objects.3.transform.quaternion",
    ),
    (
        "quaternion_len_3",
        _set("objects.3.transform.quaternion", [0, 0, 1]),
        "objects.3.transform.quaternion.3",
    ),
    (
        "rotate_and_quaternion",
        _set("objects.2.transform.quaternion", [0, 0, 0, 1]),
        "objects.2.transform.quaternion",
    ),
    ("scale_zero", _set("objects.2.transform.scale", [1, 0, 1]), "objects.2.transform.scale"),
    (
        "singular_matrix",
        _set(f"objects.{MESH}.transform.matrix", SINGULAR),
        f"objects.{MESH}.transform.matrix",
    ),
    (
        "matrix_projective_row",
        _set(f"objects.{MESH}.transform.matrix.3", [0, 0, 1, 1]),
        f"objects.{MESH}.transform.matrix",
    ),
    (
        "matrix_with_translate",
        _set(f"objects.{MESH}.transform.translate", [1, 0, 0]),
        f"objects.{MESH}.transform.matrix",
    ),
    (
        "matrix_nan",
        _set(f"objects.{MESH}.transform.matrix.1", [0, math.nan, 0, 0]),
        f"objects.{MESH}.transform.matrix.1.1",
    ),
    ("matrix_3_rows", _pop(f"objects.{MESH}.transform.matrix.3"), f"objects.{MESH}.transform.matrix.3"),
    # lights
    ("rect_parallel_edges", _set("lights.2.edge_v", [-3, 0, 0]), "lights.2.edge_v"),
    ("rect_zero_edge", _set("lights.2.edge_u", [0, 0, 0]), "lights.2.edge_u"),
    ("directional_zero", _set("lights.1.direction", [0, 0, 0]), "lights.1.direction"),
    ("duplicate_light_names", _set("lights.2.name", "key"), "lights.2.name"),
    (
        "two_sided_string",
        _set("lights.2.two_sided", "yes"),
        "lights.2.two_sided",
    ),
    # animation
    ("end_not_after_start", _set("animation", {"start": 1, "end": 1}), "animation.end"),
    (
        "keyframes_out_of_order",
        _set("animation.objects.ball", [{"time": 1, "transform": {}}, {"time": 0.5, "transform": {}}]),
        "animation.objects.ball.1.time",
    ),
    (
        "keyframes_equal_times",
        _set("animation.lights.key.1.time", 0),
        "animation.lights.key.1.time",
    ),
    ("keyframe_after_end", _set("animation.objects.ball.1.time", 2.5), "animation.objects.ball.1.time"),
    ("keyframe_before_start", _set("animation.lights.sun.0.time", -1), "animation.lights.sun.0.time"),
    ("empty_track", _set("animation.objects.ball", []), "animation.objects.ball"),
    (
        "animation_unknown_object",
        _set("animation.objects.ghost", [{"time": 0, "transform": {}}]),
        "animation.objects.ghost",
    ),
    (
        # a key that equals a union tag must survive the tag stripping
        "animation_unknown_object_named_like_a_tag",
        _set("animation.objects.sphere", [{"time": 0, "transform": {}}]),
        "animation.objects.sphere",
    ),
    (
        "animation_unnamed_light",
        _set("animation.lights.ghost", [{"time": 0, "intensity": [1, 1, 1]}]),
        "animation.lights.ghost",
    ),
    (
        "directional_light_position_keyframe",
        _set("animation.lights.sun.0.position", [0, 1, 0]),
        "animation.lights.sun.0.position",
    ),
    ("empty_light_keyframe", _pop("animation.lights.sun.0.intensity"), "animation.lights.sun.0"),
    (
        "keyframe_transform_invalid",
        _set("animation.objects.ball.1.transform.scale", [0, 1, 1]),
        "animation.objects.ball.1.transform.scale",
    ),
    # scene
    ("scene_name_empty", _set("name", ""), "name"),
    ("missing_camera", _pop("camera"), "camera"),
]


@pytest.mark.parametrize(("mutate", "field"), [c[1:] for c in BAD_CASES], ids=[c[0] for c in BAD_CASES])
def test_invalid_value_is_reported_at_its_field(mutate: Mutation, field: str) -> None:
    doc = copy.deepcopy(good_doc())
    mutate(doc)
    errors = errors_of(doc)
    assert [e["field"] for e in errors] == [field], errors
    assert errors[0]["message"] and errors[0]["type"]


def test_error_messages_carry_the_details() -> None:
    doc = good_doc()
    doc["materials"][1]["ks"] = [0.3, 0.95, 0.3]
    (err,) = errors_of(doc)
    assert err["type"] == "energy_conservation"
    assert "channel g" in err["message"] and "0.1 + 0.95" in err["message"]

    doc = good_doc()
    doc["objects"][MESH]["faces"] = [[0, 1, 2], [1, 4, 7], [-1, 0, 1]]
    (err,) = errors_of(doc)
    assert err["type"] == "face_index_out_of_range"
    assert err["message"].startswith("3 face indices out of range [0, 4)")

    doc = good_doc()
    doc["objects"][3]["material"] = "gold"
    (err,) = errors_of(doc)
    assert "'gold'" in err["message"] and "'white'" in err["message"]


def test_all_cross_reference_errors_are_reported_together() -> None:
    doc = good_doc()
    doc["objects"][0]["material"] = "gold"
    doc["objects"][1]["material"] = "silver"
    doc["lights"][2]["name"] = "key"
    assert sorted(fields_of(doc)) == ["lights.2.name", "objects.0.material", "objects.1.material"]


def test_scene_limits() -> None:
    doc = good_doc()
    doc.pop("animation")
    doc["lights"] = [{"type": "point", "position": [0, 5, 0], "intensity": [1, 1, 1]}] * 4097
    assert fields_of(doc) == ["lights"]


def test_invalid_json_and_encoding() -> None:
    for text in [b"{", b'{"camera": 1,}', b"\xff\xfe{}"]:
        with pytest.raises(ValidationError) as info:
            load_scene_json(text)
        assert format_validation_error(info.value)[0]["type"] == "json_invalid"


# --------------------------------------------------------------------------- error formatting


def test_field_path_strips_union_tags_only() -> None:
    assert field_path(("objects", 2, "sphere", "radius"), Scene) == "objects.2.radius"
    assert field_path(("camera", "perspective", "eye", 0), Scene) == "camera.eye.0"
    assert (
        field_path(("animation", "objects", "sphere", 0, "time"), Scene) == "animation.objects.sphere.0.time"
    )
    # without a root model a heuristic removes tags after list indices and "camera"
    assert field_path(("objects", 2, "sphere", "radius")) == "objects.2.radius"
    assert field_path(("body", "scene", "lights", 0, "rect", "edge_v")) == "body.scene.lights.0.edge_v"
    assert field_path(("rect", "edge_v")) == "edge_v"


def test_format_error_details_for_nested_models() -> None:
    class SceneCreate(BaseModel):
        scene: Scene

    with pytest.raises(ValidationError) as info:
        SceneCreate.model_validate(
            {"scene": {**good_doc(), "objects": [{"type": "sphere", "material": "w"}]}}
        )
    records = format_error_details(info.value.errors(), SceneCreate)
    assert [r["field"] for r in records] == ["scene.objects.0.radius"]


# --------------------------------------------------------------------------- transforms


def test_to_matrix_trs_by_hand() -> None:
    # Extrinsic x then y: R = Ry(90) @ Rx(90), which sends +x to -z, +y to +x, +z to -y.
    t = Transform(translate=(1, 2, 3), rotate_deg=(90, 90, 0), scale=(2, 3, 4))
    expected = np.array(
        [
            [0.0, 3.0, 0.0, 1.0],
            [0.0, 0.0, -4.0, 2.0],
            [-2.0, 0.0, 0.0, 3.0],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    m = t.to_matrix()
    assert m.shape == (4, 4) and m.dtype == np.float64
    np.testing.assert_allclose(m, expected, atol=1e-12)
    np.testing.assert_allclose(m @ [1, 1, 1, 1], [4, -2, 1, 1], atol=1e-12)


def test_to_matrix_quaternion_and_identity() -> None:
    rz90 = np.array([[0.0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    s = math.sqrt(0.5)
    np.testing.assert_allclose(Transform(quaternion=(0, 0, s, s)).to_matrix(), rz90, atol=1e-12)
    # unnormalised, even tiny, quaternions are normalised on use
    np.testing.assert_allclose(Transform(quaternion=(0, 0, 2, 2)).to_matrix(), rz90, atol=1e-12)
    np.testing.assert_allclose(Transform(quaternion=(0, 0, 1e-200, 1e-200)).to_matrix(), rz90, atol=1e-12)
    np.testing.assert_array_equal(Transform().to_matrix(), np.eye(4))


def test_to_matrix_explicit_matrix() -> None:
    rows = ((0.0, 0, 1e-3, 5), (0, 1e3, 0, 6), (-1, 0, 0, 7), (0, 0, 0, 1))
    np.testing.assert_array_equal(Transform(matrix=rows).to_matrix(), np.array(rows, dtype=np.float64))


# --------------------------------------------------------------------------- hashing


def _reverse_keys(node: Any) -> Any:
    if isinstance(node, dict):
        return {k: _reverse_keys(node[k]) for k in reversed(list(node))}
    if isinstance(node, list):
        return [_reverse_keys(v) for v in node]
    return node


def test_scene_hash_ignores_key_order_and_spelled_out_defaults() -> None:
    doc = good_doc()
    a = load_scene_json(json.dumps(doc))
    b = load_scene_json(json.dumps(_reverse_keys(doc), indent=3))
    assert canonical_scene_json(a) == canonical_scene_json(b)
    assert scene_hash(a) == scene_hash(b)
    doc_defaults = copy.deepcopy(doc)
    doc_defaults["objects"][0]["subdivisions"] = 5  # the default
    doc_defaults["materials"][0]["ks"] = [0, 0, 0]
    assert scene_hash(load_scene_json(json.dumps(doc_defaults))) == scene_hash(a)
    # canonical JSON round-trips
    assert scene_hash(load_scene_json(canonical_scene_json(a))) == scene_hash(a)
    assert len(scene_hash(a)) == 64 and int(scene_hash(a), 16) >= 0


@pytest.mark.parametrize(
    "mutate",
    [
        _set("objects.0.radius", 1.0000001),
        _set("lights.0.intensity", [100, 100, 91]),
        _set("camera.width", 321),
        _set("animation.end", 3),
        _set("name", "other"),
    ],
)
def test_scene_hash_changes_with_any_value(mutate: Mutation) -> None:
    doc = good_doc()
    before = scene_hash(load_scene_json(json.dumps(doc)))
    mutate(doc)
    assert scene_hash(load_scene_json(json.dumps(doc))) != before


def test_canonical_json_is_compact_and_sorted() -> None:
    text = canonical_scene_json(load_scene_json(json.dumps(good_doc())))
    assert ", " not in text and ": " not in text and "\n" not in text
    top = json.loads(text)
    assert list(top) == sorted(top)
    assert top["objects"][0]["transform"]["scale"] == [1.0, 1.0, 1.0]  # defaults included


# --------------------------------------------------------------------------- files and schema


def test_load_scene_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "scene.json"
    path.write_bytes(b"\xef\xbb\xbf" + json.dumps(good_doc()).encode("utf-8"))  # with a BOM
    assert load_scene_file(path).name == "everything"
    assert load_scene_file(str(path)).name == "everything"
    monkeypatch.setattr(scene_module, "MAX_SCENE_BYTES", 100)
    with pytest.raises(SceneFileTooLargeError):
        load_scene_file(path)
    with pytest.raises(SceneFileTooLargeError):
        load_scene_json(json.dumps(good_doc()))


def test_committed_json_schema_is_current() -> None:
    assert SCHEMA_FILE.read_text(encoding="utf-8") == render_schema(), (
        "docs/scene.schema.json is stale: run python -m api_schemas.export docs/scene.schema.json"
    )
    assert json.loads(SCHEMA_FILE.read_text(encoding="utf-8")) == scene_json_schema()


def test_export_check_mode(tmp_path: Path) -> None:
    out = tmp_path / "schema.json"
    assert export_main([str(out), "--check"]) == 1
    assert export_main([str(out)]) == 0
    assert export_main([str(out), "--check"]) == 0
    out.write_text(out.read_text() + " ")
    assert export_main([str(out), "--check"]) == 1


def test_json_schema_shape() -> None:
    schema = scene_json_schema()
    assert schema["title"] == "Scene" and schema["required"] == ["camera"]
    defs = schema["$defs"]
    # the discriminator is required in every variant, even though Python gives it a default
    for name in ["SphereObject", "MeshFileObject", "PointLight", "RectLight", "PerspectiveCamera"]:
        assert defs[name]["required"][0] == "type", name
        assert defs[name]["additionalProperties"] is False
    mapping = schema["properties"]["objects"]["items"]["discriminator"]["mapping"]
    assert set(mapping) == {"mesh_file", "mesh", "sphere", "box", "cylinder", "plane", "disk"}
    assert "description" in defs["PointLight"]["properties"]["intensity"]


def test_package_exports() -> None:
    for name in api_schemas.__all__:
        assert hasattr(api_schemas, name), name
    assert api_schemas.Scene is Scene and api_schemas.Material is Material


def test_documented_example_is_valid() -> None:
    text = (REPO / "docs" / "scene-format.md").read_text(encoding="utf-8")
    example = text.split("```json\n", 1)[1].split("```", 1)[0]
    scene = load_scene_json(example)
    assert [o.type for o in scene.objects] == ["plane", "sphere"] and scene.lights[0].type == "point"


def test_huge_coefficients_are_a_field_error_not_an_overflow():
    import pydantic

    from api_schemas import Material, format_validation_error

    with pytest.raises(pydantic.ValidationError) as e:
        Material(name="m", kd=(1.7e308, 0.1, 0.1), ks=(1.7e308, 0.0, 0.0), shininess=1.0)
    errs = format_validation_error(e.value)
    assert any(err["type"] == "energy_conservation" for err in errs)
