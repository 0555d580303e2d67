"""The API's view of jobs: state, progress and a clean error of one job, the job list, and the
ids that active jobs use.

Progress lives in ``job.meta["progress"]`` (written by the job); cancellation of a started job is
a flag key ``ibr:cancel:<job_id>`` that the job polls between chunks (a separate key, because the
running job rewrites ``job.meta`` wholesale on every ``save_meta()``).
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Iterable
from datetime import UTC, datetime
from typing import Any, cast

from redis import Redis
from rq.job import Job, JobStatus
from rq.serializers import JSONSerializer
from rq.utils import str_to_date

from api_schemas.service import JobProgress, JobPublic, JobState
from producer.ownership import JOB_INDEX_HORIZON_S, job_index_key, job_owners_key
from producer.queue import KEY_PREFIX, QUEUE_NAMES, QueueName, fetch_jobs, get_queue

__all__ = [
    "JOB_SECONDS_BUCKETS",
    "JOB_SECONDS_KEY",
    "cancel_key",
    "failed_and_canceled",
    "job_duration_histograms",
    "job_method",
    "record_job_duration",
    "cancel_requested",
    "clean_error",
    "ids_in_active_jobs",
    "job_public",
    "job_state",
    "list_jobs",
    "list_jobs_page",
    "JOB_INDEX_BUILT_KEY",
    "rebuild_job_index",
    "BadCursor",
    "JOB_SCAN_BUDGET",
    "decode_job_cursor",
    "encode_job_cursor",
]

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


JOB_SECONDS_KEY = f"{KEY_PREFIX}metrics:job_seconds"
"""Redis hash of the job-duration histograms: cumulative bucket counts, sum and count per
(queue, method, outcome), incremented by the worker that ran the job (``record_job_duration``)."""

JOB_SECONDS_BUCKETS: tuple[float, ...] = (0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0,
                                          1800.0, 3600.0)
"""Upper bounds (seconds) of the duration buckets; +Inf is implied."""

_SEP = "\t"


def cancel_key(job_id: str) -> str:
    """Redis key of the cancel flag of a job (set by ``producer.cancel.cancel``, polled by the job)."""
    return f"{KEY_PREFIX}cancel:{job_id}"


def cancel_requested(redis: Redis, job_id: str) -> bool:
    return bool(redis.exists(cancel_key(job_id)))


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


JOB_SCAN_BUDGET = 2000
"""Index entries one listing request reads at most: with a state filter that few jobs match, the
page comes back short and its ``next_cursor`` continues the scan, so no request reads every job."""
_CURSOR = re.compile(r"(\d{1,20})-([A-Za-z0-9_-]{1,128})")


class BadCursor(ValueError):
    """A listing cursor that no listing returned."""


def encode_job_cursor(score: int, job_id: str) -> str:
    return f"{score}-{job_id}"


def decode_job_cursor(cursor: str) -> tuple[int, str]:
    m = _CURSOR.fullmatch(cursor)
    if m is None:
        raise BadCursor(f"invalid cursor {cursor[:80]!r}: pass the next_cursor of the previous page")
    return int(m.group(1)), m.group(2)


def _text(raw: Any) -> str:
    return raw.decode() if isinstance(raw, bytes) else str(raw)


def _entries_after(redis: Redis, key: str, after: tuple[int, str] | None, n: int) -> list[tuple[str, int]]:
    """Up to ``n`` index entries ``(job id, score)`` newest first, strictly after ``after`` in the
    index's order (score descending, then job id descending, as ZREVRANGE orders ties)."""
    if after is None:
        first = cast(list[tuple[Any, float]], redis.zrevrange(key, 0, n - 1, withscores=True))
        return [(_text(m), int(sc)) for m, sc in first]
    score, member = after
    out: list[tuple[str, int]] = []
    offset = 0
    step = n + 8
    while True:
        chunk = cast(list[tuple[Any, float]],
                     redis.zrevrangebyscore(key, score, "-inf", start=offset, num=step, withscores=True))
        for raw, sc in chunk:
            m, s = _text(raw), int(sc)
            if s < score or m < member:  # entries tied with the cursor's score and not after it come first
                out.append((m, s))
        if len(out) >= n or len(chunk) < step:
            return out[:n]
        offset += len(chunk)


_LIST_FIELDS = ("status", "origin", "meta", "created_at", "started_at", "ended_at")


def _date(raw: Any) -> datetime:
    """An RQ timestamp (``2026-12-02T15:43:11.123456Z``) as an aware UTC datetime: the C parser,
    RQ's own (strptime, several times slower) for anything else it wrote."""
    try:
        when = datetime.fromisoformat(_text(raw))
    except ValueError:
        return str_to_date(raw)
    return when if when.tzinfo is not None else when.replace(tzinfo=UTC)


def _listed_jobs(redis: Redis, job_ids: list[str], owner: str | None) -> tuple[list[Job | None], list[bool]]:
    """The jobs of a listing page with only the fields ``job_public`` reads (state, times, meta):
    one pipelined HMGET each instead of the whole hash (payload included), which made a page's
    time grow with the size of its jobs' requests; None for a job Redis does not hold. And whether
    ``owner`` asked for each: its meta names ``owner``, or (one more round trip, only for the jobs
    it does not name) ``owner`` is in the job's owners set."""
    with redis.pipeline(transaction=False) as p:
        for jid in job_ids:
            p.hmget(Job.key_for(jid), list(_LIST_FIELDS))
        rows = cast(list[list[Any]], p.execute())
    out: list[Job | None] = []
    for jid, (status, origin, meta, created, started, ended) in zip(job_ids, rows, strict=True):
        if status is None and created is None:
            out.append(None)  # expired or deleted
            continue
        job = Job(jid, connection=redis, serializer=JSONSerializer)
        try:
            job._status = JobStatus(_text(status)) if status else JobStatus.CREATED
            job.origin = _text(origin) if origin else ""
            loaded = json.loads(meta) if meta else {}
            job.meta = loaded if isinstance(loaded, dict) else {}
            job.created_at = _date(created) if created else None  # type: ignore[assignment]
            job.started_at = _date(started) if started else None
            job.ended_at = _date(ended) if ended else None
        except (ValueError, TypeError):  # a hash that is not an RQ job's: read it the slow, checked way
            out.append(fetch_jobs(redis, [jid])[0])
            continue
        out.append(job)
    if owner is None:
        return out, [True] * len(job_ids)
    asked = [job is not None and job.meta.get("owner") == owner for job in out]
    others = [i for i, (job, a) in enumerate(zip(out, asked, strict=True)) if job is not None and not a]
    if others:
        with redis.pipeline(transaction=False) as p:
            for i in others:
                p.sismember(job_owners_key(job_ids[i]), owner)
            for i, member in zip(others, p.execute(), strict=True):
                asked[i] = bool(member)
    return out, asked


def list_jobs_page(
    redis: Redis,
    owner: str | None = None,
    states: Iterable[JobState] | None = None,
    kinds: Iterable[QueueName] = QUEUE_NAMES,
    limit: int = 100,
    cursor: str | None = None,
) -> tuple[list[JobPublic], str | None]:
    """One page of the jobs ``owner`` asked for (every job with owner None), newest first, and the
    cursor of the next page (None after the last). Reads ``owner``'s job index
    (``producer.ownership.job_index_key``) and only the jobs of this page: the time does not grow
    with the number of jobs in Redis. Entries of jobs Redis no longer holds (expired, deleted) or
    that ``owner`` can no longer see (recreated for another key) are removed from the index on
    the way. ``BadCursor`` for a cursor no listing returned."""
    wanted = set(states) if states is not None else None
    queues = set(kinds)
    key = job_index_key(owner)
    pos = decode_job_cursor(cursor) if cursor else None
    out: list[JobPublic] = []
    scanned = 0
    limit = max(1, limit)
    while len(out) < limit and scanned < JOB_SCAN_BUDGET:
        entries = _entries_after(redis, key, pos, min(limit - len(out) + 1, JOB_SCAN_BUDGET - scanned))
        if not entries:
            return out, None
        jobs, asked = _listed_jobs(redis, [jid for jid, _ in entries], owner)
        stale: list[str] = []
        for (jid, score), job, member in zip(entries, jobs, asked, strict=True):
            if len(out) == limit:
                break
            pos = (score, jid)
            scanned += 1
            if job is None or not (owner is None or member or job.meta.get("owner") == owner):
                stale.append(jid)
                continue
            if job.origin not in queues:
                continue
            pub = job_public(job)
            if wanted is None or pub.state in wanted:
                out.append(pub)
        if stale:
            redis.zrem(key, *stale)
    assert pos is not None
    more = _entries_after(redis, key, pos, 1)
    return out, encode_job_cursor(*pos) if more else None


JOB_INDEX_BUILT_KEY = f"{KEY_PREFIX}job-index-built"
"""Set once the job indexes hold the jobs enqueued before they existed (``rebuild_job_index``)."""


def rebuild_job_index(redis: Redis, batch: int = 500) -> int:
    """Put every job Redis holds (queued, scheduled, deferred, started, finished, failed, canceled)
    into the index of every job and into those of the keys that asked for it, at the time it was
    created, unless it is there already: what a Redis written before the job indexes needs once
    (``JOB_INDEX_BUILT_KEY`` records it; idempotent). Returns how many jobs were indexed (0 when
    the indexes were built already)."""
    if redis.exists(JOB_INDEX_BUILT_KEY):
        return 0
    ids: list[str] = []
    for name in QUEUE_NAMES:
        q = get_queue(redis, name)
        ids += q.get_job_ids()
        for reg in (q.scheduled_job_registry, q.deferred_job_registry, q.started_job_registry,
                    q.finished_job_registry, q.failed_job_registry, q.canceled_job_registry):
            ids += reg.get_job_ids(cleanup=False)
    ids = list(dict.fromkeys(ids))
    n = 0
    for i in range(0, len(ids), batch):
        chunk = ids[i:i + batch]
        jobs, _ = _listed_jobs(redis, chunk, None)
        with redis.pipeline(transaction=False) as p:
            for jid in chunk:
                p.smembers(job_owners_key(jid))
            askers = p.execute()
        with redis.pipeline(transaction=False) as p:
            for jid, job, asked in zip(chunk, jobs, askers, strict=True):
                if job is None:
                    continue
                when = job.created_at.replace(tzinfo=job.created_at.tzinfo or UTC) if job.created_at else None
                score = int(when.timestamp() * 1_000_000) if when else time.time_ns() // 1000
                first = job.meta.get("owner")
                owners = {_text(a) for a in cast(set[Any], asked)}
                if isinstance(first, str) and first:
                    owners.add(first)
                for owner in (None, *sorted(owners)):
                    p.zadd(job_index_key(owner), {jid: score}, nx=True)
                    p.expire(job_index_key(owner), JOB_INDEX_HORIZON_S)
                n += 1
            p.execute()
    redis.set(JOB_INDEX_BUILT_KEY, "1")
    return n


def list_jobs(
    redis: Redis,
    owner: str | None = None,
    states: Iterable[JobState] | None = None,
    kinds: Iterable[QueueName] = QUEUE_NAMES,
    limit: int = 100,
) -> list[JobPublic]:
    """The first page of ``list_jobs_page``: up to ``limit`` jobs, newest first."""
    return list_jobs_page(redis, owner, states, kinds, limit)[0]


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


def job_method(job: Job) -> str:
    """A job's method label: a render's ``RenderRequest.method`` (``reference``, ``ldc+llf``,
    ...), a bake's role (``bake-plan`` / ``bake-part`` / ``bake-merge``), else its kind
    (``walkthrough-chunk``, ``dataset-bake``, ...) or, last, its function's name."""
    meta = job.meta
    if meta.get("kind") == "render":
        try:
            payload = job.args[0] if job.args else None
        except Exception:  # an unreadable payload still gets a label
            payload = None
        req = payload.get("request") if isinstance(payload, dict) else None
        method = req.get("method", "reference") if isinstance(req, dict) else None
        return method if isinstance(method, str) and method else "reference"
    role = meta.get("bake_role")
    if isinstance(role, str) and role:
        return f"bake-{role}"
    kind = meta.get("kind")
    if isinstance(kind, str) and kind:
        return kind
    try:
        return str(job.func_name).rsplit(".", 1)[-1]
    except Exception:
        return "unknown"


def record_job_duration(redis: Redis, queue: str, method: str, outcome: JobState, seconds: float) -> None:
    """Observe one job's run time in the Redis-backed histogram (``JOB_SECONDS_KEY``): called by the
    worker where the job ran, so every worker process (and every forked horse) adds to the same
    monotonic counters, which ``GET /metrics`` exposes as a Prometheus histogram."""
    prefix = _SEP.join((queue, method, outcome))
    with redis.pipeline(transaction=True) as p:
        for le in JOB_SECONDS_BUCKETS:
            if seconds <= le:
                p.hincrby(JOB_SECONDS_KEY, f"{prefix}{_SEP}{le:g}", 1)
        p.hincrby(JOB_SECONDS_KEY, f"{prefix}{_SEP}+Inf", 1)
        p.hincrbyfloat(JOB_SECONDS_KEY, f"{prefix}{_SEP}sum", max(0.0, seconds))
        p.execute()


def job_duration_histograms(redis: Redis) -> dict[tuple[str, str, str], tuple[list[tuple[str, float]], float]]:
    """The histograms ``record_job_duration`` keeps: (queue, method, outcome) -> (cumulative
    ``[(le, count), ..., ("+Inf", count)]``, sum of seconds)."""
    raw = redis.hgetall(JOB_SECONDS_KEY)
    series: dict[tuple[str, str, str], dict[str, float]] = {}
    for field, value in raw.items():
        parts = (field.decode() if isinstance(field, bytes) else field).split(_SEP)
        if len(parts) != 4:
            continue
        series.setdefault((parts[0], parts[1], parts[2]), {})[parts[3]] = float(value)
    out: dict[tuple[str, str, str], tuple[list[tuple[str, float]], float]] = {}
    for labels, fields in series.items():
        buckets = [(f"{le:g}", fields.get(f"{le:g}", 0.0)) for le in JOB_SECONDS_BUCKETS]
        buckets.append(("+Inf", fields.get("+Inf", 0.0)))
        out[labels] = (buckets, fields.get("sum", 0.0))
    return out


def failed_and_canceled(redis: Redis, queue: QueueName) -> tuple[int, int]:
    """How many jobs of ``queue``'s failed registry failed, and how many were canceled on request
    (a started job that stops on its cancel flag, a bake horse stopped by the cancel, land in RQ's
    failed registry): the same split as ``job_state`` gives ``/v1/jobs``."""
    q = get_queue(redis, queue)
    ids = q.failed_job_registry.get_job_ids(cleanup=False)
    jobs = [j for j in Job.fetch_many(ids, connection=redis, serializer=JSONSerializer) if j is not None]
    with redis.pipeline(transaction=False) as p:
        for job in jobs:
            p.exists(cancel_key(job.id))
        flags = p.execute()
    canceled = sum(1 for job, flag in zip(jobs, flags, strict=True)
                   if job.get_status(refresh=False) == JobStatus.STOPPED or job.meta.get("cancel_requested") or flag)
    return len(ids) - canceled, canceled
