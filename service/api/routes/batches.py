"""``/v1/batches``: many scenes and renders in one call, tracked together."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, HTTPException, Path, Response
from fastapi.concurrency import run_in_threadpool
from redis import Redis

from api_schemas.errors import FieldError
from api_schemas.service import BatchPublic, BatchRequest, JobId
from producer.artifacts import mesh_paths, scene_id_for, store_scene
from producer.batches import batch_owner, batch_status, enqueue_batch
from producer.listings import index_scene
from producer.settings import Settings
from producer.store import ObjectStore
from service.api.deps import OwnerDep, RedisDep, SettingsDep, StoreDep, add_scene_owner, scene_visible
from service.api.errors import ValidationProblem, problem_responses
from service.api.routes.renders import BAKE_MISSING_409
from service.api.routes.scenes import SAMPLE_SCENE, limit_errors

router = APIRouter(prefix="/v1/batches", tags=["batches"])

BATCH_EXAMPLE: dict[str, Any] = {
    "scenes": [{"scene": SAMPLE_SCENE}],
    "renders": [],
}


def _submit(store: ObjectStore, redis: Redis, batch: BatchRequest, owner: str | None,
            settings: Settings) -> BatchPublic:
    # Validate everything before writing anything: a bad entry stores no scene and queues no job.
    errors: list[FieldError] = []
    new_ids: list[str] = []
    for i, sc in enumerate(batch.scenes):
        errors += limit_errors(sc.scene, settings, prefix=f"scenes.{i}.scene")
        for path in mesh_paths(sc.scene):
            errors.append(FieldError(
                field=f"scenes.{i}.scene",
                message=f"mesh file {path!r}: scenes with mesh files must be uploaded to POST /v1/scenes "
                        "(multipart); reference them here by scene_id",
                type="missing_file",
            ))
        new_ids.append(scene_id_for(sc.scene, {}))
    known = set(new_ids)
    for j, req in enumerate(batch.renders):
        if req.scene_id not in known:
            if scene_visible(store, req.scene_id, owner) and store.exists(f"scenes/{req.scene_id}.json"):
                known.add(req.scene_id)
            else:
                errors.append(FieldError(field=f"renders.{j}.scene_id", message=f"no scene {req.scene_id}",
                                         type="unknown_scene"))
        if req.quality is not None:
            errors.append(FieldError(
                field=f"renders.{j}.quality",
                message="quality contracts are planned one request at a time: send this render to POST /v1/renders, "
                        "or name its method here",
                type="quality_in_batch",
            ))
        if req.camera is not None and req.camera.width * req.camera.height > settings.max_image_pixels:
            errors.append(FieldError(
                field=f"renders.{j}.camera.height",
                message=f"width * height exceeds this server's limit of {settings.max_image_pixels} pixels",
                type="image_too_large",
            ))
    if errors:
        raise ValidationProblem(errors)
    for sc in batch.scenes:
        public, _ = store_scene(store, sc.scene, {}, owner)
        add_scene_owner(store, public.id, owner)
        index_scene(store, public, owner)
    return enqueue_batch(redis, list(batch.renders), owner, store=store, scene_ids=list(dict.fromkeys(new_ids)))


@router.post(
    "",
    response_model=BatchPublic,
    status_code=202,
    responses={**problem_responses(400, 401, 413, 422, 429, 503), **BAKE_MISSING_409},
)
async def create_batch(
    batch: Annotated[BatchRequest, Body(openapi_examples={"default": {"summary": "One scene, no renders yet",
                                                                       "value": BATCH_EXAMPLE}})],
    response: Response,
    store: StoreDep,
    redis: RedisDep,
    owner: OwnerDep,
    settings: SettingsDep,
) -> BatchPublic:
    """Store scenes and queue renders in one call; poll the batch for progress."""
    public = await run_in_threadpool(_submit, store, redis, batch, owner, settings)
    response.headers["Location"] = f"/v1/batches/{public.id}"
    return public


@router.get("/{batch_id}", response_model=BatchPublic, responses=problem_responses(401, 404, 422, 429, 503))
def read_batch(
    batch_id: Annotated[JobId, Path(description="Batch id")], store: StoreDep, redis: RedisDep, owner: OwnerDep
) -> BatchPublic:
    """A batch: each render's state, counts per state and overall progress."""
    if owner is not None and batch_owner(redis, batch_id) != owner:
        raise HTTPException(404, f"no batch {batch_id}")
    status = batch_status(redis, batch_id, store=store)
    if status is None:
        raise HTTPException(404, f"no batch {batch_id}")
    return status
