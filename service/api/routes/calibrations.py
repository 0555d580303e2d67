"""``/v1/scenes/{scene_id}/calibrations``: calibrate a scene's render settings for quality contracts.

``/v1/scenes/{scene_id}/walkthrough-calibrations`` does the same for walkthroughs: each bake
preset and hole fill measured on probe frames against converged frames, for ``POST
/v1/walkthroughs`` with ``quality`` (``producer/walkthrough_calibrations.py``); one model per scene.

A calibration renders a few probe views of the scene with every candidate setting and with a
converged ground truth, and fits the per-scene model the planner of ``POST /v1/renders`` with
``quality`` reads (``producer/calibrations.py``, ``docs/quality-contracts.md``). It runs on the
``bake`` queue after the bake it calibrates; one model is kept per scene and bake.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, HTTPException, Path, Query, Response
from fastapi.concurrency import run_in_threadpool

from api_schemas.errors import FieldError
from api_schemas.service import CalibrationPublic, CalibrationRequest, Sha256
from api_schemas.walkthrough import (
    WalkthroughCalibrationPublic,
    WalkthroughCalibrationRequest,
    WalkthroughSettings,
)
from producer.calibrations import calibration_status, enqueue_calibration, read_calibration
from producer.costs import Limits, calibration_cost, check, stored_scene
from producer.settings import Settings
from producer.store import NotFound
from producer.walkthrough_calibrations import (
    enqueue_walkthrough_calibration,
    read_walkthrough_calibration,
    walkthrough_calibration_status,
)
from producer.walkthroughs import bake_bound_errors
from service.api.deps import OwnerDep, RedisDep, SettingsDep, StoreDep, scene_visible
from service.api.errors import ValidationProblem, problem_responses
from service.api.routes.bakes import check_bake_cost
from service.api.routes.renders import BAKE_MISSING_409

router = APIRouter(prefix="/v1/scenes", tags=["calibrations"])

SceneIdPath = Annotated[Sha256, Path(description="Scene id (sha256 hex)")]
BakeKeyPath = Annotated[Sha256, Path(description="Bake key (sha256 hex) the calibration is for")]

CALIBRATION_EXAMPLE: dict[str, Any] = {"bake": {"ldc_resolution": 128}, "params": {"probes": 4, "size": 64},
                                       "missing_bake": "bake"}
DEFAULT_REQUEST = CalibrationRequest()


def _request(redis: Any, store: Any, scene_id: str, req: CalibrationRequest, owner: str | None,
             settings: Settings) -> CalibrationPublic:
    if not scene_visible(store, scene_id, owner):
        raise NotFound(scene_id)
    scene, triangles = stored_scene(store, scene_id)
    check(calibration_cost(scene, req.params, triangles), Limits.for_job(settings, "bake"), "params.truth_spp",
          "lower truth_spp, size or probes", "calibration_too_large")
    if req.missing_bake == "bake":
        check_bake_cost(store, scene_id, req.bake, settings)
    key, bkey, job = enqueue_calibration(redis, store, scene_id, req, owner)  # BakeMissing: 409
    return calibration_status(redis, store, scene_id, bkey, key, cached=job is None)


@router.post(
    "/{scene_id}/calibrations",
    response_model=CalibrationPublic,
    responses={
        200: {"description": "This calibration exists (`cached: true`): nothing is queued"},
        202: {"model": CalibrationPublic, "description": "Queued; follow it at Location",
              "headers": {"Location": {"schema": {"type": "string"}, "description": "The calibration's URL"}}},
        **problem_responses(400, 401, 404, 413, 422, 429, 503),
        **BAKE_MISSING_409,
    },
)
async def request_calibration(
    scene_id: SceneIdPath,
    response: Response,
    store: StoreDep,
    redis: RedisDep,
    owner: OwnerDep,
    settings: SettingsDep,
    req: Annotated[CalibrationRequest, Body(openapi_examples={"default": {"summary": "Calibrate a scene's bake",
                                                                          "value": CALIBRATION_EXAMPLE}})]
    = DEFAULT_REQUEST,
) -> CalibrationPublic:
    """Calibrate the render settings of a scene's bake: error and time per setting, for quality contracts."""
    pub = await run_in_threadpool(_request, redis, store, scene_id, req, owner, settings)
    if not pub.cached:
        response.status_code = 202
        response.headers["Location"] = f"{pub.links['self']}?key={pub.key}"
    return pub


@router.get("/{scene_id}/calibrations/{bake_key}", response_model=CalibrationPublic,
            responses=problem_responses(401, 404, 422, 429, 503))
def read_scene_calibration(scene_id: SceneIdPath, bake_key: BakeKeyPath, store: StoreDep, redis: RedisDep,
                           owner: OwnerDep,
                           key: Annotated[Sha256 | None, Query(description="The calibration key of the POST's "
                                                                   "answer: follow its job")] = None
                           ) -> CalibrationPublic:
    """The calibration of a scene's bake: its model once made (or the job, with ``?key=`` from the POST's answer)."""
    if not scene_visible(store, scene_id, owner):
        raise NotFound(scene_id)
    pub = calibration_status(redis, store, scene_id, bake_key, key)
    if pub.state == "missing" and read_calibration(store, scene_id, bake_key) is None and key is None:
        raise HTTPException(404, f"scene {scene_id} has no calibration for bake {bake_key}")
    return pub


# ------------------------------------------------------------------------------ walkthroughs

WALKTHROUGH_CALIBRATION_EXAMPLE: dict[str, Any] = {"params": {"presets": ["low", "medium"], "fills": ["both"],
                                                              "probes": 3, "size": 64}}
DEFAULT_WALKTHROUGH_REQUEST = WalkthroughCalibrationRequest()


def _walkthrough_request(redis: Any, store: Any, scene_id: str, req: WalkthroughCalibrationRequest,
                         owner: str | None) -> WalkthroughCalibrationPublic:
    if not scene_visible(store, scene_id, owner):
        raise NotFound(scene_id)
    scene, _ = stored_scene(store, scene_id)
    if scene.view_space is None:
        raise ValidationProblem([FieldError(field="scene_id", type="no_view_space",
                                            message="the scene has no view_space; add one (docs/scene-format.md) "
                                                    "to walk through it")])
    # each preset's bake must fit this server, as a walkthrough naming it must
    errors = [e for i, preset in enumerate(req.params.presets)
              for e in bake_bound_errors(WalkthroughSettings.model_validate({"quality": preset}),
                                         f"params.presets.{i}")]
    if errors:
        raise ValidationProblem(errors)
    key, job = enqueue_walkthrough_calibration(redis, store, scene_id, req, owner)
    return walkthrough_calibration_status(redis, store, scene_id, key, cached=job is None)


@router.post(
    "/{scene_id}/walkthrough-calibrations",
    response_model=WalkthroughCalibrationPublic,
    responses={
        200: {"description": "This calibration exists (`cached: true`): nothing is queued"},
        202: {"model": WalkthroughCalibrationPublic, "description": "Queued; follow it at Location",
              "headers": {"Location": {"schema": {"type": "string"}, "description": "The calibration's URL"}}},
        **problem_responses(400, 401, 404, 413, 422, 429, 503),
    },
)
async def request_walkthrough_calibration(
    scene_id: SceneIdPath,
    response: Response,
    store: StoreDep,
    redis: RedisDep,
    owner: OwnerDep,
    req: Annotated[WalkthroughCalibrationRequest, Body(openapi_examples={"default": {
        "summary": "Calibrate two presets", "value": WALKTHROUGH_CALIBRATION_EXAMPLE}})] = DEFAULT_WALKTHROUGH_REQUEST,
) -> WalkthroughCalibrationPublic:
    """Calibrate a scene's walkthrough settings (bake preset x fill): frame error and time per setting,
    for walkthrough quality contracts. Bakes the presets whose bake is not stored yet."""
    pub = await run_in_threadpool(_walkthrough_request, redis, store, scene_id, req, owner)
    if not pub.cached:
        response.status_code = 202
        response.headers["Location"] = f"{pub.links['self']}?key={pub.key}"
    return pub


@router.get("/{scene_id}/walkthrough-calibrations", response_model=WalkthroughCalibrationPublic,
            responses=problem_responses(401, 404, 422, 429, 503))
def read_walkthrough_calibration_route(
        scene_id: SceneIdPath, store: StoreDep, redis: RedisDep, owner: OwnerDep,
        key: Annotated[Sha256 | None, Query(description="The calibration key of the POST's answer: follow its job")]
        = None) -> WalkthroughCalibrationPublic:
    """The scene's walkthrough calibration: its model once made (or the job, with ``?key=`` from the POST's answer)."""
    if not scene_visible(store, scene_id, owner):
        raise NotFound(scene_id)
    pub = walkthrough_calibration_status(redis, store, scene_id, key)
    if pub.state == "missing" and read_walkthrough_calibration(store, scene_id) is None and key is None:
        raise HTTPException(404, f"scene {scene_id} has no walkthrough calibration")
    return pub


__all__ = ["router"]
