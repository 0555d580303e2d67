"""Real forking bake workers (``python -m workers.runner --queue bake``): a SIGKILLed worker's job
is retried or failed -- never 'started' forever -- and publishes nothing (docs/hard-cases.md #20); stop
requests kill the work horse; time limits (docs/hard-cases.md #24)."""

from __future__ import annotations

import signal
import time

import psutil
import pytest
from redis import Redis
from rq import Retry

from producer.artifacts import read_blob, read_manifest
from producer.cancel import cancel
from producer.queue import QueueName, fetch_job, get_queue
from producer.status import job_duration_histograms, job_public
from producer.store import ObjectStore
from tests.fixtures.redis import StartWorker, wait_for
from tests.workers.queue.jobs_for_tests import slow_artifact_key

SLOW = "tests.workers.queue.jobs_for_tests.slow_artifact"


def step(redis: Redis, job_id: str) -> int:
    job = fetch_job(redis, job_id)
    return int(job.meta.get("step", -1)) if job is not None else -1


def state(redis: Redis, job_id: str) -> str:
    job = fetch_job(redis, job_id)
    assert job is not None
    return job_public(job).state


def gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


@pytest.mark.parametrize("retries", [0, 1], ids=["no-retry-fails", "retry-reruns"])
def test_sigkilled_bake_worker_job_is_failed_or_rerun_never_started_forever(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker, retries: int
) -> None:
    label, steps = f"killed-{retries}", 50  # 5 s of work: an orphaned horse could not finish below
    key = slow_artifact_key(label, steps)
    q = get_queue(redis_conn, "bake")
    job = q.enqueue(SLOW, {"steps": steps, "dt": 0.1, "label": label}, job_id=f"bake-{label}", job_timeout=120,
                    retry=Retry(max=retries) if retries else None)
    w = worker_process("bake")
    wait_for(lambda: step(redis_conn, job.id) >= 3, 30, "the horse to be working")
    family = [p.pid for p in psutil.Process(w.pid).children(recursive=True)]
    assert family, "a forking worker runs its job in a child process"

    w.kill()  # SIGKILL to the worker's process group (worker + scheduler)
    wait_for(lambda: all(gone(p) for p in family), 3, "the work horse to die with its worker (PDEATHSIG)")
    assert state(redis_conn, job.id) == "started"  # stale: nobody has noticed yet
    assert read_manifest(worker_store, key) is None
    assert worker_store.list(f"artifacts/{key}/") == []

    t0 = time.monotonic()
    w2 = worker_process("bake")
    final = wait_for(lambda: (s := state(redis_conn, job.id)) in ("failed", "finished") and s, 40,
                     "maintenance to deal with the abandoned job")
    took = time.monotonic() - t0
    if retries:
        assert final == "finished", w2.log()
        manifest = read_manifest(worker_store, key)
        assert manifest is not None
        expected = "".join(f"{label}:{i}\n" for i in range(1000)).encode()
        assert read_blob(worker_store, key, "data.txt") == expected  # the rerun's result is the normal one
    else:
        assert final == "failed", w2.log()
        pub = job_public(fetch_job(redis_conn, job.id))  # type: ignore[arg-type]
        assert pub.error is not None and "stopped responding" in pub.error
        assert read_manifest(worker_store, key) is None
    assert took < 30
    assert w2.alive()


def test_canceling_a_started_bake_job_kills_its_horse(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    label, steps = "canceled", 100
    q = get_queue(redis_conn, "bake")
    job = q.enqueue(SLOW, {"steps": steps, "dt": 0.1, "label": label}, job_id=f"bake-{label}", job_timeout=120,
                    retry=Retry(max=2))
    w = worker_process("bake")
    wait_for(lambda: step(redis_conn, job.id) >= 2, 30, "the horse to be working")
    cancel(redis_conn, job.id)
    wait_for(lambda: state(redis_conn, job.id) == "canceled", 10, "the stop command")
    assert q.count == 0 and q.scheduled_job_registry.get_job_count(cleanup=False) == 0  # not retried
    assert read_manifest(worker_store, slow_artifact_key(label, steps)) is None
    assert w.alive()
    # a cancel, not a failure: its run time observed as canceled, the stop logged at INFO
    wait_for(lambda: ("bake", "slow_artifact", "canceled") in job_duration_histograms(redis_conn), 10,
             "the stopped job's duration")
    buckets, seconds = job_duration_histograms(redis_conn)[("bake", "slow_artifact", "canceled")]
    assert buckets[-1] == ("+Inf", 1.0) and seconds >= 0.2
    lines = [ln for ln in w.log().splitlines() if job.id in ln]
    stop = [ln for ln in lines if "stopped by user" in ln]
    assert stop and all(" INFO " in ln for ln in stop), lines
    assert not any(" WARNING " in ln or " ERROR " in ln or "Traceback" in ln for ln in lines), lines


@pytest.mark.parametrize("queue", ["bake", "render"])
def test_timeout_fails_the_job_and_the_worker_takes_the_next(
    redis_conn: Redis, worker_process: StartWorker, queue: QueueName
) -> None:
    """docs/hard-cases.md #24 on both worker kinds (forked horse / in-process job)."""
    q = get_queue(redis_conn, queue)
    slow = q.enqueue("tests.workers.queue.jobs_for_tests.sleepy", {"seconds": 30}, job_id=f"{queue}-slow",
                     job_timeout=1, retry=Retry(max=2))
    after = q.enqueue("tests.workers.queue.jobs_for_tests.quick", {}, job_id=f"{queue}-after")
    w = worker_process(queue)
    wait_for(lambda: state(redis_conn, after.id) == "finished", 30, "the next job")
    pub = job_public(fetch_job(redis_conn, slow.id))  # type: ignore[arg-type]
    assert pub.state == "failed"
    assert pub.error == "the job exceeded its time limit of 1 s and was stopped"
    assert q.scheduled_job_registry.get_job_count(cleanup=False) == 0  # a timeout is not retried
    assert w.alive()


def test_transient_failure_is_retried_after_its_interval_by_the_scheduler(
    redis_conn: Redis, worker_process: StartWorker
) -> None:
    """StoreUnavailable keeps the job's retries; the interval needs the worker's scheduler."""
    q = get_queue(redis_conn, "render")
    job = q.enqueue("tests.workers.queue.jobs_for_tests.flaky", {"failures": 1}, job_id="render-flaky",
                    retry=Retry(max=2, interval=[1]))
    worker_process("render")
    wait_for(lambda: state(redis_conn, job.id) == "finished", 30, "the retried job")
    done = fetch_job(redis_conn, job.id)
    assert done is not None and done.return_value() == {"attempts": 2} and done.retries_left == 1


@pytest.mark.parametrize("queue", ["bake", "render"])
def test_sigterm_is_a_warm_shutdown(redis_conn: Redis, worker_process: StartWorker, queue: QueueName) -> None:
    q = get_queue(redis_conn, queue)
    job = q.enqueue("tests.workers.queue.jobs_for_tests.sleepy", {"seconds": 3}, job_id=f"{queue}-warm")
    w = worker_process(queue)
    wait_for(lambda: state(redis_conn, job.id) == "started", 60, "the job to start")
    w.kill(signal.SIGTERM)
    assert w.wait(60) == 0, w.log()
    assert state(redis_conn, job.id) == "finished", w.log()  # the running job was allowed to finish
