"""``GET /v1/methods``: the render workers' warm-up readiness, read from Redis
(producer/readiness.py): only live (registered) workers count; several workers merge per kind."""

from __future__ import annotations

from fastapi.testclient import TestClient
from redis import Redis

from api_schemas.readiness import READINESS_METHODS
from producer.readiness import clear_readiness, publish_readiness
from workers import warmup
from workers.runner import build_worker
from workers.warmup_readiness import METHOD_STEPS, ReadinessTracker


def _register(redis: Redis, name: str) -> None:
    build_worker("render", redis, name=name).register_birth()


def test_no_worker_reports_unknown(client: TestClient) -> None:
    r = client.get("/v1/methods")
    assert r.status_code == 200
    doc = r.json()
    assert doc["workers"] == 0
    assert [m["method"] for m in doc["methods"]] == list(READINESS_METHODS)
    assert {m["state"] for m in doc["methods"]} == {"unknown"}


def test_live_workers_merge_and_dead_ones_are_ignored(client: TestClient, redis_conn: Redis) -> None:
    early = ReadinessTracker(list(warmup.STEPS), "render-early")
    publish_readiness(redis_conn, "render-early", early.document())
    assert client.get("/v1/methods").json()["workers"] == 0  # not registered: not a live worker

    _register(redis_conn, "render-early")
    doc = client.get("/v1/methods").json()
    assert doc["workers"] == 1
    by = {m["method"]: m for m in doc["methods"]}
    assert by["reference"]["state"] == "compiling" and by["reference"]["seconds_left"] > 0
    assert by["walkthrough"]["seconds_left"] > by["reference"]["seconds_left"]

    later = ReadinessTracker(list(warmup.STEPS), "render-later")
    for s in METHOD_STEPS["reference"]:
        later.started(s)
        later.finished(s, 0.5, True)
    _register(redis_conn, "render-later")
    publish_readiness(redis_conn, "render-later", later.document())
    by = {m["method"]: m for m in client.get("/v1/methods").json()["methods"]}
    assert by["reference"] == {"method": "reference", "state": "ready", "seconds_left": None}
    assert by["ldc"]["state"] == "compiling"

    # a worker's second lane (another warm-up process) counts as the same worker
    lane1 = ReadinessTracker(list(warmup.LANES[1]), "render-later")
    publish_readiness(redis_conn, "render-later", lane1.document(), lane=1)
    doc = client.get("/v1/methods").json()
    assert doc["workers"] == 2
    clear_readiness(redis_conn, "render-later")
    by = {m["method"]: m for m in client.get("/v1/methods").json()["methods"]}
    assert by["reference"]["state"] == "compiling"
