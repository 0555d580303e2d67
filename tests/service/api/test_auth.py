"""docs/hard-cases.md #18: API keys (401), owner isolation (another key's resources are 404), rate limits (429),
and CORS."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from redis import Redis

from service.core.security import KeyRing, RateLimited, RateLimiter, hash_key, owner_of
from tests.service.api.conftest import small_scene

KEY_A = "key-a-0123456789"
KEY_B = "key-b-9876543210"
A = {"Authorization": f"Bearer {KEY_A}"}
B = {"Authorization": f"Bearer {KEY_B}"}


@pytest.fixture
def auth_client(make_app: Any) -> Any:
    with TestClient(make_app(api_keys=[hash_key(KEY_A), hash_key(KEY_B)])) as c:
        yield c


def test_missing_malformed_and_wrong_keys_get_401(auth_client: TestClient, store_dir: Path) -> None:
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": f"Basic {KEY_A}"},
                    {"Authorization": "Bearer"}, {"Authorization": KEY_A}):
        for method, path in (("GET", "/v1/scenes"), ("POST", "/v1/scenes"), ("GET", "/v1/jobs"),
                             ("GET", "/v1/artifacts/" + "0" * 64)):
            r = auth_client.request(method, path, headers=headers, json={"scene": small_scene()})
            assert r.status_code == 401, (headers, path, r.text)
            assert r.headers["www-authenticate"].startswith("Bearer")
            assert r.headers["content-type"].startswith("application/problem+json")
    assert not [p for p in store_dir.rglob("*") if p.is_file()]  # the 401 came before any write
    # health endpoints stay open for probes
    assert auth_client.get("/healthz").status_code == 200
    assert auth_client.get("/readyz").status_code == 200


def test_a_key_cannot_see_another_keys_resources(auth_client: TestClient, redis_conn: Redis) -> None:
    sid = auth_client.post("/v1/scenes", json={"scene": small_scene()}, headers=A).json()["id"]
    assert auth_client.get(f"/v1/scenes/{sid}", headers=A).status_code == 200
    assert auth_client.get(f"/v1/scenes/{sid}", headers=B).status_code == 404
    assert auth_client.get("/v1/scenes", headers=B).json() == {"items": [], "next_cursor": None}
    assert auth_client.delete(f"/v1/scenes/{sid}", headers=B).status_code == 404
    r = auth_client.post("/v1/renders", json={"scene_id": sid}, headers=B)
    assert r.status_code == 404
    # 404 for another key's resource reads exactly like 404 for no resource at all
    # (but for the id each names, the one the request gave)
    missing = auth_client.get("/v1/scenes/" + "f" * 64, headers=B).text.replace("f" * 64, "<id>")
    hidden = auth_client.get(f"/v1/scenes/{sid}", headers=B).text.replace(sid, "<id>")
    assert missing == hidden and "scene_id '<id>' not found" in hidden

    job = auth_client.post("/v1/renders", json={"scene_id": sid}, headers=A).json()["job"]
    assert auth_client.get(f"/v1/jobs/{job['id']}", headers=A).status_code == 200
    assert auth_client.get(f"/v1/jobs/{job['id']}", headers=B).status_code == 404
    assert auth_client.post(f"/v1/jobs/{job['id']}/cancel", headers=B).status_code == 404
    assert auth_client.get("/v1/jobs", headers=B).json()["items"] == []
    assert [j["id"] for j in auth_client.get("/v1/jobs", headers=A).json()["items"]] == [job["id"]]

    batch = auth_client.post("/v1/batches", json={"renders": [{"scene_id": sid}]}, headers=A)
    assert batch.status_code == 202, batch.text
    assert auth_client.get(f"/v1/batches/{batch.json()['id']}", headers=B).status_code == 404
    assert auth_client.get(f"/v1/batches/{batch.json()['id']}", headers=A).status_code == 200
    r = auth_client.post("/v1/batches", json={"renders": [{"scene_id": sid}]}, headers=B)
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "renders.0.scene_id"


def test_same_content_from_two_keys(auth_client: TestClient) -> None:
    ra = auth_client.post("/v1/scenes", json={"scene": small_scene()}, headers=A)
    rb = auth_client.post("/v1/scenes", json={"scene": small_scene()}, headers=B)
    assert ra.status_code == 201 and rb.status_code == 201  # new for B: nothing revealed about A
    assert ra.json()["id"] == rb.json()["id"]
    sid = ra.json()["id"]
    assert auth_client.delete(f"/v1/scenes/{sid}", headers=B).status_code == 204
    assert auth_client.get(f"/v1/scenes/{sid}", headers=B).status_code == 404
    assert auth_client.get(f"/v1/scenes/{sid}", headers=A).status_code == 200  # A's copy survives
    assert auth_client.delete(f"/v1/scenes/{sid}", headers=A).status_code == 204
    assert auth_client.post("/v1/scenes", json={"scene": small_scene()}, headers=A).status_code == 201


def test_artifact_of_another_key_is_404(auth_client: TestClient, store_dir: Path) -> None:
    from engine import ENGINE_VERSION
    from producer.artifacts import write_artifact
    from producer.store import open_store

    sid = auth_client.post("/v1/scenes", json={"scene": small_scene()}, headers=A).json()["id"]
    from producer.artifacts import artifact_key

    key = artifact_key("render", {"scene": sid}, {"p": 1}, ENGINE_VERSION)
    write_artifact(open_store(str(store_dir)), key, "render", {"scene": sid}, {"p": 1}, ENGINE_VERSION,
                   {"preview.png": (b"png-bytes", "image/png")}, {})
    assert auth_client.get(f"/v1/artifacts/{key}", headers=A).status_code == 200
    assert auth_client.get(f"/v1/artifacts/{key}/image.png", headers=A).content == b"png-bytes"
    assert auth_client.get(f"/v1/artifacts/{key}", headers=B).status_code == 404
    assert auth_client.get(f"/v1/artifacts/{key}/image.png", headers=B).status_code == 404


def test_rate_limit_429_per_key(make_app: Any) -> None:
    app = make_app(api_keys=[hash_key(KEY_A), hash_key(KEY_B)], rate_limit_per_minute=3)
    with TestClient(app) as c:
        codes = [c.get("/v1/scenes", headers=A).status_code for _ in range(4)]
        assert codes == [200, 200, 200, 429]
        r = c.get("/v1/scenes", headers=A)
        assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1
        assert c.get("/v1/scenes", headers=B).status_code == 200  # B has its own bucket
        assert c.get("/healthz").status_code == 200  # probes are not rate limited


def test_rate_limiter_refills_and_is_shared_through_redis(redis_conn: Any) -> None:
    now = [1000.0]
    lim = RateLimiter(per_minute=60, burst=2, redis=lambda: redis_conn, clock=lambda: now[0])
    other_replica = RateLimiter(per_minute=60, burst=2, redis=lambda: redis_conn, clock=lambda: now[0])
    lim.hit("a")
    other_replica.hit("a")  # the same bucket: two tokens taken, none left
    with pytest.raises(RateLimited) as exc:
        lim.hit("a")
    assert exc.value.retry_after_s == 1
    other_replica.hit("b")  # another client's own bucket
    now[0] += 1.0
    other_replica.hit("a")  # one token per second
    with pytest.raises(RateLimited):
        lim.hit("a")
    assert 0 < redis_conn.ttl(RateLimiter.KEY_PREFIX + "a") <= 62  # a full bucket needs no key


def test_rate_limit_applies_to_wrong_keys_before_the_401(make_app: Any) -> None:
    app = make_app(api_keys=[hash_key(KEY_A)], rate_limit_per_minute=2)
    with TestClient(app) as c:
        wrong = {"Authorization": "Bearer not-a-key"}
        codes = [c.get("/v1/scenes", headers=wrong).status_code for _ in range(3)]
        assert codes == [401, 401, 429]
        assert c.get("/v1/scenes", headers=A).status_code == 200  # the key's bucket is its own


def test_a_redis_outage_lets_requests_through() -> None:
    from redis import Redis

    down = Redis(unix_socket_path="/nonexistent/redis.sock", socket_connect_timeout=0.2)
    RateLimiter(per_minute=1, redis=lambda: down).hit("a")
    RateLimiter(per_minute=1, redis=lambda: down).hit("a")


def test_keyring() -> None:
    ring = KeyRing([hash_key("k1")])
    assert ring.authenticate("Bearer k1") == owner_of(hash_key("k1")) == hash_key("k1")[:16]
    assert KeyRing([]).authenticate(None) is None


def test_cors(make_app: Any) -> None:
    with TestClient(make_app(cors_origins=["https://app.example"])) as c:
        r = c.options("/v1/scenes", headers={"Origin": "https://app.example", "Access-Control-Request-Method": "POST"})
        assert r.status_code == 200 and r.headers["access-control-allow-origin"] == "https://app.example"
        r = c.get("/v1/scenes", headers={"Origin": "https://evil.example"})
        assert "access-control-allow-origin" not in r.headers
    with TestClient(make_app()) as c:
        r = c.get("/v1/scenes", headers={"Origin": "https://app.example"})
        assert "access-control-allow-origin" not in r.headers
