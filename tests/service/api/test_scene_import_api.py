"""``POST /v1/scenes`` importing glTF / GLB / OBJ + MTL files (docs/scene-import.md): the stored scene
is the one a user would upload by hand, refusals name the part and store nothing."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api_schemas.service import SceneImportPublic
from producer.artifacts import blob_key
from producer.store.local import LocalStore

FIX = Path(__file__).resolve().parents[2] / "fixtures" / "scene_import"
LAMP = FIX / "gltf" / "lights-punctual-lamp"
CBOX = FIX / "obj"


def _files(store_dir: Path) -> set[Path]:
    return {p for p in store_dir.rglob("*") if p.is_file()} if store_dir.exists() else set()


def _lamp_parts() -> list[tuple[str, tuple[str, bytes, str]]]:
    return [("gltf", ("LightsPunctualLamp.gltf", (LAMP / "LightsPunctualLamp.gltf").read_bytes(), "model/gltf+json")),
            ("LightsPunctualLamp.data.bin", ("LightsPunctualLamp.data.bin",
                                             (LAMP / "LightsPunctualLamp.data.bin").read_bytes(),
                                             "application/octet-stream"))]


def test_gltf_with_its_buffer_is_stored_as_a_hand_upload_would_be(client: TestClient, store_dir: Path) -> None:
    r = client.post("/v1/scenes", files=_lamp_parts(), params={"width": 40, "height": 30})
    assert r.status_code == 201, r.text
    pub = SceneImportPublic.model_validate(r.json())
    assert pub.import_format == "gltf" and pub.n_lights == 5 and pub.n_objects == 3
    assert {w.feature for w in pub.import_warnings} >= {"textures", "transparency", "material_extension"}
    assert r.headers["location"] == f"/v1/scenes/{pub.id}"

    doc = client.get(f"/v1/scenes/{pub.id}/document").json()
    assert doc["camera"]["width"] == 40 and doc["camera"]["height"] == 30
    assert all(o["type"] == "mesh_file" and o["path"].endswith(".ply") for o in doc["objects"])
    # the same document and blobs posted by hand give the same scene id
    store = LocalStore(store_dir)
    blobs = {m.path: store.get_bytes(blob_key(m.sha256)) for m in pub.meshes}
    parts: list[Any] = [("scene", (None, json.dumps(doc).encode(), "application/json"))]
    parts += [(path, (Path(path).name, data, "application/octet-stream")) for path, data in blobs.items()]
    by_hand = client.post("/v1/scenes", files=parts)
    assert by_hand.status_code == 200 and by_hand.json()["id"] == pub.id
    assert "import_warnings" not in by_hand.json()

    again = client.post("/v1/scenes", files=_lamp_parts(), params={"width": 40, "height": 30})
    assert again.status_code == 200 and again.json()["id"] == pub.id and again.json()["import_warnings"]


def test_glb_body_and_obj_with_mtl(client: TestClient) -> None:
    glb = (FIX / "gltf" / "box-glb" / "Box.glb").read_bytes()
    r = client.post("/v1/scenes", content=glb, headers={"Content-Type": "model/gltf-binary"}, params={"name": "box"})
    assert r.status_code == 201, r.text
    assert r.json()["import_format"] == "glb" and r.json()["name"] == "box"

    parts = [("obj", ("CornellBox-Original.obj", (CBOX / "CornellBox-Original.obj").read_bytes(), "text/plain")),
             ("CornellBox-Original.mtl", ("CornellBox-Original.mtl", (CBOX / "CornellBox-Original.mtl").read_bytes(),
                                          "text/plain"))]
    r = client.post("/v1/scenes", files=parts)
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["n_lights"] == 1 and body["n_objects"] == 8 and body["name"] == "CornellBox-Original"
    doc = client.get(f"/v1/scenes/{body['id']}/document").json()
    red = next(m for m in doc["materials"] if m["name"] == "leftWall")
    np.testing.assert_allclose(red["kd"], [0.63, 0.065, 0.05])


def test_bad_imports_answer_422_naming_the_part_and_store_nothing(client: TestClient, store_dir: Path) -> None:
    before = _files(store_dir)
    gltf = (LAMP / "LightsPunctualLamp.gltf").read_bytes()
    cases: list[tuple[Any, str, str]] = []
    # the buffer is not in the upload
    cases.append(([("gltf", ("lamp.gltf", gltf, "model/gltf+json"))], "buffers[0].uri", "missing"))
    # a truncated buffer
    short = (LAMP / "LightsPunctualLamp.data.bin").read_bytes()[:1000]
    cases.append(([("gltf", ("lamp.gltf", gltf, "model/gltf+json")),
                   ("LightsPunctualLamp.data.bin", ("b", short, "application/octet-stream"))],
                  "buffers[0].byteLength", "the data has 1000"))
    # an accessor past its buffer view
    doc = json.loads(gltf)
    doc["accessors"][3]["count"] = 10**6
    cases.append(([("gltf", ("lamp.gltf", json.dumps(doc).encode(), "model/gltf+json"))] + _lamp_parts()[1:],
                  "accessors[3].count", "need"))
    # a NaN node transform (JSON has no NaN; Python writers emit it anyway)
    doc = json.loads(gltf)
    doc["nodes"][3]["matrix"][12] = float("nan")
    cases.append(([("gltf", ("lamp.gltf", json.dumps(doc).encode(), "model/gltf+json"))] + _lamp_parts()[1:],
                  "nodes[3].matrix[12]", "finite"))
    # external URIs that leave the upload
    for uri, words in (("http://example.com/x.bin", "nothing is fetched"), ("/etc/passwd", "absolute"),
                       ("../x.bin", "leaves the upload")):
        doc = json.loads(gltf)
        doc["buffers"][0]["uri"] = uri
        cases.append(([("gltf", ("lamp.gltf", json.dumps(doc).encode(), "model/gltf+json"))],
                      "buffers[0].uri", words))
    # a part the file does not name
    cases.append((_lamp_parts() + [("other.bin", ("o", b"x", "application/octet-stream"))], "files", "does not name"))
    # OBJ without its MTL
    cases.append(([("obj", ("c.obj", (CBOX / "CornellBox-Original.obj").read_bytes(), "text/plain"))],
                  "c.obj:12", "missing"))
    for parts, field, words in cases:
        r = client.post("/v1/scenes", files=parts)
        assert r.status_code == 422, (field, r.text)
        errors = r.json()["errors"]
        assert errors[0]["field"] == field and words in errors[0]["message"], (field, errors)
    # a .glb body that is not one
    r = client.post("/v1/scenes", content=b"\0" * 12, headers={"Content-Type": "model/gltf-binary"})
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "glb"
    assert _files(store_dir) == before  # nothing half-stored


def test_import_options_and_parts_are_checked(client: TestClient) -> None:
    from tests.service.api.conftest import small_scene

    r = client.post("/v1/scenes", json={"scene": small_scene()}, params={"width": 10})
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "width"
    both = [("scene", (None, json.dumps(small_scene()).encode(), "application/json"))] + _lamp_parts()
    r = client.post("/v1/scenes", files=both)
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "gltf"
    r = client.post("/v1/scenes", files=_lamp_parts(), params={"width": 20000})
    assert r.status_code == 422


@pytest.mark.slow
def test_an_imported_obj_renders_in_a_worker_like_the_direct_engine_render(
    client: TestClient, worker_process: Any, tmp_path: Path
) -> None:
    """The workers read an imported scene unchanged: the served EXR equals an in-process render of
    the import (same blobs through workers.scene_loader)."""
    from engine.imageio import read_image
    from engine.reference import ReferenceParams, ReferenceRenderer
    from producer.scene_import import ImportOptions, import_scene
    from workers.scene_loader import load_scene

    worker = worker_process("render")
    obj, mtl = (CBOX / "CornellBox-Original.obj").read_bytes(), (CBOX / "CornellBox-Original.mtl").read_bytes()
    parts = [("obj", ("CornellBox-Original.obj", obj, "text/plain")),
             ("CornellBox-Original.mtl", ("CornellBox-Original.mtl", mtl, "text/plain"))]
    r = client.post("/v1/scenes", files=parts, params={"width": 32, "height": 24})
    assert r.status_code == 201, r.text
    params = {"spp": 2, "seed": 3}
    scene_id = r.json()["id"]
    deadline = time.monotonic() + 300
    while True:
        r = client.post("/v1/renders?wait=30", json={"scene_id": scene_id, "params": params})
        if r.json()["status"] not in ("queued", "running") or time.monotonic() > deadline:
            break
    assert r.json()["status"] in ("finished", "cached"), (r.text, worker.log())
    key = r.json()["artifact"]["key"]
    (tmp_path / "served.exr").write_bytes(client.get(f"/v1/artifacts/{key}/image.exr").content)
    served, _ = read_image(tmp_path / "served.exr")

    imp = import_scene("obj", obj, {"CornellBox-Original.mtl": mtl}, ImportOptions(width=32, height=24),
                       "CornellBox-Original.obj")
    loaded = load_scene(imp.scene, lambda rel: (imp.meshes[rel], "ply"))
    direct = ReferenceRenderer(loaded.runtime).render(loaded.camera, ReferenceParams(**params)).radiance
    assert np.array_equal(served, np.asarray(direct, dtype=np.float32))
    assert float(served.max()) > 0


def test_a_file_body_over_the_upload_limit_is_413(make_app: Any, store_dir: Path) -> None:
    glb = (FIX / "gltf" / "box-glb" / "Box.glb").read_bytes()
    with TestClient(make_app(max_upload_bytes=1024)) as c:
        r = c.post("/v1/scenes", content=glb, headers={"Content-Type": "model/gltf-binary"})
        assert r.status_code == 413 and "1024" in r.text
        small = c.post("/v1/scenes", content=glb[:1000], headers={"Content-Type": "model/gltf-binary"})
        assert small.status_code == 422  # under the limit, then read (and refused: truncated)
