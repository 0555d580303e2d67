"""``/v1/renders``: a render request answered from the artifact cache or by a (shared) job."""

from __future__ import annotations

import asyncio
import time
import weakref
from collections.abc import Collection
from typing import Annotated, Any, Literal

import anyio
import anyio.to_thread
from fastapi import APIRouter, Body, Query, Response
from fastapi.concurrency import run_in_threadpool
from redis import Redis
from rq.job import Job

from api_schemas.errors import FieldError
from api_schemas.service import ArtifactManifest, BakePublic, JobPublic, RenderPublic, RenderRequest, method_needs_bake
from service.api.deps import MetricsDep, OwnerDep, RedisDep, SettingsDep, StoreDep, scene_visible
from service.api.errors import ValidationProblem, problem_responses
from workers.artifacts import get_scene, read_manifest
from workers.queues import enqueue_render, fetch_job, job_public, render_artifact_key
from workers.store import NotFound

router = APIRouter(prefix="/v1/renders", tags=["renders"])

MAX_WAIT_S = 60.0
# Waiting for a job: block on RQ's result stream of the job (``rq:results:<job id>``; the worker
# writes the result and the job's final status in one MULTI/EXEC) with XREAD BLOCK, in slices of
# at most _WAIT_SLICE_S, re-reading the job's status after each slice. The wait ends as soon as RQ
# has written the result (measured: 2.5 ms after RQ's end stamp, which comes before its own
# bookkeeping; polling answered 5-20 ms late); a job that ends without a result (canceled, stopped, its
# worker died and maintenance failed it, deleted) is noticed by the status read at the end of the
# slice. Blocking reads run on their own thread limiter (_WAIT_THREADS per event loop), so waiting
# requests never take the threads other endpoints run on; a slice frees its thread every 250 ms.
_WAIT_SLICE_S = 0.25
_WAIT_THREADS = 32
_ENDED_STATUSES = {b"finished", b"failed", b"canceled", b"stopped"}
_limiters: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, anyio.CapacityLimiter] = weakref.WeakKeyDictionary()

_STATUS: dict[str, Literal["queued", "running", "finished", "failed"]] = {
    "queued": "queued", "started": "running", "finished": "finished", "failed": "failed", "canceled": "failed",
}

RENDER_EXAMPLE: dict[str, Any] = {
    "scene_id": "0" * 64,
    "params": {"spp": 4, "max_depth": 4, "seed": 0},
}


BAKE_MISSING_409: dict[int | str, dict[str, Any]] = {409: {
    **problem_responses(409)[409],
    "description": "Bake missing: an LDC method (`ldc`, `ldc+llf`, `ldc+ibrt:k`) asked for a bake of the scene that "
                   "does not exist yet and `missing_bake` is `fail`. The problem (type "
                   "`urn:ibr:problem:bake-missing`) names the bake to request with POST /v1/scenes/{scene_id}/bakes "
                   "(or send `missing_bake: bake`).",
}}
"""OpenAPI entry of the 409 of the render endpoints (``POST /v1/renders``, ``POST /v1/batches``)."""


_LINKED_BLOBS = (("image.exr", "radiance.exr"), ("image.png", "preview.png"), ("provenance.png", "provenance.png"))


def artifact_links(key: str, blobs: Collection[str] = ("radiance.exr", "preview.png")) -> dict[str, str]:
    """The artifact's URLs: its manifest and the images it holds (``blobs``: blob names)."""
    base = f"/v1/artifacts/{key}"
    return {"artifact": base, **{link: f"{base}/{link}" for link, blob in _LINKED_BLOBS if blob in blobs}}


def _answer(key: str, job: JobPublic | None, manifest: ArtifactManifest | None, cached: bool,
            outputs: Collection[str] | None = None) -> RenderPublic:
    if manifest is not None:
        links = artifact_links(key, [b.name for b in manifest.blobs])
    else:  # not rendered yet: what the request asked for
        links = artifact_links(key, ("radiance.exr", "preview.png") if outputs is None else
                               [f"{o}.exr" if o == "radiance" else f"{o}.png" for o in outputs])
    if job is not None:
        links["job"] = f"/v1/jobs/{job.id}"
    if manifest is not None:
        return RenderPublic(artifact_key=key, status="cached" if cached else "finished", job=job,
                            artifact=manifest, links=links)
    assert job is not None
    return RenderPublic(artifact_key=key, status=_STATUS[job.state], job=job, links=links)


def _check_request(req: RenderRequest, store: Any, owner: str | None, max_pixels: int) -> None:
    if not scene_visible(store, req.scene_id, owner):
        raise NotFound(req.scene_id)
    scene, _, _ = get_scene(store, req.scene_id)  # NotFound -> 404
    cam = req.camera if req.camera is not None else scene.camera
    if cam.width * cam.height > max_pixels:
        where = "camera.height" if req.camera is not None else "scene_id"
        raise ValidationProblem([FieldError(
            field=where,
            message=f"image of {cam.width} x {cam.height} = {cam.width * cam.height} pixels exceeds this "
                    f"server's limit of {max_pixels}",
            type="image_too_large",
        )])


@router.post(
    "",
    response_model=RenderPublic,
    responses={
        200: {"description": "The artifact: cached, or rendered within `wait` seconds (or the job failed)"},
        202: {"model": RenderPublic, "description": "Queued or running; poll the job named by Location",
              "headers": {"Location": {"schema": {"type": "string"}, "description": "The job's URL"}}},
        **problem_responses(400, 401, 404, 413, 422, 429, 503),
        **BAKE_MISSING_409,
    },
)
async def request_render(
    req: Annotated[RenderRequest, Body(openapi_examples={"default": {"summary": "Render a stored scene",
                                                                      "value": RENDER_EXAMPLE}})],
    response: Response,
    store: StoreDep,
    redis: RedisDep,
    owner: OwnerDep,
    settings: SettingsDep,
    metrics: MetricsDep,
    wait: Annotated[float, Query(ge=0, le=MAX_WAIT_S, description="Seconds to wait for the result (0..60)")] = 0,
) -> RenderPublic:
    """Render a stored scene: 200 with the artifact when cached or done within `wait`, else 202 and the job."""
    await run_in_threadpool(_check_request, req, store, owner, settings.max_image_pixels)
    if req.outputs is not None:  # a subset of the images: the full artifact, when it exists, holds them
        full_key = render_artifact_key(req.model_copy(update={"outputs": None}))
        manifest = await run_in_threadpool(read_manifest, store, full_key)
        if manifest is not None:
            metrics.render_cache.labels("hit").inc()
            return _answer(full_key, None, manifest, cached=True)
    key, job = await run_in_threadpool(enqueue_render, redis, req, owner, store=store)  # BakeMissing: 409
    if job is None:
        manifest = await run_in_threadpool(read_manifest, store, key)
        if manifest is not None:
            metrics.render_cache.labels("hit").inc()
            return _answer(key, None, manifest, cached=True)
        # the artifact vanished between the two reads (invalidated): queue it again
        key, job = await run_in_threadpool(enqueue_render, redis, req, owner, store=store)
        if job is None:
            manifest = await run_in_threadpool(read_manifest, store, key)
            if manifest is not None:
                metrics.render_cache.labels("hit").inc()
                return _answer(key, None, manifest, cached=True)
            raise NotFound(key)
    metrics.render_cache.labels("miss").inc()
    bake = None
    if method_needs_bake(req.method) and job.meta.get("waits_for_bake"):
        bake = await run_in_threadpool(_bake_of, req, job, redis, store)
    public, manifest = await _wait_for(job, wait, store, key)
    if public.state == "finished" and manifest is not None:
        return _answer(key, public, manifest, cached=False)
    if public.state in ("failed", "canceled"):
        return _answer(key, public, None, cached=False, outputs=req.outputs).model_copy(update={"bake": bake})
    response.status_code = 202
    response.headers["Location"] = f"/v1/jobs/{public.id}"
    return _answer(key, public, None, cached=False, outputs=req.outputs).model_copy(update={"bake": bake})


def _bake_of(req: RenderRequest, job: Job, redis: Any, store: Any) -> BakePublic | None:
    """The bake an LDC render's job waits for (``missing_bake: "bake"``); None otherwise (no store
    reads on the common path: a render of a finished bake)."""
    if not method_needs_bake(req.method) or not job.meta.get("waits_for_bake"):
        return None
    from workers.bakes import bake_key, bake_status

    pub = bake_status(redis, store, req.scene_id, bake_key(req.scene_id, req.bake), req.bake)
    return None if pub.state == "finished" else pub


def _wait_limiter() -> anyio.CapacityLimiter:
    loop = asyncio.get_running_loop()
    limiter = _limiters.get(loop)
    if limiter is None:
        limiter = _limiters[loop] = anyio.CapacityLimiter(_WAIT_THREADS)
    return limiter


def _result_stream(job_id: str) -> str:
    from rq.results import Result

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


def _end_state(job: Job, public: JobPublic, store: Any, key: str) -> tuple[JobPublic, ArtifactManifest | None]:
    fresh = fetch_job(job.connection, job.id)
    if fresh is not None:
        public = job_public(fresh)
    return public, read_manifest(store, key) if public.state == "finished" else None


async def _wait_for(job: Job, wait: float, store: Any, key: str) -> tuple[JobPublic, ArtifactManifest | None]:
    """Wait until the job ends or ``wait`` seconds pass: its last public state, and the artifact's
    manifest when it finished. (Few thread hops: each costs ~0.5 ms on a loaded machine.)"""
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
                                                         min(_WAIT_SLICE_S, remaining), limiter=limiter)
    return await run_in_threadpool(_end_state, job, public, store, key)
