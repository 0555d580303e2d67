"""Canceling a job; canceling a scene bake's own job cancels its plan and part jobs and the
renders queued behind it.

Identical requests share one job, so a job can have several owners (``producer.ownership``).
:func:`cancel_for` cancels on behalf of one owner: it detaches that owner, and the job itself is
canceled only when no owner remains attached; until then the answer shows the job as it is (still
queued or running for the others). One key can never cancel work another key is waiting for."""

from __future__ import annotations

from collections.abc import Sequence

from redis import Redis
from rq.command import send_stop_job_command
from rq.exceptions import InvalidJobOperation, NoSuchJobError
from rq.job import JobStatus
from rq.serializers import JSONSerializer

from api_schemas.service import JobPublic
from producer.errors import JobNotCancelable, JobNotFound
from producer.names import scene_bake_part_job_id, scene_bake_plan_job_id
from producer.ownership import detach_job_owner
from producer.queue import (
    ACTIVE_STATUSES,
    ENQUEUE_LOCK_TIMEOUT_S,
    FAILURE_TTL_S,
    KEY_PREFIX,
    WAITING_STATUSES,
    fetch_job,
)
from producer.status import cancel_key, job_public

__all__ = ["cancel", "cancel_for"]


def cancel_for(redis: Redis, job_id: str, owner: str | None) -> JobPublic:
    """Cancel ``job_id`` for ``owner`` (None: auth off, cancel it outright). The owner is detached;
    the job is canceled (:func:`cancel`) when nobody who asked for it is still attached. Raises
    :class:`JobNotFound` / :class:`JobNotCancelable` as :func:`cancel` does (an ended job is not
    cancelable for anybody)."""
    if owner is None:
        return cancel(redis, job_id)
    job = fetch_job(redis, job_id)
    if job is None:
        raise JobNotFound(f"no job {job_id}")
    if job.get_status(refresh=True) not in ACTIVE_STATUSES:
        raise JobNotCancelable(job_public(job))
    first = job.meta.get("owner")
    # under enqueue_unique's lock: a key joining the job right now is either seen here or gets a new job
    with redis.lock(f"{KEY_PREFIX}lock:enqueue:{job_id}", timeout=ENQUEUE_LOCK_TIMEOUT_S,
                    blocking_timeout=ENQUEUE_LOCK_TIMEOUT_S):
        if detach_job_owner(redis, job_id, owner, first if isinstance(first, str) else None):
            return job_public(job)  # others still wait for it
        return cancel(redis, job_id)


def cancel(redis: Redis, job_id: str) -> JobPublic:
    """Cancel a job.

    queued (or scheduled / deferred) -> removed from its queue, state 'canceled'.
    started -> a cancel flag the job polls between chunks (render) plus, on the forking bake
    workers, ``send_stop_job_command`` which kills the work horse; the answer still says
    'started' with progress stage 'canceling' until the worker has stopped it.
    finished / failed / canceled -> :class:`JobNotCancelable` (HTTP 409).
    Raises :class:`JobNotFound` for an unknown id.
    """
    job = fetch_job(redis, job_id)
    if job is None:
        raise JobNotFound(f"no job {job_id}")
    status = job.get_status(refresh=True)
    if status not in ACTIVE_STATUSES:
        raise JobNotCancelable(job_public(job))
    # The flag first: a worker may be dequeuing the job right now.
    redis.set(cancel_key(job_id), b"1", ex=FAILURE_TTL_S)
    if status in WAITING_STATUSES:
        try:
            job.cancel()
        except InvalidJobOperation:
            pass  # canceled concurrently
    elif job.origin == "bake":
        try:
            send_stop_job_command(redis, job_id, serializer=JSONSerializer)
        except (InvalidJobOperation, NoSuchJobError):
            pass  # it just ended
    if job.meta.get("bake_role") == "merge" and isinstance(job.meta.get("bake_key"), str):
        waiting = [j for j in job.dependent_ids if j.startswith("render-")]  # renders queued behind the bake
        _cancel_bake_jobs(redis, str(job.meta["bake_key"]), waiting)
    refreshed = fetch_job(redis, job_id)
    return job_public(refreshed if refreshed is not None else job)


def _cancel_bake_jobs(redis: Redis, bake_key: str, renders: Sequence[str] = ()) -> None:
    """Canceling a bake's own job (``bake-<key>``) also cancels its plan job and its part jobs
    (part keys derive from the bake key, so no other bake shares them) and the renders queued to run
    after it (``missing_bake="bake"``), which could never run now."""
    ids = [scene_bake_plan_job_id(bake_key), *renders]
    plan = fetch_job(redis, ids[0])
    if plan is not None and plan.get_status(refresh=False) == JobStatus.FINISHED:
        rv = plan.return_value()
        if isinstance(rv, dict):
            ids += [scene_bake_part_job_id(str(p["key"])) for p in rv.get("parts", [])
                    if isinstance(p, dict) and "key" in p]
    for jid in ids:
        try:
            cancel(redis, jid)
        except (JobNotFound, JobNotCancelable):
            pass  # never queued, already done
