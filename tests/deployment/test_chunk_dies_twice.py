"""A bake chunk whose job process dies twice (SIGKILL of the work horse, as the OOM killer or a lost
machine would kill it) fails the bake with the chunk named, and requesting the bake again redoes
only the missing chunk (docs/api.md, bakes). A dead job process is a transient failure: the chunk
keeps its one retry (``producer.bakes.chunk_retry``, 5 s later, by the worker's scheduler) the
first time, and fails the second. The other parts are left alone by both runs."""

from __future__ import annotations

import os
import signal
import time
from typing import Any

import psutil
import pytest
from redis import Redis

from api_schemas.service import BakeParams
from producer import bakes
from producer.artifacts import put_scene, read_manifest
from producer.names import scene_bake_plan_job_id
from producer.queue import fetch_job
from producer.status import job_public
from producer.store import ObjectStore
from tests.fixtures.redis import StartWorker, WorkerProcess, wait_for
from tests.workers.queue.bake_waits import wait_bake, wait_parts
from tests.workers.queue.jobs_for_tests import tiny_scene

PARAMS = BakeParams.model_validate({
    "ldc_resolution": 24, "max_layers": 8, "area_light_samples": 1, "seed": 11,
    # one chunk per axis, enough paths that a chunk runs for a moment after its horse starts
    "indirect": {"noise": 0.01, "min_paths": 32, "max_paths": 32, "round_paths": 16, "bounces": 2, "chunks": 1},
})
VICTIM = "ldc-indirect-0-0"


def horse_of(worker: WorkerProcess) -> int | None:
    """The worker's running work horse: RQ forks it into a process group of its own (the
    scheduler child stays in the worker's group)."""
    try:
        children = psutil.Process(worker.pid).children()
    except psutil.NoSuchProcess:
        return None
    for child in children:
        try:
            if os.getpgid(child.pid) == child.pid and child.status() != psutil.STATUS_ZOMBIE:
                return child.pid
        except (ProcessLookupError, psutil.NoSuchProcess):
            continue
    return None


def kill_running(redis: Redis, job_id: str, worker: WorkerProcess, timeout: float) -> float:
    """SIGKILL the horse of ``job_id`` as soon as the job is 'started'; the time it was killed."""
    def running_horse() -> int | None:
        job = fetch_job(redis, job_id)
        if job is None or job.get_status(refresh=False) != "started":
            return None
        return horse_of(worker)

    pid = wait_for(running_horse, timeout, f"{job_id} to run", interval=0.01)
    os.kill(pid, signal.SIGKILL)
    return time.monotonic()


@pytest.mark.slow  # two bakes on one worker with a 5 s retry interval: ~20-30 s
def test_a_chunk_whose_job_process_dies_twice_fails_the_bake_named_and_is_redone_alone(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    scene = put_scene(worker_store, tiny_scene(), {}, None)
    key, job = bakes.enqueue_bake(redis_conn, worker_store, scene.id, PARAMS, owner=None)
    assert job is not None
    w = worker_process("bake")
    st = wait_parts(redis_conn, worker_store, scene.id, key, PARAMS, 300, w)
    victim = next(p for p in st.parts if p.name == VICTIM)
    assert victim.job_id is not None

    kill_running(redis_conn, victim.job_id, w, 300)  # first death: a retry is left
    # the status and the retry count are separate writes: a read between them sees "scheduled" with
    # the count not yet lowered, so wait for both (a count that never drops still fails here)
    again = wait_for(lambda: (j := fetch_job(redis_conn, victim.job_id)) is not None  # type: ignore[arg-type]
                     and j.get_status(refresh=False) == "scheduled" and j.retries_left == 0 and j, 20,
                     "the retry to be scheduled with no retry left")
    assert again.retries_left == 0
    kill_running(redis_conn, victim.job_id, w, 30)  # second death: no retry left
    st = wait_bake(redis_conn, worker_store, scene.id, key, PARAMS, 120, w)

    assert st.state == "failed" and st.error is not None, (st, w.log())
    assert f"1 of {len(st.parts)} bake parts are missing" in st.error, st.error
    assert VICTIM in st.error and "was killed (signal 9)" in st.error and "redo only the missing parts" in st.error
    chunk = job_public(fetch_job(redis_conn, victim.job_id))  # type: ignore[arg-type]
    assert chunk.state == "failed" and chunk.error is not None and "killed (signal 9)" in chunk.error
    parts = {p.name: p for p in st.parts}
    assert parts[VICTIM].state == "failed" and read_manifest(worker_store, victim.key) is None
    created: dict[str, Any] = {n: read_manifest(worker_store, p.key).created_at  # type: ignore[union-attr]
                               for n, p in parts.items() if n != VICTIM}
    assert len(created) == len(parts) - 1  # every other part is stored
    assert w.alive()  # the worker itself lived through both deaths of its job process

    # the bake requested again: only the chunk is redone, the stored parts are reused as they are
    key2, job2 = bakes.enqueue_bake(redis_conn, worker_store, scene.id, PARAMS, owner=None)
    assert key2 == key and job2 is not None
    st2 = wait_bake(redis_conn, worker_store, scene.id, key, PARAMS, 120, w)
    assert st2.state == "finished", (st2.error, w.log())
    planned: dict[str, Any] = fetch_job(redis_conn, scene_bake_plan_job_id(key)).return_value()  # type: ignore[union-attr,assignment]
    assert planned["enqueued"] == [VICTIM]
    for name, p in {p.name: p for p in st2.parts}.items():
        m = read_manifest(worker_store, p.key)
        assert m is not None
        if name != VICTIM:
            assert m.created_at == created[name], name
