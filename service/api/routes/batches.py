"""``/v1/batches``: many scenes and renders in one call, tracked together.

A batch is JSON (``BatchRequest``), or ``multipart/form-data`` when its scenes have mesh files: a
part ``batch`` (the same JSON) and one file part per mesh file of scene ``i``, named
``scenes.<i>.<mesh_file path>``. :class:`BatchRoute` turns the multipart form into the JSON body
FastAPI validates (so both forms share one model and one OpenAPI schema) and hands the mesh files
to the route by scene index.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Coroutine, Mapping
from typing import Annotated, Any

from fastapi import APIRouter, Body, HTTPException, Path, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.routing import APIRoute
from redis import Redis
from starlette.types import Scope

from api_schemas.errors import FieldError
from api_schemas.scene import MeshFileObject
from api_schemas.service import BatchPublic, BatchRequest, JobId
from producer.artifacts import mesh_paths, scene_id_for, sha256_hex, store_scene
from producer.batches import batch_owner, batch_status, enqueue_batch
from producer.costs import (
    Cost,
    CostOverLimit,
    Limits,
    batch_cost,
    check,
    mesh_triangles,
    render_cost,
    scene_auto_glossy_rays,
    scene_light_traced,
    scene_triangles,
    stored_scene,
)
from producer.listings import index_scene
from producer.settings import Settings
from producer.store import NotFound, ObjectStore
from service.api.deps import OwnerDep, RedisDep, SettingsDep, StoreDep, add_scene_owner, scene_visible
from service.api.errors import ValidationProblem, problem_responses
from service.api.limits import read_multipart
from service.api.routes.renders import BAKE_MISSING_409, time_error
from service.api.routes.scenes import SAMPLE_SCENE, limit_errors, mesh_problem

BATCH_PART = "batch"
_MESH_PART = re.compile(r"scenes\.(0|[1-9][0-9]{0,5})\.(.+)", re.S)

SceneFiles = dict[int, dict[str, bytes]]
"""Mesh files of a multipart batch: scene index -> ``mesh_file`` path -> bytes."""


class _BatchJsonRequest(Request):
    """The ``batch`` part of a multipart batch, seen by FastAPI as a JSON body."""

    def __init__(self, scope: Scope, body: bytes) -> None:
        super().__init__(scope)
        self._batch_json = body

    async def body(self) -> bytes:
        return self._batch_json


async def _multipart_batch(request: Request) -> Request:
    """The request with its ``batch`` part as a JSON body and its mesh files in ``state.scene_files``."""
    settings: Settings = request.app.state.settings
    parts = await read_multipart(request, max_part_bytes=settings.max_upload_bytes,
                                 max_parts=settings.max_upload_files + 1,
                                 field_limits={BATCH_PART: settings.json_limit_bytes})
    batch_parts = [p for p in parts if p.name == BATCH_PART]
    errors: list[FieldError] = []
    if len(batch_parts) != 1:
        errors.append(FieldError(
            field=BATCH_PART, message=f"exactly one part named {BATCH_PART!r} (the batch JSON) is required"
                                      + (f"; found {len(batch_parts)}" if batch_parts else ""),
            type="missing" if not batch_parts else "duplicate_part"))
    files: SceneFiles = {}
    for part in parts:
        if part.name == BATCH_PART:
            continue
        m = _MESH_PART.fullmatch(part.name)
        if m is None:
            errors.append(FieldError(
                field=f"files.{part.name[:200]}", type="unexpected_part",
                message=f"file part {part.name[:200]!r}: name each mesh file part scenes.<i>.<mesh_file path>, "
                        "with i the scene's index in the batch"))
            continue
        scene_files = files.setdefault(int(m.group(1)), {})
        if m.group(2) in scene_files:
            errors.append(FieldError(field=f"files.{part.name}", message=f"file part {part.name!r} sent twice",
                                     type="duplicate_part"))
        scene_files[m.group(2)] = part.data
    if errors:
        raise ValidationProblem(errors)
    headers = [(k, v) for k, v in request.scope["headers"] if k not in (b"content-type", b"content-length")]
    scope = {**request.scope, "headers": [*headers, (b"content-type", b"application/json")]}
    scope.setdefault("state", {})["scene_files"] = files
    return _BatchJsonRequest(scope, batch_parts[0].data)


class BatchRoute(APIRoute):
    """Routes that also take a batch as ``multipart/form-data`` (see the module docstring). The form
    is read before the route's dependencies run (API key, rate limit), as FastAPI reads a JSON body,
    under the same body limit."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handle = super().get_route_handler()

        async def route_handler(request: Request) -> Response:
            ctype = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
            if request.method == "POST" and ctype == "multipart/form-data":
                request = await _multipart_batch(request)
            return await handle(request)

        return route_handler


router = APIRouter(prefix="/v1/batches", tags=["batches"], route_class=BatchRoute)

_MULTIPART_SCHEMA: dict[str, Any] = {
    "type": "object",
    "required": [BATCH_PART],
    "properties": {BATCH_PART: {"type": "string", "description": "The batch JSON (a BatchRequest)"}},
    "additionalProperties": {
        "type": "string",
        "format": "binary",
        "description": "One file part per mesh_file path of each scene, named scenes.<i>.<path> (i: the "
                       "scene's index in the batch's scenes)",
    },
}

BATCH_EXAMPLE: dict[str, Any] = {
    "scenes": [{"scene": SAMPLE_SCENE}],
    "renders": [],
}


def _mesh_errors(batch: BatchRequest, files: Mapping[int, Mapping[str, bytes]]) -> list[FieldError]:
    """Each scene's mesh files against its ``mesh_file`` paths: missing, unreferenced, or files a
    worker would refuse."""
    errors: list[FieldError] = []
    for i in sorted(set(files) - set(range(len(batch.scenes)))):
        errors.append(FieldError(field=f"files.scenes.{i}", type="unexpected_part",
                                 message=f"mesh file parts for scene {i}, but the batch has "
                                         f"{len(batch.scenes)} scenes"))
    for i, sc in enumerate(batch.scenes):
        given = files.get(i, {})
        needed = mesh_paths(sc.scene)
        for path in sorted(set(given) - set(needed)):
            errors.append(FieldError(field=f"files.scenes.{i}.{path}", type="unexpected_part",
                                     message=f"file part 'scenes.{i}.{path}': scene {i} has no mesh_file {path!r}"))
        for path in needed:
            if path not in given:
                k = next(k for k, o in enumerate(sc.scene.objects) if isinstance(o, MeshFileObject) and o.path == path)
                errors.append(FieldError(
                    field=f"scenes.{i}.scene.objects.{k}.path", type="missing_file",
                    message=f"mesh file {path!r}: send the batch as multipart/form-data with the file as the "
                            f"part 'scenes.{i}.{path}' (the batch JSON as the part '{BATCH_PART}')"))
            else:
                problem = mesh_problem(path, given[path])
                if problem is not None:
                    errors.append(FieldError(field=f"files.scenes.{i}.{path}", message=problem,
                                             type="invalid_mesh"))
    return errors


def _pixels(req: Any, scene: Any) -> int:
    cam = req.camera if req.camera is not None else scene.camera
    return int(cam.width * cam.height)


def _submit(store: ObjectStore, redis: Redis, batch: BatchRequest, files: SceneFiles, owner: str | None,
            settings: Settings) -> BatchPublic:
    # Validate everything before writing anything: a bad entry stores no scene and queues no job.
    errors: list[FieldError] = _mesh_errors(batch, files)
    new_ids: list[str] = []
    scenes: dict[str, tuple[Any, int]] = {}  # scene id -> (scene, triangles after tessellation)
    for i, sc in enumerate(batch.scenes):
        errors += limit_errors(sc.scene, settings, prefix=f"scenes.{i}.scene")
        meshes = files.get(i, {})
        new_ids.append(scene_id_for(sc.scene, {p: sha256_hex(meshes[p]) for p in mesh_paths(sc.scene) if p in meshes}))
        counts = {p: mesh_triangles(p, meshes[p]) for p in mesh_paths(sc.scene) if p in meshes}
        scenes[new_ids[-1]] = (sc.scene, scene_triangles(sc.scene, counts))
    costs: list[Cost] = []
    for j, req in enumerate(batch.renders):
        if req.scene_id not in scenes:
            try:
                if not scene_visible(store, req.scene_id, owner):
                    raise NotFound(req.scene_id)
                scenes[req.scene_id] = stored_scene(store, req.scene_id)
            except NotFound:
                errors.append(FieldError(field=f"renders.{j}.scene_id", message=f"no scene {req.scene_id}",
                                         type="unknown_scene"))
        if req.scene_id in scenes:
            problem = time_error(req, scenes[req.scene_id][0], prefix=f"renders.{j}.")
            if problem is not None:
                errors.append(problem)
        if req.scene_id in scenes and req.quality is None and _pixels(req, scenes[req.scene_id][0]) <= \
                settings.max_image_pixels:
            scene, triangles = scenes[req.scene_id]
            cam = req.camera if req.camera is not None else scene.camera
            cost = render_cost(req, cam.width, cam.height, triangles, scene_auto_glossy_rays(scene),
                               scene_light_traced(scene, cam))
            try:
                costs.append(check(cost, Limits.for_job(settings, "render"),
                                   "camera.height" if req.camera is not None else "scene_id",
                                   "render a smaller image or with fewer samples", "render_too_large"))
            except CostOverLimit as exc:
                errors.append(FieldError(field=f"renders.{j}.{exc.field}", message=exc.message, type=exc.type))
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
    if costs and not errors:
        try:  # every render's time together, as one request's
            check(batch_cost(costs), Limits.for_job(settings, "render"), "renders", "split the batch")
        except CostOverLimit as exc:
            errors.append(FieldError(field="renders", message=exc.message, type=exc.type))
    if errors:
        raise ValidationProblem(errors)
    for i, sc in enumerate(batch.scenes):
        public, _ = store_scene(store, sc.scene, files.get(i, {}), owner)
        add_scene_owner(store, public.id, owner)
        index_scene(store, public, owner)
    return enqueue_batch(redis, list(batch.renders), owner, store=store, scene_ids=list(dict.fromkeys(new_ids)))


@router.post(
    "",
    response_model=BatchPublic,
    status_code=202,
    responses={**problem_responses(400, 401, 413, 422, 429, 503), **BAKE_MISSING_409},
    openapi_extra={"requestBody": {"content": {"multipart/form-data": {"schema": _MULTIPART_SCHEMA}}}},
)
async def create_batch(
    batch: Annotated[BatchRequest, Body(openapi_examples={"default": {"summary": "One scene, no renders yet",
                                                                       "value": BATCH_EXAMPLE}})],
    request: Request,
    response: Response,
    store: StoreDep,
    redis: RedisDep,
    owner: OwnerDep,
    settings: SettingsDep,
) -> BatchPublic:
    """Store scenes and queue renders in one call; poll the batch for progress. Scenes with mesh
    files: send ``multipart/form-data``, the batch JSON as the part ``batch`` and each mesh file of
    scene ``i`` as the part ``scenes.<i>.<mesh_file path>``."""
    files: SceneFiles = request.state.scene_files if hasattr(request.state, "scene_files") else {}
    public = await run_in_threadpool(_submit, store, redis, batch, files, owner, settings)
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
