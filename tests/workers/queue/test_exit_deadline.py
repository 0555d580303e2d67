"""A worker process ends within its exit deadline even when something keeps the interpreter from
exiting, and says what held it (workers/runner.py ``exit_within``)."""

from __future__ import annotations

import time

from redis import Redis

from producer.queue import get_queue
from tests.fixtures.redis import StartWorker


def test_a_worker_held_at_exit_leaves_at_its_deadline_with_the_stacks_logged(
    redis_conn: Redis, worker_process: StartWorker
) -> None:
    q = get_queue(redis_conn, "render")
    job = q.enqueue("tests.workers.queue.jobs_for_tests.leave_a_thread_running", {}, job_id="render-held")
    w = worker_process("render", "--exit-deadline", "2", burst=True)
    t0 = time.monotonic()
    assert w.wait(60) == 0, w.log()
    assert job.get_status(refresh=True) == "finished"
    log = w.log()
    assert "still running 2 s after the work loop ended" in log, log
    assert "never_ending_thread" in log, log  # the held thread's stack names what held the exit
    assert time.monotonic() - t0 < 45


def test_a_worker_with_nothing_held_exits_without_waiting_for_its_deadline(
    redis_conn: Redis, worker_process: StartWorker
) -> None:
    q = get_queue(redis_conn, "render")
    q.enqueue("tests.workers.queue.jobs_for_tests.quick", {}, job_id="render-free")
    w = worker_process("render", "--exit-deadline", "30", burst=True)
    assert w.wait(60) == 0, w.log()
    assert "still running" not in w.log()
