"""A render whose estimated peak memory (``producer.costs.render_cost``: the image's buffers and the scene
the worker builds) exceeds ``IBR_MAX_RENDER_BYTES`` is refused with 422 naming the estimate and the limit,
before anything is queued; one under the limit is queued."""

from __future__ import annotations

from typing import Any

from fastapi.testclient import TestClient
from redis import Redis

from api_schemas.scene import Scene
from api_schemas.service import RenderRequest
from producer.costs import estimate_render_bytes, render_cost, scene_triangles
from tests.service.api.conftest import SMALL_SCENE, small_scene

LIMIT = 3 << 29  # 1.5 GiB


def _camera(width: int, height: int) -> dict[str, Any]:
    return {**SMALL_SCENE["camera"], "width": width, "height": height}


def test_estimate_grows_with_pixels_and_samples() -> None:
    sid = "0" * 64
    ref = estimate_render_bytes(RenderRequest(scene_id=sid), 1000, 1000)
    assert estimate_render_bytes(RenderRequest(scene_id=sid), 2000, 2000) > ref + 200 * 3_000_000  # per pixel
    assert estimate_render_bytes(RenderRequest(scene_id=sid, params={"spp": 64}), 1000, 1000) > ref
    # 7000 x 7000 (a render that swelled a worker to 9.2 GB at 5 % progress) is over the default limit
    from producer.settings import Settings

    assert estimate_render_bytes(RenderRequest(scene_id=sid), 7000, 7000) > Settings().max_render_bytes


def test_over_the_limit_is_refused_before_it_is_queued(make_app: Any, redis_conn: Redis) -> None:
    with TestClient(make_app(max_render_bytes=LIMIT)) as c:
        sid = c.post("/v1/scenes", json={"scene": small_scene()}).json()["id"]
        side = 2000
        triangles = scene_triangles(Scene.model_validate(small_scene()))
        need = render_cost(RenderRequest(scene_id=sid, camera=_camera(side, side)), side, side, triangles).peak_bytes
        assert need > LIMIT
        r = c.post("/v1/renders", json={"scene_id": sid, "camera": _camera(side, side)})
        assert r.status_code == 422, r.text
        (err,) = r.json()["errors"]
        assert err["field"] == "camera.height" and err["type"] == "render_too_large"
        assert f"{need / (1 << 30):.2f} GiB" in err["message"] and "1.50 GiB" in err["message"], err
        assert f"IBR_MAX_RENDER_BYTES = {LIMIT}" in err["message"]
        # spp counts: the same view at 1 spp fits, at 64 spp it does not
        side = 600
        ok = c.post("/v1/renders", json={"scene_id": sid, "camera": _camera(side, side)})
        assert ok.status_code == 202, ok.text
        heavy = c.post("/v1/renders", json={"scene_id": sid, "camera": _camera(side, side), "params": {"spp": 64}})
        assert heavy.status_code == 422 and "64 spp" in heavy.json()["errors"][0]["message"], heavy.text
        # the LDC methods are estimated too (and refused before any bake is asked for)
        r = c.post("/v1/renders", json={"scene_id": sid, "camera": _camera(2600, 2600), "method": "ldc",
                                        "missing_bake": "bake"})
        assert r.status_code == 422 and "a ldc render of 2600 x 2600" in r.json()["errors"][0]["message"], r.text
        # only the accepted render was queued
        assert [k.decode() for k in redis_conn.keys("rq:job:*")] == [f"rq:job:{ok.json()['job']['id']}"]


def test_scenes_own_camera_is_estimated_too(make_app: Any) -> None:
    with TestClient(make_app(max_render_bytes=LIMIT)) as c:
        sid = c.post("/v1/scenes", json={"scene": small_scene(camera=_camera(1500, 1500))}).json()["id"]
        r = c.post("/v1/renders", json={"scene_id": sid})
        assert r.status_code == 422 and r.json()["errors"][0]["field"] == "scene_id", r.text


def test_batches_are_estimated_render_by_render_and_as_a_whole(make_app: Any, redis_conn: Redis) -> None:
    with TestClient(make_app(max_render_bytes=LIMIT, max_bake_cpu_s=60.0)) as c:
        stored = c.post("/v1/scenes", json={"scene": small_scene()}).json()["id"]
        new_scene = small_scene(camera=_camera(64, 48))
        big = {"scene_id": stored, "camera": _camera(2000, 2000)}
        r = c.post("/v1/batches", json={"scenes": [{"scene": new_scene}], "renders": [{"scene_id": stored}, big]})
        assert r.status_code == 422, r.text
        (err,) = r.json()["errors"]
        assert err["field"] == "renders.1.camera.height" and err["type"] == "render_too_large", err
        assert "IBR_MAX_RENDER_BYTES" in err["message"]
        # each render fits, together their CPU time does not (IBR_MAX_BAKE_CPU_S bounds one request's jobs)
        per = render_cost(RenderRequest(scene_id=stored, params={"spp": 16}), 64, 48,
                          scene_triangles(Scene.model_validate(small_scene()))).total_cpu_s
        n = int(60.0 / per) + 2
        renders = [{"scene_id": stored, "params": {"spp": 16, "seed": i}, "camera": _camera(64, 48)} for i in range(n)]
        r = c.post("/v1/batches", json={"renders": renders})
        assert r.status_code == 422 and r.json()["errors"][0]["field"] == "renders", r.text
        assert "IBR_MAX_BAKE_CPU_S" in r.json()["errors"][0]["message"]
        # nothing was stored or queued by the refused batches; a fitting one is queued
        assert not redis_conn.keys("rq:job:*")
        ok = c.post("/v1/batches", json={"renders": renders[:2]})
        assert ok.status_code == 202, ok.text
