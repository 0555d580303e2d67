"""Enqueueing with de-duplication: one job per job id, however many identical requests arrive.

Job id = ``f"{kind}-{artifact_key}"`` (``producer.names``): identical requests share one job. The
check for an existing job and the enqueue run under a Redis lock per job id, so two concurrent
identical requests (threads, processes or API replicas) create exactly one job.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from redis import Redis
from rq import Retry
from rq.exceptions import DuplicateJobError
from rq.job import Dependency, Job, JobStatus

from producer.ownership import add_job_owner, index_job, job_owners_key
from producer.queue import (
    ACTIVE_STATUSES,
    ENQUEUE_LOCK_TIMEOUT_S,
    FAILURE_TTL_S,
    KEY_PREFIX,
    RESULT_TTL_S,
    QueueName,
    fetch_job,
    get_queue,
)
from producer.status import cancel_key

__all__ = ["enqueue_unique"]


def enqueue_unique(
    redis: Redis,
    queue: QueueName,
    func: str,
    payload: dict[str, Any],
    job_id: str,
    *,
    timeout: int,
    meta: dict[str, Any],
    retry: Retry | None,
    description: str,
    owner: str | None = None,
    is_cached: Callable[[], bool] | None = None,
    depends_on: Dependency | None = None,
) -> Job | None:
    """Enqueue ``func(payload)`` as ``job_id`` unless that job is already waiting or running.

    Under a Redis lock per job id: an active job (queued / started / scheduled / deferred) is
    returned as it is; a finished job for which ``is_cached()`` holds means the result exists
    (returns None); any other previous job with that id (failed, canceled, finished but its
    artifact gone) is deleted and replaced by a fresh one. ``depends_on``: RQ dependencies of a
    new job (it waits, 'deferred', until they end).
    """
    with redis.lock(f"{KEY_PREFIX}lock:enqueue:{job_id}", timeout=ENQUEUE_LOCK_TIMEOUT_S,
                    blocking_timeout=ENQUEUE_LOCK_TIMEOUT_S):
        job = fetch_job(redis, job_id)
        if job is not None:
            status = job.get_status(refresh=False)
            if status in ACTIVE_STATUSES:
                add_job_owner(redis, job_id, owner, timeout)
                return job
            if status == JobStatus.FINISHED and is_cached is not None and is_cached():
                return None
            job.delete(remove_from_queue=True)
        redis.delete(cancel_key(job_id), job_owners_key(job_id))
        q = get_queue(redis, queue)
        try:
            job = q.enqueue_call(
                func,
                args=(payload,),
                timeout=timeout,
                result_ttl=RESULT_TTL_S,
                failure_ttl=FAILURE_TTL_S,
                description=description,
                job_id=job_id,
                meta=meta,
                retry=retry,
                unique=depends_on is None,  # RQ refuses unique with dependencies; the lock covers it
                depends_on=depends_on,
            )
        except DuplicateJobError:  # only possible if someone enqueued around the lock
            existing = fetch_job(redis, job_id)
            if existing is None:
                raise
            job = existing
        index_job(redis, job_id, owner)
        add_job_owner(redis, job_id, owner, timeout)
        return job
