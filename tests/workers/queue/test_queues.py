"""The producer layer (queue, enqueue, status, cancel, batches) against a real (embedded) Redis,
without workers: keys, de-duplication, cache hits, cancellation of queued jobs, job views, listings, batches."""

from __future__ import annotations

import subprocess
import sys
import threading
from typing import Any

import pytest
from redis import Redis
from rq import Retry
from rq.serializers import JSONSerializer

from api_schemas.service import RenderRequest
from engine import ENGINE_VERSION
from producer.artifacts import put_scene, write_artifact
from producer.batches import batch_owner, batch_status, enqueue_batch
from producer.cancel import cancel
from producer.errors import JobNotCancelable, JobNotFound, UnknownScene
from producer.ownership import job_owners
from producer.payloads import RenderJobPayload
from producer.queue import (
    BAKE_TIMEOUT_S,
    FAILURE_TTL_S,
    RENDER_TIMEOUT_S,
    RESULT_TTL_S,
    get_queue,
    queue_depths,
    redis_from_url,
)
from producer.renders import enqueue_render, render_artifact_key, render_params
from producer.status import cancel_requested, clean_error, job_public, list_jobs
from producer.store import ObjectStore
from tests.workers.queue.jobs_for_tests import tiny_scene


@pytest.fixture
def scene_id(worker_store: ObjectStore) -> str:
    return put_scene(worker_store, tiny_scene(), {}, owner="alice").id


def _req(scene_id: str, **params: Any) -> RenderRequest:
    return RenderRequest(scene_id=scene_id, params=params or {"spp": 1})


def test_redis_from_url_schemes(embedded_redis: str) -> None:
    assert embedded_redis.startswith("unix://")
    assert redis_from_url(embedded_redis).ping()
    with pytest.raises(ValueError, match="unsupported Redis URL"):
        redis_from_url("http://localhost:6379")


def test_get_queue_is_json_with_explicit_timeouts(redis_conn: Redis) -> None:
    render = get_queue(redis_conn, "render")
    bake = get_queue(redis_conn, "bake")
    assert render.serializer is JSONSerializer or render.serializer == JSONSerializer
    assert render._default_timeout == RENDER_TIMEOUT_S == 600
    assert bake._default_timeout == BAKE_TIMEOUT_S == 3600
    with pytest.raises(ValueError):
        get_queue(redis_conn, "other")  # type: ignore[arg-type]


def test_engine_version_is_a_plain_import_without_numba() -> None:
    """The producer reads ``engine.ENGINE_VERSION`` by importing it: ``engine`` itself is numba-free."""
    code = ("import sys, engine, producer.renders, producer.bakes, producer.datasets; "
            "assert not any(m == 'numba' or m.startswith(('numba.', 'engine._numba_setup')) for m in sys.modules), "
            "sorted(sys.modules); print(engine.ENGINE_VERSION)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ENGINE_VERSION


def test_enqueue_render_creates_a_well_formed_job(redis_conn: Redis, worker_store: ObjectStore,
                                                  scene_id: str) -> None:
    req = _req(scene_id)
    key, job = enqueue_render(redis_conn, req, "alice", store=worker_store)
    assert job is not None
    assert job.id == f"render-{key}" and job.origin == "render"
    assert key == render_artifact_key(req)
    assert job.func_name == "workers.jobs.render.render_job"
    assert job.timeout == 600
    assert job.retries_left == 2 and job.retry_intervals == [5, 30]
    assert job.result_ttl == RESULT_TTL_S and job.failure_ttl == FAILURE_TTL_S
    assert job.meta["owner"] == "alice" and job.meta["batch_id"] is None
    assert job.meta["progress"]["fraction"] == 0.0
    (payload,) = job.args
    assert RenderJobPayload.model_validate(payload).artifact_key == key
    assert "store_url" not in payload  # the worker's settings choose the store
    pub = job_public(job)
    assert (pub.state, pub.kind, pub.progress.stage) == ("queued", "render", "queued")


def test_params_change_the_key_and_scene_id_is_an_input(redis_conn: Redis, worker_store: ObjectStore,
                                                        scene_id: str) -> None:
    k1 = render_artifact_key(_req(scene_id, spp=1))
    k2 = render_artifact_key(_req(scene_id, spp=2))
    k3 = render_artifact_key(_req(scene_id, spp=1, seed=0))  # explicit default: same request
    assert k1 != k2 and k1 == k3
    other = put_scene(worker_store, tiny_scene(name="other"), {}, owner=None).id
    assert render_artifact_key(_req(other, spp=1)) != k1


def test_identical_requests_share_one_job(redis_conn: Redis, worker_store: ObjectStore, scene_id: str) -> None:
    req = _req(scene_id)
    k1, j1 = enqueue_render(redis_conn, req, "alice", store=worker_store)
    k2, j2 = enqueue_render(redis_conn, req, "bob", store=worker_store)
    assert k1 == k2 and j1 is not None and j2 is not None and j1.id == j2.id
    assert get_queue(redis_conn, "render").count == 1
    assert job_owners(redis_conn, j1.id) == {"alice", "bob"}
    assert [p.id for p in list_jobs(redis_conn, owner="bob")] == [j1.id]


def test_concurrent_identical_enqueues_make_one_job(redis_conn: Redis, worker_store: ObjectStore,
                                                   scene_id: str, embedded_redis: str) -> None:
    """docs/hard-cases.md #21: many requests at the same instant, one job (each thread its own client)."""
    req = _req(scene_id)
    n = 8
    barrier = threading.Barrier(n)
    ids: list[str | None] = []
    errors: list[BaseException] = []

    def go() -> None:
        conn = redis_from_url(embedded_redis)
        try:
            barrier.wait()
            _, job = enqueue_render(conn, req, None, store=worker_store)
            ids.append(job.id if job else None)
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)
        finally:
            conn.close()

    threads = [threading.Thread(target=go) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert not errors
    assert len(ids) == n and len(set(ids)) == 1 and ids[0] is not None
    q = get_queue(redis_conn, "render")
    assert q.get_job_ids() == [ids[0]]


def test_cache_hit_returns_no_job(redis_conn: Redis, worker_store: ObjectStore, scene_id: str) -> None:
    req = _req(scene_id)
    key = render_artifact_key(req)
    write_artifact(worker_store, key, "render", {"scene": scene_id}, render_params(req),
                   ENGINE_VERSION, {"radiance.exr": (b"x", "image/x-exr")}, {})
    assert enqueue_render(redis_conn, req, None, store=worker_store) == (key, None)
    assert get_queue(redis_conn, "render").count == 0


def test_unknown_scene_is_refused_when_a_store_is_given(redis_conn: Redis, worker_store: ObjectStore) -> None:
    with pytest.raises(UnknownScene):
        enqueue_render(redis_conn, _req("0" * 64), None, store=worker_store)


def test_cancel_a_queued_job_and_enqueue_again(redis_conn: Redis, worker_store: ObjectStore, scene_id: str) -> None:
    req = _req(scene_id)
    _, job = enqueue_render(redis_conn, req, "alice", store=worker_store)
    assert job is not None
    pub = cancel(redis_conn, job.id)
    assert pub.state == "canceled" and pub.error
    assert get_queue(redis_conn, "render").count == 0
    with pytest.raises(JobNotCancelable) as info:
        cancel(redis_conn, job.id)
    assert info.value.job.state == "canceled"
    with pytest.raises(JobNotFound):
        cancel(redis_conn, "render-" + "0" * 64)
    # asking again after a cancel makes a fresh job (and clears the cancel flag)
    _, again = enqueue_render(redis_conn, req, "alice", store=worker_store)
    assert again is not None and again.id == job.id
    assert job_public(again).state == "queued"
    assert not cancel_requested(redis_conn, job.id)
    assert get_queue(redis_conn, "render").get_job_ids() == [job.id]
    assert get_queue(redis_conn, "render").canceled_job_registry.get_job_ids(cleanup=False) == []


def test_finished_or_failed_jobs_cannot_be_canceled(redis_conn: Redis) -> None:
    q = get_queue(redis_conn, "render")
    job = q.enqueue("tests.workers.queue.jobs_for_tests.quick", {"a": 1}, job_id="render-done")
    job.set_status("finished")
    with pytest.raises(JobNotCancelable, match="finished"):
        cancel(redis_conn, job.id)


@pytest.mark.parametrize(("exc", "expected"), [
    ("Traceback (most recent call last):\n  File \"x.py\", line 1, in f\n    raise X\n"
     "engine.errors.NonFiniteOutputError: reference render produced 3 non-finite values\n",
     "NonFiniteOutputError: reference render produced 3 non-finite values"),
    ("Traceback (most recent call last):\n  File \"x.py\", line 3, in g\n    foo()\n"
     "rq.timeouts.JobTimeoutException: Task exceeded maximum timeout value (600 seconds)\n",
     "the job exceeded its time limit of 600 s and was stopped"),
    ("Moved to FailedJobRegistry, due to AbandonedJobError, at 2025-01-01 00:00:00",
     "the worker running this job stopped responding (killed or out of memory) and the job was abandoned"),
    ("Work-horse terminated unexpectedly; waitpid returned 9 (signal 9); ",
     "the worker process running this job was killed (signal 9)"),
    ("Traceback (most recent call last):\n  File \"x.py\", line 1, in f\n    raise X\n"
     "producer.payloads.InvalidPayload: invalid render job payload: request.params.spp: too big\n",
     "InvalidPayload: invalid render job payload: request.params.spp: too big"),
])
def test_clean_error(exc: str, expected: str) -> None:
    assert clean_error(exc) == expected


def test_list_jobs_and_queue_depths(redis_conn: Redis, worker_store: ObjectStore, scene_id: str) -> None:
    _, a = enqueue_render(redis_conn, _req(scene_id, spp=1), "alice", store=worker_store)
    _, b = enqueue_render(redis_conn, _req(scene_id, spp=2), "bob", store=worker_store)
    assert a is not None and b is not None
    cancel(redis_conn, b.id)
    assert {p.id for p in list_jobs(redis_conn)} == {a.id, b.id}
    assert [p.id for p in list_jobs(redis_conn, owner="alice")] == [a.id]
    assert [p.id for p in list_jobs(redis_conn, states=["canceled"])] == [b.id]
    assert list_jobs(redis_conn, kinds=["bake"]) == []
    depths = queue_depths(redis_conn)
    assert depths["render"]["queued"] == 1 and depths["render"]["canceled"] == 1
    assert depths["bake"]["queued"] == 0 and depths["render"]["workers"] == 0


def test_batches(redis_conn: Redis, worker_store: ObjectStore, scene_id: str) -> None:
    cached_req = _req(scene_id, spp=3)
    key = render_artifact_key(cached_req)
    write_artifact(worker_store, key, "render", {"scene": scene_id}, render_params(cached_req),
                   ENGINE_VERSION, {"radiance.exr": (b"x", "image/x-exr")}, {})
    reqs = [_req(scene_id, spp=1), _req(scene_id, spp=1), _req(scene_id, spp=2), cached_req]
    batch = enqueue_batch(redis_conn, reqs, "alice", store=worker_store, scene_ids=[scene_id])
    assert batch.scene_ids == [scene_id]
    assert [r.status for r in batch.renders] == ["queued", "queued", "queued", "cached"]
    assert batch.counts == {"queued": 3, "cached": 1}  # two members share one job
    assert get_queue(redis_conn, "render").count == 2
    assert batch.progress.fraction == pytest.approx(0.25)
    assert batch_owner(redis_conn, batch.id) == "alice"
    first = batch.renders[0].job
    assert first is not None and first.batch_id == batch.id
    cancel(redis_conn, first.id)
    again = batch_status(redis_conn, batch.id, store=worker_store)
    assert again is not None
    assert again.counts == {"canceled": 2, "queued": 1, "cached": 1}
    assert again.progress.fraction == pytest.approx(0.75)
    assert batch_status(redis_conn, "nope") is None


def test_scheduled_retry_counts_as_queued(redis_conn: Redis) -> None:
    q = get_queue(redis_conn, "render")
    job = q.enqueue("tests.workers.queue.jobs_for_tests.quick", {}, job_id="render-x", retry=Retry(max=1))
    job.set_status("scheduled")
    assert job_public(job).state == "queued"
