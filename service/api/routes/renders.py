"""``/v1/renders``: a render request answered from the artifact cache or by a (shared) job."""

from __future__ import annotations

import asyncio
import time
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Query, Response
from fastapi.concurrency import run_in_threadpool
from rq.job import Job

from api_schemas.errors import FieldError
from api_schemas.service import ArtifactManifest, BakePublic, JobPublic, RenderPublic, RenderRequest, method_needs_bake
from service.api.deps import MetricsDep, OwnerDep, RedisDep, SettingsDep, StoreDep, scene_visible
from service.api.errors import ValidationProblem, problem_responses
from workers.artifacts import get_scene, read_manifest
from workers.queues import enqueue_render, fetch_job, job_public
from workers.store import NotFound

router = APIRouter(prefix="/v1/renders", tags=["renders"])

MAX_WAIT_S = 60.0
# Waiting for a job: one HGET of its status every 5..20 ms for the first 2 s (interactive LDC
# views finish in a few hundred ms; a coarse back-off answered them up to 170 ms late), then
# every 250 ms.
_POLL_FIRST_S = 0.005
_POLL_FINE_MAX_S = 0.02
_POLL_FINE_S = 2.0
_POLL_SLOW_S = 0.25
_ENDED_STATUSES = {b"finished", b"failed", b"canceled", b"stopped"}

_STATUS: dict[str, Literal["queued", "running", "finished", "failed"]] = {
    "queued": "queued", "started": "running", "finished": "finished", "failed": "failed", "canceled": "failed",
}

RENDER_EXAMPLE: dict[str, Any] = {
    "scene_id": "0" * 64,
    "params": {"spp": 4, "max_depth": 4, "seed": 0},
}


def artifact_links(key: str) -> dict[str, str]:
    base = f"/v1/artifacts/{key}"
    return {"artifact": base, "image.exr": f"{base}/image.exr", "image.png": f"{base}/image.png"}


def _answer(key: str, job: JobPublic | None, manifest: ArtifactManifest | None, cached: bool) -> RenderPublic:
    links = artifact_links(key)
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
        **problem_responses(400, 401, 404, 409, 413, 422, 429, 503),
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
    bake = await run_in_threadpool(_bake_of, req, job, redis, store)
    public = await _wait_for(job, wait)
    if public.state == "finished":
        manifest = await run_in_threadpool(read_manifest, store, key)
        if manifest is not None:
            return _answer(key, public, manifest, cached=False)
    if public.state in ("failed", "canceled"):
        return _answer(key, public, None, cached=False).model_copy(update={"bake": bake})
    response.status_code = 202
    response.headers["Location"] = f"/v1/jobs/{public.id}"
    return _answer(key, public, None, cached=False).model_copy(update={"bake": bake})


def _bake_of(req: RenderRequest, job: Job, redis: Any, store: Any) -> BakePublic | None:
    """The bake an LDC render's job waits for (``missing_bake: "bake"``); None otherwise (no store
    reads on the common path: a render of a finished bake)."""
    if not method_needs_bake(req.method) or not job.meta.get("waits_for_bake"):
        return None
    from workers.bakes import bake_key, bake_status

    pub = bake_status(redis, store, req.scene_id, bake_key(req.scene_id, req.bake), req.bake)
    return None if pub.state == "finished" else pub


async def _wait_for(job: Job, wait: float) -> JobPublic:
    """Wait until the job ends or ``wait`` seconds pass; its last public state."""
    public = await run_in_threadpool(job_public, job)
    if public.state not in ("queued", "started") or wait <= 0:
        return public
    started = time.monotonic()
    deadline = started + wait
    delay = _POLL_FIRST_S
    while time.monotonic() < deadline:
        await asyncio.sleep(min(delay, max(0.0, deadline - time.monotonic())))
        elapsed = time.monotonic() - started
        delay = min(_POLL_FINE_MAX_S if elapsed < _POLL_FINE_S else _POLL_SLOW_S, delay * 1.5)
        status = await run_in_threadpool(job.connection.hget, job.key, "status")
        if status is None or status in _ENDED_STATUSES:  # gone, or ended
            break
    fresh = await run_in_threadpool(fetch_job, job.connection, job.id)
    return await run_in_threadpool(job_public, fresh) if fresh is not None else public
