"""producer/embedded.py: the bundled redis-server on a unix socket, its persistence (docs/hard-cases.md #22),
reuse of a running server, clear start-up errors."""

from __future__ import annotations

import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from producer.embedded import EmbeddedRedisError, start_embedded_redis
from producer.queue import fetch_job, get_queue, redis_from_url
from producer.status import job_public


@pytest.fixture
def data_dir() -> Iterator[Path]:
    # short path: unix socket paths are limited to ~100 bytes
    with tempfile.TemporaryDirectory(prefix="ibr-r-") as d:
        yield Path(d)


def test_start_reuse_and_stop(data_dir: Path) -> None:
    server = start_embedded_redis(data_dir)
    try:
        assert server.owned and server.url == f"unix://{data_dir.resolve()}/redis.sock"
        sock = data_dir / "redis.sock"
        assert stat.S_ISSOCK(sock.stat().st_mode) and stat.S_IMODE(sock.stat().st_mode) == 0o700
        conf = (data_dir / "redis.conf").read_text()
        assert "port 0" in conf and "appendonly yes" in conf and "daemonize no" in conf
        r = redis_from_url(server.url)
        r.set("k", "v")
        again = start_embedded_redis(data_dir)  # already running: reused, not owned
        assert not again.owned and again.url == server.url
        again.stop()  # leaves the owner's server alone
        assert r.get("k") == b"v"
        with pytest.raises(EmbeddedRedisError, match="already running"):
            start_embedded_redis(data_dir, reuse=False)
        url, stop = start_embedded_redis(data_dir)  # the (url, stop) form of the design doc
        assert url == server.url
    finally:
        server.stop()
    assert not server.is_running() and server.process is not None and server.process.returncode == 0
    assert not (data_dir / "redis.sock").exists()


def test_queued_job_survives_a_restart(data_dir: Path) -> None:
    """docs/hard-cases.md #22: with persistence on (append-only file), a queued job is still queued after
    Redis stops and starts again on the same data directory."""
    with start_embedded_redis(data_dir) as server:
        r = redis_from_url(server.url)
        q = get_queue(r, "render")
        job = q.enqueue("tests.workers.queue.jobs_for_tests.quick", {"x": [1, 2.5]}, job_id="render-kept",
                        meta={"owner": "alice", "progress": {"fraction": 0.0, "stage": "queued"}})
        r.close()
    with start_embedded_redis(data_dir) as server:
        r = redis_from_url(server.url)
        q = get_queue(r, "render")
        assert q.get_job_ids() == [job.id]
        kept = fetch_job(r, job.id)
        assert kept is not None and list(kept.args) == [{"x": [1, 2.5]}] and kept.meta["owner"] == "alice"
        assert job_public(kept).state == "queued"
        r.close()


def test_without_persistence_a_restart_loses_the_queue(data_dir: Path) -> None:
    """The other half of docs/hard-cases.md #22: why the embedded server runs with appendonly."""
    with start_embedded_redis(data_dir, appendonly=False) as server:
        r = redis_from_url(server.url)
        get_queue(r, "render").enqueue("tests.workers.queue.jobs_for_tests.quick", {}, job_id="render-x")
        r.close()
    with start_embedded_redis(data_dir, appendonly=False) as server:
        r = redis_from_url(server.url)
        assert get_queue(r, "render").count == 0
        r.close()


def test_stale_socket_is_replaced(data_dir: Path) -> None:
    (data_dir / "redis.sock").write_text("left over by a crash")
    with start_embedded_redis(data_dir) as server:
        assert server.owned and redis_from_url(server.url).ping()


def test_start_up_failures_are_clear(data_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(EmbeddedRedisError, match="exited with status"):
        start_embedded_redis(data_dir, redis_server=Path("/bin/false"))
    deep = tmp_path / ("d" * 60) / ("e" * 60)
    with pytest.raises(EmbeddedRedisError, match="longer than"):
        start_embedded_redis(deep)
