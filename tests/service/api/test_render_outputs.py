"""``RenderRequest.outputs`` (ask for a subset of the images), the server-side wait of
``POST /v1/renders?wait=`` (blocking on the job's RQ result stream) and the documented 409 of the
render endpoints."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from redis import Redis

from api_schemas.service import RenderRequest
from engine import ENGINE_VERSION
from producer.artifacts import artifact_key
from producer.cancel import cancel
from producer.renders import render_artifact_key
from tests.service.api.conftest import small_scene

CAM = {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0], "width": 12, "height": 8}
PARAMS = {"spp": 1, "max_depth": 1, "glossy_samples": 1, "area_light_samples": 1, "seed": 3}


def _scene(c: TestClient, **changes: Any) -> str:
    r = c.post("/v1/scenes", json={"scene": small_scene(**changes)})
    assert r.status_code in (200, 201), r.text
    sid: str = r.json()["id"]
    return sid


def test_outputs_are_validated_with_the_allowed_values(client: TestClient) -> None:
    sid = _scene(client)
    r = client.post("/v1/renders", json={"scene_id": sid, "outputs": ["preview", "aovs"]})
    assert r.status_code == 422
    err = r.json()["errors"][0]
    assert err["field"] == "outputs.1"
    for name in ("preview", "radiance", "depth", "normal", "object_id", "material_id", "provenance"):
        assert f"'{name}'" in err["message"]
    r = client.post("/v1/renders", json={"scene_id": sid, "outputs": []})
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "outputs"
    assert "at least one of preview, radiance" in r.json()["errors"][0]["message"]
    r = client.post("/v1/renders", json={"scene_id": sid, "outputs": ["preview", "provenance"]})
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "outputs"
    assert "LDC methods only" in r.json()["errors"][0]["message"]
    r = client.post("/v1/renders", json={"scene_id": sid, "outputs": "preview"})
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "outputs"


def test_outputs_are_part_of_the_artifact_key_and_the_default_key_is_unchanged(client: TestClient) -> None:
    sid = _scene(client)
    full = RenderRequest.model_validate({"scene_id": sid, "camera": CAM})
    # the key of a request without `outputs` is the key it had before the field existed
    legacy_params = full.model_dump(mode="json", exclude={"scene_id", "missing_bake", "outputs", "bake", "quality",
                                                          "view"})
    assert render_artifact_key(full) == artifact_key("render", {"scene": sid}, legacy_params, ENGINE_VERSION)
    lean = full.model_copy(update={"outputs": ["preview"]})
    assert render_artifact_key(lean) != render_artifact_key(full)

    a = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM, "outputs": ["radiance", "preview"]}).json()
    b = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM,
                                         "outputs": ["preview", "radiance", "preview"]}).json()
    c = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM}).json()
    assert a["job"]["id"] == b["job"]["id"]  # normalised: same set, same artifact, same job
    assert c["job"]["id"] != a["job"]["id"] and c["artifact_key"] == render_artifact_key(full)
    # links name only the images the artifact will hold
    assert {"image.png", "image.exr"} <= set(a["links"]) and {"image.png", "image.exr"} <= set(c["links"])
    d = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM, "outputs": ["preview"]}).json()
    assert set(d["links"]) == {"artifact", "image.png", "job"}


def test_openapi_documents_the_409_of_the_render_endpoints(client: TestClient) -> None:
    spec = client.get("/openapi.json").json()
    for path in ("/v1/renders", "/v1/batches"):
        resp = spec["paths"][path]["post"]["responses"]
        assert "409" in resp, path
        assert "bake" in resp["409"]["description"].lower() and "application/problem+json" in resp["409"]["content"]
    outputs = spec["components"]["schemas"]["RenderRequest"]["properties"]["outputs"]
    assert "provenance" in str(outputs) and outputs.get("description")


def test_an_ldc_render_without_its_bake_is_the_documented_409(client: TestClient) -> None:
    sid = _scene(client)
    for path, body in (("/v1/renders", {"scene_id": sid, "method": "ldc"}),
                       ("/v1/batches", {"renders": [{"scene_id": sid, "method": "ldc+ibrt:1"}]})):
        r = client.post(path, json=body)
        assert r.status_code == 409, (path, r.text)
        assert r.headers["content-type"].startswith("application/problem+json")
        assert r.json()["type"] == "urn:ibr:problem:bake-missing" and "/bakes" in r.json()["detail"]


def test_the_wait_ignores_an_older_result_of_the_same_job_id(client: TestClient, redis_conn: Redis) -> None:
    """A job id is reused when a render is requested again (its artifact was invalidated): the result
    stream may still hold the previous run's result, which must not end the wait of the new run."""
    sid = _scene(client)
    body = {"scene_id": sid, "camera": CAM}
    job_id = client.post("/v1/renders", json=body).json()["job"]["id"]
    redis_conn.xadd(f"rq:results:{job_id}", {"type": "1", "worker_name": "earlier-run"})
    t0 = time.monotonic()
    r = client.post("/v1/renders?wait=0.6", json=body)
    assert r.status_code == 202 and r.json()["status"] == "queued"
    assert time.monotonic() - t0 >= 0.6


def test_the_wait_ends_soon_after_a_cancel(client: TestClient, redis_conn: Redis) -> None:
    """A job that ends without a result (canceled; likewise a dead worker's job failed by maintenance)
    ends the wait at the end of the current read slice, not at the deadline."""
    sid = _scene(client)
    body = {"scene_id": sid, "camera": CAM}
    job_id = client.post("/v1/renders", json=body).json()["job"]["id"]
    timer = threading.Timer(0.3, cancel, args=(redis_conn, job_id))
    timer.start()
    try:
        t0 = time.monotonic()
        r = client.post("/v1/renders?wait=20", json=body)
        took = time.monotonic() - t0
    finally:
        timer.join()
    assert r.status_code == 200 and r.json()["job"]["state"] == "canceled", r.text
    assert 0.3 <= took < 5.0


@pytest.mark.slow
def test_a_lean_render_through_a_worker(client: TestClient, worker_process: Any, tmp_path: Path) -> None:
    worker = worker_process("render")
    sid = _scene(client)
    body = {"scene_id": sid, "camera": CAM, "params": PARAMS}

    lean = client.post("/v1/renders?wait=60", json={**body, "outputs": ["preview"]})
    assert lean.status_code == 200 and lean.json()["status"] == "finished", (lean.text, worker.log())
    lkey = lean.json()["artifact_key"]
    assert {b["name"] for b in lean.json()["artifact"]["blobs"]} == {"preview.png"}
    assert lean.json()["artifact"]["params"]["outputs"] == ["preview"]
    png = client.get(f"/v1/artifacts/{lkey}/image.png")
    assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert client.get(f"/v1/artifacts/{lkey}/image.exr").status_code == 404
    assert set(lean.json()["links"]) == {"artifact", "image.png", "job"}

    # the full request is never served the lean artifact
    full = client.post("/v1/renders?wait=60", json=body)
    assert full.status_code == 200 and full.json()["status"] == "finished", full.text
    fkey = full.json()["artifact_key"]
    assert fkey != lkey and set(full.json()["links"]) == {"artifact", "image.png", "image.exr", "job"}
    assert {b["name"] for b in full.json()["artifact"]["blobs"]} == {
        "preview.png", "radiance.exr", "depth.exr", "normal.exr", "object_id.exr", "material_id.exr"}
    # same view, same pixels (the bytes differ: each image's metadata names its artifact key)
    from engine.imageio import read_image

    (tmp_path / "lean.png").write_bytes(png.content)
    (tmp_path / "full.png").write_bytes(client.get(f"/v1/artifacts/{fkey}/image.png").content)
    lean_px, lean_md = read_image(tmp_path / "lean.png")
    full_px, full_md = read_image(tmp_path / "full.png")
    assert np.array_equal(lean_px, full_px) and lean_md["artifact_key"] == lkey and full_md["artifact_key"] == fkey

    # a subset that was never rendered on its own is served from the full artifact
    sub = client.post("/v1/renders?wait=60", json={**body, "outputs": ["radiance", "preview"]})
    assert sub.status_code == 200 and sub.json()["status"] == "cached" and sub.json()["artifact_key"] == fkey
    assert sub.json()["job"] is None
    assert worker.alive()


def test_many_waiting_requests_leave_the_default_threads_to_other_endpoints(client: TestClient) -> None:
    """More waiting renders than the default thread pool (40) has threads: the blocking reads run on
    their own limiter in short slices, so a sync endpoint still answers at once."""
    from concurrent.futures import ThreadPoolExecutor

    sid = _scene(client)
    n_waiting = 45

    def wait(i: int) -> int:
        cam = {**CAM, "width": 8 + i}
        return client.post("/v1/renders?wait=2.5", json={"scene_id": sid, "camera": cam}).status_code

    with ThreadPoolExecutor(n_waiting) as pool:
        futures = [pool.submit(wait, i) for i in range(n_waiting)]
        time.sleep(1.0)  # all of them are waiting now (no worker)
        t0 = time.monotonic()
        r = client.get("/v1/jobs", params={"state": "queued", "limit": 5})  # a sync (threadpool) endpoint
        took = time.monotonic() - t0
        assert r.status_code == 200 and not any(f.done() for f in futures)
    # starved, it would answer only when the first waits end, 1.5 s after t0; the bound leaves room
    # for a loaded CI machine (0.6 s seen with another test worker busy)
    assert took < 1.0, took
    assert [f.result() for f in futures] == [202] * n_waiting
