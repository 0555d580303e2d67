"""Queues, enqueueing with de-duplication, job status for the API, cancellation, batches.

Imported by the service process, so this module never imports numba or the engine (the
engine version is read from ``engine/__init__.py`` without importing it, see
:func:`engine_version`).

Conventions (docs/service-design.md "Queues and jobs"):

- two queues, ``bake`` and ``render``, on one Redis, ``JSONSerializer`` (never pickle);
- jobs are enqueued by import path with ONE JSON-safe dict argument;
- job id = ``f"{kind}-{artifact_key}"``: identical requests share one job. The check for an
  existing job and the enqueue run under a Redis lock per job id, so two concurrent identical
  requests (threads, processes or API replicas) create exactly one job (HARD_CASES 21);
- ``Retry(max=2, interval=[5, 30])``; the workers' exception handler (workers/runner.py)
  keeps retries only for transient errors (store unavailable, Redis connection trouble, a
  worker that died), so bad input and NaN renders fail at once;
- progress lives in ``job.meta["progress"]``; cancellation of a started job is a flag key
  ``ibr:cancel:<job_id>`` that the job polls between chunks (a separate key, because the
  running job rewrites ``job.meta`` wholesale on every ``save_meta()``).
"""

from __future__ import annotations

import ast
import importlib.util
import json
import re
import uuid
from collections.abc import Callable, Iterable, Sequence
from datetime import UTC, datetime
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast

from redis import Redis
from rq import Queue, Retry
from rq.command import send_stop_job_command
from rq.exceptions import DuplicateJobError, InvalidJobOperation, NoSuchJobError
from rq.job import Dependency, Job, JobStatus
from rq.serializers import JSONSerializer

from api_schemas.service import (
    BatchPublic,
    JobProgress,
    JobPublic,
    JobState,
    RenderPublic,
    RenderRequest,
    method_needs_bake,
)
from workers.jobs import RENDER_JOB
from workers.jobs.payloads import RenderJobPayload

if TYPE_CHECKING:
    from workers.store import ObjectStore

__all__ = [
    "ids_in_active_jobs",
    "BAKE_TIMEOUT_S",
    "BATCH_TTL_S",
    "BakeMissing",
    "FAILURE_TTL_S",
    "QUEUE_NAMES",
    "RENDER_RETRY_INTERVALS_S",
    "RENDER_TIMEOUT_S",
    "RESULT_TTL_S",
    "JobNotCancelable",
    "JobNotFound",
    "QueueName",
    "UnknownScene",
    "add_job_owner",
    "batch_owner",
    "batch_status",
    "cancel",
    "cancel_key",
    "cancel_requested",
    "clean_error",
    "engine_version",
    "enqueue_batch",
    "enqueue_render",
    "enqueue_unique",
    "fetch_job",
    "get_queue",
    "job_owners",
    "job_public",
    "job_state",
    "list_jobs",
    "queue_depths",
    "redis_from_url",
    "render_artifact_key",
    "render_job_id",
    "render_params",
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

_KEY_PREFIX = "ibr:"
_ACTIVE = frozenset({
    JobStatus.CREATED, JobStatus.QUEUED, JobStatus.STARTED, JobStatus.DEFERRED, JobStatus.SCHEDULED,
    JobStatus.READY_TO_ENQUEUE, JobStatus.RATE_LIMITED,
})
_WAITING = _ACTIVE - {JobStatus.STARTED}
_STATE_OF: dict[JobStatus, JobState] = {
    JobStatus.CREATED: "queued",
    JobStatus.QUEUED: "queued",
    JobStatus.DEFERRED: "queued",
    JobStatus.SCHEDULED: "queued",  # e.g. waiting for a retry
    JobStatus.READY_TO_ENQUEUE: "queued",
    JobStatus.RATE_LIMITED: "queued",
    JobStatus.STARTED: "started",
    JobStatus.FINISHED: "finished",
    JobStatus.FAILED: "failed",
    JobStatus.STOPPED: "canceled",  # rq's send_stop_job_command (bake horses)
    JobStatus.CANCELED: "canceled",
}


class JobNotFound(LookupError):
    """No job with that id (never existed, or expired from Redis): HTTP 404."""


class JobNotCancelable(RuntimeError):
    """The job already ended (finished / failed / canceled): HTTP 409. ``job`` is its state."""

    def __init__(self, job: JobPublic):
        super().__init__(f"job {job.id} is {job.state}; only queued or started jobs can be canceled")
        self.job = job


class UnknownScene(LookupError):
    """The render request names a scene the store does not hold: HTTP 404 / 422."""


class BakeMissing(LookupError):
    """An LDC render (``missing_bake: "fail"``) of a scene whose bake is not complete: HTTP 409.
    ``bake_key`` names the bake; ``job_id`` is its running job, if any."""

    def __init__(self, scene_id: str, bake_key: str, job_id: str | None):
        running = f" (in progress: job {job_id})" if job_id else ""
        super().__init__(
            f"scene {scene_id} has no complete bake {bake_key}{running}; request it with POST "
            f"/v1/scenes/{scene_id}/bakes (same bake params), or send missing_bake: \"bake\" to queue the "
            "render after the bake")
        self.scene_id = scene_id
        self.bake_key = bake_key
        self.job_id = job_id


# ------------------------------------------------------------------------------------ connections


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


def fetch_job(redis: Redis, job_id: str) -> Job | None:
    """The job, or None when Redis has no such job."""
    try:
        return Job.fetch(job_id, connection=redis, serializer=JSONSerializer)
    except NoSuchJobError:
        return None


# ------------------------------------------------------------------------------------ keys


@lru_cache(maxsize=1)
def engine_version() -> str:
    """``engine.ENGINE_VERSION`` without importing ``engine`` (whose ``__init__`` imports numba).

    One source of truth: the constant in ``engine/__init__.py`` is read with ``ast`` from the file
    the import system would load. The render job checks that this equals the imported constant.
    """
    spec = importlib.util.find_spec("engine")  # a top-level package: found, not executed
    if spec is None or spec.origin is None:
        raise RuntimeError("cannot locate the engine package to read ENGINE_VERSION")
    tree = ast.parse(Path(spec.origin).read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "ENGINE_VERSION"
                                                for t in node.targets):
            value = ast.literal_eval(node.value)
            if isinstance(value, str) and value:
                return value
    raise RuntimeError(f"{spec.origin} does not define ENGINE_VERSION as a string literal")


def render_params(req: RenderRequest) -> dict[str, Any]:
    """The artifact parameters of a render: the request without its scene id and without
    ``missing_bake`` (what to do when the bake is missing does not change the image); the bake
    params for the methods that read a bake, the reference params for ``reference`` (JSON types)."""
    params = req.model_dump(mode="json", exclude={"scene_id", "missing_bake"})
    if params.get("outputs") is None:  # every image (the default): the key of a full artifact stays as it was
        params.pop("outputs", None)
    if method_needs_bake(req.method):
        params.pop("params")  # the LDC methods shade with the bake's settings
    else:
        params.pop("bake")
    return params


def render_artifact_key(req: RenderRequest) -> str:
    """Content key of the render's artifact: (kind, scene, request params, engine version)."""
    from workers.artifacts import artifact_key

    return artifact_key("render", {"scene": req.scene_id}, render_params(req), engine_version())


def render_job_id(key: str) -> str:
    return f"render-{key}"


def cancel_key(job_id: str) -> str:
    """Redis key of the cancel flag of a job (set by :func:`cancel`, polled by the job)."""
    return f"{_KEY_PREFIX}cancel:{job_id}"


def _owners_key(job_id: str) -> str:
    return f"{_KEY_PREFIX}job-owners:{job_id}"


def _batch_key(batch_id: str) -> str:
    return f"{_KEY_PREFIX}batch:{batch_id}"


def cancel_requested(redis: Redis, job_id: str) -> bool:
    return bool(redis.exists(cancel_key(job_id)))


def job_owners(redis: Redis, job_id: str) -> set[str]:
    """Everybody who asked for this job (identical requests share one job)."""
    return {m.decode() if isinstance(m, bytes) else str(m) for m in cast(set[Any], redis.smembers(_owners_key(job_id)))}


# ------------------------------------------------------------------------------------ enqueue


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
    with redis.lock(f"{_KEY_PREFIX}lock:enqueue:{job_id}", timeout=ENQUEUE_LOCK_TIMEOUT_S,
                    blocking_timeout=ENQUEUE_LOCK_TIMEOUT_S):
        job = fetch_job(redis, job_id)
        if job is not None:
            status = job.get_status(refresh=False)
            if status in _ACTIVE:
                _add_owner(redis, job_id, owner, timeout)
                return job
            if status == JobStatus.FINISHED and is_cached is not None and is_cached():
                return None
            job.delete(remove_from_queue=True)
        redis.delete(cancel_key(job_id), _owners_key(job_id))
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
        _add_owner(redis, job_id, owner, timeout)
        return job


def add_job_owner(redis: Redis, job_id: str, owner: str | None, timeout: int) -> None:
    """Record ``owner`` as one of the keys that asked for ``job_id`` (so they may see it)."""
    _add_owner(redis, job_id, owner, timeout)


def _add_owner(redis: Redis, job_id: str, owner: str | None, timeout: int) -> None:
    if owner:
        key = _owners_key(job_id)
        with redis.pipeline() as p:
            p.sadd(key, owner)
            p.expire(key, timeout + FAILURE_TTL_S)
            p.execute()


def enqueue_render(
    redis: Redis,
    req: RenderRequest,
    owner: str | None,
    batch_id: str | None = None,
    *,
    store: ObjectStore | None = None,
    timeout: int = RENDER_TIMEOUT_S,
) -> tuple[str, Job | None]:
    """Queue a render, or find it done or in progress.

    Returns ``(artifact_key, None)`` when the artifact's manifest is in ``store`` (cache hit),
    ``(artifact_key, job)`` otherwise -- the existing job when an identical request is already
    queued or running, else a new one. With ``store=None`` the manifest is not checked (every
    call that finds no active job enqueues one; the job itself returns early when the artifact
    exists). Raises :class:`UnknownScene` when ``store`` is given and holds no such scene.
    """
    key = render_artifact_key(req)

    def cached() -> bool:
        if store is None:
            return False
        from workers.artifacts import read_manifest

        return read_manifest(store, key) is not None

    if cached():
        return key, None
    if store is not None and not store.exists(f"scenes/{req.scene_id}.json"):
        raise UnknownScene(f"scene {req.scene_id} does not exist")
    depends_on: Dependency | None = None
    if method_needs_bake(req.method) and store is not None:
        from workers.bakes import bake_complete, bake_job_id, bake_key, enqueue_bake

        bkey = bake_key(req.scene_id, req.bake)
        if not bake_complete(store, bkey):
            if req.missing_bake == "fail":
                running = fetch_job(redis, bake_job_id(bkey))
                active = running is not None and running.get_status(refresh=False) in _ACTIVE
                raise BakeMissing(req.scene_id, bkey, running.id if running is not None and active else None)
            _, merge = enqueue_bake(redis, store, req.scene_id, req.bake, owner)
            if merge is not None:
                depends_on = Dependency(jobs=[merge.id], allow_failure=True)
    payload = RenderJobPayload(request=req, artifact_key=key).model_dump(mode="json")
    meta: dict[str, Any] = {
        "kind": "render",
        "artifact_key": key,
        "owner": owner,
        "batch_id": batch_id,
        "progress": {"fraction": 0.0, "stage": "waiting for the bake" if depends_on else "queued", "eta_s": None},
    }
    if depends_on is not None:
        meta["waits_for_bake"] = True
    job = enqueue_unique(
        redis, "render", RENDER_JOB, payload, render_job_id(key),
        timeout=timeout, meta=meta, retry=Retry(max=RENDER_RETRY_MAX, interval=list(RENDER_RETRY_INTERVALS_S)),
        description=f"render scene {req.scene_id[:12]} ({req.method})", owner=owner, is_cached=cached,
        depends_on=depends_on,
    )
    return key, job


# ------------------------------------------------------------------------------------ job status


def job_state(job: Job, status: JobStatus | None = None) -> JobState:
    """RQ status -> API state. A job that failed because it was asked to stop is 'canceled'."""
    st = status if status is not None else job.get_status(refresh=False)
    state = _STATE_OF.get(st, "queued") if st is not None else "queued"
    if state == "failed" and (job.meta.get("cancel_requested") or cancel_requested(job.connection, job.id)):
        return "canceled"
    return state


def _progress(job: Job, state: JobState) -> JobProgress:
    raw = job.meta.get("progress")
    frac, stage, eta = 0.0, "", None
    if isinstance(raw, dict):
        f = raw.get("fraction")
        if isinstance(f, int | float) and f == f:  # not NaN
            frac = min(1.0, max(0.0, float(f)))
        s = raw.get("stage")
        stage = s if isinstance(s, str) else ""
        e = raw.get("eta_s")
        eta = float(e) if isinstance(e, int | float) and e == e and e >= 0 else None
    if state == "finished":
        return JobProgress(fraction=1.0, stage="done", eta_s=0.0)
    if state == "started" and cancel_requested(job.connection, job.id):
        stage = "canceling"
    return JobProgress(fraction=frac, stage=stage, eta_s=eta)


_CLEAN_ERRORS: tuple[tuple[re.Pattern[str], str], ...] = (
    (re.compile(r"AbandonedJobError"),
     "the worker running this job stopped responding (killed or out of memory) and the job was abandoned"),
    (re.compile(r"Work-horse terminated unexpectedly.*?signal (\d+)"),
     r"the worker process running this job was killed (signal \1)"),
    (re.compile(r"Work-horse terminated unexpectedly"), "the worker process running this job died unexpectedly"),
    (re.compile(r"JobTimeoutException: Task exceeded maximum timeout value \((\d+) seconds\)"),
     r"the job exceeded its time limit of \1 s and was stopped"),
    (re.compile(r"Job stopped by user"), "the job was canceled"),
)
_EXC_LINE = re.compile(r"^(?:[A-Za-z_][\w]*\.)*([A-Za-z_]\w*(?:Error|Exception|Exit|Canceled|Payload|Mismatch|Found|"
                       r"Unavailable|Interrupt)):\s*(.*)$")


def _error_text(job: Job) -> str | None:
    result = job.latest_result()
    exc: str | None = None
    if result is not None and result.type == result.Type.FAILED:
        exc = result.exc_string
    if not exc:
        exc = cast(str | None, getattr(job, "_exc_info", None))
    if not exc:
        return None
    return clean_error(exc)


def clean_error(exc_string: str) -> str:
    """The last exception of a traceback (or an RQ failure note) as one line a user can act on."""
    for pat, repl in _CLEAN_ERRORS:
        m = pat.search(exc_string)
        if m:
            return m.expand(repl)
    lines = [ln for ln in exc_string.strip().splitlines() if ln.strip()]
    # the final exception block starts after the last stack frame ("  File ...", then its code line)
    last_frame = max((i for i, ln in enumerate(lines) if ln.startswith("  File ")), default=-1)
    tail = lines[last_frame + 1:] if last_frame >= 0 else lines
    while tail and tail[0].startswith("    "):  # source line of the last frame, carets
        tail = tail[1:]
    text = tail[0] if tail else (lines[-1] if lines else exc_string)
    m = _EXC_LINE.match(text.strip())
    if m:
        text = f"{m.group(1)}: {m.group(2)}" if m.group(2) else m.group(1)
    text = text.strip()
    return text[:500] + ("..." if len(text) > 500 else "")


def job_public(job: Job) -> JobPublic:
    """The API view of an RQ job (state, progress from ``job.meta``, clean error, small result)."""
    status = job.get_status(refresh=False)
    state = job_state(job, status)
    kind = job.meta.get("kind") or job.origin
    if kind not in ("render", "bake"):
        kind = "bake" if job.id.startswith("bake-") else "render"
    result: dict[str, Any] | None = None
    error: str | None = None
    if state == "finished":
        rv = job.return_value()
        result = rv if isinstance(rv, dict) else None
    elif state == "failed":
        error = _error_text(job) or "the job failed"
    elif state == "canceled":
        error = "canceled on request"
    links = {"self": f"/v1/jobs/{job.id}"}
    key = job.meta.get("artifact_key")
    if state == "finished" and isinstance(key, str):
        links["artifact"] = f"/v1/artifacts/{key}"
    batch_id = job.meta.get("batch_id")
    return JobPublic(
        id=job.id,
        kind="bake" if kind == "bake" else "render",
        state=state,
        progress=_progress(job, state),
        created_at=job.created_at,
        started_at=job.started_at if state != "queued" else None,
        ended_at=job.ended_at if state in ("finished", "failed", "canceled") else None,
        error=error,
        result=result,
        batch_id=batch_id if isinstance(batch_id, str) else None,
        links=links,
    )


# ------------------------------------------------------------------------------------ cancel


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
    if status not in _ACTIVE:
        raise JobNotCancelable(job_public(job))
    # The flag first: a worker may be dequeuing the job right now.
    redis.set(cancel_key(job_id), b"1", ex=FAILURE_TTL_S)
    if status in _WAITING:
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
    ids = [f"bake-plan-{bake_key}", *renders]
    plan = fetch_job(redis, ids[0])
    if plan is not None and plan.get_status(refresh=False) == JobStatus.FINISHED:
        rv = plan.return_value()
        if isinstance(rv, dict):
            ids += [f"bake-part-{p['key']}" for p in rv.get("parts", []) if isinstance(p, dict) and "key" in p]
    for jid in ids:
        try:
            cancel(redis, jid)
        except (JobNotFound, JobNotCancelable):
            pass  # never queued, already done


# ------------------------------------------------------------------------------------ listing


def _queue_job_ids(q: Queue) -> list[str]:
    ids: list[str] = list(q.get_job_ids())
    for reg in (q.scheduled_job_registry, q.deferred_job_registry, q.started_job_registry,
                q.finished_job_registry, q.failed_job_registry, q.canceled_job_registry):
        ids.extend(reg.get_job_ids(cleanup=False))
    return ids


def list_jobs(
    redis: Redis,
    owner: str | None = None,
    states: Iterable[JobState] | None = None,
    kinds: Iterable[QueueName] = QUEUE_NAMES,
    limit: int = 100,
) -> list[JobPublic]:
    """Jobs still known to Redis, newest first; optionally only ``owner``'s and only ``states``."""
    wanted = set(states) if states is not None else None
    seen: dict[str, None] = {}
    for name in kinds:
        for jid in _queue_job_ids(get_queue(redis, name)):
            seen.setdefault(jid, None)
    jobs = [j for j in Job.fetch_many(list(seen), connection=redis, serializer=JSONSerializer) if j is not None]
    out: list[JobPublic] = []
    for job in jobs:
        if owner is not None and job.meta.get("owner") != owner and owner not in job_owners(redis, job.id):
            continue
        pub = job_public(job)
        if wanted is None or pub.state in wanted:
            out.append(pub)
    epoch = datetime.min.replace(tzinfo=UTC)
    out.sort(key=lambda p: p.created_at or epoch, reverse=True)
    return out[: max(0, limit)]


def queue_depths(redis: Redis) -> dict[str, dict[str, int]]:
    """Per queue: jobs queued / started / scheduled / deferred / finished / failed / canceled, and workers."""
    from rq import Worker

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


# ------------------------------------------------------------------------------------ batches


def enqueue_batch(
    redis: Redis,
    requests: Sequence[RenderRequest],
    owner: str | None,
    *,
    store: ObjectStore | None = None,
    batch_id: str | None = None,
    scene_ids: Sequence[str] = (),
) -> BatchPublic:
    """Enqueue many renders as one batch and remember its members (Redis hash ``ibr:batch:<id>``).

    ``scene_ids``: scenes the caller stored for this batch (listed in the answer). Each render
    goes through :func:`enqueue_render` (cache hits and de-duplication included).
    """
    bid = batch_id or uuid.uuid4().hex
    if store is not None:  # an LDC render without its bake fails the whole batch before anything is queued
        from workers.bakes import bake_complete, bake_key

        for req in requests:
            if method_needs_bake(req.method) and req.missing_bake == "fail":
                bkey = bake_key(req.scene_id, req.bake)
                if not bake_complete(store, bkey):
                    raise BakeMissing(req.scene_id, bkey, None)
    members: list[dict[str, str | None]] = []
    for req in requests:
        key, job = enqueue_render(redis, req, owner, batch_id=bid, store=store)
        members.append({"artifact_key": key, "job_id": job.id if job is not None else None})
    record = {
        "owner": owner or "",
        "created_at": datetime.now(UTC).isoformat(),
        "scene_ids": json.dumps(list(scene_ids)),
        "renders": json.dumps(members),
    }
    with redis.pipeline() as p:
        p.hset(_batch_key(bid), mapping=record)  # type: ignore[arg-type]  # redis-py Mapping key invariance
        p.expire(_batch_key(bid), BATCH_TTL_S)
        p.execute()
    status = batch_status(redis, bid, store=store)
    assert status is not None
    return status


def batch_owner(redis: Redis, batch_id: str) -> str | None:
    raw = redis.hget(_batch_key(batch_id), "owner")
    if raw is None:
        return None
    text = raw.decode() if isinstance(raw, bytes) else str(raw)
    return text or None


_RENDER_STATUS: dict[JobState, Literal["queued", "running", "finished", "failed"]] = {
    "queued": "queued", "started": "running", "finished": "finished", "failed": "failed", "canceled": "failed",
}


def batch_status(redis: Redis, batch_id: str, *, store: ObjectStore | None = None) -> BatchPublic | None:
    """A batch's renders with their states, counts per state (plus ``cached`` and ``lost``) and the
    mean progress (a finished, failed, canceled or cached render counts as done). None if unknown.

    A member whose job has expired from Redis counts as finished when ``store`` holds its
    artifact, else as ``lost`` (e.g. Redis restarted without persistence, HARD_CASES 22).
    """
    raw = cast(dict[bytes, bytes], redis.hgetall(_batch_key(batch_id)))
    if not raw:
        return None
    members = json.loads(raw.get(b"renders", b"[]"))
    scene_ids = json.loads(raw.get(b"scene_ids", b"[]"))
    job_ids = [m["job_id"] for m in members if m.get("job_id")]
    fetched = Job.fetch_many(job_ids, connection=redis, serializer=JSONSerializer) if job_ids else []
    by_id = dict(zip(job_ids, fetched, strict=True))
    renders: list[RenderPublic] = []
    counts: dict[str, int] = {}
    total = 0.0
    for m in members:
        key = m["artifact_key"]
        links = {"artifact": f"/v1/artifacts/{key}"}
        jid = m.get("job_id")
        if not jid:
            renders.append(RenderPublic(artifact_key=key, status="cached", links=links))
            counts["cached"] = counts.get("cached", 0) + 1
            total += 1.0
            continue
        job = by_id.get(jid)
        if job is None:
            done = False
            if store is not None:
                from workers.artifacts import read_manifest

                done = read_manifest(store, key) is not None
            label = "finished" if done else "lost"
            counts[label] = counts.get(label, 0) + 1
            renders.append(RenderPublic(artifact_key=key, status="finished" if done else "failed", links=links))
            total += 1.0
            continue
        pub = job_public(job)
        counts[pub.state] = counts.get(pub.state, 0) + 1
        total += 1.0 if pub.state in ("finished", "failed", "canceled") else pub.progress.fraction
        renders.append(RenderPublic(artifact_key=key, status=_RENDER_STATUS[pub.state], job=pub,
                                    links={**links, "job": f"/v1/jobs/{jid}"}))
    n = len(members)
    frac = total / n if n else 1.0
    n_open = sum(counts.get(s, 0) for s in ("queued", "started"))
    stage = "done" if n_open == 0 else f"{n - n_open} of {n} renders done"
    return BatchPublic(id=batch_id, scene_ids=scene_ids, renders=renders,
                       progress=JobProgress(fraction=min(1.0, frac), stage=stage), counts=counts)


def ids_in_active_jobs(redis: Redis, keys: Iterable[str]) -> set[str]:
    """String values stored under any of ``keys`` (at any depth) in the payloads of queued,
    scheduled, deferred or started jobs of every queue: e.g. the scene or dataset ids that a
    DELETE must not pull from under a running job."""
    wanted = frozenset(keys)
    ids: list[str] = []
    for name in QUEUE_NAMES:
        q = get_queue(redis, name)
        ids += q.get_job_ids()
        for reg in (q.started_job_registry, q.scheduled_job_registry, q.deferred_job_registry):
            ids += reg.get_job_ids(cleanup=False)
    out: set[str] = set()
    for job in Job.fetch_many(list(dict.fromkeys(ids)), connection=redis, serializer=JSONSerializer):
        if job is None:
            continue
        try:
            args = job.args
        except Exception:  # an unreadable payload cannot be attributed to anything
            continue
        _collect_ids(args, wanted, out)
    return out


def _collect_ids(value: Any, keys: frozenset[str], out: set[str], depth: int = 0) -> None:
    if depth > 8:
        return
    if isinstance(value, dict):
        for k, v in value.items():
            if k in keys and isinstance(v, str):
                out.add(v)
            else:
                _collect_ids(v, keys, out, depth + 1)
    elif isinstance(value, list | tuple):
        for v in value:
            _collect_ids(v, keys, out, depth + 1)
