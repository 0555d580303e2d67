"""A worker process ends within its exit deadline even when something keeps the interpreter from
exiting, and says what held it (workers/runner.py ``exit_within``)."""

from __future__ import annotations

import time

from redis import Redis

from producer.queue import get_queue
from tests.fixtures.redis import StartWorker
from workers.runner import build_worker


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
    t0 = time.monotonic()
    assert w.wait(60) == 0, w.log()
    assert "still running" not in w.log()
    # nothing held: the exit takes no poll interval of RQ's pub/sub listener (60 s)
    assert time.monotonic() - t0 < 15, w.log()


def test_unsubscribing_takes_no_poll_interval_of_the_listener(redis_conn: Redis) -> None:
    # RQ's pub/sub listener polls every 60 s; once it has read the UNSUBSCRIBE reply it waits
    # that long for a new subscription. Since redis-py 8.2 ``PubSubWorkerThread.stop()`` joins
    # the listener, so a worker that reached this state before stopping it waited a minute to exit.
    worker = build_worker("render", redis_conn, name="unsubscribe-timing")
    worker.subscribe()
    listener = worker.pubsub_thread
    assert listener is not None
    time.sleep(0.3)
    worker.pubsub.unsubscribe()
    time.sleep(0.5)  # the listener reads the reply and starts its 60 s wait
    t0 = time.monotonic()
    worker.unsubscribe()
    assert time.monotonic() - t0 < 5
