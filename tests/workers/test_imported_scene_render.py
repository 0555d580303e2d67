"""Imported scenes render through the reference renderer as the workers load them (the stored PLY
blobs through ``workers.scene_loader``): light from the imported lights where it should be, in the
units docs/scene-import.md gives (1 cd -> 1 W/sr)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from engine.reference import ReferenceParams, ReferenceRenderer
from producer.scene_import import ImportedScene, ImportOptions, companions, import_scene
from workers.scene_loader import load_scene

FIX = Path(__file__).resolve().parents[1] / "fixtures" / "scene_import"


def _import(path: Path, **options: int) -> ImportedScene:
    fmt = path.suffix.lstrip(".")
    data = path.read_bytes()
    files = {c: (path.parent / c).read_bytes() for c in companions(fmt, data)}
    return import_scene(fmt, data, files, ImportOptions(**options), path.name)


def _render(imp: ImportedScene, lights: bool = True, spp: int = 4) -> tuple[np.ndarray, np.ndarray]:
    scene = imp.scene if lights else imp.scene.model_copy(update={"lights": []})
    loaded = load_scene(scene, lambda rel: (imp.meshes[rel], rel.rsplit(".", 1)[1]))
    out = ReferenceRenderer(loaded.runtime).render(loaded.camera, ReferenceParams(spp=spp))
    return np.asarray(out.radiance, dtype=np.float64), np.asarray(out.object_id)


def test_cornell_box_obj_red_left_green_right_and_lit() -> None:
    imp = _import(FIX / "obj" / "CornellBox-Original.obj", width=32, height=24)
    img, ids = _render(imp)
    h, w, _ = img.shape
    rows = slice(h // 3, 2 * h // 3)
    left = img[rows, : w // 6].reshape(-1, 3).mean(axis=0)
    right = img[rows, -(w // 6):].reshape(-1, 3).mean(axis=0)
    assert left[0] > 2 * left[1] and left[0] > 2 * left[2], left  # the red wall (x = -1) on the left
    assert right[1] > 1.5 * right[0] and right[1] > 1.5 * right[2], right  # the green wall on the right
    index = {o.material: i for i, o in enumerate(imp.scene.objects)}
    floor, ceiling = ids == index["floor"], ids == index["ceiling"]
    assert floor.sum() > 20 and ceiling.sum() > 20
    assert (img[floor].sum(axis=1) > 0).mean() > 0.9  # lit, but for the boxes' shadows
    # the rect light emits down only: without indirect light the ceiling stays dark (but for pixels
    # that also cover the light or a wall)
    assert np.median(img[ceiling].sum(axis=1)) < 0.05 * np.median(img[floor].sum(axis=1))


def test_gltf_lamp_is_lit_by_its_punctual_lights() -> None:
    imp = _import(FIX / "gltf" / "lights-punctual-lamp" / "LightsPunctualLamp.gltf", width=32, height=24)
    lit, ids = _render(imp)
    dark, _ = _render(imp, lights=False)
    hit = ids >= 0
    assert hit.sum() > 20
    assert float(dark[hit].max()) == 0.0  # no emission, no ambient: all light comes from the five lights
    assert (lit[hit].sum(axis=1) > 0).mean() > 0.5


def test_point_light_under_an_orthographic_glTF_camera_matches_the_closed_form() -> None:
    """A diffuse-ish quad (metallic 0, roughness 1: kd = 0.96 c, ks = 0.04 with exponent 0) under a
    point light of I cd at height d, seen straight down: L = (kd + ks) / pi * I / d^2."""
    quad = np.array([[-1, 0, -1], [-1, 0, 1], [1, 0, 1], [1, 0, -1]], dtype="<f4").tobytes()
    idx = np.array([0, 1, 2, 0, 2, 3], dtype="<u2").tobytes()
    import base64

    blob = quad + idx
    s = math.sqrt(0.5)
    doc = {
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_lights_punctual"],
        "extensions": {"KHR_lights_punctual": {"lights": [{"type": "point", "intensity": 10,
                                                            "color": [1, 0.5, 0.25]}]}},
        "buffers": [{"byteLength": len(blob),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode()}],
        "bufferViews": [{"buffer": 0, "byteLength": 48}, {"buffer": 0, "byteOffset": 48, "byteLength": 12}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3"},
                      {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"}],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1], "metallicFactor": 0,
                                                "roughnessFactor": 1}, "doubleSided": True}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]}],
        "cameras": [{"type": "orthographic", "orthographic": {"xmag": 0.01, "ymag": 0.01}}],
        "nodes": [{"mesh": 0}, {"translation": [0, 2, 0], "extensions": {"KHR_lights_punctual": {"light": 0}}},
                  {"translation": [0, 5, 0], "rotation": [-s, 0, 0, s], "camera": 0}],
        "scenes": [{"nodes": [0, 1, 2]}],
    }
    imp = import_scene("gltf", json.dumps(doc).encode(), options=ImportOptions(width=4, height=4))
    img, _ = _render(imp, spp=1)
    expected = (0.48 + 0.04) / math.pi * 10 * np.array([1, 0.5, 0.25]) / 4
    np.testing.assert_allclose(img.reshape(-1, 3), np.tile(expected, (16, 1)), rtol=1e-3)
