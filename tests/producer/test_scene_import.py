"""Scene import (producer/scene_import, docs/scene-import.md) on real third-party files and on bad input.

Geometry is checked against trimesh's own glTF / OBJ readers (an independent implementation): the
imported meshes, read back from their PLY blobs by trimesh and placed by the objects' transforms,
must cover the same world-space surface (triangle count, total area, bounds). Lights, cameras and
materials are checked against the files' JSON / MTL text and the closed forms of the mapping."""

from __future__ import annotations

import base64
import copy
import io
import json
import math
import socket
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from api_schemas.scene import MAX_LIGHTS, MAX_OBJECTS, MeshFileObject, PointLight, RectLight
from producer.scene_import import ImportedScene, ImportOptions, ImportProblem, companions, import_scene
from producer.scene_import.common import pbr_material, roughness_to_exponent
from service.api.routes.scenes import mesh_problem

FIX = Path(__file__).resolve().parents[1] / "fixtures" / "scene_import"
GLTF = FIX / "gltf"
VAL = FIX / "validator"


def load(path: Path, fmt: str | None = None, **options: Any) -> ImportedScene:
    fmt = fmt or path.suffix.lstrip(".")
    data = path.read_bytes()
    files = {c: (path.parent / c).read_bytes() for c in companions(fmt, data)}
    return import_scene(fmt, data, files, ImportOptions(**options), path.name)


def problem(fmt: str, data: bytes, files: dict[str, bytes] | None = None) -> list[tuple[str, str]]:
    with pytest.raises(ImportProblem) as e:
        import_scene(fmt, data, files or {}, None, f"t.{fmt}")
    return e.value.errors


def world_triangles(imp: ImportedScene) -> np.ndarray:
    """(n, 3, 3) world-space triangles, the blobs read by trimesh's PLY reader."""
    tris = []
    for obj in imp.scene.objects:
        assert isinstance(obj, MeshFileObject)
        mesh = trimesh.load(io.BytesIO(imp.meshes[obj.path]), file_type="ply", process=False)
        m = obj.transform.to_matrix()
        v = np.asarray(mesh.vertices) @ m[:3, :3].T + m[:3, 3]
        tris.append(v[np.asarray(mesh.faces)])
    return np.concatenate(tris)


def trimesh_triangles(path: Path) -> np.ndarray:
    sc = trimesh.load_scene(str(path), process=False)
    tris = []
    for node in sc.graph.nodes_geometry:
        m, name = sc.graph[node]
        g = sc.geometry[name]
        v = np.asarray(g.vertices) @ np.asarray(m)[:3, :3].T + np.asarray(m)[:3, 3]
        tris.append(v[np.asarray(g.faces)])
    return np.concatenate(tris)


def area(t: np.ndarray) -> float:
    return float(np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum() / 2)


def features(imp: ImportedScene) -> set[str]:
    return {w["feature"] for w in imp.warnings}


# ------------------------------------------------------------------------------ real files


@pytest.mark.parametrize("rel", [
    "box-glb/Box.glb", "cameras/Cameras.gltf", "lights-punctual-lamp/LightsPunctualLamp.gltf",
    "metal-rough-spheres-notextures/MetalRoughSpheresNoTextures.gltf", "specular-test/SpecularTest.gltf",
    "emissive-strength-test/EmissiveStrengthTest.gltf",
])
def test_gltf_geometry_matches_trimesh(rel: str) -> None:
    path = GLTF / rel
    imp = load(path)
    ours, ref = world_triangles(imp), trimesh_triangles(path)
    assert len(ours) == len(ref)
    assert area(ours) == pytest.approx(area(ref), rel=1e-9)
    lo, hi = ours.reshape(-1, 3).min(0), ours.reshape(-1, 3).max(0)
    np.testing.assert_allclose(lo, ref.reshape(-1, 3).min(0), atol=1e-9 * float(np.abs(hi).max()))
    np.testing.assert_allclose(hi, ref.reshape(-1, 3).max(0), atol=1e-9 * float(np.abs(hi).max()))
    for blob_path, blob in imp.meshes.items():  # what the API's upload check and the worker read
        assert mesh_problem(blob_path, blob) is None


def test_obj_geometry_matches_trimesh() -> None:
    path = FIX / "obj" / "CornellBox-Sphere.obj"
    imp = load(path)
    ours = world_triangles(imp)
    ref = trimesh.load(str(path), process=False, force="mesh")
    ref_tris = np.asarray(ref.vertices)[np.asarray(ref.faces)]
    assert len(ours) == len(ref_tris)
    assert area(ours) == pytest.approx(area(ref_tris), rel=1e-9)


def test_lights_punctual_lamp_lights_are_placed_by_their_nodes() -> None:
    doc = json.loads((GLTF / "lights-punctual-lamp" / "LightsPunctualLamp.gltf").read_text())
    imp = load(GLTF / "lights-punctual-lamp" / "LightsPunctualLamp.gltf")
    lights = doc["extensions"]["KHR_lights_punctual"]["lights"]
    expected = {}
    for node in doc["nodes"]:
        li = node.get("extensions", {}).get("KHR_lights_punctual", {}).get("light")
        if li is not None:
            m = node["matrix"]  # column-major: the translation is elements 12..14
            rgb = [c * lights[li]["intensity"] for c in lights[li].get("color", [1, 1, 1])]
            expected[lights[li]["name"].replace(".", ".")] = (m[12:15], rgb)
    assert len(imp.scene.lights) == 5 and all(isinstance(L, PointLight) for L in imp.scene.lights)
    for light in imp.scene.lights:
        assert isinstance(light, PointLight) and light.name is not None
        pos, rgb = expected[light.name]
        np.testing.assert_allclose(light.position, pos, rtol=1e-12)
        np.testing.assert_allclose(light.intensity, rgb, rtol=1e-12)
    # what the file has and the project cannot show is reported, not dropped
    assert {"textures", "transparency", "material_extension", "emissive_texture", "no_camera"} <= features(imp)
    tex = next(w for w in imp.warnings if w["feature"] == "textures")
    assert "materials[0].pbrMetallicRoughness.baseColorTexture" in tex["where"]


def test_cameras_first_camera_node_transforms() -> None:
    imp = load(GLTF / "cameras" / "Cameras.gltf")
    cam = imp.scene.camera
    assert cam.type == "perspective"
    assert cam.fov_y_deg == pytest.approx(math.degrees(0.7))
    assert cam.width == cam.height == 480  # aspectRatio 1
    np.testing.assert_allclose(cam.eye, [0.5, 0.5, 3.0])
    d = np.subtract(cam.look_at, cam.eye)
    np.testing.assert_allclose(d / np.linalg.norm(d), [0, 0, -1], atol=1e-12)
    (obj,) = imp.scene.objects
    m = obj.transform.to_matrix()
    ref = Rotation.from_quat([-0.383, 0.0, 0.0, 0.92375]).as_matrix()
    np.testing.assert_allclose(m[:3, :3], ref, atol=1e-12)
    assert {"cameras_beyond_first", "clip_planes"} <= features(imp)
    sized = load(GLTF / "cameras" / "Cameras.gltf", width=64)
    assert (sized.scene.camera.width, sized.scene.camera.height) == (64, 64)


def test_box_glb_hierarchy_composes_parent_and_child() -> None:
    data = (GLTF / "box-glb" / "Box.glb").read_bytes()
    jlen = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + jlen])
    parent = np.array(doc["nodes"][0]["matrix"], dtype=float).reshape(4, 4).T
    assert doc["nodes"][0]["children"] == [1] and "mesh" in doc["nodes"][1]
    imp = load(GLTF / "box-glb" / "Box.glb")
    (obj,) = imp.scene.objects
    np.testing.assert_allclose(obj.transform.to_matrix(), parent, atol=1e-15)  # the child has no transform
    (mat,) = imp.scene.materials
    base = doc["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"][:3]
    np.testing.assert_allclose(mat.kd, [c * 0.96 for c in base], rtol=1e-9)  # metallic 0: base (1 - 0.04)


def test_emissive_strength_multiplies_the_factor() -> None:
    doc = json.loads((GLTF / "emissive-strength-test" / "EmissiveStrengthTest.gltf").read_text())
    imp = load(GLTF / "emissive-strength-test" / "EmissiveStrengthTest.gltf")
    by_name = {m.name: m for m in imp.scene.materials}
    checked = 0
    for m in doc["materials"]:
        if "emissiveFactor" in m:
            s = m.get("extensions", {}).get("KHR_materials_emissive_strength", {}).get("emissiveStrength", 1)
            np.testing.assert_allclose(by_name[m["name"]].emission, [e * s for e in m["emissiveFactor"]])
            checked += 1
    assert checked == 5
    assert "emission_not_a_light" in features(imp)  # boxes: seen, but they light nothing


def test_specular_extension_sets_the_dielectric_reflectance() -> None:
    doc = json.loads((GLTF / "specular-test" / "SpecularTest.gltf").read_text())
    imp = load(GLTF / "specular-test" / "SpecularTest.gltf")
    by_name = {m.name: m for m in imp.scene.materials}
    checked = 0
    for m in doc["materials"]:
        ext = m.get("extensions", {}).get("KHR_materials_specular")
        pbr = m["pbrMetallicRoughness"]
        if ext is None or pbr.get("metallicFactor", 1) != 0:
            continue
        f0 = [min(0.04 * c, 1.0) * ext.get("specularFactor", 1.0) for c in ext.get("specularColorFactor", [1, 1, 1])]
        got = by_name[m["name"]]
        np.testing.assert_allclose(got.ks, f0, rtol=1e-9, atol=1e-12)
        base = pbr.get("baseColorFactor", [1, 1, 1, 1])[:3]
        np.testing.assert_allclose(got.kd, [b * (1 - max(f0)) for b in base], rtol=1e-9, atol=1e-12)
        checked += 1
    assert checked >= 10


def test_metallic_roughness_mapping_closed_forms() -> None:
    # the GGX alpha = r^2 lobe as a Phong exponent: n = (2 / alpha^2 - 2) / 4
    for r in (0.25, 0.5, 0.8):
        assert roughness_to_exponent(r) == pytest.approx((2 / r**4 - 2) / 4)
    assert roughness_to_exponent(0.0) == 1e4 and roughness_to_exponent(1.0) == 0.0
    dielectric = pbr_material("d", (0.5, 0.2, 0.1), 0.0, 0.5, (0.04,) * 3, (0, 0, 0))
    np.testing.assert_allclose(dielectric["kd"], [0.5 * 0.96, 0.2 * 0.96, 0.1 * 0.96])
    assert dielectric["ks"] == [0.04] * 3 and "kg" not in dielectric
    metal = pbr_material("m", (0.9, 0.6, 0.2), 1.0, 0.3, (0.04,) * 3, (0, 0, 0))
    assert metal["kd"] == [0.0] * 3
    np.testing.assert_allclose(metal["ks"], [0.45, 0.3, 0.1])
    np.testing.assert_allclose(metal["kg"], [0.45, 0.3, 0.1])
    assert metal["gloss_exponent"] == pytest.approx(roughness_to_exponent(0.3))
    mirror = pbr_material("mirror", (1, 1, 1), 1.0, 0.0, (0.04,) * 3, (0, 0, 0))
    assert mirror["kr"] == [0.5] * 3 and "kg" not in mirror
    rough_metal = pbr_material("rm", (1, 1, 1), 1.0, 1.0, (0.04,) * 3, (0, 0, 0))
    assert rough_metal["ks"] == [1.0] * 3 and "kg" not in rough_metal and "kr" not in rough_metal
    # every material of the 98-material grid passes the schema's energy budget (the Scene validated)
    imp = load(GLTF / "metal-rough-spheres-notextures" / "MetalRoughSpheresNoTextures.gltf")
    assert len(imp.scene.materials) >= 98


def test_cornell_box_obj_mtl() -> None:
    mtl = (FIX / "obj" / "CornellBox-Original.mtl").read_text()
    kd = {}
    for block in mtl.split("newmtl ")[1:]:
        name = block.split()[0]
        line = next(ln for ln in block.splitlines() if ln.strip().startswith("Kd"))
        kd[name] = [float(x) for x in line.split()[1:4]]
    imp = load(FIX / "obj" / "CornellBox-Original.obj", height=32)
    by_name = {m.name: m for m in imp.scene.materials}
    assert set(by_name) == set(kd)
    for name, values in kd.items():
        np.testing.assert_allclose(by_name[name].kd, values)
    np.testing.assert_allclose(by_name["light"].emission, [17, 12, 4])
    (light,) = imp.scene.lights  # the emissive quad also lights the box
    assert isinstance(light, RectLight)
    np.testing.assert_allclose(light.radiance, [17, 12, 4])
    normal = np.cross(light.edge_u, light.edge_v)
    assert normal[1] < 0 and abs(normal[0]) < 1e-12 and abs(normal[2]) < 1e-12  # emits down, into the box
    assert abs(normal[1]) == pytest.approx(0.47 * 0.38)
    corners = np.array([light.corner, np.add(light.corner, light.edge_u), np.add(light.corner, light.edge_v)])
    np.testing.assert_allclose(corners[:, 1], 1.98)
    assert imp.scene.camera.height == 32 and "no_camera" in features(imp)


def test_cornell_sphere_mirror_and_glass() -> None:
    imp = load(FIX / "obj" / "CornellBox-Sphere.obj")
    by_name = {m.name: m for m in imp.scene.materials}
    np.testing.assert_allclose(by_name["leftSphere"].kr, [0.95] * 3)  # illum 5: a mirror
    assert by_name["leftSphere"].ks == (0.0, 0.0, 0.0)
    np.testing.assert_allclose(by_name["rightSphere"].kr, [0.30] * 3)  # illum 7: glass keeps its reflection
    assert {"refraction", "fresnel"} <= features(imp)


def test_validator_valid_files() -> None:
    node = load(VAL / "ext/KHR_lights_punctual/data/node/valid.gltf")
    (light,) = node.scene.lights
    assert isinstance(light, PointLight) and light.position == (0, 0, 0) and light.intensity == (1, 1, 1)
    spot = load(VAL / "ext/KHR_lights_punctual/data/light/valid.gltf")
    assert spot.scene.lights == [] and "lights_not_placed" in features(spot)
    em = load(VAL / "ext/KHR_materials_emissive_strength/data/material/valid.gltf")
    assert em.scene.objects == []


@pytest.mark.parametrize(("rel", "field"), [
    ("base/data/json/invalid_syntax.gltf", "gltf"),
    ("base/data/glb/invalid_magic.glb", "glb"),
    ("base/data/glb/length_mismatch.glb", "glb"),
    ("base/data/glb/truncated_chunk_header.glb", "glb chunk 0"),
    ("base/data/node/node_loop.gltf", "nodes[0].children"),
    ("base/data/buffer/not_found.gltf", "buffers[0].uri"),
    ("ext/KHR_lights_punctual/data/light/spot_invalid_angles.gltf", "extensions.KHR_lights_punctual.lights[0].spot"),
    ("ext/KHR_lights_punctual/data/node/unresolved_light_empty_root_array.gltf",
     "nodes[0].extensions.KHR_lights_punctual.light"),
])
def test_validator_invalid_files_are_refused_naming_the_part(rel: str, field: str) -> None:
    path = VAL / rel
    errors = problem(path.suffix.lstrip("."), path.read_bytes())
    assert errors[0][0] == field, errors


# ------------------------------------------------------------------------------ constructed bad input


def _triangle(**over: Any) -> dict[str, Any]:
    """One triangle with indices, its buffer a data: URI: positions (36 bytes) then 3 uint16 (6 bytes)."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype="<f4").tobytes()
    idx = np.array([0, 1, 2], dtype="<u2").tobytes()
    blob = pos + idx
    doc: dict[str, Any] = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(blob),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36},
                        {"buffer": 0, "byteOffset": 36, "byteLength": 6}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"},
                      {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "scene": 0,
    }
    doc.update(over)
    return doc


def _bad(mutate: Any) -> list[tuple[str, str]]:
    doc = _triangle()
    mutate(doc)
    return problem("gltf", json.dumps(doc).encode())


def test_the_constructed_triangle_imports() -> None:
    imp = import_scene("gltf", json.dumps(_triangle()).encode())
    assert len(imp.scene.objects) == 1 and world_triangles(imp).shape == (1, 3, 3)


@pytest.mark.parametrize(("mutate", "field", "words"), [
    (lambda d: d["buffers"][0].update(uri="triangle.bin"), "buffers[0].uri", "missing"),
    (lambda d: d["buffers"][0].update(byteLength=4096), "buffers[0].byteLength", "the data has 42"),
    (lambda d: d["buffers"][0].pop("uri"), "buffers[0]", "no uri"),
    (lambda d: d["bufferViews"][1].update(byteOffset=40), "bufferViews[1].byteLength", "past the end"),
    (lambda d: d["accessors"][0].update(count=4), "accessors[0].count", "need 48 bytes"),
    (lambda d: d["accessors"][0].update(count=10**15), "accessors[0].count", "more than"),
    (lambda d: d["accessors"][0].update(count=10**6), "accessors[0].count", "bufferViews[0] has 36"),
    (lambda d: d["accessors"][0].update(count=0), "accessors[0].count", "out of range"),
    (lambda d: (d["accessors"][0].pop("bufferView"), d["accessors"][0].update(count=10**12)), "accessors[0].count",
     "more than"),
    (lambda d: d["accessors"][0].update(byteOffset=2), "accessors[0].byteOffset", "multiple"),
    (lambda d: d["accessors"][0].update(byteOffset=-4), "accessors[0].byteOffset", "out of range"),
    (lambda d: d["accessors"][0].update(byteOffset=36), "accessors[0].byteOffset", "runs past bufferViews[0]"),
    (lambda d: d["accessors"][0].update(byteOffset=4), "accessors[0].count", "need 40 bytes"),
    (lambda d: d["accessors"][0].update(componentType=5123), "accessors[0].componentType", "FLOAT"),
    (lambda d: d["accessors"][0].update(componentType=9999), "accessors[0].componentType", "not a glTF"),
    (lambda d: d["accessors"][0].update(type="VEC4"), "accessors[0].count", "need"),
    (lambda d: d["accessors"][1].update(componentType=5120), "accessors[1].componentType", "UNSIGNED"),
    (lambda d: d["accessors"][0].update(bufferView=7), "accessors[0].bufferView", "bufferViews[7]"),
    (lambda d: d["meshes"][0]["primitives"][0].update(indices=5), "meshes[0].primitives[0].indices", "accessors[5]"),
    (lambda d: d["nodes"][0].update(mesh=3), "nodes[0].mesh", "meshes[3]"),
    (lambda d: d["nodes"][0].update(translation=[0, float("nan"), 0]), "nodes[0].translation[1]", "finite"),
    (lambda d: d["nodes"][0].update(rotation=[0, 0, 0, float("inf")]), "nodes[0].rotation[3]", "finite"),
    (lambda d: d["nodes"][0].update(matrix=[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, float("nan"), 0, 0, 1]),
     "nodes[0].matrix[12]", "finite"),
    (lambda d: d["nodes"][0].update(matrix=[1, 0, 0, 1, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]),
     "nodes[0].matrix", "affine"),
    (lambda d: d["nodes"][0].update(matrix=[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1], scale=[2, 2, 2]),
     "nodes[0].matrix", "must not also"),
    (lambda d: d["nodes"][0].update(children=[0]), "nodes[0].children", "loop"),
    (lambda d: d["scenes"][0].update(nodes=[0, 0]), "scenes[0].nodes[1]", "twice"),
    (lambda d: d.update(nodes=[{"children": [2]}, {"children": [2]}, {"mesh": 0}]), "nodes[1].children[0]",
     "two parents"),
    (lambda d: d["buffers"][0].update(uri="http://example.com/triangle.bin"), "buffers[0].uri", "nothing is fetched"),
    (lambda d: d["buffers"][0].update(uri="https://example.com/t.bin"), "buffers[0].uri", "URL"),
    (lambda d: d["buffers"][0].update(uri="file:///etc/passwd"), "buffers[0].uri", "URL"),
    (lambda d: d["buffers"][0].update(uri="/etc/passwd"), "buffers[0].uri", "absolute"),
    (lambda d: d["buffers"][0].update(uri="C:/data/t.bin"), "buffers[0].uri", "URL"),
    (lambda d: d["buffers"][0].update(uri="../t.bin"), "buffers[0].uri", "leaves the upload"),
    (lambda d: d["buffers"][0].update(uri="a/../../t.bin"), "buffers[0].uri", "leaves the upload"),
    (lambda d: d.update(images=[{"uri": "http://example.com/tex.png"}]), "images[0].uri", "URL"),
    (lambda d: d.update(extensionsRequired=["KHR_draco_mesh_compression"]), "extensionsRequired", "draco"),
    (lambda d: d["asset"].update(version="1.0"), "asset.version", "2.x"),
])
def test_bad_gltf_is_refused_naming_the_part(mutate: Any, field: str, words: str) -> None:
    errors = _bad(mutate)
    assert errors[0][0] == field, errors
    assert words.lower() in errors[0][1].lower(), errors


def test_indices_past_the_vertex_count() -> None:
    doc = _triangle()
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype="<f4").tobytes()
    blob = pos + np.array([0, 1, 7], dtype="<u2").tobytes()
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
    (err,) = problem("gltf", json.dumps(doc).encode())
    assert err[0] == "accessors[1]" and "past the vertex count 3" in err[1]


def test_nan_positions_name_the_accessor() -> None:
    doc = _triangle()
    pos = np.array([[0, 0, 0], [1, np.nan, 0], [0, 1, 0]], dtype="<f4").tobytes()
    blob = pos + np.array([0, 1, 2], dtype="<u2").tobytes()
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
    (err,) = problem("gltf", json.dumps(doc).encode())
    assert err[0] == "accessors[0]" and "NaN" in err[1]


def test_absurd_instance_counts_stop_at_the_scene_limit() -> None:
    n = MAX_OBJECTS + 1
    doc = _triangle(nodes=[{"mesh": 0, "translation": [i, 0, 0]} for i in range(n)],
                    scenes=[{"nodes": list(range(n))}])
    (err,) = problem("gltf", json.dumps(doc).encode())
    assert err[0] == f"nodes[{MAX_OBJECTS}]" and str(MAX_OBJECTS) in err[1]


def test_absurd_light_counts_stop_at_the_scene_limit() -> None:
    n = MAX_LIGHTS + 1
    doc = _triangle(extensions={"KHR_lights_punctual": {"lights": [{"type": "point"}]}},
                    nodes=[{"mesh": 0}] + [{"extensions": {"KHR_lights_punctual": {"light": 0}}}] * n,
                    scenes=[{"nodes": list(range(n + 1))}])
    (err,) = problem("gltf", json.dumps(doc).encode())
    assert err[0] == f"nodes[{MAX_LIGHTS + 1}]" and str(MAX_LIGHTS) in err[1]


def test_external_buffer_from_the_upload_and_glb() -> None:
    doc = _triangle()
    blob = base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1])
    doc["buffers"][0]["uri"] = "data%20files/tri.bin"
    imp = import_scene("gltf", json.dumps(doc).encode(), {"data files/tri.bin": blob})
    assert world_triangles(imp).shape == (1, 3, 3)
    # the same as a .glb: buffers[0] without uri is the binary chunk
    doc.pop("buffers")
    doc["buffers"] = [{"byteLength": len(blob)}]
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    bin_ = blob + b"\0" * (-len(blob) % 4)
    glb = struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(js) + 8 + len(bin_))
    glb += struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(bin_), 0x004E4942) + bin_
    assert world_triangles(import_scene("glb", glb)).shape == (1, 3, 3)
    # a chunk that claims more bytes than the file has
    broken = glb[:20 + len(js)] + struct.pack("<II", 10**9, 0x004E4942) + bin_
    broken = struct.pack("<4sII", b"glTF", 2, len(broken)) + broken[12:]
    assert problem("glb", broken)[0][0] == "glb chunk 1"


def test_nothing_is_fetched_from_the_network(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_network(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the importer opened a network connection")

    monkeypatch.setattr(socket.socket, "connect", no_network)
    monkeypatch.setattr(socket, "create_connection", no_network)
    for uri in ("http://127.0.0.1:9/t.bin", "https://example.com/t.bin", "ftp://example.com/t.bin"):
        errors = _bad(lambda d, u=uri: d["buffers"][0].update(uri=u))
        assert errors[0][0] == "buffers[0].uri"


def test_spot_and_directional_lights() -> None:
    lights = [{"type": "spot", "intensity": 5, "color": [1, 0.5, 0.25], "spot": {"outerConeAngle": 0.5}},
              {"type": "directional", "intensity": 3}]
    half = math.sqrt(0.5)
    doc = _triangle(extensions={"KHR_lights_punctual": {"lights": lights}},
                    extensionsUsed=["KHR_lights_punctual"],
                    nodes=[{"mesh": 0}, {"translation": [1, 2, 3], "extensions": {"KHR_lights_punctual": {"light": 0}}},
                           {"rotation": [-half, 0, 0, half], "extensions": {"KHR_lights_punctual": {"light": 1}}}],
                    scenes=[{"nodes": [0, 1, 2]}])
    imp = import_scene("gltf", json.dumps(doc).encode())
    spot, sun = imp.scene.lights
    assert spot.type == "point" and spot.position == (1, 2, 3)
    np.testing.assert_allclose(spot.intensity, [5, 2.5, 1.25])
    assert sun.type == "directional"
    np.testing.assert_allclose(sun.irradiance, [3, 3, 3])
    np.testing.assert_allclose(sun.direction, [0, -1, 0], atol=1e-12)  # -z turned -90 deg about x: down
    assert "spot_as_point" in features(imp)


def test_unsupported_features_are_listed() -> None:
    doc = _triangle(animations=[{"channels": [], "samplers": []}], skins=[{"joints": [0]}],
                    cameras=[{"type": "perspective", "perspective": {"yfov": 1.0}}] * 2,
                    nodes=[{"mesh": 0, "camera": 0, "children": [1]}, {"camera": 1}],
                    extensionsUsed=["EXT_unknown_thing"])
    doc["meshes"][0]["primitives"][0]["targets"] = [{"POSITION": 0}]
    imp = import_scene("gltf", json.dumps(doc).encode())
    assert {"animations", "skins", "morph_targets", "cameras_beyond_first", "unknown_extension"} <= features(imp)


# ------------------------------------------------------------------------------ OBJ bad input


OBJ = b"mtllib box.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nusemtl red\nf 1 2 3\nf -3 -1 -2\n"
MTL = b"newmtl red\nKd 0.8 0.1 0.1\nKs 0.5 0.5 0.5\nNs 20\n"


def test_obj_imports_with_relative_indices_and_scaled_energy() -> None:
    imp = import_scene("obj", OBJ, {"box.mtl": MTL})
    assert world_triangles(imp).shape == (2, 3, 3)
    (m,) = imp.scene.materials
    np.testing.assert_allclose(np.add(m.kd, m.ks), [1, 0.6 / 1.3, 0.6 / 1.3], rtol=1e-6)  # scaled to <= 1
    assert m.shininess == 20 and "energy_scaled" in features(imp)


@pytest.mark.parametrize(("obj", "files", "field", "words"), [
    (OBJ, {}, "t.obj:1", "missing"),
    (OBJ.replace(b"box.mtl", b"../box.mtl"), {"box.mtl": MTL}, "t.obj:1", "leaves the upload"),
    (OBJ.replace(b"box.mtl", b"/etc/box.mtl"), {"box.mtl": MTL}, "t.obj:1", "absolute"),
    (OBJ.replace(b"f 1 2 3", b"f 1 2 9"), {"box.mtl": MTL}, "t.obj:7", "index 9 is out of range"),
    (OBJ.replace(b"f 1 2 3", b"f 1 2 0"), {"box.mtl": MTL}, "t.obj:7", "index 0"),
    (OBJ.replace(b"f -3 -1 -2", b"f -3 -1 -9"), {"box.mtl": MTL}, "t.obj:8", "index -9"),
    (OBJ.replace(b"v 1 0 0", b"v 1 nan 0"), {"box.mtl": MTL}, "t.obj:3", "NaN"),
    (OBJ.replace(b"f 1 2 3", b"f 1 2"), {"box.mtl": MTL}, "t.obj:7", "at least 3"),
    (OBJ, {"box.mtl": b"Kd 1 1 1\n"}, "box.mtl:1", "before any newmtl"),
    (b"v 0 0 0\n", {}, "t.obj", "no faces"),
    (b"\x00\x01binary", {}, "t.obj", "NUL"),
])
def test_bad_obj_is_refused_naming_the_line(obj: bytes, files: dict[str, bytes], field: str, words: str) -> None:
    errors = problem("obj", obj, files)
    assert errors[0][0] == field and words.lower() in errors[0][1].lower(), errors


def test_import_is_deterministic() -> None:
    a = load(GLTF / "cameras" / "Cameras.gltf")
    b = load(GLTF / "cameras" / "Cameras.gltf")
    assert a.scene == b.scene and a.meshes == b.meshes
    assert copy.deepcopy(a.warnings) == b.warnings


def _paths(o: Any, pre: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out: list[tuple[Any, ...]] = []
    items = o.items() if isinstance(o, dict) else enumerate(o) if isinstance(o, list) else []
    for k, v in items:
        out.append(pre + (k,))
        out += _paths(v, pre + (k,))
    return out


_JUNK = [None, -1, 0, 2, 3.5, 1e300, float("nan"), float("inf"), "x", [], {}, [1, 2, 3], True, 10**20, 5123, "VEC3"]


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_any_mangled_field_is_an_import_problem_or_a_valid_scene(data: Any) -> None:
    """Whatever a field holds, the import answers ImportProblem (a 422) or a valid scene, never
    another exception (a 500)."""
    doc = _triangle(extensions={"KHR_lights_punctual": {"lights": [{"type": "spot", "spot": {}}]}},
                    cameras=[{"type": "perspective", "perspective": {"yfov": 1.0}}],
                    materials=[{"pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1]}}],
                    nodes=[{"mesh": 0, "children": [1]},
                           {"camera": 0, "extensions": {"KHR_lights_punctual": {"light": 0}}}])
    doc["meshes"][0]["primitives"][0]["material"] = 0
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(_paths(doc)))
        target: Any = doc
        for k in path[:-1]:
            target = target[k]
        if isinstance(target, dict) and data.draw(st.booleans()):
            target.pop(path[-1], None)
        else:
            target[path[-1]] = copy.deepcopy(data.draw(st.sampled_from(_JUNK)))
    try:
        imp = import_scene("gltf", json.dumps(doc).encode())
    except ImportProblem as exc:
        assert exc.errors and not exc.errors[0][0].startswith("converted scene"), exc.errors
    else:
        for path, blob in imp.meshes.items():
            assert mesh_problem(path, blob) is None


def _emissive_quad(scale: list[float]) -> ImportedScene:
    """A unit quad in the local xy plane, counter-clockwise seen from +z, emissive, under a node scale."""
    quad = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype="<f4").tobytes()
    idx = np.array([0, 1, 2, 0, 2, 3], dtype="<u2").tobytes()
    blob = quad + idx
    doc = _triangle(materials=[{"emissiveFactor": [1, 2, 3]}], nodes=[{"mesh": 0, "scale": scale}])
    doc["buffers"][0] = {"byteLength": len(blob),
                         "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode()}
    doc["bufferViews"] = [{"buffer": 0, "byteLength": 48}, {"buffer": 0, "byteOffset": 48, "byteLength": 12}]
    doc["accessors"][0]["count"], doc["accessors"][1]["count"] = 4, 6
    doc["meshes"][0]["primitives"][0]["material"] = 0
    return import_scene("gltf", json.dumps(doc).encode())


def test_an_emissive_quad_becomes_a_rect_light_facing_its_front_side() -> None:
    for scale, area_ in (([1, 1, 1], 1.0), ([2, 1, 1], 2.0), ([-1, 1, 1], 1.0), ([1, 1, -3], 1.0)):
        imp = _emissive_quad(scale)
        (light,) = imp.scene.lights
        assert isinstance(light, RectLight)
        np.testing.assert_allclose(light.radiance, [1, 2, 3])
        normal = np.cross(light.edge_u, light.edge_v)
        # glTF: under a mirroring transform (negative determinant) the front side is the clockwise one,
        # so the front stays the local +z carried by the inverse transpose
        front = np.linalg.inv(np.diag(np.array(scale, dtype=float))).T @ [0, 0, 1]
        assert float(np.dot(normal, front)) > 0, (scale, normal)
        assert float(np.linalg.norm(normal)) == pytest.approx(area_)
