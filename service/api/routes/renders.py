"""``/v1/renders``: a render request answered from the artifact cache or by a (shared) job."""

from __future__ import annotations

from collections.abc import Collection
from functools import partial
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Query, Response
from fastapi.concurrency import run_in_threadpool
from rq.job import Job

from api_schemas.errors import FieldError
from api_schemas.scene import Scene
from api_schemas.service import (
    ArtifactManifest,
    BakePublic,
    ContractPublic,
    JobPublic,
    RenderPublic,
    RenderRequest,
    method_needs_bake,
)
from producer.artifacts import read_manifest
from producer.bakes import bake_key, bake_status
from producer.calibrations import enqueue_verification, plan_render, verification_status
from producer.costs import (
    Cost,
    Limits,
    check,
    render_cost,
    scene_auto_glossy_rays,
    scene_light_traced,
    stored_scene,
)
from producer.renders import enqueue_render, render_artifact_key
from producer.store import NotFound
from producer.wait import wait_for_job
from service.api.deps import MetricsDep, OwnerDep, RedisDep, SettingsDep, StoreDep, scene_visible
from service.api.errors import MissingResource, ValidationProblem, problem_responses

router = APIRouter(prefix="/v1/renders", tags=["renders"])

MAX_WAIT_S = 60.0

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


def achieved_ms(manifest: ArtifactManifest | None) -> float | None:
    """The render's time in the worker (the renderer's call), from an artifact's result."""
    if manifest is None:
        return None
    timings = manifest.result.get("timings") or {}
    wall = timings.get("render_wall")
    return 1000.0 * float(wall) if isinstance(wall, (int, float)) else None


def _with_contract(pub: RenderPublic, contract: ContractPublic | None) -> RenderPublic:
    if contract is None:
        return pub
    return pub.model_copy(update={"contract": contract.model_copy(update=contract_outcome(contract, pub.artifact))})


def contract_outcome(contract: ContractPublic, manifest: ArtifactManifest | None) -> dict[str, Any]:
    """What the render achieved, from its artifact: ``achieved_ms`` and, for the adaptive reference,
    ``estimated_error`` (its own estimate times the calibrated ``error_scale``)."""
    out: dict[str, Any] = {"achieved_ms": achieved_ms(manifest)}
    if contract.estimated_error_source == "render" and manifest is not None and contract.error_scale is not None:
        est = (manifest.result.get("adaptive") or {}).get("estimated_error")
        if isinstance(est, (int, float)):
            out["estimated_error"] = contract.error_scale * float(est)
    return out


def _check_visible(req: RenderRequest, store: Any, owner: str | None) -> None:
    if not scene_visible(store, req.scene_id, owner):
        raise MissingResource("scene_id", req.scene_id)


def time_error(req: RenderRequest, scene: Scene, prefix: str = "") -> FieldError | None:
    """The problem of the request's animation ``time`` against its scene: a scene without animation, or a
    time outside ``[animation.start, animation.end]`` (the worker's ``AnimatedScene.check_time`` refuses
    the same, this answers before anything is queued)."""
    if req.time is None:
        return None
    anim = scene.animation
    if anim is None:
        return FieldError(field=prefix + "time", type="no_animation",
                          message="the scene has no animation, so there is no moment to render: leave out time")
    if not anim.start <= req.time <= anim.end:
        return FieldError(field=prefix + "time", type="time_out_of_range",
                          message=f"time {req.time:g} is outside the animation interval "
                                  f"[{anim.start:g}, {anim.end:g}]")
    return None


def _check_request(req: RenderRequest, store: Any, owner: str | None, settings: Any) -> Cost:
    """The render's estimated cost (``producer.costs``); 422 when the image or the estimate is over this
    server's limits."""
    _check_visible(req, store, owner)
    try:
        scene, triangles = stored_scene(store, req.scene_id)
    except NotFound:
        raise MissingResource("scene_id", req.scene_id) from None
    problem = time_error(req, scene)
    if problem is not None:
        raise ValidationProblem([problem])
    cam = req.camera if req.camera is not None else scene.camera
    where = "camera.height" if req.camera is not None else "scene_id"
    if cam.width * cam.height > settings.max_image_pixels:
        raise ValidationProblem([FieldError(
            field=where,
            message=f"image of {cam.width} x {cam.height} = {cam.width * cam.height} pixels exceeds this "
                    f"server's limit of {settings.max_image_pixels}",
            type="image_too_large",
        )])
    cost = render_cost(req, cam.width, cam.height, triangles, scene_auto_glossy_rays(scene),
                       scene_light_traced(scene, cam))
    lower = "render a smaller image" + ("" if method_needs_bake(req.method) else " or with fewer samples")
    return check(cost, Limits.for_job(settings, "render"), where, lower, "render_too_large")


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
    """Render a stored scene: 200 with the artifact when cached or done within `wait`, else 202 and the job.
    With `quality` instead of a method, the planner picks the method from the scene's calibration
    (409 when there is none) and the answer's `contract` states the plan."""
    contract: ContractPublic | None = None
    if req.quality is not None:
        await run_in_threadpool(_check_visible, req, store, owner)
        req, planned = await run_in_threadpool(partial(  # 409/422
            plan_render, redis, store, req, settings.max_render_bytes, error_margin=settings.contract_error_margin,
            time_margin=settings.contract_time_margin))
        contract = planned
        if planned.verify and req.outputs is not None and "radiance" not in req.outputs:  # the measurement reads it
            req = RenderRequest.model_validate({**req.model_dump(mode="json"), "outputs": [*req.outputs, "radiance"]})
    pub = await _render(req, response, store, redis, owner, settings, metrics, wait, contract)
    if contract is not None and contract.verify and pub.status not in ("failed", "canceled"):
        await run_in_threadpool(enqueue_verification, redis, store, req, pub.artifact_key, contract, owner)
        verification = await run_in_threadpool(verification_status, redis, store, req.scene_id, pub.artifact_key)
        contract = contract.model_copy(update={"verification": verification})
    return _with_contract(pub, contract)


async def _render(req: RenderRequest, response: Response, store: Any, redis: Any, owner: str | None, settings: Any,
                  metrics: Any, wait: float, contract: ContractPublic | None) -> RenderPublic:
    await run_in_threadpool(_check_request, req, store, owner, settings)
    if req.outputs is not None:  # a subset of the images: the full artifact, when it exists, holds them
        full_key = render_artifact_key(req.model_copy(update={"outputs": None}))
        manifest = await run_in_threadpool(read_manifest, store, full_key)
        if manifest is not None:
            metrics.render_cache.labels("hit").inc()
            return _answer(full_key, None, manifest, cached=True)
    key, job = await run_in_threadpool(partial(enqueue_render, redis, req, owner, store=store,
                                               contract=contract))  # BakeMissing: 409
    if job is None:
        manifest = await run_in_threadpool(read_manifest, store, key)
        if manifest is not None:
            metrics.render_cache.labels("hit").inc()
            return _answer(key, None, manifest, cached=True)
        # the artifact vanished between the two reads (invalidated): queue it again
        key, job = await run_in_threadpool(partial(enqueue_render, redis, req, owner, store=store, contract=contract))
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
    public, manifest = await wait_for_job(job, wait, store, key)
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
    pub = bake_status(redis, store, req.scene_id, bake_key(req.scene_id, req.bake), req.bake)
    return None if pub.state == "finished" else pub
