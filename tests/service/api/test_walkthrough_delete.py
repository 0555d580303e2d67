"""DELETE /v1/walkthroughs/{key} without workers: 409 while its jobs wait in the queues, 204 once the
walkthrough failed (its waiting jobs are canceled), 404 afterwards and for other API keys."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import FastAPI
from fastapi.testclient import TestClient
from redis import Redis
from rq.job import Job
from rq.serializers import JSONSerializer

from api_schemas.walkthrough import WalkthroughPublic
from tests.service.api.test_walkthroughs import BAKE, ROOM, _frames


def test_delete_walkthrough_conflicts_while_queued_then_removes_everything(client: TestClient,
                                                                           redis_conn: Redis) -> None:
    sid = client.post("/v1/scenes", json={"scene": ROOM}).json()["id"]
    r = client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": _frames(4), "chunk_frames": 2,
                                              "bake": BAKE})
    assert r.status_code == 202, r.text
    pub = WalkthroughPublic.model_validate(r.json())
    # queued (no workers): refused, naming a job to cancel
    d = client.delete(f"/v1/walkthroughs/{pub.key}")
    assert d.status_code == 409 and d.headers["content-type"].startswith("application/problem+json")
    assert "queued or running job" in d.json()["detail"] and "wtchunk-" in d.json()["detail"]
    assert client.get(f"/v1/walkthroughs/{pub.key}").status_code == 200
    # a canceled chunk fails the walkthrough: now it can go, and its other jobs are canceled with it
    chunk = next(j.id for j in pub.jobs if j.id.startswith("wtchunk-"))
    assert client.post(f"/v1/jobs/{chunk}/cancel").status_code == 200
    assert client.get(f"/v1/walkthroughs/{pub.key}").json()["status"] == "failed"
    assert client.delete(f"/v1/walkthroughs/{pub.key}").status_code == 204
    assert client.get(f"/v1/walkthroughs/{pub.key}").status_code == 404
    assert client.get(f"/v1/walkthroughs/{pub.key}/video.mp4").status_code == 404
    assert client.delete(f"/v1/walkthroughs/{pub.key}").status_code == 404
    ids = [j.id for j in pub.jobs if not j.id.startswith("wtbake-")]
    assert Job.fetch_many(ids, connection=redis_conn, serializer=JSONSerializer) == [None] * len(ids)
    # the shared bake job is not the walkthrough's to delete
    bake_job = next(j.id for j in pub.jobs if j.id.startswith("wtbake-"))
    assert client.get(f"/v1/jobs/{bake_job}").status_code == 200
    # the same request again starts afresh
    again = client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": _frames(4), "chunk_frames": 2,
                                                  "bake": BAKE})
    assert again.status_code == 202 and again.json()["key"] == pub.key and again.json()["status"] == "queued"


def test_delete_walkthrough_of_another_key_is_404(make_app: Callable[..., FastAPI]) -> None:
    from service.core.security import hash_key

    app = make_app(api_keys=[hash_key("alice-key-0123456789"), hash_key("bob-key-9876543210")])
    with TestClient(app) as c:
        alice: dict[str, Any] = {"Authorization": "Bearer alice-key-0123456789"}
        bob: dict[str, Any] = {"Authorization": "Bearer bob-key-9876543210"}
        sid = c.post("/v1/scenes", json={"scene": ROOM}, headers=alice).json()["id"]
        r = c.post("/v1/walkthroughs", json={"scene_id": sid, "frames": _frames(2), "bake": BAKE}, headers=alice)
        assert r.status_code == 202, r.text
        key = r.json()["key"]
        assert c.delete(f"/v1/walkthroughs/{key}", headers=bob).status_code == 404
        assert c.delete(f"/v1/walkthroughs/{key}").status_code == 401
        assert c.delete(f"/v1/walkthroughs/{key}", headers=alice).status_code == 409
