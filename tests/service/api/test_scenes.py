"""Scenes over HTTP: JSON and multipart creation, get, list, delete, and bad uploads
(docs/hard-cases.md #15 at upload time, #16 and #17)."""

from __future__ import annotations

import hashlib
import json
import os
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient
from hypothesis import given, settings
from hypothesis import strategies as st
from redis import Redis

from api_schemas.service import ScenePublic
from tests.service.api.conftest import TEAPOT_PLY, small_scene, teapot_scene


def _multipart(scene: dict[str, Any], files: dict[str, bytes], filenames: dict[str, str] | None = None) -> Any:
    names = filenames or {}
    parts: list[tuple[str, tuple[str | None, bytes, str]]] = [
        ("scene", (None, json.dumps(scene).encode(), "application/json"))
    ]
    for path, data in files.items():
        parts.append((path, (names.get(path, Path(path).name), data, "application/octet-stream")))
    return parts


def _all_files(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


def test_json_create_get_list_delete(client: TestClient, store_dir: Path) -> None:
    r = client.post("/v1/scenes", json={"scene": small_scene()})
    assert r.status_code == 201, r.text
    created = ScenePublic.model_validate(r.json())
    assert r.headers["location"] == f"/v1/scenes/{created.id}"
    assert created.n_objects == 2 and created.n_lights == 1 and created.meshes == []

    again = client.post("/v1/scenes", json={"scene": small_scene()})
    assert again.status_code == 200 and again.json()["id"] == created.id  # same content, same id

    # key order and omitted defaults do not change the id
    doc = small_scene()
    doc["ambient"] = [0, 0, 0]
    shuffled = dict(reversed(list(doc.items())))
    assert client.post("/v1/scenes", json={"scene": shuffled}).json()["id"] == created.id

    got = client.get(f"/v1/scenes/{created.id}")
    assert got.status_code == 200 and got.json()["id"] == created.id
    listing = client.get("/v1/scenes").json()
    assert [s["id"] for s in listing["items"]] == [created.id] and listing["next_cursor"] is None

    assert client.delete(f"/v1/scenes/{created.id}").status_code == 204
    assert client.get(f"/v1/scenes/{created.id}").status_code == 404
    assert client.delete(f"/v1/scenes/{created.id}").status_code == 404
    assert client.get("/v1/scenes").json()["items"] == []


def test_multipart_teapot(client: TestClient, store_dir: Path) -> None:
    data = TEAPOT_PLY.read_bytes()
    r = client.post("/v1/scenes", files=_multipart(teapot_scene(), {"meshes/teapot.ply": data}))
    assert r.status_code == 201, r.text
    body = r.json()
    sha = hashlib.sha256(data).hexdigest()
    assert body["meshes"] == [{"path": "meshes/teapot.ply", "sha256": sha, "size": len(data)}]
    assert (store_dir / "blobs" / sha).read_bytes() == data

    # the scene part may also be a SceneCreate document, and a file part
    parts = [("scene", ("scene.json", json.dumps({"scene": teapot_scene()}).encode(), "application/json")),
             ("meshes/teapot.ply", ("whatever.bin", data, "application/octet-stream"))]
    again = client.post("/v1/scenes", files=parts)
    assert again.status_code == 200 and again.json()["id"] == body["id"]


def test_scene_document_round_trips_to_the_same_id(client: TestClient) -> None:
    sid = client.post("/v1/scenes", json={"scene": small_scene()}).json()["id"]
    got = client.get(f"/v1/scenes/{sid}")
    assert got.json()["links"]["document"] == f"/v1/scenes/{sid}/document"
    doc = client.get(f"/v1/scenes/{sid}/document")
    assert doc.status_code == 200, doc.text
    assert doc.json()["camera"]["width"] == small_scene()["camera"]["width"]
    assert client.post("/v1/scenes", json={"scene": doc.json()}).json()["id"] == sid
    # with mesh files: the document names them by path, the same files give the same id again
    data = TEAPOT_PLY.read_bytes()
    tid = client.post("/v1/scenes", files=_multipart(teapot_scene(), {"meshes/teapot.ply": data})).json()["id"]
    tdoc = client.get(f"/v1/scenes/{tid}/document").json()
    assert client.post("/v1/scenes", files=_multipart(tdoc, {"meshes/teapot.ply": data})).json()["id"] == tid
    assert client.get(f"/v1/scenes/{'0' * 64}/document").status_code == 404


def test_multipart_missing_and_extra_parts_are_named(client: TestClient, store_dir: Path) -> None:
    before = _all_files(store_dir)
    r = client.post("/v1/scenes", files=_multipart(teapot_scene(), {"meshes/other.ply": b"ply\n"}))
    assert r.status_code == 422, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    errors = {e["field"]: e for e in r.json()["errors"]}
    assert "scene.objects.0.path" in errors and "meshes/teapot.ply" in errors["scene.objects.0.path"]["message"]
    assert "files" in errors and "meshes/other.ply" in errors["files"]["message"]
    assert _all_files(store_dir) == before

    r = client.post("/v1/scenes", files=[("meshes/teapot.ply", ("t.ply", b"ply\n", "text/plain"))])
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "scene"


def test_json_scene_with_mesh_file_needs_multipart(client: TestClient) -> None:
    r = client.post("/v1/scenes", json={"scene": teapot_scene()})
    assert r.status_code == 422
    (err,) = r.json()["errors"]
    assert err["field"] == "scene.objects.0.path" and "multipart" in err["message"]


def test_validation_errors_name_the_field(client: TestClient) -> None:
    bad = small_scene()
    bad["objects"][0]["radius"] = -1
    r = client.post("/v1/scenes", json={"scene": bad})
    assert r.status_code == 422
    assert [e["field"] for e in r.json()["errors"]] == ["scene.objects.0.radius"]

    bad = small_scene()
    bad["objects"][1]["material"] = "nope"
    r = client.post("/v1/scenes", json={"scene": bad, "extra": 1})
    fields = {e["field"] for e in r.json()["errors"]}
    assert fields == {"extra"} or "scene.objects.1.material" in fields

    r = client.post("/v1/scenes", content=b"{not json", headers={"content-type": "application/json"})
    assert r.status_code == 422 and r.json()["errors"][0]["type"] == "json_invalid"

    # multipart with the scene bare: same field names, rooted at "scene"
    bad = small_scene()
    bad["camera"]["width"] = 0
    r = client.post("/v1/scenes", files=[("scene", (None, json.dumps(bad).encode(), "application/json"))])
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "scene.camera.width"

    r = client.post("/v1/scenes", content=b"x", headers={"content-type": "text/plain"})
    assert r.status_code == 415

    # numbers near the float limit: an energy_conservation field error, never a 500
    huge = small_scene()
    huge["materials"][0] = {"name": "white", "kd": [1.7e308, 0, 0], "ks": [1.7e308, 0, 0]}
    r = client.post("/v1/scenes", json={"scene": huge})
    assert r.status_code == 422
    assert [(e["field"], e["type"]) for e in r.json()["errors"]] == [("scene.materials.0", "energy_conservation")]


def test_unsupported_mesh_type_and_pixel_limit(make_app: Any) -> None:
    with TestClient(make_app(max_image_pixels=100)) as c:
        scene = small_scene()
        scene["objects"].append({"type": "mesh_file", "path": "m/model.fbx", "material": "white"})
        r = c.post("/v1/scenes", files=_multipart(scene, {"m/model.fbx": b"x"}))
        assert r.status_code == 422
        fields = {e["field"]: e["message"] for e in r.json()["errors"]}
        assert "unsupported mesh file type .fbx" in fields["scene.objects.2.path"]
        assert "100 pixels" in fields["scene.camera.height"]


# ------------------------------------------------------------------ docs/hard-cases.md #15 at upload


def _binary_ply(vertices: Sequence[tuple[float, float, float]], faces: Sequence[tuple[int, ...]]) -> bytes:
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    body = b"".join(struct.pack("<3f", *v) for v in vertices)
    body += b"".join(struct.pack("<B", len(f)) + struct.pack(f"<{len(f)}i", *f) for f in faces)
    return header + body


def _mesh_scene(path: str) -> dict[str, Any]:
    scene = small_scene()
    scene["objects"] = [{"type": "mesh_file", "path": path, "material": "white"}]
    return scene


def test_mesh_with_out_of_range_indices_is_refused_at_upload(client: TestClient, store_dir: Path) -> None:
    before = _all_files(store_dir)
    verts = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
    ply = _binary_ply(verts, [(0, 1, 2), (0, 1, 7), (-1, 1, 2)])
    r = client.post("/v1/scenes", files=_multipart(_mesh_scene("a.ply"), {"a.ply": ply}))
    assert r.status_code == 422, r.text
    (err,) = r.json()["errors"]
    assert err["field"] == "files.a.ply" and err["type"] == "invalid_mesh"
    assert "2 face indices out of range 0..2 (1 negative, 1 too large) in 2 of 3 faces" in err["message"]

    ascii_ply = (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                 b"element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n")
    r = client.post("/v1/scenes", files=_multipart(_mesh_scene("b.ply"), {"b.ply": ascii_ply}))
    assert r.status_code == 422 and "1 face indices out of range" in r.json()["errors"][0]["message"]

    obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 4\nf -4 1 2\nf 0 1 2\n"
    r = client.post("/v1/scenes", files=_multipart(_mesh_scene("c.obj"), {"c.obj": obj}))
    assert r.status_code == 422
    assert "3 OBJ face indices out of range 1..3 (1 zero" in r.json()["errors"][0]["message"]
    assert _all_files(store_dir) == before


def test_wrong_file_type_and_truncated_files(client: TestClient, store_dir: Path) -> None:
    before = _all_files(store_dir)
    png = b"\x89PNG\r\n\x1a\n" + b"\0" * 64
    exr_huge = (b"\x76\x2f\x31\x01" + b"\x02\0\0\0" + b"dataWindow\0box2i\0"
                + struct.pack("<I4i", 16, 0, 0, 99999, 99999))
    teapot = TEAPOT_PLY.read_bytes()
    cases = {
        "img.ply": (png, "not a PLY file"),  # an image where a mesh is expected
        "huge.obj": (exr_huge, "binary data"),  # docs/hard-cases.md #16: an EXR declaring 100k x 100k pixels
        "cut.ply": (teapot[: len(teapot) // 2], "truncated"),
        "cut.stl": (b"\0" * 80 + struct.pack("<I", 1000) + b"\0" * 100, "truncated"),
        "cut.glb": (b"glTF" + struct.pack("<II", 2, 1000) + b"\0" * 20, "truncated"),
        "ext.gltf": (json.dumps({"asset": {"version": "2.0"}, "buffers": [{"uri": "../../etc/passwd",
                                                                            "byteLength": 3}]}).encode(),
                     "external file"),
        "empty.obj": (b"", "empty"),
    }
    for path, (data, expect) in cases.items():
        r = client.post("/v1/scenes", files=_multipart(_mesh_scene(path), {path: data}))
        assert r.status_code == 422, (path, r.text)
        assert expect in r.json()["errors"][0]["message"], (path, r.json())
    assert _all_files(store_dir) == before


# ------------------------------------------------------------------ docs/hard-cases.md #17


def test_hostile_upload_names_are_metadata_only(client: TestClient, store_dir: Path, tmp_path: Path) -> None:
    data = TEAPOT_PLY.read_bytes()
    outside_before = {p.name for p in tmp_path.parent.iterdir()}
    for filename in ("../../x", "C:\\..\\x", "a\x00b.ply", "/etc/passwd", "..\\..\\evil.ply"):
        r = client.post("/v1/scenes", files=_multipart(teapot_scene(), {"meshes/teapot.ply": data},
                                                       {"meshes/teapot.ply": filename}))
        assert r.status_code in (200, 201), (filename, r.text)
    # part names (= mesh paths) that try to escape are refused by the scene schema itself
    for path in ("../../x.ply", "C:\\..\\x.ply", "a\x00b.ply", "/abs.ply"):
        r = client.post("/v1/scenes", files=_multipart(_mesh_scene(path), {path: data}))
        assert r.status_code in (400, 422), (path, r.text)
    sha = hashlib.sha256(data).hexdigest()
    files = {p.relative_to(store_dir).as_posix() for p in _all_files(store_dir)}
    assert f"blobs/{sha}" in files
    assert all(f.startswith(("blobs/", "scenes/", "scene-owners/", "scene-summaries/", "scene-index/"))
                   for f in files), files
    assert {p.name for p in tmp_path.parent.iterdir()} == outside_before
    assert not os.path.exists("/x") and not Path(store_dir.parent.parent, "x").exists()


# ------------------------------------------------------------------ 409 while in use


def test_delete_refused_while_a_job_uses_the_scene(client: TestClient, redis_conn: Redis) -> None:
    sid = client.post("/v1/scenes", json={"scene": small_scene()}).json()["id"]
    r = client.post("/v1/renders", json={"scene_id": sid})
    assert r.status_code == 202
    job_id = r.json()["job"]["id"]
    r = client.delete(f"/v1/scenes/{sid}")
    assert r.status_code == 409 and "queued or running job" in r.json()["detail"]
    assert client.get(f"/v1/scenes/{sid}").status_code == 200
    assert client.post(f"/v1/jobs/{job_id}/cancel").json()["state"] == "canceled"
    assert client.delete(f"/v1/scenes/{sid}").status_code == 204


@settings(max_examples=300, deadline=None, derandomize=True)
@given(
    ext=st.sampled_from(["ply", "obj", "stl", "glb", "gltf"]),
    head=st.sampled_from([b"", b"ply\nformat ascii 1.0\n", b"ply\nformat binary_little_endian 1.0\n",
                          b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty float x\n"
                          b"element face 99999999999\nproperty list uchar uint vertex_indices\nend_header\n",
                          b"glTF\x02\0\0\0", b"solid x\n", b"v 1 2 3\nf ", b'{"buffers": [']),
    body=st.binary(max_size=300),
)
def test_mesh_precheck_never_raises(ext: str, head: bytes, body: bytes) -> None:
    """Arbitrary bytes get an answer (a reason or None), never an exception (which would be a 500)."""
    from service.api.routes.scenes import mesh_problem

    result = mesh_problem(f"m.{ext}", head + body)
    assert result is None or isinstance(result, str)
