"""``/v1/datasets``, ``/v1/relights``, ``/v1/composites``: illumination datasets and relighting.

Upload a dataset in one multipart request (a ``manifest`` part plus one part per file, named by
the file name the manifest uses), or resumably: ``POST /v1/datasets`` with the manifest as JSON
(every file's sha256 given) answers which files are missing, ``PUT /v1/datasets/uploads/{sha256}``
sends each, ``POST /v1/datasets/{id}/commit`` stores the dataset. A file received once is never
asked for again. Then bake it (``POST /v1/datasets/{id}/bake``, bake queue) and relight it under
any lights (``POST /v1/relights``, render queue); the answers follow ``POST /v1/renders``: 200
with the artifact when cached or done within ``wait``, else 202 and the job.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, HTTPException, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from pydantic import ValidationError
from redis import Redis
from rq.job import Job

from api_schemas.datasets import (
    BakeRequest,
    CompositeRequest,
    DatasetBakePublic,
    DatasetList,
    DatasetManifest,
    DatasetPublic,
    DatasetUploadStatus,
    FileUploadPublic,
    GenerateRequest,
    GenerationPublic,
    RelightEnvironmentLight,
    RelightPublic,
    RelightRequest,
)
from api_schemas.errors import FieldError
from api_schemas.service import ArtifactManifest, JobPublic, Sha256
from producer.artifacts import put_blob_unless_intact, read_blob, read_manifest, sha256_hex
from producer.costs import (
    Cost,
    Limits,
    composite_cost,
    dataset_bake_cost,
    generate_cost,
    light_count,
    relight_cost,
    stored_scene,
)
from producer.costs import check as within_limits
from producer.datasets import (
    DatasetInvalid,
    FileProblem,
    ImageTooLarge,
    bake_artifact_key,
    commit_dataset,
    composite_artifact_key,
    dataset_id_for,
    decode_slots,
    delete_dataset,
    fill_shas,
    generate_artifact_key,
    get_dataset,
    list_dataset_page,
    manifest_errors,
    missing_files,
    owned_blob_info,
    put_pending,
    read_file_blob,
    read_pending,
    relight_artifact_key,
    sniff_extension,
    store_file,
)
from producer.enqueue import enqueue_unique
from producer.listings import BadCursor
from producer.names import (
    COMPOSITE_JOB,
    COMPOSITE_KIND,
    DATASET_BAKE_JOB,
    DATASET_BAKE_KIND,
    GENERATE_JOB,
    GENERATE_KIND,
    RELIGHT_JOB,
    RELIGHT_KIND,
    dataset_job_id,
)
from producer.ownership import add_dataset_owner, dataset_visible
from producer.payloads import CompositeJobPayload, DatasetBakeJobPayload, GenerateJobPayload, RelightJobPayload
from producer.queue import BAKE_TIMEOUT_S, RENDER_TIMEOUT_S, QueueName, fetch_job, job_retry
from producer.settings import Settings
from producer.status import ids_in_active_jobs, job_public
from producer.store import NotFound, ObjectStore
from producer.wait import wait_for_job
from service.api.deps import OwnerDep, RedisDep, SettingsDep, StoreDep, scene_visible
from service.api.errors import ValidationProblem, problem_responses
from service.api.limits import BodyTooLarge, read_multipart

router = APIRouter(tags=["datasets"])

MAX_WAIT_S = 60.0

DatasetId = Annotated[Sha256, Path(description="Dataset id (sha256 hex)")]
FileSha = Annotated[Sha256, Path(description="sha256 of the file's bytes")]
ArtifactKeyPath = Annotated[Sha256, Path(description="Artifact key (sha256 hex)")]
Wait = Annotated[float, Query(ge=0, le=MAX_WAIT_S, description="Seconds to wait for the result (0..60)")]

_STATUS: dict[str, Literal["queued", "running", "finished", "failed"]] = {
    "queued": "queued", "started": "running", "finished": "finished", "failed": "failed", "canceled": "failed",
}

_MULTIPART_SCHEMA: dict[str, Any] = {
    "type": "object",
    "required": ["manifest"],
    "properties": {"manifest": {"type": "string", "description": "The DatasetManifest JSON"}},
    "additionalProperties": {"type": "string", "format": "binary",
                             "description": "One part per file of the manifest, named by its file name"},
}


# ------------------------------------------------------------------------------ helpers


def _invalid(exc: DatasetInvalid) -> ValidationProblem:
    detail = "files missing: upload them first" if exc.status == 409 else ""
    return ValidationProblem(exc.errors, detail=detail, status=exc.status)


def _parse_manifest(raw: bytes, prefix: str) -> DatasetManifest:
    if raw.startswith(b"\xef\xbb\xbf"):
        raw = raw[3:]
    try:
        doc = json.loads(raw)
    except (ValueError, RecursionError) as exc:
        raise ValidationProblem([FieldError(field=prefix, message=f"not valid JSON: {exc}", type="json_invalid")]
                                ) from None
    try:
        return DatasetManifest.model_validate(doc)
    except ValidationError as exc:
        raise ValidationProblem(manifest_errors(exc, prefix)) from None


def _visible_dataset(store: ObjectStore, dataset_id: str, owner: str | None) -> DatasetPublic:
    if not dataset_visible(store, dataset_id, owner):
        raise NotFound(dataset_id)
    return get_dataset(store, dataset_id)[1]


_DECODE_WAIT_S = 30.0


def _store_file(store: ObjectStore, data: bytes, settings: Settings, owner: str | None, expected_sha: str | None
                ) -> dict[str, Any]:
    """``store_file`` in one of the process's ``max_concurrent_decodes`` slots (503 when none frees
    up within 30 s), with the decoded-size budget: no upload can make the API hold more than
    slots x ``max_decoded_image_bytes`` of pixels."""
    slots = decode_slots(settings.max_concurrent_decodes)
    if not slots.acquire(timeout=_DECODE_WAIT_S):
        raise HTTPException(503, "too many images are being validated at once; retry shortly",
                            headers={"Retry-After": "5"})
    try:
        return store_file(store, data, max_pixels=settings.max_image_pixels, expected_sha=expected_sha, owner=owner,
                          max_decoded_bytes=settings.max_decoded_image_bytes)
    finally:
        slots.release()


def _file_error(field: str, label: str, exc: FileProblem) -> FieldError:
    return FieldError(field=field, message=f"{label}: {exc}",
                      type="image_too_large" if isinstance(exc, ImageTooLarge) else "invalid_image")


def _store_multipart(store: ObjectStore, manifest: DatasetManifest, files: dict[str, bytes], settings: Settings,
                     owner: str | None) -> tuple[DatasetPublic, bool]:
    """Validate and store every part, fill in the sha256s, commit."""
    errors: list[FieldError] = []
    shas: dict[str, str] = {}
    refs = manifest.file_refs()
    for field, name, sha, _ in refs:
        data = files.get(name)
        if data is None:
            if sha is not None and owned_blob_info(store, sha, owner) is not None:
                shas[name] = sha  # this key sent it earlier (resumed upload): no need to send it again
                continue
            errors.append(FieldError(field=f"manifest.{field}.file",
                                     message=f"no file part named {name!r}: send the file as a part with that name",
                                     type="missing_file"))
            continue
        try:
            info = _store_file(store, data, settings, owner, sha)
        except FileProblem as exc:
            errors.append(_file_error(f"files.{name}", name, exc))
            continue
        shas[name] = str(info["sha256"])
    if errors:
        raise ValidationProblem(errors)
    full = fill_shas(manifest, shas)
    try:
        return commit_dataset(store, full, owner)
    except DatasetInvalid as exc:
        raise _invalid(exc) from None


def _upload_status(store: ObjectStore, manifest: DatasetManifest, owner: str | None) -> DatasetUploadStatus:
    dataset_id = dataset_id_for(manifest)
    links = {"self": f"/v1/datasets/{dataset_id}", "commit": f"/v1/datasets/{dataset_id}/commit"}
    if dataset_visible(store, dataset_id, owner) and store.exists(f"datasets/{dataset_id}.json"):
        return DatasetUploadStatus(dataset_id=dataset_id, state="committed", missing=[],
                                   received=len({r[2] for r in manifest.file_refs()}), links=links)
    if manifest.geometry.type == "scene" and not (
            scene_visible(store, manifest.geometry.scene_id, owner)
            and store.exists(f"scenes/{manifest.geometry.scene_id}.json")):
        raise ValidationProblem([FieldError(field="geometry.scene_id", message=f"no stored scene "
                                            f"{manifest.geometry.scene_id}", type="unknown_scene")])
    put_pending(store, manifest, dataset_id)
    missing, received = missing_files(store, manifest, dataset_id, owner)
    return DatasetUploadStatus(dataset_id=dataset_id, state="pending", missing=missing, received=received,
                               links=links)


def _enqueue(redis: Redis, queue: QueueName, func: str, payload: dict[str, Any], kind: str, key: str,
             owner: str | None, store: ObjectStore, description: str) -> Job | None:
    timeout = BAKE_TIMEOUT_S if queue == "bake" else RENDER_TIMEOUT_S
    meta: dict[str, Any] = {"kind": queue, "job_type": kind, "artifact_key": key, "owner": owner,
                            "progress": {"fraction": 0.0, "stage": "queued", "eta_s": None}}
    return enqueue_unique(redis, queue, func, payload, dataset_job_id(kind, key), timeout=timeout, meta=meta,
                          retry=job_retry(), description=description,
                          owner=owner, is_cached=lambda: read_manifest(store, key) is not None)


def _result_links(base: str, key: str, job: JobPublic | None) -> dict[str, str]:
    links = {"artifact": f"{base}/{key}", "image.exr": f"{base}/{key}/image.exr",
             "image.png": f"{base}/{key}/image.png", "outside.png": f"{base}/{key}/outside.png"}
    if job is not None:
        links["job"] = f"/v1/jobs/{job.id}"
    return links


def _status(job: JobPublic | None, manifest: ArtifactManifest | None, cached: bool
            ) -> Literal["cached", "queued", "running", "finished", "failed"]:
    if manifest is not None:
        return "cached" if cached else "finished"
    assert job is not None
    return _STATUS[job.state]


async def _run(response: Response, redis: Redis, store: ObjectStore, queue: QueueName, func: str,
               payload: dict[str, Any], kind: str, key: str, owner: str | None, wait: float, description: str
               ) -> tuple[JobPublic | None, ArtifactManifest | None, bool]:
    """(job, manifest, cached): the cached artifact, or the job run / joined and waited for."""
    manifest = await run_in_threadpool(read_manifest, store, key)
    if manifest is not None:
        return None, manifest, True
    job = await run_in_threadpool(_enqueue, redis, queue, func, payload, kind, key, owner, store, description)
    if job is None:  # finished meanwhile
        manifest = await run_in_threadpool(read_manifest, store, key)
        if manifest is not None:
            return None, manifest, True
        raise NotFound(key)
    public, manifest = await wait_for_job(job, wait, store, key)
    if manifest is None and public.state in ("queued", "started"):
        response.status_code = 202
        response.headers["Location"] = f"/v1/jobs/{public.id}"
    return public, manifest, False


# ------------------------------------------------------------------------------ datasets: upload


@router.post(
    "/v1/datasets",
    response_model=DatasetPublic | DatasetUploadStatus,
    status_code=200,
    responses={
        201: {"model": DatasetPublic, "description": "Multipart upload: the dataset was stored"},
        **problem_responses(400, 401, 404, 409, 413, 415, 422, 429, 503),
    },
    openapi_extra={"requestBody": {"required": True, "content": {
        "application/json": {"schema": {"$ref": "#/components/schemas/DatasetManifest"}},
        "multipart/form-data": {"schema": _MULTIPART_SCHEMA},
    }}},
    tags=["datasets"],
)
async def create_dataset(request: Request, response: Response, store: StoreDep, owner: OwnerDep,
                         settings: SettingsDep) -> DatasetPublic | DatasetUploadStatus:
    """Multipart (``manifest`` + file parts): 201 ``DatasetPublic`` (200 when already stored).
    JSON manifest with every sha256: 200 ``DatasetUploadStatus`` listing the files still missing."""
    ctype = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    if ctype == "multipart/form-data":
        parts = await read_multipart(request, max_part_bytes=settings.max_upload_bytes,
                                     max_parts=settings.max_upload_files + 1,
                                     field_limits={"manifest": settings.json_limit_bytes})
        manifests = [p for p in parts if p.name == "manifest"]
        if len(manifests) != 1:
            raise ValidationProblem([FieldError(
                field="manifest", message="exactly one part named 'manifest' (the dataset manifest JSON) is required"
                + (f"; found {len(manifests)}" if manifests else ""),
                type="missing" if not manifests else "duplicate_part")])
        manifest = await run_in_threadpool(_parse_manifest, manifests[0].data, "manifest")
        files: dict[str, bytes] = {}
        errors: list[FieldError] = []
        for part in parts:
            if part.name == "manifest":
                continue
            if part.name in files:
                errors.append(FieldError(field=f"files.{part.name}", message=f"file part {part.name!r} sent twice",
                                         type="duplicate_part"))
            files[part.name] = part.data
        names = {r[1] for r in manifest.file_refs()}
        extra = sorted(set(files) - names)
        if extra:
            errors.append(FieldError(field="files", message="file parts the manifest does not name: "
                                     + ", ".join(repr(e) for e in extra[:20]), type="unexpected_part"))
        if errors:
            raise ValidationProblem(errors)
        public, created = await run_in_threadpool(_store_multipart, store, manifest, files, settings, owner)
        if created:
            response.status_code = 201
            response.headers["Location"] = f"/v1/datasets/{public.id}"
        return public
    if ctype == "application/json" or ctype.endswith("+json") or ctype == "":
        manifest = await run_in_threadpool(_parse_manifest, await request.body(), "")
        unset = [FieldError(field=f"{f}.sha256", message=f"the sha256 of {name!r} is required when files are "
                            "uploaded separately (or send everything in one multipart request)", type="missing")
                 for f, name, sha, _ in manifest.file_refs() if sha is None]
        if unset:
            raise ValidationProblem(unset)
        return await run_in_threadpool(_upload_status, store, manifest, owner)
    raise ValidationProblem([FieldError(field="", message=f"unsupported Content-Type {ctype!r}; use "
                                        "application/json or multipart/form-data", type="content_type")], status=415)


@router.put(
    "/v1/datasets/uploads/{sha256}",
    response_model=FileUploadPublic,
    status_code=201,
    responses={200: {"model": FileUploadPublic, "description": "Already received"},
               **problem_responses(400, 401, 413, 422, 429, 503)},
    openapi_extra={"requestBody": {"required": True, "content": {
        "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}}},
)
async def upload_file(sha256: FileSha, request: Request, response: Response, store: StoreDep, owner: OwnerDep,
                      settings: SettingsDep) -> FileUploadPublic:
    """Upload one file (image, depth map, mask, environment map, plate) by its sha256. 200 when this
    API key sent it before; a file stored already for another key is stored once, but each key
    proves it holds the bytes by sending them (the answer is then 201 for it)."""
    known = await run_in_threadpool(owned_blob_info, store, sha256, owner)
    limit = settings.max_upload_bytes
    buf = bytearray()
    async for chunk in request.stream():
        buf += chunk
        if len(buf) > limit:
            raise BodyTooLarge(f"file exceeds the {limit}-byte limit per file", field=f"files.{sha256}")
    if known is not None:
        if sha256_hex(bytes(buf)) == sha256:  # the same bytes: they replace a stored copy gone bad
            await run_in_threadpool(put_blob_unless_intact, store, sha256, bytes(buf))
        response.status_code = 200
        return FileUploadPublic.model_validate({k: known[k] for k in FileUploadPublic.model_fields})
    try:
        info = await run_in_threadpool(_store_file, store, bytes(buf), settings, owner, sha256)
    except FileProblem as exc:
        raise ValidationProblem([_file_error(f"files.{sha256}", f"file {sha256}", exc)]) from None
    return FileUploadPublic.model_validate({k: info[k] for k in FileUploadPublic.model_fields})


@router.get("/v1/datasets/uploads/{sha256}", response_model=FileUploadPublic,
            responses=problem_responses(401, 404, 422, 429, 503))
def read_upload(sha256: FileSha, store: StoreDep, owner: OwnerDep) -> FileUploadPublic:
    """Whether this API key sent a file (200 with its facts) or not (404, also when only another key did)."""
    info = owned_blob_info(store, sha256, owner)
    if info is None:
        raise NotFound(sha256)
    return FileUploadPublic.model_validate({k: info[k] for k in FileUploadPublic.model_fields})


@router.post(
    "/v1/datasets/{dataset_id}/commit",
    response_model=DatasetPublic,
    status_code=201,
    responses={200: {"model": DatasetPublic, "description": "Already stored"},
               **problem_responses(401, 404, 409, 422, 429, 503)},
)
def commit(dataset_id: DatasetId, response: Response, store: StoreDep, owner: OwnerDep) -> DatasetPublic:
    """Store a dataset whose manifest was sent as JSON once all its files are received (409 names the
    missing ones; 422 names files of the wrong size, with NaN or negative values, ...)."""
    manifest = read_pending(store, dataset_id)
    if manifest is None:
        if dataset_visible(store, dataset_id, owner) and store.exists(f"datasets/{dataset_id}.json"):
            response.status_code = 200
            return get_dataset(store, dataset_id)[1]
        raise NotFound(dataset_id)
    try:
        public, created = commit_dataset(store, manifest, owner)
    except DatasetInvalid as exc:
        raise _invalid(exc) from None
    if created:
        response.headers["Location"] = f"/v1/datasets/{public.id}"
    else:
        response.status_code = 200
    return public


# ------------------------------------------------------------------------------ datasets: read, delete


@router.get("/v1/datasets", response_model=DatasetList, responses=problem_responses(401, 422, 429, 503))
def list_all(store: StoreDep, owner: OwnerDep,
             limit: Annotated[int, Query(ge=1, le=1000, description="Datasets per page at most")] = 100,
             cursor: Annotated[str | None, Query(max_length=160, description="The next_cursor of the previous page")]
             = None) -> DatasetList:
    """The datasets this API key stored (or generated), oldest first, a page at a time: follow
    ``next_cursor`` until it is null."""
    try:
        items, nxt = list_dataset_page(store, owner, limit, cursor)
    except BadCursor as exc:
        raise ValidationProblem([FieldError(field="query.cursor", message=str(exc), type="invalid_cursor")]) from None
    return DatasetList(items=items, next_cursor=nxt)


@router.get("/v1/datasets/{dataset_id}", response_model=DatasetPublic,
            responses=problem_responses(401, 404, 422, 429, 503))
def read_dataset(dataset_id: DatasetId, store: StoreDep, owner: OwnerDep) -> DatasetPublic:
    """One dataset: its canonical manifest (file sha256s), size, light kind."""
    return _visible_dataset(store, dataset_id, owner)


_MEDIA = {".exr": "image/x-exr", ".png": "image/png", ".tif": "image/tiff", ".hdr": "image/vnd.radiance",
          ".jpg": "image/jpeg"}


@router.get(
    "/v1/datasets/{dataset_id}/files/{sha256}",
    response_class=Response,
    responses={200: {"content": {m: {"schema": {"type": "string", "format": "binary"}} for m in _MEDIA.values()},
                     "description": "The file as uploaded (or as generated)"},
               **problem_responses(401, 404, 422, 429, 503)},
)
def read_dataset_file(dataset_id: DatasetId, sha256: FileSha, store: StoreDep, owner: OwnerDep) -> Response:
    """One file of a dataset (image, depth map, mask) by its sha256, verified before it is sent."""
    public = _visible_dataset(store, dataset_id, owner)
    if sha256 not in {r[2] for r in public.manifest.file_refs()}:
        raise NotFound(sha256)
    data = read_file_blob(store, sha256)
    return Response(data, media_type=_MEDIA.get(sniff_extension(data) or "", "application/octet-stream"),
                    headers={"ETag": f'"{sha256}"', "Cache-Control": "private, max-age=31536000, immutable"})


@router.delete("/v1/datasets/{dataset_id}", status_code=204, response_class=Response,
               responses=problem_responses(401, 404, 409, 422, 429, 503))
def remove_dataset(dataset_id: DatasetId, store: StoreDep, redis: RedisDep, owner: OwnerDep) -> Response:
    """Delete a dataset (409 while a queued or running job uses it). Its files stay (content-addressed)."""
    if not dataset_visible(store, dataset_id, owner) or not store.exists(f"datasets/{dataset_id}.json"):
        raise NotFound(dataset_id)
    if dataset_id in ids_in_active_jobs(redis, ("dataset_id", "object_dataset_id", "background_dataset_id")):
        raise HTTPException(409, f"dataset {dataset_id} is used by a queued or running job; cancel it or wait")
    try:
        delete_dataset(store, dataset_id, owner)
    except NotFound:
        pass  # deleted concurrently
    return Response(status_code=204)


# ------------------------------------------------------------------------------ bake, generate


def _accepted(model: type[Any]) -> dict[int | str, dict[str, Any]]:
    return {202: {"model": model, "description": "Queued or running; poll the job named by Location",
                  "headers": {"Location": {"schema": {"type": "string"}, "description": "The job's URL"}}}}


@router.post(
    "/v1/datasets/{dataset_id}/bake",
    response_model=DatasetBakePublic,
    responses={**_accepted(DatasetBakePublic),
               **problem_responses(400, 401, 404, 413, 422, 429, 503)},
)
async def bake(dataset_id: DatasetId, response: Response, store: StoreDep, redis: RedisDep, owner: OwnerDep,
               settings: SettingsDep, req: Annotated[BakeRequest | None, Body()] = None,
               wait: Wait = 0) -> DatasetBakePublic:
    """Bake a dataset for relighting (bake queue): dedupe and triangulate the lights, build the
    lookup, reorganise the image stack. 200 when cached / done within ``wait``, else 202."""
    public = await run_in_threadpool(_visible_dataset, store, dataset_id, owner)
    params = (req or BakeRequest()).params
    within_limits(dataset_bake_cost(public.n_images, public.width, public.height, params),
                  Limits.for_job(settings, "bake"), "params", "use a smaller dataset", "bake_too_large")
    key = bake_artifact_key(dataset_id, params)
    payload = DatasetBakeJobPayload(dataset_id=dataset_id, params=params, artifact_key=key).model_dump(mode="json")
    job, manifest, cached = await _run(response, redis, store, "bake", DATASET_BAKE_JOB, payload, DATASET_BAKE_KIND,
                                       key, owner, wait, f"bake dataset {dataset_id[:12]}")
    links = {"dataset": f"/v1/datasets/{dataset_id}"}
    if job is not None:
        links["job"] = f"/v1/jobs/{job.id}"
    return DatasetBakePublic(dataset_id=dataset_id, artifact_key=key, status=_status(job, manifest, cached), job=job,
                             artifact=manifest, links=links)


@router.post(
    "/v1/datasets/generate",
    response_model=GenerationPublic,
    responses={**_accepted(GenerationPublic),
               **problem_responses(400, 401, 404, 413, 422, 429, 503)},
)
async def generate(req: GenerateRequest, response: Response, store: StoreDep, redis: RedisDep, owner: OwnerDep,
                   settings: SettingsDep, wait: Wait = 0) -> GenerationPublic:
    """Generate a dataset from a stored scene (bake queue): one reference render per point light
    placed over a part of a sphere. The result is a dataset like an uploaded one."""
    def check() -> None:
        if not scene_visible(store, req.scene_id, owner) or not store.exists(f"scenes/{req.scene_id}.json"):
            raise NotFound(req.scene_id)
        if req.camera is not None and req.camera.width * req.camera.height > settings.max_image_pixels:
            raise ValidationProblem([FieldError(field="camera.height", message="image exceeds this server's limit "
                                                f"of {settings.max_image_pixels} pixels", type="image_too_large")])
        missing = [FieldError(field=f"ground_truth.{i}.image_sha256", message="environment map not uploaded: PUT it "
                              f"to /v1/datasets/uploads/{light.image_sha256}", type="missing_file")
                   for i, light in enumerate(req.ground_truth)
                   if isinstance(light, RelightEnvironmentLight)
                   and owned_blob_info(store, light.image_sha256, owner) is None]
        if missing:
            raise ValidationProblem(missing)
        scene, triangles = stored_scene(store, req.scene_id)
        cam = req.camera if req.camera is not None else scene.camera
        cost = generate_cost(req, cam.width, cam.height, triangles, light_count(req))
        within_limits(cost, Limits.for_job(settings, "bake"), "params.spp",
                      "lower the image size, the samples (params) or the lights (placement.spacing_deg, max_lights)",
                      "bake_too_large")

    await run_in_threadpool(check)
    key = generate_artifact_key(req)
    payload = GenerateJobPayload(request=req, artifact_key=key, owner=owner).model_dump(mode="json")
    job, manifest, cached = await _run(response, redis, store, "bake", GENERATE_JOB, payload, GENERATE_KIND, key,
                                       owner, wait, f"generate dataset from scene {req.scene_id[:12]}")
    dataset_id = str(manifest.result["dataset_id"]) if manifest is not None else None
    links: dict[str, str] = {"self": f"/v1/datasets/generations/{key}"}
    if dataset_id is not None:
        await run_in_threadpool(add_dataset_owner, store, dataset_id, owner)
        links["dataset"] = f"/v1/datasets/{dataset_id}"
    for i in range(len(req.ground_truth)):
        links[f"ground_truth.{i}"] = f"/v1/datasets/generations/{key}/ground_truth_{i}.exr"
    if job is not None:
        links["job"] = f"/v1/jobs/{job.id}"
    return GenerationPublic(artifact_key=key, status=_status(job, manifest, cached), dataset_id=dataset_id, job=job,
                            artifact=manifest, links=links)


def _visible_generation(store: ObjectStore, key: str, owner: str | None) -> ArtifactManifest:
    manifest = read_manifest(store, key)
    if manifest is None or manifest.kind != GENERATE_KIND:
        raise NotFound(key)
    scene_id = manifest.inputs.get("scene", "")
    if owner is not None and not scene_visible(store, scene_id, owner):
        raise NotFound(key)
    return manifest


@router.get("/v1/datasets/generations/{key}", response_model=ArtifactManifest,
            responses=problem_responses(401, 404, 422, 429, 503))
def read_generation(key: ArtifactKeyPath, store: StoreDep, owner: OwnerDep) -> ArtifactManifest:
    """A generation's record: the request, the dataset id and counts in ``result``, ground-truth blobs."""
    return _visible_generation(store, key, owner)


@router.get(
    "/v1/datasets/generations/{key}/{name}",
    response_class=Response,
    responses={200: {"content": {"image/x-exr": {"schema": {"type": "string", "format": "binary"}}},
                     "description": "A ground-truth render (linear float EXR)"},
               **problem_responses(401, 404, 422, 429, 503)},
)
def read_ground_truth(key: ArtifactKeyPath, name: Annotated[str, Path(pattern=r"^ground_truth_[0-9]{1,2}\.exr$")],
                      store: StoreDep, owner: OwnerDep) -> Response:
    """Ground-truth render ``ground_truth_<i>.exr``: the scene under ``ground_truth[i]`` alone."""
    manifest = _visible_generation(store, key, owner)
    if name not in {b.name for b in manifest.blobs}:
        raise NotFound(name)
    return Response(read_blob(store, key, name), media_type="image/x-exr",
                    headers={"Cache-Control": "private, max-age=31536000, immutable"})


# ------------------------------------------------------------------------------ relight, composite


def _check_relight_inputs(store: ObjectStore, redis: Redis, owner: str | None, datasets: dict[str, str],
                          req: Any) -> None:
    errors: list[FieldError] = []
    for field, did in datasets.items():
        if not dataset_visible(store, did, owner) or not store.exists(f"datasets/{did}.json"):
            errors.append(FieldError(field=field, message=f"no dataset {did}", type="unknown_dataset"))
    if errors:
        raise NotFound(errors[0]["message"])
    for i, light in enumerate(req.lights):
        if isinstance(light, RelightEnvironmentLight) and owned_blob_info(store, light.image_sha256, owner) is None:
            errors.append(FieldError(field=f"lights.{i}.image_sha256", message="environment map not uploaded: PUT it "
                                     f"to /v1/datasets/uploads/{light.image_sha256}", type="missing_file"))
    for field in ("plate_sha256", "object_mask_sha256", "active_region_sha256"):
        sha = getattr(req, field, None)
        if sha is not None and owned_blob_info(store, sha, owner) is None:
            errors.append(FieldError(field=field, message=f"file not uploaded: PUT it to /v1/datasets/uploads/{sha}",
                                     type="missing_file"))
    if errors:
        raise ValidationProblem(errors)
    unbaked = [(field, did) for field, did in datasets.items()
               if read_manifest(store, bake_artifact_key(did, req.bake)) is None]
    if unbaked:
        problems = []
        for field, did in unbaked:
            job_id = dataset_job_id(DATASET_BAKE_KIND, bake_artifact_key(did, req.bake))
            job = fetch_job(redis, job_id)
            pending = job is not None and job_public(job).state in ("queued", "started")
            hint = (f"its bake job /v1/jobs/{job_id} is still {job_public(job).state}: wait for it" if pending and job
                    else f"POST /v1/datasets/{did}/bake (with the same 'params') first")
            problems.append(FieldError(field=field, message=f"dataset {did} is not baked with these bake parameters; "
                                       + hint, type="not_baked"))
        raise ValidationProblem(problems, detail="bake the dataset first", status=409)


def _check_relight_cost(store: ObjectStore, dataset_id: str, settings: Settings,
                        cost: Callable[[int, int, int], Cost]) -> None:
    """422 when the relight or composite of ``dataset_id`` (``cost(n_images, width, height)``) is over the
    render queue's limits."""
    _, public = get_dataset(store, dataset_id)
    within_limits(cost(public.n_images, public.width, public.height), Limits.for_job(settings, "render"),
                  "lights", "use a smaller dataset", "render_too_large")


@router.post(
    "/v1/relights",
    response_model=RelightPublic,
    responses={**_accepted(RelightPublic),
               **problem_responses(400, 401, 404, 409, 413, 422, 429, 503)},
)
async def request_relight(req: RelightRequest, response: Response, store: StoreDep, redis: RedisDep,
                          owner: OwnerDep, settings: SettingsDep, wait: Wait = 0) -> RelightPublic:
    """Relight a baked dataset under new lights (render queue). 200 with the artifact (relit EXR,
    PNG preview, coverage mask, counts, timings) when cached or done within ``wait``, else 202."""
    await run_in_threadpool(_check_relight_inputs, store, redis, owner, {"dataset_id": req.dataset_id}, req)
    await run_in_threadpool(_check_relight_cost, store, req.dataset_id, settings,
                            lambda n, w, h: relight_cost(req, n, w, h))
    key = relight_artifact_key(req)
    payload = RelightJobPayload(request=req, artifact_key=key).model_dump(mode="json")
    job, manifest, cached = await _run(response, redis, store, "render", RELIGHT_JOB, payload, RELIGHT_KIND, key,
                                       owner, wait, f"relight dataset {req.dataset_id[:12]}")
    return RelightPublic(artifact_key=key, status=_status(job, manifest, cached), job=job, artifact=manifest,
                         links=_result_links("/v1/relights", key, job))


@router.post(
    "/v1/composites",
    response_model=RelightPublic,
    responses={**_accepted(RelightPublic),
               **problem_responses(400, 401, 404, 409, 413, 422, 429, 503)},
)
async def request_composite(req: CompositeRequest, response: Response, store: StoreDep, redis: RedisDep,
                            owner: OwnerDep, settings: SettingsDep, wait: Wait = 0) -> RelightPublic:
    """Composite a relit object into a background plate (render queue): object pixels from the relit
    object dataset, active-region pixels of the plate scaled by I_object / I_background."""
    datasets = {"object_dataset_id": req.object_dataset_id, "background_dataset_id": req.background_dataset_id}
    await run_in_threadpool(_check_relight_inputs, store, redis, owner, datasets, req)
    await run_in_threadpool(_check_relight_cost, store, req.object_dataset_id, settings,
                            lambda n, w, h: composite_cost(req, n, w, h))
    key = composite_artifact_key(req)
    payload = CompositeJobPayload(request=req, artifact_key=key).model_dump(mode="json")
    job, manifest, cached = await _run(response, redis, store, "render", COMPOSITE_JOB, payload, COMPOSITE_KIND, key,
                                       owner, wait, f"composite dataset {req.object_dataset_id[:12]}")
    return RelightPublic(artifact_key=key, status=_status(job, manifest, cached), job=job, artifact=manifest,
                         links=_result_links("/v1/composites", key, job))


# ------------------------------------------------------------------------------ results

_RESULT_BLOBS = {"image.exr": ("radiance.exr", "image/x-exr"), "image.png": ("preview.png", "image/png"),
                 "outside.png": ("outside.png", "image/png")}


def _visible_result(store: ObjectStore, key: str, owner: str | None, kind: str) -> ArtifactManifest:
    manifest = read_manifest(store, key)
    if manifest is None or manifest.kind != kind:
        raise NotFound(key)
    if owner is not None:
        for role in ("dataset", "background"):
            did = manifest.inputs.get(role)
            if did is not None and not dataset_visible(store, did, owner):
                raise NotFound(key)
    return manifest


def _blob(store: ObjectStore, key: str, owner: str | None, kind: str, which: str) -> Response:
    _visible_result(store, key, owner, kind)
    name, media = _RESULT_BLOBS[which]
    data = read_blob(store, key, name)  # ChecksumMismatch -> 404 "stored data corrupt"
    return Response(data, media_type=media, headers={"Cache-Control": "private, max-age=31536000, immutable",
                                                     "Content-Disposition": f'inline; filename="{key[:16]}-{which}"'})


_IMAGE_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"content": {"image/x-exr": {"schema": {"type": "string", "format": "binary"}},
                      "image/png": {"schema": {"type": "string", "format": "binary"}}},
          "description": "The image"},
    **problem_responses(401, 404, 422, 429, 503),
}


_BLOB_DOCS = {
    "image.exr": "The linear float image (OpenEXR).",
    "image.png": "sRGB preview (PNG, the request's exposure).",
    "outside.png": "Coverage mask (PNG): white where some light direction fell outside the dataset's coverage "
                   "(that light contributed 0 there).",
}


def _blob_endpoint(kind: str, which: str) -> Any:
    def endpoint(key: ArtifactKeyPath, store: StoreDep, owner: OwnerDep) -> Response:
        return _blob(store, key, owner, kind, which)

    endpoint.__doc__ = _BLOB_DOCS[which]
    endpoint.__name__ = f"{kind.replace('-', '_')}_{which.replace('.', '_')}"
    return endpoint


for _base, _kind in (("/v1/relights", RELIGHT_KIND), ("/v1/composites", COMPOSITE_KIND)):

    def _make(kind: str, base: str) -> None:
        @router.get(f"{base}/{{key}}", response_model=ArtifactManifest, responses=problem_responses(401, 404, 422, 429,
                                                                                                     503),
                    name=f"read_{kind}")
        def read_result(key: ArtifactKeyPath, store: StoreDep, owner: OwnerDep) -> ArtifactManifest:
            """The result's manifest: blobs with checksums, counts (``n_outside``: pixels with a light
            direction outside the dataset's coverage) and timings."""
            return _visible_result(store, key, owner, kind)

        for which in _RESULT_BLOBS:
            router.add_api_route(f"{base}/{{key}}/{which}", _blob_endpoint(kind, which), methods=["GET"],
                                 response_class=Response, responses=_IMAGE_RESPONSES, name=f"{kind}_{which}")

    _make(_kind, _base)


__all__ = ["router"]
