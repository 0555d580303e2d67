"""Requests whose estimated cost (``producer.costs``) is over this server's limits are refused with 422
naming the estimate, the limit and its setting, before anything is built or queued: scenes by their
triangles after tessellation (the 10,000 spheres at subdivision 8), bakes by their part memory and
CPU time, dataset generations, calibrations and walkthrough bakes."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient
from redis import Redis

from tests.service.api.conftest import small_scene

REPO = Path(__file__).resolve().parents[3]


def _refused(r: Any, setting: str, type_: str) -> dict[str, Any]:
    assert r.status_code == 422, r.text
    body = r.json()
    (err,) = body["errors"]
    assert err["type"] == type_ and setting in err["message"], body
    return dict(err)


def test_ten_thousand_spheres_at_subdivision_8_are_refused_before_anything_is_built(
        client: TestClient, store_dir: Path) -> None:
    sphere = {"type": "sphere", "radius": 0.1, "subdivisions": 8, "material": "red"}
    scene = small_scene(objects=[{**sphere, "center": [0.3 * (i % 100), 0, 0.3 * (i // 100)]}
                                 for i in range(10_000)])
    body = json.dumps({"scene": scene})
    assert len(body) > 1 << 20  # the 1.1 MiB scene of the report
    t0 = time.monotonic()
    r = client.post("/v1/scenes", content=body, headers={"Content-Type": "application/json"})
    took = time.monotonic() - t0
    err = _refused(r, "IBR_MAX_SCENE_TRIANGLES", "scene_too_large")
    assert "13,107,200,000 triangles" in err["message"] and "8,000,000" in err["message"], err
    assert took < 20, took  # validation of 10,000 objects; nothing tessellated
    assert not list((store_dir / "scenes").glob("*.json")) if (store_dir / "scenes").exists() else True


def test_mesh_files_count_toward_the_triangle_limit(make_app: Any) -> None:
    teapot = (REPO / "samples/meshes/teapot.ply").read_bytes()
    scene = small_scene(objects=[{"type": "mesh_file", "path": "teapot.ply", "material": "red"}])
    with TestClient(make_app(max_scene_triangles=1000)) as c:
        r = c.post("/v1/scenes", files={"scene": (None, json.dumps(scene)),
                                        "teapot.ply": ("teapot.ply", teapot, "application/octet-stream")})
        err = _refused(r, "IBR_MAX_SCENE_TRIANGLES", "scene_too_large")
        assert err["field"] == "scene.objects" and "over this server's limit of 1,000" in err["message"]
        assert c.post("/v1/scenes", json={"scene": small_scene(objects=[
            {"type": "sphere", "radius": 1, "subdivisions": 2, "material": "red"}])}).status_code == 201


def test_bakes_over_their_memory_or_cpu_limit_are_refused_before_they_are_queued(make_app: Any,
                                                                                  redis_conn: Redis) -> None:
    with TestClient(make_app(max_bake_part_bytes=256 << 20)) as c:
        sid = c.post("/v1/scenes", json={"scene": small_scene()}).json()["id"]
        r = c.post(f"/v1/scenes/{sid}/bakes", json={"ldc_resolution": 1024, "max_layers": 16})
        err = _refused(r, "IBR_MAX_BAKE_PART_BYTES = 268435456", "bake_too_large")
        assert "a scene bake needs an estimated" in err["message"] and "256 MiB" in err["message"], err
    with TestClient(make_app(max_bake_cpu_s=600)) as c:
        r = c.post(f"/v1/scenes/{sid}/bakes", json={"ldc_resolution": 512, "max_layers": 4,
                                                     "indirect": {"max_paths": 4096, "min_paths": 1024}})
        err = _refused(r, "IBR_MAX_BAKE_CPU_S = 600", "bake_too_large")
        assert "of CPU time in" in err["message"], err
        assert redis_conn.keys("rq:job:*") == []
        ok = c.post(f"/v1/scenes/{sid}/bakes", json={"ldc_resolution": 64})
        assert ok.status_code == 202, ok.text


def test_generations_and_calibrations_are_estimated(make_app: Any, redis_conn: Redis) -> None:
    with TestClient(make_app(max_bake_job_cpu_s=60)) as c:
        sid = c.post("/v1/scenes", json={"scene": small_scene()}).json()["id"]
        cam = {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0], "fov_y_deg": 40,
               "width": 256, "height": 256}
        r = c.post("/v1/datasets/generate", json={"scene_id": sid, "camera": cam})
        err = _refused(r, "IBR_MAX_BAKE_JOB_CPU_S = 60", "bake_too_large")
        assert "dataset generation of" in err["message"], err
    with TestClient(make_app(max_render_bytes=512 << 20)) as c:
        r = c.post(f"/v1/scenes/{sid}/calibrations", json={"params": {"size": 256, "truth_spp": 1024},
                                                           "missing_bake": "bake"})
        err = _refused(r, "IBR_MAX_RENDER_BYTES", "calibration_too_large")
        assert redis_conn.keys("rq:job:*") == []


def test_walkthrough_bakes_are_estimated(make_app: Any) -> None:
    room = json.loads((REPO / "examples/walkthrough/room.json").read_text())
    path = json.loads((REPO / "examples/walkthrough/path.json").read_text())
    with TestClient(make_app(max_render_bytes=64 << 20)) as c:
        sid = c.post("/v1/scenes", json={"scene": room.get("scene", room)}).json()["id"]
        frames = [{**f, "camera": {"type": "perspective", **f["camera"]}} for f in path]
        req = {"frames": frames, "scene_id": sid, "bake": {"quality": "low"}}
        r = c.post("/v1/walkthroughs", json=req)
        err = _refused(r, "IBR_MAX_RENDER_BYTES", "bake_too_large")
        assert "walkthrough bake needs an estimated" in err["message"], err
