"""Real render workers (``python -m workers.runner --queue render`` subprocesses) on the embedded
Redis: end-to-end render, cache hit, one job and one artifact under concurrent requests,
progress, cancellation, bad payloads, NaN renders (time limits: test_bake_worker.py)."""

from __future__ import annotations

import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from redis import Redis
from rq import Retry

from api_schemas.service import RenderRequest
from producer.artifacts import delete_artifact, put_scene, read_blob, read_manifest
from producer.cancel import cancel
from producer.errors import JobNotCancelable
from producer.names import RENDER_JOB
from producer.queue import fetch_job, get_queue, redis_from_url
from producer.renders import enqueue_render, render_artifact_key
from producer.status import job_public
from producer.store import ObjectStore
from tests.fixtures.redis import StartWorker, wait_for
from tests.workers.queue.jobs_for_tests import overflow_scene, tiny_scene


def public(redis: Redis, job_id: str) -> Any:
    job = fetch_job(redis, job_id)
    assert job is not None, f"job {job_id} vanished"
    return job_public(job)


def direct_render(scene_id_req: RenderRequest, store: ObjectStore) -> Any:
    """The same render, straight through the engine in this process."""
    from engine.reference import ReferenceParams, ReferenceRenderer
    from producer.artifacts import blob_reader, get_scene
    from workers.scene_loader import camera_params, load_scene

    scene, shas, _ = get_scene(store, scene_id_req.scene_id)
    loaded = load_scene(scene, blob_reader(store, shas))
    cam = camera_params(scene_id_req.camera) if scene_id_req.camera else loaded.camera
    return ReferenceRenderer(loaded.runtime).render(cam, ReferenceParams(**scene_id_req.params.model_dump()))


def read_exr(data: bytes) -> tuple[np.ndarray, dict[str, Any]]:
    from engine.imageio import read_image

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "x.exr"
        p.write_bytes(data)
        return read_image(p)


def test_render_end_to_end_cache_hit_and_idempotent_rerun(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    sid = put_scene(worker_store, tiny_scene(), {}, owner="alice").id
    req = RenderRequest(scene_id=sid, params={"spp": 2, "seed": 7},
                        camera={"type": "perspective", "eye": [0.5, 1.2, 3.5], "look_at": [0, 0.5, 0],
                                "width": 40, "height": 30})
    key, job = enqueue_render(redis_conn, req, "alice", store=worker_store)
    assert job is not None
    w = worker_process("render", burst=True)
    assert w.wait(60) == 0, w.log()

    pub = public(redis_conn, job.id)
    assert pub.state == "finished", (pub, w.log())
    assert pub.progress.fraction == 1.0 and pub.links["artifact"] == f"/v1/artifacts/{key}"
    assert pub.result is not None and pub.result["artifact_key"] == key
    assert set(pub.result) == {"artifact_key", "timings", "counts", "mesh_reports"}
    assert pub.result["timings"]["total"] > 0 and pub.result["counts"]["camera"] > 0
    assert pub.result["counts"]["width"] == 40

    manifest = read_manifest(worker_store, key)
    assert manifest is not None and manifest.kind == "render" and manifest.inputs == {"scene": sid}
    names = {b.name: b for b in manifest.blobs}
    assert set(names) == {"radiance.exr", "preview.png", "depth.exr", "normal.exr", "object_id.exr",
                          "material_id.exr"}
    assert names["radiance.exr"].content_type == "image/x-exr" and names["preview.png"].content_type == "image/png"

    radiance, meta = read_exr(read_blob(worker_store, key, "radiance.exr"))
    expected = direct_render(req, worker_store)
    assert radiance.shape == (30, 40, 3)
    np.testing.assert_array_equal(radiance, expected.radiance)  # deterministic: exactly equal
    assert meta["camera"]["eye"] == [0.5, 1.2, 3.5] and meta["scene_id"] == sid
    assert meta["render_params"]["seed"] == 7 and meta["artifact_key"] == key
    depth, _ = read_exr(read_blob(worker_store, key, "depth.exr"))
    np.testing.assert_array_equal(depth[..., 0], expected.depth)
    oid, _ = read_exr(read_blob(worker_store, key, "object_id.exr"))
    np.testing.assert_array_equal(oid[..., 0], expected.object_id.astype(np.float32))

    # the same request again: served from the store, no job
    assert enqueue_render(redis_conn, req, "bob", store=worker_store) == (key, None)

    # at-least-once: computing it again writes byte-identical blobs under the same key
    before = {b.name: b.sha256 for b in manifest.blobs}
    delete_artifact(worker_store, key)
    key2, job2 = enqueue_render(redis_conn, req, "alice", store=worker_store)
    assert key2 == key and job2 is not None and job2.id == job.id
    w2 = worker_process("render", burst=True)
    assert w2.wait(60) == 0, w2.log()
    again = read_manifest(worker_store, key)
    assert again is not None and {b.name: b.sha256 for b in again.blobs} == before


def test_concurrent_identical_requests_give_one_job_and_one_artifact(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker, embedded_redis: str
) -> None:
    """docs/hard-cases.md #21, end to end: both requesters get the same finished artifact."""
    sid = put_scene(worker_store, tiny_scene(), {}, owner=None).id
    req = RenderRequest(scene_id=sid, params={"spp": 1})
    results: list[tuple[str, str | None]] = []
    barrier = threading.Barrier(6)

    def go() -> None:
        conn = redis_from_url(embedded_redis)
        barrier.wait()
        k, j = enqueue_render(conn, req, None, store=worker_store)
        results.append((k, j.id if j else None))
        conn.close()

    threads = [threading.Thread(target=go) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert len(set(results)) == 1
    key, job_id = results[0]
    assert job_id is not None
    # two workers race for the queue: still one execution
    w1 = worker_process("render", burst=True)
    w2 = worker_process("render", burst=True)
    assert w1.wait(60) == 0 and w2.wait(60) == 0
    assert public(redis_conn, job_id).state == "finished"
    assert worker_store.list("artifacts/") == sorted(
        f"artifacts/{key}/{n}" for n in ("radiance.exr", "preview.png", "depth.exr", "normal.exr",
                                         "object_id.exr", "material_id.exr", "manifest.json"))
    executed = sum("Job OK" in w.log() for w in (w1, w2))
    assert executed == 1, (w1.log(), w2.log())


def test_progress_is_visible_and_a_started_job_can_be_canceled(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    sid = put_scene(worker_store, tiny_scene(width=160, height=120), {}, owner=None).id
    req = RenderRequest(scene_id=sid, params={"spp": 1024})  # ~10+ s: long enough to watch
    key, job = enqueue_render(redis_conn, req, "alice", store=worker_store)
    assert job is not None
    w = worker_process("render")

    def rendering() -> Any:
        p = public(redis_conn, job.id)
        return p if p.state == "started" and p.progress.stage == "render" and p.progress.fraction > 0.06 else None

    running = wait_for(rendering, 60, "render progress in job.meta")
    assert 0.05 < running.progress.fraction < 0.95
    assert running.progress.eta_s is not None and running.progress.eta_s > 0
    assert running.started_at is not None

    pub = cancel(redis_conn, job.id)
    assert pub.state in ("started", "canceled")
    # The engine returns to Python between chunks (>= 8 per image, two in flight), so the job
    # stops within about two chunk times, long before the render would end.
    final = wait_for(lambda: (p := public(redis_conn, job.id)).state != "started" and p, 20, "the cancel")
    assert final.state == "canceled", (final, w.log())
    assert final.error == "canceled on request"
    stopped_at = fetch_job(redis_conn, job.id).meta["progress"]  # type: ignore[union-attr]
    assert stopped_at["stage"] == "canceled" and stopped_at["fraction"] < 0.8
    assert read_manifest(worker_store, key) is None
    assert worker_store.list(f"artifacts/{key}/") == []
    with pytest.raises(JobNotCancelable):
        cancel(redis_conn, job.id)
    # not retried, and the worker lives on and takes the next job
    assert get_queue(redis_conn, "render").scheduled_job_registry.get_job_count(cleanup=False) == 0
    assert w.alive()
    quick = RenderRequest(scene_id=sid, params={"spp": 1}, camera={
        "type": "perspective", "eye": [0, 1.5, 4], "look_at": [0, 0.5, 0], "width": 16, "height": 16})
    _, j2 = enqueue_render(redis_conn, quick, None, store=worker_store)
    assert j2 is not None
    wait_for(lambda: public(redis_conn, j2.id).state == "finished", 30, "the next job")


def test_bad_payloads_fail_at_once_without_retry(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    sid = put_scene(worker_store, tiny_scene(), {}, owner=None).id
    good = RenderRequest(scene_id=sid, params={"spp": 1})
    key = render_artifact_key(good)
    q = get_queue(redis_conn, "render")
    retry = Retry(max=2, interval=[5, 30])
    bad_payloads = {
        "render-bad-field": {"request": {"scene_id": sid, "params": {"spp": 0}}, "artifact_key": key},
        "render-extra": {"request": good.model_dump(mode="json"), "artifact_key": key, "store_url": "file:///etc"},
        "render-wrong-key": {"request": good.model_dump(mode="json"), "artifact_key": "f" * 64},
        "render-no-scene": {"request": {"scene_id": "a" * 64, "params": {"spp": 1}},
                            "artifact_key": render_artifact_key(RenderRequest(scene_id="a" * 64,
                                                                                      params={"spp": 1}))},
    }
    for job_id, payload in bad_payloads.items():
        q.enqueue(RENDER_JOB, payload, job_id=job_id, retry=retry)
    w = worker_process("render", burst=True)
    assert w.wait(60) == 0, w.log()
    errors = {}
    for job_id in bad_payloads:
        pub = public(redis_conn, job_id)
        assert pub.state == "failed", (job_id, pub, w.log())
        errors[job_id] = pub.error
    assert q.scheduled_job_registry.get_job_count(cleanup=False) == 0  # nothing waits for a retry
    assert "request.params.spp" in errors["render-bad-field"] and "InvalidPayload" in errors["render-bad-field"]
    assert "store_url" in errors["render-extra"]
    assert "does not match the request" in errors["render-wrong-key"]
    assert "SceneNotFound" in errors["render-no-scene"] and "a" * 64 in errors["render-no-scene"]
    assert worker_store.list("artifacts/") == []


def test_nan_render_fails_with_a_clear_message_and_no_manifest(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    """docs/hard-cases.md #13 through the queue."""
    sid = put_scene(worker_store, overflow_scene(), {}, owner=None).id
    key, job = enqueue_render(redis_conn, RenderRequest(scene_id=sid, params={"spp": 1}), None,
                                     store=worker_store)
    assert job is not None
    w = worker_process("render", burst=True)
    assert w.wait(60) == 0, w.log()
    pub = public(redis_conn, job.id)
    assert pub.state == "failed"
    assert pub.error is not None and pub.error.startswith("NonFiniteOutputError: ") and "non-finite" in pub.error
    assert get_queue(redis_conn, "render").scheduled_job_registry.get_job_count(cleanup=False) == 0
    assert read_manifest(worker_store, key) is None and worker_store.list("artifacts/") == []
