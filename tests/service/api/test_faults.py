"""Faults and configuration: store or Redis unreachable -> 503 + Retry-After with nothing
half-written (docs/hard-cases.md #25), readiness and settings that fail at start-up (that the API process
never imports numba: tests/service/test_api_imports_no_numba.py)."""

from __future__ import annotations

import json
import socket
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr, ValidationError

from producer.settings import Settings, load_settings
from producer.store import LocalStore, StoreUnavailable
from service.core.security import hash_key
from service.main import create_app
from tests.service.api.conftest import TEAPOT_PLY, small_scene, teapot_scene


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
    return port  # closed again: connections are refused


def test_s3_store_unreachable_gives_503(embedded_redis: str, redis_conn: Any, tmp_path: Path) -> None:
    settings = Settings(redis_url=embedded_redis, store_url="s3://bucket/ibr",
                        s3_endpoint_url=f"http://127.0.0.1:{_closed_port()}", s3_access_key="a",
                        s3_secret_key=SecretStr("b"), s3_region="us-east-1", data_dir=tmp_path)
    with TestClient(create_app(settings)) as c:
        for method, path, body in (("POST", "/v1/scenes", {"scene": small_scene()}), ("GET", "/v1/scenes", None),
                                   ("GET", "/v1/scenes/" + "a" * 64, None),
                                   ("POST", "/v1/renders", {"scene_id": "a" * 64}),
                                   ("GET", "/v1/artifacts/" + "a" * 64, None)):
            r = c.request(method, path, json=body)
            assert r.status_code == 503, (path, r.text)
            assert r.headers["retry-after"] == "5"
            assert r.headers["content-type"].startswith("application/problem+json")
            assert "object store" in r.json()["detail"]
        r = c.get("/readyz")
        assert r.status_code == 503 and r.json()["checks"]["redis"] == "ok" and r.json()["checks"]["store"] != "ok"
        assert c.get("/healthz").status_code == 200
    assert redis_conn.keys("rq:job:*") == []  # no job was queued for the failed requests


class FlakyStore(LocalStore):
    """A LocalStore whose writes fail after ``ok_puts`` successful ones (a store going away mid-request)."""

    def __init__(self, root: Path, ok_puts: int) -> None:
        super().__init__(root)
        self.ok_puts = ok_puts

    def put_bytes(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        if self.ok_puts <= 0:
            raise StoreUnavailable(f"injected failure writing {key}")
        self.ok_puts -= 1
        super().put_bytes(key, data, content_type)


def test_store_failing_mid_upload_leaves_no_scene(make_app: Any, embedded_redis: str, redis_conn: Any,
                                                  store_dir: Path, tmp_path: Path) -> None:
    settings = Settings(redis_url=embedded_redis, store_url=str(store_dir), data_dir=tmp_path)
    flaky = FlakyStore(store_dir, ok_puts=1)  # the mesh blob is written, the scene record is not
    files = [("scene", (None, json.dumps(teapot_scene()).encode(), "application/json")),
             ("meshes/teapot.ply", ("t.ply", TEAPOT_PLY.read_bytes(), "application/octet-stream"))]
    with TestClient(create_app(settings, store=flaky)) as c:
        r = c.post("/v1/scenes", files=files)
        assert r.status_code == 503 and r.headers["retry-after"] == "5"
        assert c.get("/v1/scenes").json()["items"] == []  # no scene became visible
        assert not (store_dir / "scenes").exists() or not any((store_dir / "scenes").iterdir())
    with TestClient(make_app()) as c:  # the store is back: the retry succeeds, reusing the blob
        r = c.post("/v1/scenes", files=files)
        assert r.status_code == 201
        assert c.get(f"/v1/scenes/{r.json()['id']}").status_code == 200


def test_redis_unreachable_gives_503(store_dir: Path, tmp_path: Path) -> None:
    settings = Settings(redis_url=f"redis://127.0.0.1:{_closed_port()}/0", store_url=str(store_dir), data_dir=tmp_path)
    with TestClient(create_app(settings)) as c:
        sid = c.post("/v1/scenes", json={"scene": small_scene()}).json()["id"]  # the store alone works
        for method, path, body in (("POST", "/v1/renders", {"scene_id": sid}), ("GET", "/v1/jobs", None),
                                   ("GET", "/v1/jobs/render-x", None), ("DELETE", f"/v1/scenes/{sid}", None)):
            r = c.request(method, path, json=body)
            assert r.status_code == 503, (path, r.text)
            assert r.headers["retry-after"] == "5" and "Redis" in r.json()["detail"]
        assert c.get(f"/v1/scenes/{sid}").status_code == 200  # the refused delete removed nothing
        r = c.get("/readyz")
        assert r.status_code == 503 and r.headers["retry-after"] == "5"
        assert r.json()["checks"]["store"] == "ok" and r.json()["checks"]["redis"] != "ok"
        assert "ibr_redis_up 0.0" in c.get("/metrics").text


def test_settings_fail_at_startup_with_clear_messages(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ValidationError, match="sha256 hex digest"):
        Settings(api_keys=["my-plain-key"])
    with pytest.raises(ValidationError, match="must not exceed max_body_bytes"):
        Settings(max_body_bytes=2048, max_upload_bytes=4096)
    with pytest.raises(ValidationError, match="redis://"):
        Settings(redis_url="http://localhost")
    with pytest.raises(ValidationError, match="s3://bucket"):
        Settings(store_url="ftp://x")
    with pytest.raises(ValidationError):
        Settings(rate_limit_per_minute=-1)

    monkeypatch.setenv("IBR_API_KEYS", f"{hash_key('a')}, {hash_key('b').upper()}")
    monkeypatch.setenv("IBR_CORS_ORIGINS", '["https://a.example"]')
    s = load_settings()
    assert s.api_keys == [hash_key("a"), hash_key("b")] and s.cors_origins == ["https://a.example"]
    monkeypatch.setenv("IBR_API_KEYS", "secret")
    with pytest.raises(SystemExit, match="IBR_API_KEYS"):
        load_settings()
    monkeypatch.setenv("IBR_API_KEYS", "")
    monkeypatch.setenv("IBR_MAX_BODY_BYTES", "lots")
    with pytest.raises(SystemExit, match="IBR_MAX_BODY_BYTES"):
        create_app()
