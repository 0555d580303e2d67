"""End to end through a real RQ render worker: upload, render, poll, download; the EXR equals a
direct engine render; identical requests are cached; bad meshes fail the job clearly; a corrupt
artifact is never served."""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from redis import Redis

from tests.service.api.conftest import TEAPOT_PLY, small_scene, teapot_scene

PARAMS = {"spp": 1, "max_depth": 2, "glossy_samples": 2, "area_light_samples": 1, "seed": 7}


def _upload_teapot(c: TestClient, scene: dict[str, Any]) -> str:
    files = [("scene", (None, json.dumps(scene).encode(), "application/json")),
             ("meshes/teapot.ply", ("teapot.ply", TEAPOT_PLY.read_bytes(), "application/octet-stream"))]
    r = c.post("/v1/scenes", files=files)
    assert r.status_code == 201, r.text
    sid: str = r.json()["id"]
    return sid


def _poll(c: TestClient, url: str, timeout: float = 180.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    seen_states = []
    while time.monotonic() < deadline:
        job: dict[str, Any] = c.get(url).json()
        seen_states.append(job["state"])
        if job["state"] in ("finished", "failed", "canceled"):
            return job
        time.sleep(0.2)
    raise AssertionError(f"job not done after {timeout} s: {seen_states[-5:]}")


def _direct_render(scene_doc: dict[str, Any], params: dict[str, Any]) -> np.ndarray:
    from api_schemas.scene import Scene
    from engine.reference import ReferenceParams, ReferenceRenderer
    from workers.scene_loader import load_scene

    def resolver(path: str) -> tuple[bytes, str]:
        assert path == "meshes/teapot.ply"
        return TEAPOT_PLY.read_bytes(), "ply"

    loaded = load_scene(Scene.model_validate(scene_doc), resolver)
    out = ReferenceRenderer(loaded.runtime).render(loaded.camera, ReferenceParams(**params))
    return np.asarray(out.radiance)


@pytest.mark.slow
def test_render_roundtrip_equals_direct_engine_render(
    client: TestClient, worker_process: Any, redis_conn: Redis, tmp_path: Path, store_dir: Path
) -> None:
    worker = worker_process("render")
    scene = teapot_scene(32, 24)
    sid = _upload_teapot(client, scene)

    r = client.post("/v1/renders", json={"scene_id": sid, "params": PARAMS})
    assert r.status_code == 202, r.text
    body = r.json()
    job_url = r.headers["location"]
    assert job_url == f"/v1/jobs/{body['job']['id']}" and body["status"] == "queued"
    # an identical request while the first is pending shares its job
    r2 = client.post("/v1/renders", json={"scene_id": sid, "params": PARAMS})
    assert r2.status_code == 202 and r2.json()["job"]["id"] == body["job"]["id"]

    job = _poll(client, job_url)
    assert job["state"] == "finished", (job, worker.log())
    assert job["result"]["artifact_key"] == body["artifact_key"] and job["progress"]["fraction"] == 1.0
    key = body["artifact_key"]

    manifest = client.get(f"/v1/artifacts/{key}").json()
    assert {b["name"] for b in manifest["blobs"]} >= {"radiance.exr", "preview.png"}
    exr = client.get(f"/v1/artifacts/{key}/image.exr")
    assert exr.status_code == 200 and exr.headers["content-type"] == "image/x-exr"
    png = client.get(f"/v1/artifacts/{key}/image.png")
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert png.content[:8] == b"\x89PNG\r\n\x1a\n"

    from engine.imageio import read_image

    (tmp_path / "dl.exr").write_bytes(exr.content)
    served, meta = read_image(tmp_path / "dl.exr")
    assert served.shape == (24, 32, 3) and meta["scene_id"] == sid
    direct = _direct_render(scene, PARAMS)
    assert served.dtype == np.float32 and np.array_equal(served, direct.astype(np.float32))

    # the same request again: served from the cache, no new job
    jobs_before = sorted(redis_conn.keys("rq:job:*"))
    cached = client.post("/v1/renders", json={"scene_id": sid, "params": PARAMS})
    assert cached.status_code == 200 and cached.json()["status"] == "cached"
    assert cached.json()["artifact"]["key"] == key and cached.json()["job"] is None
    assert sorted(redis_conn.keys("rq:job:*")) == jobs_before
    assert 'ibr_render_cache_total{result="hit"} 1.0' in client.get("/metrics").text

    # wait=: another seed, answered in one request once the worker is done
    r = client.post("/v1/renders?wait=60", json={"scene_id": sid, "params": {**PARAMS, "seed": 8}})
    assert r.status_code == 200 and r.json()["status"] == "finished", r.text
    assert r.json()["artifact"]["blobs"]

    metrics = client.get("/metrics").text
    assert 'ibr_queue_jobs{queue="render",state="finished"}' in metrics
    assert 'ibr_job_duration_seconds_count{method="reference",outcome="finished",queue="render"}' in metrics

    # docs/hard-cases.md #23: corrupt the stored EXR -> never served, manifest gone, a new request rebakes
    (store_dir / "artifacts" / key / "radiance.exr").write_bytes(b"garbage")
    bad = client.get(f"/v1/artifacts/{key}/image.exr")
    assert bad.status_code == 404 and "corrupt" in bad.json()["title"].lower()
    assert client.get(f"/v1/artifacts/{key}").status_code == 404
    again = client.post("/v1/renders?wait=60", json={"scene_id": sid, "params": PARAMS})
    assert again.status_code == 200 and again.json()["status"] == "finished", again.text
    assert client.get(f"/v1/artifacts/{key}/image.exr").content == exr.content  # deterministic rebake
    assert worker.alive()


def _quad_ply_with_bad_index() -> bytes:
    """Quads: the upload pre-check leaves polygons to the worker, whose loader must refuse it."""
    verts = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
    header = (b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
              b"property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n")
    body = b"".join(struct.pack("<3f", *v) for v in verts)
    body += struct.pack("<B4i", 4, 0, 1, 2, 3) + struct.pack("<B4i", 4, 0, 1, 2, 99)
    return header + body


@pytest.mark.slow
def test_bad_mesh_fails_the_job_with_a_clear_message(client: TestClient, worker_process: Any) -> None:
    """docs/hard-cases.md #15 past the upload pre-check: the job fails, naming the problem; the worker lives."""
    worker = worker_process("render")
    scene = small_scene()
    scene["objects"] = [{"type": "mesh_file", "path": "quad.ply", "material": "white"}]
    files = [("scene", (None, json.dumps(scene).encode(), "application/json")),
             ("quad.ply", ("quad.ply", _quad_ply_with_bad_index(), "application/octet-stream"))]
    r = client.post("/v1/scenes", files=files)
    assert r.status_code == 201, r.text
    r = client.post("/v1/renders?wait=60", json={"scene_id": r.json()["id"], "params": PARAMS})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["status"] == "failed" and body["artifact"] is None
    error = body["job"]["error"]
    assert "objects.0" in error and "out of range" in error, error
    assert worker.alive()
