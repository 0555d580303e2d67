"""``POST /v1/batches`` with scenes that have mesh files: a multipart batch (the batch JSON as the
part ``batch``, each mesh file of scene ``i`` as the part ``scenes.<i>.<mesh_file path>``), checked
all-or-nothing like a JSON batch, and ``ibr batch`` sending such scenes in one batch."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient
from typer.testing import CliRunner

from api_schemas.service import BatchPublic
from service.cli import app as cli_app
from service.client import Client
from tests.service.api.conftest import TEAPOT_PLY, small_scene, teapot_scene

EXAMPLES = Path(__file__).resolve().parents[3] / "examples" / "scenes"


def _multipart(body: dict[str, Any], files: dict[str, bytes]) -> list[tuple[str, tuple[str | None, bytes, str]]]:
    return [("batch", (None, json.dumps(body).encode(), "application/json")),
            *[(name, (Path(name).name, data, "application/octet-stream")) for name, data in files.items()]]


def _scene_count(client: TestClient) -> int:
    return len(client.get("/v1/scenes", params={"limit": 1000}).json()["items"])


def test_a_multipart_batch_stores_scenes_with_their_meshes(client: TestClient) -> None:
    teapot = teapot_scene()
    mesh_path = teapot["objects"][0]["path"]
    ply = TEAPOT_PLY.read_bytes()
    body = {"scenes": [{"scene": small_scene(name="plain")}, {"scene": teapot}], "renders": []}
    r = client.post("/v1/batches", files=_multipart(body, {f"scenes.1.{mesh_path}": ply}))
    assert r.status_code == 202, r.text
    batch = BatchPublic.model_validate(r.json())
    assert len(batch.scene_ids) == 2
    stored = client.get(f"/v1/scenes/{batch.scene_ids[1]}").json()
    assert [m["path"] for m in stored["meshes"]] == [mesh_path]
    # the same scene and mesh through POST /v1/scenes: the same content, the same id
    r = client.post("/v1/scenes", files=[("scene", ("s.json", json.dumps({"scene": teapot}).encode(),
                                                    "application/json")), (mesh_path, ("t.ply", ply, "x"))])
    assert r.status_code == 200 and r.json()["id"] == batch.scene_ids[1]
    # renders of a mesh scene in the same multipart batch are queued like any other
    r = client.post("/v1/batches", files=_multipart(
        {"scenes": [{"scene": teapot}], "renders": [{"scene_id": batch.scene_ids[1], "params": {"spp": 1}}]},
        {f"scenes.0.{mesh_path}": ply}))
    assert r.status_code == 202, r.text
    assert BatchPublic.model_validate(r.json()).counts == {"queued": 1}


def test_mesh_problems_are_named_and_nothing_is_stored(client: TestClient) -> None:
    teapot = teapot_scene()
    mesh_path = teapot["objects"][0]["path"]
    body = {"scenes": [{"scene": small_scene(name="ok")}, {"scene": teapot}], "renders": []}
    before = _scene_count(client)
    cases: list[tuple[dict[str, bytes], dict[str, str]]] = [
        ({}, {"scenes.1.scene.objects.0.path": "missing_file"}),
        ({f"scenes.1.{mesh_path}": b"ply\nnot really"}, {f"files.scenes.1.{mesh_path}": "invalid_mesh"}),
        ({f"scenes.1.{mesh_path}": TEAPOT_PLY.read_bytes(), "scenes.0.extra.ply": b"x"},
         {"files.scenes.0.extra.ply": "unexpected_part"}),
        ({f"scenes.1.{mesh_path}": TEAPOT_PLY.read_bytes(), f"scenes.5.{mesh_path}": b"x"},
         {"files.scenes.5": "unexpected_part"}),
        ({f"scenes.1.{mesh_path}": TEAPOT_PLY.read_bytes(), mesh_path: b"x"},
         {f"files.{mesh_path}": "unexpected_part"}),
    ]
    for files, expected in cases:
        r = client.post("/v1/batches", files=_multipart(body, files))
        assert r.status_code == 422, (files.keys(), r.text)
        assert {e["field"]: e["type"] for e in r.json()["errors"]} == expected, r.json()
    missing = client.post("/v1/batches", files=_multipart(body, {}))
    assert f"'scenes.1.{mesh_path}'" in missing.json()["errors"][0]["message"]
    # the JSON form names the same field and says how to send the file
    r = client.post("/v1/batches", json=body)
    assert r.status_code == 422
    (err,) = r.json()["errors"]
    assert err["field"] == "scenes.1.scene.objects.0.path" and "multipart/form-data" in err["message"]
    # no batch part, two batch parts, invalid batch JSON
    r = client.post("/v1/batches", files=[(f"scenes.0.{mesh_path}", ("t.ply", b"x", "x"))])
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "batch"
    r = client.post("/v1/batches", files=_multipart(body, {}) + _multipart(body, {}))
    assert r.status_code == 422 and r.json()["errors"][0]["type"] == "duplicate_part"
    r = client.post("/v1/batches", files=_multipart({"scenes": [{"scene": {"camera": 1}}]}, {}))
    assert r.status_code == 422 and r.json()["errors"][0]["field"].startswith("scenes.0.scene")
    assert _scene_count(client) == before


def test_openapi_documents_both_forms(client: TestClient) -> None:
    body = client.get("/openapi.json").json()["paths"]["/v1/batches"]["post"]["requestBody"]["content"]
    assert body["application/json"]["schema"] == {"$ref": "#/components/schemas/BatchRequest"}
    assert body["multipart/form-data"]["schema"]["required"] == ["batch"]


def test_cli_batch_sends_mesh_scenes_in_the_batch(api_url: str) -> None:
    env = {"IBR_API_URL": api_url, "IBR_API_KEY": ""}
    pyramid, spheres = str(EXAMPLES / "pyramid.json"), str(EXAMPLES / "spheres.json")
    r = CliRunner().invoke(cli_app, ["batch", pyramid, spheres, "--no-render"], env=env)
    assert r.exit_code == 0, r.output
    batch_id = r.stdout.strip()
    with Client(api_url) as c:
        b = c.get_batch(batch_id)
        assert len(b.scene_ids) == 2 and b.renders == []
        assert [m.path for m in c.get_scene(b.scene_ids[0]).meshes] == ["meshes/pyramid.obj"]
    r = CliRunner().invoke(cli_app, ["scenes", "add", pyramid], env=env)
    assert r.exit_code == 0 and r.stdout.strip() == b.scene_ids[0]  # one scene id, whichever route stored it
    r = CliRunner().invoke(cli_app, ["batch", pyramid, spheres, "--spp", "1"], env=env)
    assert r.exit_code == 0, r.output
    with Client(api_url) as c:
        b = c.get_batch(r.stdout.strip())
        assert len(b.renders) == 2 and b.counts == {"queued": 2}  # no workers here: queued
