"""``/v1/walkthroughs``: render a camera path through a stored scene from walkthrough bases.

``POST`` validates the request against the scene (a ``view_space`` is required, every eye must lie
inside it, every time inside the animation: 422 naming ``frames.<i>.camera.eye`` /
``frames.<i>.time`` with the allowed range), queues the bake, one render job per chunk of frames
and the video job (``producer/walkthroughs.py``) and answers 202 with ``Location``; a walkthrough
already rendered answers 200. With ``quality`` instead of ``bake`` and ``fill`` the planner picks
them from the scene's walkthrough calibration (``producer/walkthrough_calibrations.py``; 409
without one, 422 for a contract no setting meets) and the answer states the contract.
``GET /v1/walkthroughs/{key}`` shows the state, the progress (frames done) and, once finished,
links to ``video.mp4`` and the frame chunks (artifacts). ``DELETE /v1/walkthroughs/{key}``
removes the video, the frames and the request (204; 409 while its jobs are queued or running;
the shared bake stays).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, HTTPException, Path, Response
from fastapi.concurrency import run_in_threadpool

from api_schemas.errors import FieldError
from api_schemas.service import Sha256
from api_schemas.walkthrough import WalkthroughPublic, WalkthroughRequest
from producer.costs import Limits, check, stored_scene, walkthrough_costs
from producer.errors import WalkthroughInUse
from producer.settings import Settings
from producer.store import NotFound
from producer.walkthrough_calibrations import plan_walkthrough_request, with_contract, write_contract
from producer.walkthroughs import (
    check_against_scene,
    chunk_key,
    chunks,
    delete_walkthrough,
    enqueue_walkthrough,
    read_request,
    walkthrough_status,
)
from service.api.deps import OwnerDep, RedisDep, SettingsDep, StoreDep, scene_visible
from service.api.errors import ValidationProblem, problem_responses
from service.api.routes.artifacts import blob_response

router = APIRouter(prefix="/v1/walkthroughs", tags=["walkthroughs"])

KeyPath = Annotated[Sha256, Path(description="Walkthrough key (sha256 hex), from the answer to POST")]

WALKTHROUGH_EXAMPLE: dict[str, Any] = {
    "scene_id": "0" * 64,
    "bake": {"quality": "low"},
    "fill": "both",
    "frames": [
        {"time": 0.0, "camera": {"type": "perspective", "eye": [200, 273, 30], "look_at": [278, 150, 420],
                                 "fov_y_deg": 60, "width": 320, "height": 240}},
        {"time": 0.5, "camera": {"type": "perspective", "eye": [230, 273, 43], "look_at": [278, 150, 420],
                                 "fov_y_deg": 60, "width": 320, "height": 240}},
    ],
    "chunk_frames": 16,
    "fps": 24,
}


def _check(req: WalkthroughRequest, store: Any, owner: str | None, settings: Settings) -> None:
    max_pixels = settings.max_image_pixels
    if not scene_visible(store, req.scene_id, owner):
        raise NotFound(req.scene_id)
    scene, triangles = stored_scene(store, req.scene_id)  # NotFound -> 404
    cam = req.frames[0].camera
    errors: list[FieldError] = []
    if cam.width * cam.height > max_pixels:
        errors.append(FieldError(field="frames.0.camera.height", type="image_too_large",
                                 message=f"frames of {cam.width} x {cam.height} pixels exceed this server's limit of "
                                         f"{max_pixels}"))
    errors += check_against_scene(scene, req)
    if errors:
        raise ValidationProblem(errors)
    bake, frames = walkthrough_costs(req, triangles)
    check(bake, Limits.for_job(settings, "bake"), "bake.face_res",
          "lower face_res, max_views or max_time_samples", "bake_too_large")
    check(frames, Limits.for_job(settings, "render"), "chunk_frames",
          "lower chunk_frames, the frames' size or their number", "render_too_large")


def _request(redis: Any, store: Any, req: WalkthroughRequest, owner: str | None,
             settings: Settings) -> WalkthroughPublic:
    contract = None
    if req.quality is not None:
        _check(req, store, owner, settings)  # the frames against the scene, before the calibration is read
        req, contract = plan_walkthrough_request(store, req, error_margin=settings.contract_error_margin,
                                                 time_margin=settings.contract_time_margin)
    _check(req, store, owner, settings)
    key, _finished = enqueue_walkthrough(redis, store, req, owner)
    if contract is not None:
        write_contract(store, key, contract)
    pub = walkthrough_status(redis, store, key)
    assert pub is not None
    # an explicit request sharing a contract's frames asked for no contract: its answer states none
    return with_contract(store, pub) if contract is not None else pub


@router.post(
    "",
    response_model=WalkthroughPublic,
    responses={
        200: {"description": "Already rendered: the links name the video and the frames"},
        202: {"model": WalkthroughPublic, "description": "Queued; follow the walkthrough at Location",
              "headers": {"Location": {"schema": {"type": "string"}, "description": "The walkthrough's URL"}}},
        **problem_responses(400, 401, 404, 409, 413, 422, 429, 503),
    },
)
async def request_walkthrough(
    req: Annotated[WalkthroughRequest, Body(openapi_examples={"default": {"summary": "Two frames, low quality",
                                                                          "value": WALKTHROUGH_EXAMPLE}})],
    response: Response,
    store: StoreDep,
    redis: RedisDep,
    owner: OwnerDep,
    settings: SettingsDep,
) -> WalkthroughPublic:
    """Render every frame of a camera path (with times) through a scene's view space.

    With `quality` instead of `bake` and `fill`, the planner picks both from the scene's walkthrough
    calibration (`POST /v1/scenes/{id}/walkthrough-calibrations`) and `contract` states the plan."""
    pub = await run_in_threadpool(_request, redis, store, req, owner, settings)
    if pub.status != "finished":
        response.status_code = 202
        response.headers["Location"] = f"/v1/walkthroughs/{pub.key}"
    return pub


def _status(redis: Any, store: Any, key: str, owner: str | None) -> WalkthroughPublic:
    req = read_request(store, key)
    if req is None or not scene_visible(store, req.scene_id, owner):
        raise NotFound(key)
    pub = walkthrough_status(redis, store, key)
    if pub is None:
        raise NotFound(key)
    return with_contract(store, pub)


@router.get("/{key}", response_model=WalkthroughPublic, responses=problem_responses(401, 404, 422, 429, 503))
async def read_walkthrough(key: KeyPath, store: StoreDep, redis: RedisDep, owner: OwnerDep) -> WalkthroughPublic:
    """A walkthrough: state, frames done, jobs, and the video / frame links once finished."""
    return await run_in_threadpool(_status, redis, store, key, owner)


def _delete(redis: Any, store: Any, key: str, owner: str | None) -> None:
    req = read_request(store, key)
    if req is None or not scene_visible(store, req.scene_id, owner):
        raise NotFound(key)
    try:
        delete_walkthrough(redis, store, key)
    except WalkthroughInUse as exc:
        raise HTTPException(409, str(exc)) from None


@router.delete("/{key}", status_code=204, response_class=Response,
               responses=problem_responses(401, 404, 409, 422, 429, 503))
async def remove_walkthrough(key: KeyPath, store: StoreDep, redis: RedisDep, owner: OwnerDep) -> Response:
    """Delete a walkthrough: its video, frames and request (409 while one of its jobs is queued or
    running; a failed walkthrough's waiting jobs are canceled). The bake stays: other walkthroughs of
    the scene with the same bake settings share it."""
    await run_in_threadpool(_delete, redis, store, key, owner)
    return Response(status_code=204)


def _frame_blob(store: Any, key: str, owner: str | None, name: str, media_type: str) -> Response:
    req = read_request(store, key)
    if req is None or not scene_visible(store, req.scene_id, owner):
        raise NotFound(key)
    return blob_response(store, key, None, name, media_type, name.rsplit(".", 1)[-1])


@router.get(
    "/{key}/video.mp4",
    response_class=Response,
    responses={200: {"content": {"video/mp4": {"schema": {"type": "string", "format": "binary"}}},
                     "description": "H.264 preview of the walkthrough"}, **problem_responses(401, 404, 422, 429, 503)},
)
async def read_video(key: KeyPath, store: StoreDep, owner: OwnerDep) -> Response:
    """The walkthrough's MP4 preview (404 until it is finished)."""
    return await run_in_threadpool(_frame_blob, store, key, owner, "video.mp4", "video/mp4")


def _frame(store: Any, key: str, owner: str | None, index: int, kind: str) -> Response:
    req = read_request(store, key)
    if req is None or not scene_visible(store, req.scene_id, owner):
        raise NotFound(key)
    if not 0 <= index < len(req.frames):
        raise ValidationProblem([FieldError(field="index", type="frame_index",
                                            message=f"frame index {index} is outside [0, {len(req.frames) - 1}]")])
    for i, (a, b) in enumerate(chunks(req)):
        if a <= index < b:
            ck = chunk_key(key, i, a, b)
            name = f"provenance_{index:05d}.png" if kind == "provenance" else f"frame_{index:05d}.{kind}"
            media = "image/x-exr" if kind == "exr" else "image/png"
            return blob_response(store, ck, None, name, media, name.rsplit(".", 1)[-1])
    raise NotFound(key)  # pragma: no cover - chunks cover every index


@router.get(
    "/{key}/frames/{index}.{kind}",
    response_class=Response,
    responses={200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}},
                                 "image/x-exr": {"schema": {"type": "string", "format": "binary"}}},
                     "description": "One frame: exr (linear radiance), png (sRGB preview) or provenance (8-bit "
                                    "codes: 0 hole, 1 reprojected, 2 foreground fill, 3 background fill, 4 traced, "
                                    "5 sky)"}, **problem_responses(401, 404, 422, 429, 503)},
)
async def read_frame(key: KeyPath, index: int, kind: Literal["exr", "png", "provenance"], store: StoreDep,
                     owner: OwnerDep) -> Response:
    """One frame of a walkthrough (404 until its chunk is rendered)."""
    return await run_in_threadpool(_frame, store, key, owner, index, kind)


__all__ = ["router"]
