"""DELETE /v1/scenes/{id} takes the scene's bakes and walkthroughs with it (they can never be
requested again without the scene): 409 with nothing removed while any of their jobs waits,
204 once they are canceled, and a re-upload of the same scene starts with no bakes or walkthroughs."""

from __future__ import annotations

from fastapi.testclient import TestClient
from redis import Redis
from rq.job import Job
from rq.serializers import JSONSerializer

from tests.service.api.test_bakes_api import BAKE, _diffuse_scene
from tests.service.api.test_walkthroughs import BAKE as WT_BAKE
from tests.service.api.test_walkthroughs import ROOM, _frames


def _active_ids(redis_conn: Redis, ids: list[str]) -> list[str]:
    jobs = Job.fetch_many(ids, connection=redis_conn, serializer=JSONSerializer)
    return [j.id for j in jobs if j is not None and j.get_status() in ("queued", "deferred", "started", "scheduled")]


def test_scene_delete_removes_its_bakes_after_a_409_while_they_wait(client: TestClient, redis_conn: Redis) -> None:
    scene = _diffuse_scene()
    sid = client.post("/v1/scenes", json={"scene": scene}).json()["id"]
    r = client.post(f"/v1/scenes/{sid}/bakes", json=BAKE)
    assert r.status_code == 202, r.text
    bake_url, key = r.headers["location"], r.json()["key"]
    # no workers: the bake waits, so the scene cannot go and nothing changes
    d = client.delete(f"/v1/scenes/{sid}")
    assert d.status_code == 409 and "queued or running" in d.json()["detail"], d.text
    assert client.get(f"/v1/scenes/{sid}").status_code == 200 and client.get(bake_url).status_code == 200
    ids = [j["id"] for j in client.get("/v1/jobs?limit=100").json()["items"]]
    assert client.post(f"/v1/jobs/bake-{key}/cancel").status_code == 200  # cancels its plan job with it
    assert _active_ids(redis_conn, ids) == []
    assert client.delete(f"/v1/scenes/{sid}").status_code == 204
    assert client.get(f"/v1/scenes/{sid}").status_code == 404
    # the same scene uploaded again has no bakes: the record went with the scene
    assert client.post("/v1/scenes", json={"scene": scene}).json()["id"] == sid
    assert client.get(f"/v1/scenes/{sid}/bakes").json()["items"] == []
    assert client.get(f"/v1/scenes/{sid}/bakes/{key}").status_code == 404


def test_scene_delete_removes_its_walkthroughs(client: TestClient, redis_conn: Redis) -> None:
    sid = client.post("/v1/scenes", json={"scene": ROOM}).json()["id"]
    r = client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": _frames(2), "bake": WT_BAKE})
    assert r.status_code == 202, r.text
    wkey = r.json()["key"]
    ids = [j["id"] for j in r.json()["jobs"]]
    assert client.delete(f"/v1/scenes/{sid}").status_code == 409
    assert client.get(f"/v1/walkthroughs/{wkey}").status_code == 200
    for jid in _active_ids(redis_conn, ids):
        assert client.post(f"/v1/jobs/{jid}/cancel").status_code in (200, 409)  # 409: ended with an earlier one
    assert _active_ids(redis_conn, ids) == []
    assert client.delete(f"/v1/scenes/{sid}").status_code == 204
    assert client.get(f"/v1/walkthroughs/{wkey}").status_code == 404
    # uploaded again (same id): the old walkthrough's record and frames did not survive
    assert client.post("/v1/scenes", json={"scene": ROOM}).json()["id"] == sid
    assert client.get(f"/v1/walkthroughs/{wkey}").status_code == 404
    assert Job.fetch_many(ids, connection=redis_conn, serializer=JSONSerializer) == [None] * len(ids)
