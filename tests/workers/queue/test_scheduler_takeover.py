"""A queue's scheduler lock held by a scheduler that stopped refreshing it -- its host was lost, so
its process can neither refresh nor release it, and its pid means nothing here -- is released by a
live worker once it has been silent for the scheduler's period plus the heartbeat grace (the rule
for abandoned jobs), so a retry due meanwhile is enqueued seconds after it is due instead of
waiting up to 61 s for the lock to expire. A lock refreshed recently is left alone."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from datetime import timedelta

import pytest
from redis import Redis
from rq.scheduler import SCHEDULER_KEY_TEMPLATE, RQScheduler

from producer.queue import get_queue
from tests.fixtures.redis import WorkerProcess, wait_for
from workers.runner import SCHEDULER_INTERVAL_S, DyingScheduler, build_worker

QUICK = "tests.workers.queue.jobs_for_tests.quick"
LOCK_TTL_S = SCHEDULER_INTERVAL_S + 60  # what RQ sets at every refresh


def lost_holder(redis: Redis, queue: str, silent_s: float, name: str = "sched-of-lost-host") -> str:
    """A scheduler lock (and the scheduler's registration) as a host lost ``silent_s`` seconds ago
    leaves them: its last refresh set the TTL to 61 s, of which ``silent_s`` have passed."""
    redis.set(RQScheduler.get_locking_key(queue), name, px=int((LOCK_TTL_S - silent_s) * 1000))
    redis.hset(SCHEDULER_KEY_TEMPLATE % name, mapping={"name": name, "hostname": "lost-host", "pid": "1",
                                                        "queues": queue})
    redis.expire(SCHEDULER_KEY_TEMPLATE % name, int(LOCK_TTL_S - silent_s))
    return name


def holder(redis: Redis, queue: str) -> str | None:
    v = redis.get(RQScheduler.get_locking_key(queue))
    return v.decode() if v else None


@pytest.mark.parametrize("queue", ["render", "bake"])
def test_a_silent_lock_is_released_and_a_recent_one_is_kept(redis_conn: Redis, queue: str) -> None:
    w = build_worker(queue, redis_conn, heartbeat_grace=20)  # type: ignore[arg-type]
    lost_holder(redis_conn, queue, silent_s=SCHEDULER_INTERVAL_S + 20 - 2)  # not silent long enough yet
    w.take_over_silent_scheduler_locks()  # type: ignore[attr-defined]
    assert holder(redis_conn, queue) == "sched-of-lost-host"
    lost_holder(redis_conn, queue, silent_s=SCHEDULER_INTERVAL_S + 20 + 1)
    w.take_over_silent_scheduler_locks()  # type: ignore[attr-defined]
    assert holder(redis_conn, queue) is None
    other = "render" if queue == "bake" else "bake"
    lost_holder(redis_conn, other, silent_s=50)  # another queue's lock: not this worker's business
    w.take_over_silent_scheduler_locks()  # type: ignore[attr-defined]
    assert holder(redis_conn, other) == "sched-of-lost-host"
    redis_conn.persist(RQScheduler.get_locking_key(other))  # no TTL: not RQ's lease, never taken
    w2 = build_worker(other, redis_conn, heartbeat_grace=20)  # type: ignore[arg-type]
    w2.take_over_silent_scheduler_locks()  # type: ignore[attr-defined]
    assert holder(redis_conn, other) == "sched-of-lost-host"


@pytest.mark.slow
def test_a_retry_due_under_a_lost_hosts_lock_is_enqueued_by_a_live_worker(
    redis_conn: Redis, worker_process: Callable[..., WorkerProcess]
) -> None:
    """The worker (maintenance every second, 2 s grace) starts while another host's scheduler holds
    the lock, silent for 1 s: stock RQ would leave it 60 s more. The job scheduled 2 s from now runs
    once the holder has been silent 3 s, and this worker's scheduler (on this host) holds the lock."""
    q = get_queue(redis_conn, "render")
    lost_holder(redis_conn, "render", silent_s=1)
    w = worker_process("render", "--no-warmup")
    t0 = time.monotonic()
    job = q.enqueue_in(timedelta(seconds=2), QUICK, {"n": 1})
    wait_for(lambda: job.get_status() == "finished", 40, f"the scheduled job to run; log:\n{w.log()}")
    took = time.monotonic() - t0
    assert took < 20, f"ran {took:.1f} s after it was scheduled (the lost lock expires after 60 s)\n{w.log()}"
    name = holder(redis_conn, "render")
    assert name and name != "sched-of-lost-host"
    assert redis_conn.hget(SCHEDULER_KEY_TEMPLATE % name, "hostname") == socket.gethostname().encode()
    assert "scheduler lock of scheduler sched-of-lost-host on lost-host, silent for more than 3 s" in w.log()


def test_a_scheduler_whose_lock_was_taken_over_stops(redis_conn: Redis) -> None:
    """Silent through a long Redis outage, its lock taken by another host's worker: at its next
    refresh it stops (its worker starts a new one once the lock is free) instead of looping on
    without a lock for RQ's 10-minute fallback."""
    s = DyingScheduler([get_queue(redis_conn, "bake")], connection=redis_conn)
    assert s.acquire_locks() == {"bake"}
    s.heartbeat()
    assert not s._stop_requested
    redis_conn.set(RQScheduler.get_locking_key("bake"), "another-scheduler", ex=LOCK_TTL_S)
    s.heartbeat()
    assert s._stop_requested and not s.acquired_locks
    assert holder(redis_conn, "bake") == "another-scheduler"
