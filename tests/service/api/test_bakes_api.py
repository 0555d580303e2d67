"""The bake API and the LDC render methods through the HTTP API, with real Redis and real worker
subprocesses: request a bake (202 + Location), follow its parts to 1.0, get it cached the second
time, list and delete it; an ``ldc`` render of the baked scene returns an image, a provenance image
and timings per stage; a render of an unbaked scene is a clear 409 (or waits for the bake when asked);
bad parameters are 422 naming the field."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from redis import Redis

from tests.service.api.conftest import small_scene

BAKE = {"ldc_resolution": 24, "max_layers": 8, "area_light_samples": 1, "indirect": {"mode": "off"}}
"""Direct light only where a test is not about indirect light (the default indirect pass adds 12
chunk jobs per bake)."""


def _diffuse_scene() -> dict[str, Any]:
    return small_scene(camera={"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0], "fov_y_deg": 40,
                               "width": 32, "height": 24})


def _scene(c: TestClient) -> str:
    r = c.post("/v1/scenes", json={"scene": _diffuse_scene()})
    assert r.status_code == 201, r.text
    sid: str = r.json()["id"]
    return sid


def _poll(c: TestClient, url: str, done: tuple[str, ...], timeout: float = 120.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    body: dict[str, Any] = {}
    while time.monotonic() < deadline:
        body = c.get(url).json()
        if body["state"] in done:
            return body
        time.sleep(0.1)
    raise AssertionError(f"{url} not done after {timeout} s: {body.get('state')} {body.get('progress')}")


def _fields(r: Any) -> set[str]:
    return {e["field"] for e in r.json()["errors"]}


def test_indirect_settings_out_of_range_are_422_with_the_allowed_range(client: TestClient) -> None:
    sid = _scene(client)
    r = client.post(f"/v1/scenes/{sid}/bakes", json={"indirect": {"noise": 0.0001, "bounces": 40, "mode": "always",
                                                                  "chunks": 0}})
    assert r.status_code == 422, r.text
    msgs = {e["field"]: e["message"] for e in r.json()["errors"]}
    assert set(msgs) == {"indirect.noise", "indirect.bounces", "indirect.mode", "indirect.chunks"}, msgs
    assert "[0.001, 0.5]" in msgs["indirect.noise"] and "[1, 16]" in msgs["indirect.bounces"]
    assert "auto" in msgs["indirect.mode"] and "off" in msgs["indirect.mode"] and "1" in msgs["indirect.chunks"]
    r = client.post(f"/v1/scenes/{sid}/bakes", json={"indirect": {"min_paths": 64, "max_paths": 40000000}})
    assert r.status_code == 422 and "[2, 65536]" in r.json()["errors"][0]["message"], r.text
    r = client.post(f"/v1/scenes/{sid}/bakes", json={"indirect": {"min_paths": 36}})  # not a multiple of 8
    assert r.status_code == 422 and "multiple of round_paths (8)" in r.text, r.text
    r = client.post("/v1/renders", json={"scene_id": sid, "method": "ldc", "bake": {"indirect": {"max_paths": 1}}})
    assert r.status_code == 422 and "[2, 65536]" in r.text  # the render's bake is the same model
    # the schema says the ranges too
    schema = client.get("/openapi.json").json()["components"]["schemas"]["IndirectBakeParams"]["properties"]
    assert (schema["noise"]["minimum"], schema["noise"]["maximum"]) == (0.001, 0.5)


def test_bad_bake_and_render_params_are_422_naming_the_field(client: TestClient) -> None:
    sid = _scene(client)
    r = client.post(f"/v1/scenes/{sid}/bakes", json={"ldc_resolution": 2, "llf_f": 99, "llf": "sometimes"})
    assert r.status_code == 422 and _fields(r) == {"ldc_resolution", "llf_f", "llf"}
    msgs = {e["field"]: e["message"] for e in r.json()["errors"]}
    assert "8" in msgs["ldc_resolution"] and "16" in msgs["llf_f"]  # the allowed range is in the message
    r = client.post(f"/v1/scenes/{sid}/bakes", json={"ldc_resolution": 4096, "max_layers": 256})
    assert r.status_code == 422 and _fields(r) == {"ldc_resolution"} and "MiB" in r.text
    r = client.post(f"/v1/scenes/{sid}/bakes", json={"llf": "always", "llf_resolution": 512, "llf_chunk": 1026,
                                                     "llf_f": 16, "max_layers": 64})
    assert r.status_code == 422 and _fields(r) == {"llf_chunk"}
    r = client.post("/v1/renders", json={"scene_id": sid, "method": "ldc+ibrt:9"})
    assert r.status_code == 422 and _fields(r) == {"method"} and "0..8" in r.text
    r = client.post("/v1/renders", json={"scene_id": sid, "method": "ldc", "bake": {"max_layers": 0}})
    assert r.status_code == 422 and _fields(r) == {"bake.max_layers"}
    assert client.post(f"/v1/scenes/{'0' * 64}/bakes", json=BAKE).status_code == 404
    assert client.get(f"/v1/scenes/{sid}/bakes/{'1' * 64}").status_code == 404


def test_render_without_bake_is_409_naming_the_bake(client: TestClient, redis_conn: Redis) -> None:
    sid = _scene(client)
    r = client.post("/v1/renders", json={"scene_id": sid, "method": "ldc", "bake": BAKE})
    assert r.status_code == 409, r.text
    assert f"/v1/scenes/{sid}/bakes" in r.json()["detail"] and "missing_bake" in r.json()["detail"]
    assert r.headers["content-type"].startswith("application/problem+json")


@pytest.mark.slow
def test_bake_then_ldc_render_end_to_end(client: TestClient, worker_process: Any, redis_conn: Redis,
                                         tmp_path: Path) -> None:
    sid = _scene(client)
    bake_worker = worker_process("bake")
    r = client.post(f"/v1/scenes/{sid}/bakes", json=BAKE)
    assert r.status_code == 202, r.text
    url = r.headers["location"]
    body = r.json()
    assert url == f"/v1/scenes/{sid}/bakes/{body['key']}" and body["state"] == "queued" and not body["cached"]
    assert body["job"]["id"] == f"bake-{body['key']}"
    done = _poll(client, url, ("finished", "failed", "missing"))
    assert done["state"] == "finished", (done, bake_worker.log())
    assert done["progress"]["fraction"] == 1.0
    assert [p["name"] for p in done["parts"]] == ["ldc-axis-0", "ldc-axis-1", "ldc-axis-2"]  # diffuse: no LLF
    assert done["plan"]["bake_llf"] is False and done["artifact"]["kind"] == "bake"
    again = client.post(f"/v1/scenes/{sid}/bakes", json=BAKE)
    assert again.status_code == 200 and again.json()["cached"] and again.json()["key"] == body["key"]
    listed = client.get(f"/v1/scenes/{sid}/bakes").json()["items"]
    assert [b["key"] for b in listed] == [body["key"]] and listed[0]["state"] == "finished"

    render_worker = worker_process("render")
    r = client.post("/v1/renders?wait=60", json={"scene_id": sid, "method": "ldc", "bake": BAKE})
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["status"] == "finished", (out, render_worker.log())
    manifest = out["artifact"]
    names = {b["name"] for b in manifest["blobs"]}
    assert {"radiance.exr", "preview.png", "depth.exr", "normal.exr", "provenance.png"} <= names
    res = manifest["result"]
    assert res["bake_key"] == body["key"] and res["plan"]
    assert {"warp", "holes", "fill", "load_bake", "encode"} <= set(res["timings"]), res["timings"]
    assert "hole_pixels" in res["counts"] and res["counts"]["width"] == 32
    prov = res["counts"]["provenance"]
    assert sum(prov.values()) == 32 * 24 and prov["warped"] > 0
    png = client.get(f"/v1/artifacts/{out['artifact_key']}/image.png")
    assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"
    # the provenance image holds the codes themselves, matching the counts
    r = client.get(f"/v1/artifacts/{out['artifact_key']}/provenance.png")
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    path = tmp_path / "provenance.png"
    path.write_bytes(r.content)
    import OpenImageIO as oiio

    codes = np.asarray(oiio.ImageBuf(str(path)).get_pixels(oiio.UINT8)).reshape(24, 32)
    assert int((codes == 1).sum()) == prov["warped"] and int((codes == 0).sum()) == prov["background"]
    assert set(np.unique(codes).tolist()) <= {0, 1, 2, 3, 4}

    # missing_bake="bake": a render of another (missing) bake queues that bake and runs after it
    bake2 = {**BAKE, "seed": 3}
    r = client.post("/v1/renders", json={"scene_id": sid, "method": "ldc", "bake": bake2, "missing_bake": "bake"})
    assert r.status_code == 202, r.text
    waiting = r.json()
    assert waiting["bake"] is not None and waiting["bake"]["state"] in ("queued", "running")
    assert waiting["job"]["progress"]["stage"] == "waiting for the bake"
    job = _poll(client, r.headers["location"], ("finished", "failed", "canceled"))
    assert job["state"] == "finished", (job, bake_worker.log(), render_worker.log())
    assert job["result"]["bake_key"] == waiting["bake"]["key"] != body["key"]

    # deleting the bake removes it and its parts; the render artifact stays
    assert client.delete(url).status_code == 204
    assert client.get(url).status_code == 404
    assert client.get(f"/v1/artifacts/{body['key']}").status_code == 404
    assert [b["key"] for b in client.get(f"/v1/scenes/{sid}/bakes").json()["items"]] == [waiting["bake"]["key"]]
    assert client.get(f"/v1/artifacts/{out['artifact_key']}/image.png").status_code == 200


def test_bakes_are_visible_only_to_keys_that_see_the_scene(make_app: Any) -> None:
    from service.core.security import hash_key

    a, b = {"Authorization": "Bearer key-a-0123456789"}, {"Authorization": "Bearer key-b-9876543210"}
    with TestClient(make_app(api_keys=[hash_key("key-a-0123456789"), hash_key("key-b-9876543210")])) as c:
        sid = c.post("/v1/scenes", json={"scene": _diffuse_scene()}, headers=a).json()["id"]
        r = c.post(f"/v1/scenes/{sid}/bakes", json=BAKE, headers=a)
        assert r.status_code == 202
        url, job = r.headers["location"], r.json()["job"]["id"]
        assert c.get(url, headers=a).status_code == 200 and c.get(f"/v1/jobs/{job}", headers=a).status_code == 200
        for req in (("GET", url), ("DELETE", url), ("GET", f"/v1/scenes/{sid}/bakes"), ("GET", f"/v1/jobs/{job}")):
            assert c.request(*req, headers=b).status_code == 404, req  # as if it did not exist
        assert c.post(f"/v1/scenes/{sid}/bakes", json=BAKE, headers=b).status_code == 404
        assert c.get(url).status_code == 401
