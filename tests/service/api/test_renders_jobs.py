"""Renders, jobs, batches, artifacts and health without a worker: what the API answers while
jobs wait, and the errors it gives."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient
from redis import Redis

from api_schemas.service import BatchPublic, JobPublic, RenderPublic
from tests.service.api.conftest import small_scene

CAM = {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0, 0], "width": 8, "height": 8}


def _scene(c: TestClient, **changes: Any) -> str:
    r = c.post("/v1/scenes", json={"scene": small_scene(**changes)})
    assert r.status_code in (200, 201), r.text
    sid: str = r.json()["id"]
    return sid


def test_render_queues_one_shared_job(client: TestClient, redis_conn: Redis) -> None:
    sid = _scene(client)
    r = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM})
    assert r.status_code == 202
    body = RenderPublic.model_validate(r.json())
    assert body.status == "queued" and body.job is not None and body.artifact is None
    assert r.headers["location"] == f"/v1/jobs/{body.job.id}" == body.links["job"]
    assert body.job.id == f"render-{body.artifact_key}"
    # identical request -> same job; another camera -> another job
    assert client.post("/v1/renders", json={"scene_id": sid, "camera": CAM}).json()["job"]["id"] == body.job.id
    other = client.post("/v1/renders", json={"scene_id": sid, "camera": {**CAM, "width": 9}}).json()
    assert other["job"]["id"] != body.job.id
    # wait > 0 with no worker: still 202 after the wait
    r = client.post("/v1/renders?wait=0.3", json={"scene_id": sid, "camera": CAM})
    assert r.status_code == 202 and r.json()["job"]["id"] == body.job.id
    assert 'ibr_render_cache_total{result="miss"} 4.0' in client.get("/metrics").text

    job = JobPublic.model_validate(client.get(f"/v1/jobs/{body.job.id}").json())
    assert job.state == "queued" and job.kind == "render"
    listed = client.get("/v1/jobs", params={"state": "queued"}).json()["items"]
    assert {j["id"] for j in listed} == {body.job.id, other["job"]["id"]}
    assert client.get("/v1/jobs", params={"state": "finished"}).json()["items"] == []

    canceled = client.post(f"/v1/jobs/{body.job.id}/cancel")
    assert canceled.status_code == 200 and canceled.json()["state"] == "canceled"
    again = client.post(f"/v1/jobs/{body.job.id}/cancel")
    assert again.status_code == 409 and "canceled" in again.json()["detail"]
    # a canceled job is replaced by a fresh one on the next request
    r = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM})
    assert r.status_code == 202 and r.json()["job"]["state"] == "queued"


def test_render_errors(make_app: Any) -> None:
    with TestClient(make_app(max_image_pixels=1000)) as c:
        sid = _scene(c)  # 24 x 16 = 384 pixels: under the limit
        r = c.post("/v1/renders", json={"scene_id": "0" * 64})
        assert r.status_code == 404 and r.headers["content-type"].startswith("application/problem+json")
        r = c.post("/v1/renders", json={"scene_id": sid, "camera": {**CAM, "width": 100, "height": 100}})
        assert r.status_code == 422 and r.json()["errors"][0]["field"] == "camera.height"
        r = c.post("/v1/renders?wait=61", json={"scene_id": sid, "params": {"spp": 0}, "method": "ldc+ibrt:9"})
        assert r.status_code == 422
        assert {e["field"] for e in r.json()["errors"]} == {"query.wait", "params.spp", "method"}
        r = c.post("/v1/renders", json={"scene_id": sid, "camera": {**CAM, "type": "fisheye"}})
        assert r.status_code == 422 and r.json()["errors"][0]["field"] == "camera.type"
        assert c.get("/v1/jobs/render-nope").status_code == 404
        assert c.get("/v1/jobs/bad id!").status_code in (404, 422)
        assert c.post("/v1/jobs/render-nope/cancel").status_code == 404
        assert c.get("/v1/artifacts/" + "0" * 64).status_code == 404
        assert c.get("/v1/artifacts/nothex/image.png").status_code == 422
        assert c.get("/v1/nowhere").json()["status"] == 404
        assert c.put("/v1/scenes").status_code == 405


def test_batches(client: TestClient, store_dir: Path) -> None:
    existing = _scene(client)
    new_scene = small_scene(name="batch-made")
    r = client.post("/v1/batches", json={"scenes": [{"scene": new_scene}],
                                         "renders": [{"scene_id": existing}, {"scene_id": existing, "camera": CAM}]})
    assert r.status_code == 202, r.text
    batch = BatchPublic.model_validate(r.json())
    assert r.headers["location"] == f"/v1/batches/{batch.id}"
    assert len(batch.scene_ids) == 1 and batch.counts == {"queued": 2} and len(batch.renders) == 2
    assert client.get(f"/v1/scenes/{batch.scene_ids[0]}").json()["name"] == "batch-made"
    got = BatchPublic.model_validate(client.get(f"/v1/batches/{batch.id}").json())
    assert got.id == batch.id and got.progress.fraction == 0.0
    assert all(rp.job is not None and rp.job.batch_id == batch.id for rp in got.renders)

    # a render may name a scene created in the same batch
    from api_schemas.scene import Scene
    from producer.artifacts import scene_id_for

    sid2 = scene_id_for(Scene.model_validate(small_scene(name="two")), {})
    r = client.post("/v1/batches", json={"scenes": [{"scene": small_scene(name="two")}],
                                         "renders": [{"scene_id": sid2}]})
    assert r.status_code == 202 and r.json()["scene_ids"] == [sid2]

    # all-or-nothing: one bad entry stores no scene and queues no job
    scenes_before = len(client.get("/v1/scenes").json()["items"])
    mesh = small_scene(name="m")
    mesh["objects"].append({"type": "mesh_file", "path": "x.ply", "material": "white"})
    r = client.post("/v1/batches", json={"scenes": [{"scene": small_scene(name="three")}, {"scene": mesh}],
                                         "renders": [{"scene_id": "f" * 64}]})
    assert r.status_code == 422
    assert {e["field"] for e in r.json()["errors"]} == {"scenes.1.scene.objects.2.path", "renders.0.scene_id"}
    assert len(client.get("/v1/scenes").json()["items"]) == scenes_before
    assert client.get("/v1/batches/nope").status_code == 404


def test_health_and_metrics(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    r = client.get("/readyz")
    assert r.status_code == 200 and r.json() == {"status": "ready", "checks": {"redis": "ok", "store": "ok"}}
    sid = _scene(client)
    client.post("/v1/renders", json={"scene_id": sid})
    text = client.get("/metrics").text
    assert "ibr_redis_up 1.0" in text
    assert 'ibr_queue_jobs{queue="render",state="queued"} 1.0' in text
    assert 'ibr_queue_workers{queue="render"} 0.0' in text
    assert 'ibr_http_requests_total{method="POST",route="/v1/scenes",status="201"} 1.0' in text


def test_request_id_and_json_access_log(client: TestClient, caplog: Any) -> None:
    import json
    import logging

    from service.core.logging import JsonFormatter

    with caplog.at_level(logging.INFO, logger="ibr.access"):
        r = client.get("/healthz", headers={"X-Request-ID": "abc-123"})
        assert r.headers["x-request-id"] == "abc-123"
        r = client.get("/healthz", headers={"X-Request-ID": "bad id with spaces"})
        assert len(r.headers["x-request-id"]) == 32
    lines = [JsonFormatter().format(rec) for rec in caplog.records if rec.name == "ibr.access"]
    records = [json.loads(line) for line in lines]
    assert records[0]["request_id"] == "abc-123" and records[0]["status"] == 200
    assert records[0]["method"] == "GET" and records[0]["path"] == "/healthz" and records[0]["duration_ms"] >= 0
    assert records[1]["request_id"] == r.headers["x-request-id"]


def test_openapi_document(client: TestClient) -> None:
    spec = client.get("/openapi.json").json()
    ops = [(m, p, op) for p, item in spec["paths"].items() for m, op in item.items()]
    assert len(ops) >= 16  # the core 16 plus the datasets and bakes routers (each checked below)
    for method, path, op in ops:
        assert op.get("description") or op.get("summary"), (method, path)
        assert op.get("tags"), (method, path)
    scenes_post = spec["paths"]["/v1/scenes"]["post"]["requestBody"]["content"]
    # a scene document as JSON or multipart (with its meshes), or a file to import (docs/scene-import.md)
    assert set(scenes_post) == {"application/json", "multipart/form-data", "model/gltf-binary", "model/gltf+json",
                                "model/obj"}
    assert scenes_post["application/json"]["examples"]
    assert spec["paths"]["/v1/renders"]["post"]["requestBody"]["content"]["application/json"]["examples"]
    assert "bearerAuth" in str(spec["components"].get("securitySchemes", {})) or \
        "HTTPBearer" in str(spec["components"].get("securitySchemes", {}))
