"""``/v1/jobs``: RQ jobs (renders and bakes), their progress, results and cancellation."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Path, Query
from redis import Redis

from api_schemas.errors import FieldError
from api_schemas.service import JobId, JobList, JobPublic, JobState
from producer.cancel import cancel_for
from producer.errors import JobNotCancelable, JobNotFound
from producer.ownership import job_owners
from producer.queue import fetch_job
from producer.status import BadCursor, job_public, list_jobs_page
from service.api.deps import OwnerDep, RedisDep
from service.api.errors import MissingResource, ValidationProblem, problem_responses

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

JobIdPath = Annotated[JobId, Path(description="Job id, e.g. render-<artifact key>")]


def _visible_job_or_404(redis: Redis, job_id: str, owner: str | None) -> JobPublic:
    job = fetch_job(redis, job_id)
    if job is None:
        raise MissingResource("path.job_id", job_id)
    if owner is not None and job.meta.get("owner") != owner and owner not in job_owners(redis, job_id):
        raise MissingResource("path.job_id", job_id)  # another key's job: do not reveal it exists
    return job_public(job)


@router.get("", response_model=JobList, responses=problem_responses(401, 422, 429, 503))
def list_my_jobs(
    redis: RedisDep,
    owner: OwnerDep,
    state: Annotated[list[JobState] | None, Query(description="Only jobs in these states")] = None,
    limit: Annotated[int, Query(ge=1, le=1000, description="Jobs per page at most")] = 100,
    cursor: Annotated[str | None, Query(max_length=160, description="The next_cursor of the previous page")] = None,
) -> JobList:
    """Jobs this API key asked for, newest first, a page at a time: follow ``next_cursor`` until
    it is null. With a ``state`` filter a page may hold fewer than ``limit`` jobs (each request
    scans a bounded part of the key's jobs) while ``next_cursor`` is not null."""
    try:
        items, nxt = list_jobs_page(redis, owner=owner, states=state, limit=limit, cursor=cursor)
    except BadCursor as exc:
        raise ValidationProblem([FieldError(field="query.cursor", message=str(exc), type="invalid_cursor")]) from None
    return JobList(items=items, next_cursor=nxt)


@router.get("/{job_id}", response_model=JobPublic, responses=problem_responses(401, 404, 422, 429, 503))
def read_job(job_id: JobIdPath, redis: RedisDep, owner: OwnerDep) -> JobPublic:
    """One job: state, progress, error or result."""
    return _visible_job_or_404(redis, job_id, owner)


@router.post(
    "/{job_id}/cancel", response_model=JobPublic, responses=problem_responses(401, 404, 409, 422, 429, 503)
)
def cancel_job(job_id: JobIdPath, redis: RedisDep, owner: OwnerDep) -> JobPublic:
    """Cancel a queued or running job (409 when it already ended). A job shared by identical
    requests of several API keys is canceled once every one of them has canceled it; until then the
    answer shows it still queued or running (for the others)."""
    _visible_job_or_404(redis, job_id, owner)
    try:
        return cancel_for(redis, job_id, owner)
    except JobNotFound:
        raise MissingResource("path.job_id", job_id) from None
    except JobNotCancelable as exc:
        raise HTTPException(409, str(exc)) from None
