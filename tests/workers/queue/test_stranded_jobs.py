"""A job taken from its queue by a worker that never starts it (the worker's host went away while
its blocking dequeue was open: Redis moved the job into RQ's intermediate queue for a connection
nobody reads) is queued again by a live worker's maintenance within seconds, no retry spent,
instead of waiting for RQ's own clean-up (a minute or more, and a spent retry)."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest
from redis import Redis
from rq import Retry

from producer.queue import get_queue
from tests.fixtures.redis import WorkerProcess, wait_for
from workers.runner import STRANDED_AFTER_S

pytestmark = pytest.mark.slow

QUICK = "tests.workers.queue.jobs_for_tests.quick"


def test_a_job_taken_by_a_lost_worker_is_queued_again_and_runs(
    redis_conn: Redis, worker_process: Callable[..., WorkerProcess]
) -> None:
    q = get_queue(redis_conn, "render")
    job = q.enqueue(QUICK, {"n": 1}, retry=Retry(max=2))
    # what a lost worker's open BLMOVE does: the job leaves the queue for the intermediate list, 'queued'
    assert redis_conn.lmove(q.key, q.intermediate_queue_key) is not None
    assert job.get_status() == "queued" and q.count == 0
    t0 = time.monotonic()
    worker = worker_process("render")  # maintenance every second
    wait_for(lambda: job.get_status() == "finished", 60, f"the stranded job to run; log:\n{worker.log()}")
    took = time.monotonic() - t0
    assert took < STRANDED_AFTER_S + 25, took  # RQ's own clean-up: 60 s or more, and a spent retry
    job.refresh()
    assert job.retries_left == 2, "queued again without spending a retry"
    assert redis_conn.llen(q.intermediate_queue_key) == 0
    assert "never started" in worker.log()
