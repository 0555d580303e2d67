"""``/v1/scenes/{scene_id}/bakes``: request, follow and delete the bakes (LDC + LLF) of a scene.

A bake is content-addressed (scene id + ``BakeParams`` + engine version): requesting one that
exists answers 200 with ``cached: true`` and no work; otherwise its jobs are queued on the ``bake``
queue (a plan job, one job per part, a merge job; see ``producer/bakes.py``) and the answer is 202 with
``Location`` naming the bake, whose ``GET`` shows every part's state and the aggregated progress.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, HTTPException, Path, Response
from fastapi.concurrency import run_in_threadpool

from api_schemas.errors import FieldError
from api_schemas.service import BakeList, BakeParams, BakePublic, Sha256
from producer.artifacts import get_scene
from producer.bakes import (
    BAKE_MAX_PART_BYTES,
    bake_key,
    bake_status,
    delete_bake,
    enqueue_bake,
    ldc_upper_bound_bytes,
    list_bakes,
    llf_direction_count,
    read_bake_record,
)
from producer.costs import Cost, Limits, bake_cost, check, stored_scene
from producer.errors import BakeInUse
from producer.names import scene_bake_job_id
from producer.ownership import (
    add_bake_owner,
    attached_job_owners,
    bake_owners,
    detach_job_owner,
    remove_bake_owner,
)
from producer.queue import fetch_job
from producer.settings import Settings
from producer.store import NotFound
from service.api.deps import OwnerDep, RedisDep, SettingsDep, StoreDep, scene_visible
from service.api.errors import ValidationProblem, problem_responses

router = APIRouter(prefix="/v1/scenes", tags=["bakes"])

SceneIdPath = Annotated[Sha256, Path(description="Scene id (sha256 hex)")]
BakeKeyPath = Annotated[Sha256, Path(description="Bake key (sha256 hex), from the answer to POST .../bakes")]

BAKE_EXAMPLE: dict[str, Any] = {"ldc_resolution": 256, "max_layers": 32, "llf": "auto", "llf_f": 4,
                                "llf_resolution": 64, "llf_chunk": 16}
_LLF_SAMPLE_BYTES = 20 + 12
DEFAULT_BAKE = BakeParams()


def _check_size(params: BakeParams, n_lights: int) -> None:
    """Refuse, before anything is queued, a bake whose parts could need more memory than a worker
    may allocate (engine-free upper bounds; the plan job checks the exact estimate again)."""
    errors: list[FieldError] = []
    ldc = ldc_upper_bound_bytes(params, n_lights)
    if ldc > BAKE_MAX_PART_BYTES:
        errors.append(FieldError(
            field="ldc_resolution",
            message=f"ldc_resolution {params.ldc_resolution} x max_layers {params.max_layers} needs up to "
                    f"{ldc / 2**20:.0f} MiB per LDC axis, over this server's limit of "
                    f"{BAKE_MAX_PART_BYTES / 2**20:.0f} MiB; lower ldc_resolution or max_layers",
            type="bake_too_large"))
    if params.llf != "never":
        views = min(params.llf_chunk, llf_direction_count(params.llf_f))
        llf = views * (params.llf_resolution ** 2 * (9 + params.max_layers * _LLF_SAMPLE_BYTES) + 8)
        if llf > BAKE_MAX_PART_BYTES:
            errors.append(FieldError(
                field="llf_chunk",
                message=f"{views} light-field directions per job at llf_resolution {params.llf_resolution} x "
                        f"max_layers {params.max_layers} need up to {llf / 2**20:.0f} MiB, over this server's "
                        f"limit of {BAKE_MAX_PART_BYTES / 2**20:.0f} MiB; lower llf_chunk or llf_resolution",
                type="bake_too_large"))
    if errors:
        raise ValidationProblem(errors)


def _visible_scene(store: Any, scene_id: str, owner: str | None) -> int:
    """The scene's light count; NotFound (404) when it does not exist or is another key's."""
    if not scene_visible(store, scene_id, owner):
        raise NotFound(scene_id)
    _scene, _, public = get_scene(store, scene_id)
    return public.n_lights


def check_bake_cost(store: Any, scene_id: str, params: BakeParams, settings: Settings) -> Cost:
    """The bake's estimated cost (``producer.costs.bake_cost``); 422 over this server's limits."""
    scene, triangles = stored_scene(store, scene_id)
    cost = bake_cost(scene, params, triangles, settings.bake_paths_per_s)
    return check(cost, Limits.for_job(settings, "bake", bake_part=True), "ldc_resolution",
                 "lower ldc_resolution, max_layers or the indirect paths (indirect.max_paths, indirect.min_paths), "
                 "or raise indirect.chunks", "bake_too_large")


def _request(redis: Any, store: Any, scene_id: str, params: BakeParams, owner: str | None,
             settings: Settings) -> BakePublic:
    n_lights = _visible_scene(store, scene_id, owner)
    _check_size(params, n_lights)
    check_bake_cost(store, scene_id, params, settings)
    key, job = enqueue_bake(redis, store, scene_id, params, owner)
    if owner is not None:
        add_bake_owner(store, key, owner, _recorded_owner(store, scene_id, key))
    return bake_status(redis, store, scene_id, key, params, cached=job is None)


@router.post(
    "/{scene_id}/bakes",
    response_model=BakePublic,
    responses={
        200: {"description": "The bake exists already (`cached: true`): nothing is queued"},
        202: {"model": BakePublic, "description": "Queued (or joined a running bake); follow the bake at Location",
              "headers": {"Location": {"schema": {"type": "string"}, "description": "The bake's URL"}}},
        **problem_responses(400, 401, 404, 413, 422, 429, 503),
    },
)
async def request_bake(
    scene_id: SceneIdPath,
    response: Response,
    store: StoreDep,
    redis: RedisDep,
    owner: OwnerDep,
    settings: SettingsDep,
    params: Annotated[BakeParams, Body(openapi_examples={"default": {"summary": "A bake with the defaults",
                                                                     "value": BAKE_EXAMPLE}})] = DEFAULT_BAKE,
) -> BakePublic:
    """Bake a scene's layered depth cube (and light field when its materials need one)."""
    pub = await run_in_threadpool(_request, redis, store, scene_id, params, owner, settings)
    if not pub.cached:
        response.status_code = 202
        response.headers["Location"] = f"/v1/scenes/{scene_id}/bakes/{pub.key}"
    return pub


@router.get("/{scene_id}/bakes", response_model=BakeList, responses=problem_responses(401, 404, 422, 429, 503))
def list_scene_bakes(scene_id: SceneIdPath, store: StoreDep, redis: RedisDep, owner: OwnerDep) -> BakeList:
    """Every bake of this scene this API key requested (and did not delete), oldest first, with its state."""
    _visible_scene(store, scene_id, owner)
    return BakeList(items=[bake_status(redis, store, scene_id, key, params)
                           for key, params in list_bakes(store, scene_id) if _held(store, redis, scene_id, key, owner)])


def _recorded_owner(store: Any, scene_id: str, key: str) -> str | None:
    """The owner the bake's record names (the key that first asked for it), if any."""
    doc = read_bake_record(store, scene_id, key)
    who = doc.get("owner") if doc is not None else None
    return who if isinstance(who, str) else None


def _held(store: Any, redis: Any, scene_id: str, key: str, owner: str | None) -> bool:
    """Does ``owner`` hold the bake? With auth off, yes; otherwise if it requested the bake
    (``POST .../bakes``), or is still waiting for the bake's job (a render with
    ``missing_bake="bake"`` queued it): that hold is then recorded like a request's. A key that
    shares the scene but never asked for this bake neither sees nor deletes it."""
    if owner is None:
        return True
    recorded = _recorded_owner(store, scene_id, key)
    if owner in bake_owners(store, key, recorded):
        return True
    job = fetch_job(redis, scene_bake_job_id(key))
    if job is None:
        return False
    first = job.meta.get("owner")
    if owner not in attached_job_owners(redis, job.id, first if isinstance(first, str) else None):
        return False
    add_bake_owner(store, key, owner, recorded)
    return True


def _params_of(store: Any, scene_id: str, key: str) -> BakeParams:
    doc = read_bake_record(store, scene_id, key)
    if doc is None:
        raise HTTPException(404, f"scene {scene_id} has no bake {key}")
    params = BakeParams.model_validate(doc["params"])
    if bake_key(scene_id, params) != key:  # a record from another engine version
        raise HTTPException(404, f"bake {key} was made by another engine version; request it again")
    return params


@router.get("/{scene_id}/bakes/{bake_key}", response_model=BakePublic,
            responses=problem_responses(401, 404, 422, 429, 503))
def read_bake(scene_id: SceneIdPath, bake_key: BakeKeyPath, store: StoreDep, redis: RedisDep,
              owner: OwnerDep) -> BakePublic:
    """A bake: state, plan, every part (LDC axis, LLF chunk) with its state, and the aggregated progress."""
    _visible_scene(store, scene_id, owner)
    if not _held(store, redis, scene_id, bake_key, owner):
        raise HTTPException(404, f"scene {scene_id} has no bake {bake_key}")
    return bake_status(redis, store, scene_id, bake_key, _params_of(store, scene_id, bake_key))


@router.delete("/{scene_id}/bakes/{bake_key}", status_code=204, response_class=Response,
               responses=problem_responses(401, 404, 409, 422, 429, 503))
def remove_bake(scene_id: SceneIdPath, bake_key: BakeKeyPath, store: StoreDep, redis: RedisDep,
                owner: OwnerDep) -> Response:
    """Delete a bake: its manifest and every part (409 while one of its jobs is queued or running).
    A bake several API keys requested is shared: deleting it lets go of this key's hold (the bake
    is no longer listed for it) and the bake itself goes with the last holder."""
    _visible_scene(store, scene_id, owner)
    if not _held(store, redis, scene_id, bake_key, owner):
        raise HTTPException(404, f"scene {scene_id} has no bake {bake_key}")
    params = _params_of(store, scene_id, bake_key)
    if owner is not None and bake_owners(store, bake_key, _recorded_owner(store, scene_id, bake_key)) - {owner}:
        remove_bake_owner(store, bake_key, owner)  # others still hold it
        job = fetch_job(redis, scene_bake_job_id(bake_key))
        if job is not None:  # and no longer waits for its jobs: a cancel by the others is theirs alone
            first = job.meta.get("owner")
            detach_job_owner(redis, job.id, owner, first if isinstance(first, str) else None)
        return Response(status_code=204)
    try:
        delete_bake(redis, store, scene_id, bake_key, params)
    except BakeInUse as exc:
        raise HTTPException(409, str(exc)) from None
    remove_bake_owner(store, bake_key, None)
    return Response(status_code=204)


__all__ = ["router"]
