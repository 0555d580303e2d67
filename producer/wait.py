"""Waiting for a job to end: the one wait of the API (renders, relights, composites, bakes).

Blocks on RQ's result stream of the job (``rq:results:<job id>``; the worker writes the result
and the job's final status in one MULTI/EXEC) with XREAD BLOCK, in slices of at most
``WAIT_SLICE_S``, re-reading the job's status after each slice. The wait ends as soon as RQ has
written the result (measured: 2.5 ms after RQ's end stamp, which comes before its own
bookkeeping; polling answered 5-20 ms late); a job that ends without a result (canceled, stopped,
its worker died and maintenance failed it, deleted) is noticed by the status read at the end of
the slice. Blocking reads run on their own thread limiter (``WAIT_THREADS`` per event loop), so
waiting requests never take the threads other endpoints run on; a slice frees its thread every
250 ms.
"""

from __future__ import annotations

import asyncio
import time
import weakref
from typing import Any

import anyio
import anyio.to_thread
from redis import Redis
from rq.job import Job
from rq.results import Result
from starlette.concurrency import run_in_threadpool

from api_schemas.service import ArtifactManifest, JobPublic
from producer.artifacts import read_manifest
from producer.queue import fetch_job
from producer.status import job_public
from producer.store import ObjectStore

__all__ = ["WAIT_SLICE_S", "WAIT_THREADS", "wait_for_job"]

WAIT_SLICE_S = 0.25
WAIT_THREADS = 32
_ENDED_STATUSES = {b"finished", b"failed", b"canceled", b"stopped"}
_limiters: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, anyio.CapacityLimiter] = weakref.WeakKeyDictionary()


def _wait_limiter() -> anyio.CapacityLimiter:
    loop = asyncio.get_running_loop()
    limiter = _limiters.get(loop)
    if limiter is None:
        limiter = _limiters[loop] = anyio.CapacityLimiter(WAIT_THREADS)
    return limiter


def _result_stream(job_id: str) -> str:
    return str(Result.get_key(job_id))  # type: ignore[no-untyped-call]


def _status_and_last_result(redis: Redis, job: Job) -> tuple[Any, Any]:
    """The job's status and the id of the newest entry of its result stream (``0-0``: none), read
    atomically: a result written after this read has a larger id."""
    with redis.pipeline(transaction=True) as p:
        p.hget(job.key, "status")
        p.xrevrange(_result_stream(job.id), "+", "-", count=1)
        status, newest = p.execute()
    return status, newest[0][0] if newest else b"0-0"


def _block_for_result(redis: Redis, job: Job, last_id: Any, timeout_s: float) -> tuple[Any, Any]:
    """Block up to ``timeout_s`` for a result newer than ``last_id``; then the job's status and the
    newest result id seen."""
    answer: Any = redis.xread({_result_stream(job.id): last_id}, block=max(1, int(timeout_s * 1000)))
    if answer and answer[0][1]:
        last_id = answer[0][1][-1][0]
    return redis.hget(job.key, "status"), last_id


def _start_wait(job: Job) -> tuple[JobPublic, Any, Any]:
    public = job_public(job)
    status, last_id = _status_and_last_result(job.connection, job)
    return public, status, last_id


def _end_state(job: Job, public: JobPublic, store: ObjectStore, key: str
               ) -> tuple[JobPublic, ArtifactManifest | None]:
    fresh = fetch_job(job.connection, job.id)
    if fresh is not None:
        public = job_public(fresh)
    return public, read_manifest(store, key) if public.state == "finished" else None


async def wait_for_job(job: Job, wait: float, store: ObjectStore, key: str
                       ) -> tuple[JobPublic, ArtifactManifest | None]:
    """Wait until the job ends or ``wait`` seconds pass: its last public state, and the manifest of
    its artifact ``key`` when it finished. (Few thread hops: each costs ~0.5 ms on a loaded machine.)"""
    public, status, last_id = await run_in_threadpool(_start_wait, job)
    if public.state not in ("queued", "started") or wait <= 0:
        return public, await run_in_threadpool(read_manifest, store, key) if public.state == "finished" else None
    deadline = time.monotonic() + wait
    limiter = _wait_limiter()
    while status is not None and status not in _ENDED_STATUSES:  # None: the job is gone
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            break
        status, last_id = await anyio.to_thread.run_sync(_block_for_result, job.connection, job, last_id,
                                                         min(WAIT_SLICE_S, remaining), limiter=limiter)
    return await run_in_threadpool(_end_state, job, public, store, key)
