"""The Redis connection, the two queues and their policies (timeouts, retries, TTLs), job lookup.

Conventions (docs/service-design.md "Queues and jobs"):

- two queues, ``bake`` and ``render``, on one Redis, ``JSONSerializer`` (never pickle);
- jobs are enqueued by import path (``producer.names``) with ONE JSON-safe dict argument
  (``producer.payloads``);
- ``Retry(max=2, interval=[5, 30])``; the workers' exception handler (workers/runner.py) keeps
  retries only for transient errors (store unavailable, Redis connection trouble, a worker that
  died), so bad input and NaN renders fail at once.
"""

from __future__ import annotations

import re
from typing import Literal

from redis import Redis
from rq import Queue, Retry, Worker
from rq.exceptions import NoSuchJobError
from rq.job import Job, JobStatus
from rq.serializers import JSONSerializer

__all__ = [
    "ACTIVE_STATUSES",
    "BAKE_TIMEOUT_S",
    "BATCH_TTL_S",
    "DEFAULT_TIMEOUTS",
    "ENQUEUE_LOCK_TIMEOUT_S",
    "FAILURE_TTL_S",
    "KEY_PREFIX",
    "QUEUE_NAMES",
    "RENDER_RETRY_INTERVALS_S",
    "RENDER_RETRY_MAX",
    "RENDER_TIMEOUT_S",
    "RESULT_TTL_S",
    "WAITING_STATUSES",
    "QueueName",
    "fetch_job",
    "fetch_jobs",
    "get_queue",
    "job_retry",
    "queue_depths",
    "redis_from_url",
]

QueueName = Literal["bake", "render"]
QUEUE_NAMES: tuple[QueueName, ...] = ("bake", "render")

RENDER_TIMEOUT_S = 600
BAKE_TIMEOUT_S = 3600
DEFAULT_TIMEOUTS: dict[str, int] = {"render": RENDER_TIMEOUT_S, "bake": BAKE_TIMEOUT_S}
RENDER_RETRY_MAX = 2
RENDER_RETRY_INTERVALS_S = (5, 30)
RESULT_TTL_S = 24 * 3600
"""How long a finished job (its small JSON result) stays in Redis; the artifact stays in the store."""
FAILURE_TTL_S = 7 * 24 * 3600
"""How long a failed job and its error stay in Redis."""
BATCH_TTL_S = 7 * 24 * 3600
ENQUEUE_LOCK_TIMEOUT_S = 30

KEY_PREFIX = "ibr:"
"""Prefix of this service's own Redis keys (RQ's are ``rq:...``)."""

ACTIVE_STATUSES = frozenset({
    JobStatus.CREATED, JobStatus.QUEUED, JobStatus.STARTED, JobStatus.DEFERRED, JobStatus.SCHEDULED,
    JobStatus.READY_TO_ENQUEUE, JobStatus.RATE_LIMITED,
})
"""RQ statuses of a job that has not ended."""
WAITING_STATUSES = ACTIVE_STATUSES - {JobStatus.STARTED}
"""RQ statuses of a job that has not started yet."""


def redis_from_url(url: str) -> Redis:
    """A Redis client for ``redis://``, ``rediss://`` or ``unix:///path/to/redis.sock`` URLs.

    Responses stay bytes (RQ needs that). A short connect timeout makes an unreachable server a
    quick, clear error instead of a hang; RQ workers raise the read timeout above their
    blocking-pop timeout themselves.
    """
    if not re.match(r"^(redis|rediss|unix)://", url):
        raise ValueError(f"unsupported Redis URL {url!r}: use redis://host:port/db, rediss://... or unix:///path")
    return Redis.from_url(url, socket_connect_timeout=5, health_check_interval=30)


def get_queue(redis: Redis, name: QueueName) -> Queue:
    """The ``bake`` or ``render`` queue: JSON serializer and an explicit default timeout."""
    if name not in DEFAULT_TIMEOUTS:
        raise ValueError(f"unknown queue {name!r}; queues are {QUEUE_NAMES}")
    return Queue(name, connection=redis, serializer=JSONSerializer, default_timeout=DEFAULT_TIMEOUTS[name])


def job_retry() -> Retry:
    """The retry policy of every job (transient errors only, see the module docstring)."""
    return Retry(max=RENDER_RETRY_MAX, interval=list(RENDER_RETRY_INTERVALS_S))


def fetch_job(redis: Redis, job_id: str) -> Job | None:
    """The job, or None when Redis has no such job."""
    try:
        return Job.fetch(job_id, connection=redis, serializer=JSONSerializer)
    except NoSuchJobError:
        return None


def fetch_jobs(redis: Redis, job_ids: list[str]) -> list[Job | None]:
    """The jobs in the order of ``job_ids`` (None for each one Redis does not hold)."""
    return Job.fetch_many(job_ids, connection=redis, serializer=JSONSerializer) if job_ids else []


def queue_depths(redis: Redis) -> dict[str, dict[str, int]]:
    """Per queue: jobs queued / started / scheduled / deferred / finished / failed / canceled, and workers."""
    out: dict[str, dict[str, int]] = {}
    for name in QUEUE_NAMES:
        q = get_queue(redis, name)
        out[name] = {
            "queued": q.count,
            "started": q.started_job_registry.get_job_count(cleanup=False),
            "scheduled": q.scheduled_job_registry.get_job_count(cleanup=False),
            "deferred": q.deferred_job_registry.get_job_count(cleanup=False),
            "finished": q.finished_job_registry.get_job_count(cleanup=False),
            "failed": q.failed_job_registry.get_job_count(cleanup=False),
            "canceled": q.canceled_job_registry.get_job_count(cleanup=False),
            "workers": Worker.count(connection=redis, queue=q),
        }
    return out
