"""Worker parts without a worker process: settings, the renderer LRU, the retry policy,
the runner's start-up checks, the render job called directly."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from pydantic import ValidationError
from redis.exceptions import ConnectionError as RedisConnectionError
from rq.exceptions import AbandonedJobError
from rq.timeouts import JobTimeoutException

from engine.errors import NonFiniteOutputError
from producer.payloads import InvalidPayload
from producer.renders import render_artifact_key
from producer.settings import Settings, reset_settings_cache
from producer.store import StoreUnavailable
from tests.workers.queue.jobs_for_tests import tiny_scene
from workers import runner
from workers.cache import LRUBytesCache, RendererCache, runtime_scene_bytes

# ------------------------------------------------------------------------------ settings


def test_settings_defaults_point_at_the_embedded_redis_and_local_store(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    for var in ("IBR_REDIS_URL", "IBR_STORE_URL"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("IBR_DATA_DIR", str(tmp_path))
    s = Settings()
    assert s.effective_redis_url == f"unix://{tmp_path.resolve()}/redis.sock"
    assert s.effective_store_url == f"file://{tmp_path.resolve()}/store"
    monkeypatch.setenv("IBR_REDIS_URL", "redis://cache:6379/1")
    monkeypatch.setenv("IBR_STORE_URL", "s3://bucket/prefix")
    monkeypatch.setenv("IBR_S3_ACCESS_KEY", "ibr")
    monkeypatch.setenv("IBR_S3_SECRET_KEY", "hunter2")
    monkeypatch.setenv("IBR_CACHE_BYTES", "1000")
    s = Settings()
    assert (s.effective_redis_url, s.effective_store_url, s.cache_bytes) == ("redis://cache:6379/1",
                                                                             "s3://bucket/prefix", 1000)
    assert "hunter2" not in repr(s)


@pytest.mark.parametrize(("var", "value"), [
    ("IBR_REDIS_URL", "http://x"), ("IBR_REDIS_URL", "unix://"), ("IBR_STORE_URL", "ftp://x/y"),
    ("IBR_CACHE_BYTES", "0"), ("IBR_MAINTENANCE_INTERVAL_S", "0"),
])
def test_bad_settings_are_refused(monkeypatch: pytest.MonkeyPatch, var: str, value: str) -> None:
    monkeypatch.setenv(var, value)
    with pytest.raises(ValidationError, match=var.removeprefix("IBR_").lower()):
        Settings()


def test_runner_exits_cleanly_on_bad_settings_or_unreachable_redis(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("IBR_REDIS_URL", "http://nope")
    assert runner.main(["--queue", "bake"]) == 2
    assert "IBR_" in capsys.readouterr().err
    monkeypatch.setenv("IBR_REDIS_URL", f"unix://{tmp_path}/missing.sock")
    assert runner.main(["--queue", "bake"]) == 3
    assert "cannot reach Redis" in capsys.readouterr().err


# ------------------------------------------------------------------------------ retry policy


@pytest.mark.parametrize(("exc", "keeps"), [
    (StoreUnavailable, True), (RedisConnectionError, True), (AbandonedJobError, True),
    (InvalidPayload, False), (ValueError, False), (NonFiniteOutputError, False), (JobTimeoutException, False),
    (KeyError, False),
])
def test_retry_policy_keeps_retries_only_for_transient_errors(exc: type[BaseException], keeps: bool) -> None:
    job: Any = SimpleNamespace(id="j", retries_left=2)
    assert runner.retry_policy(job, exc, exc(), None) is True
    assert job.retries_left == (2 if keeps else 0)


def test_worker_timings(embedded_redis: str) -> None:
    from producer.queue import redis_from_url

    r = redis_from_url(embedded_redis)
    w: Any = runner.build_worker("bake", r, maintenance_interval=7, job_monitoring_interval=3, heartbeat_grace=4)
    assert isinstance(w, runner.BakeWorker)
    assert w.dequeue_timeout == 7  # idle workers wake up for maintenance
    job: Any = SimpleNamespace(timeout=600)
    assert w.get_heartbeat_ttl(job) == 3 + 4
    assert w.get_heartbeat_ttl(job, working_time=599.5) == 1 + 4  # never 0 or negative
    rw: Any = runner.build_worker("render", r, heartbeat_grace=5)
    assert isinstance(rw, runner.RenderWorker) and rw.get_heartbeat_ttl(job) == 10 + 5
    assert runner.retry_policy in rw._exc_handlers
    with pytest.raises(ValueError):
        runner.build_worker("other", r)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ LRU


def test_lru_evicts_least_recently_used_by_bytes() -> None:
    c: LRUBytesCache[str] = LRUBytesCache(100)
    c.put("a", "A", 40)
    c.put("b", "B", 40)
    assert c.get("a") == "A"  # a is now the most recent
    c.put("c", "C", 40)  # over budget: b goes
    assert c.keys() == ["a", "c"] and c.total_bytes == 80 and c.evictions == 1
    c.put("big", "X", 500)  # larger than the budget: kept alone
    assert c.keys() == ["big"] and c.total_bytes == 500
    c.put("d", "D", 10)
    assert c.keys() == ["d"]
    assert c.pop("d") == "D" and len(c) == 0 and c.total_bytes == 0
    with pytest.raises(ValueError):
        LRUBytesCache(0)


def test_get_or_create_loads_once_under_concurrency() -> None:
    c: LRUBytesCache[int] = LRUBytesCache(1000)
    calls: list[int] = []

    def factory() -> tuple[int, int]:
        calls.append(1)
        time.sleep(0.05)
        return 42, 10

    results: list[tuple[int, bool]] = []
    threads = [threading.Thread(target=lambda: results.append(c.get_or_create("k", factory))) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1 and {v for v, _ in results} == {42}
    assert sorted(hit for _, hit in results) == [False] + [True] * 7


def test_renderer_cache_keeps_scenes_warm() -> None:
    from workers.scene_loader import load_scene

    cache = RendererCache(1 << 30)
    loads: list[int] = []

    def load() -> Any:
        loads.append(1)
        return load_scene(tiny_scene())

    first, hit1 = cache.get_or_load("s1", load)
    second, hit2 = cache.get_or_load("s1", load)
    assert (hit1, hit2) == (False, True) and first is second and len(loads) == 1
    n = first.loaded.runtime.n_triangles
    assert runtime_scene_bytes(first.loaded.runtime) >= first.loaded.runtime.tri_p.nbytes + 160 * n
    assert cache.total_bytes == runtime_scene_bytes(first.loaded.runtime)
    small = RendererCache(1)
    small.get_or_load("s1", load)
    small.get_or_load("s2", load)
    assert small.keys() == ["s2"]


# ------------------------------------------------------------------------------ render job, directly


def test_render_job_in_process(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Outside a worker (no current RQ job) the job still validates, renders and publishes."""
    from api_schemas.service import RenderRequest
    from producer.artifacts import put_scene, read_manifest
    from producer.payloads import RenderJobPayload
    from producer.store import open_store
    from workers.jobs import render
    from workers.jobs.common import set_worker_store

    monkeypatch.setenv("IBR_STORE_URL", str(tmp_path))
    reset_settings_cache()
    previous = set_worker_store(None)  # opened from the settings on first use
    try:
        store = open_store(str(tmp_path))
        sid = put_scene(store, tiny_scene(width=8, height=8), {}, owner=None).id
        req = RenderRequest(scene_id=sid, params={"spp": 1})
        key = render_artifact_key(req)
        payload = RenderJobPayload(request=req, artifact_key=key).model_dump(mode="json")
        out = render.render_job(payload)
        assert out["artifact_key"] == key and read_manifest(store, key) is not None
        again = render.render_job(payload)  # published already: returns its result, writes nothing
        assert again["artifact_key"] == key and again["counts"] == out["counts"]
        with pytest.raises(InvalidPayload, match="request.params.spp"):
            render.render_job({"request": {"scene_id": sid, "params": {"spp": -1}}, "artifact_key": key})
    finally:
        set_worker_store(previous)
        reset_settings_cache()
