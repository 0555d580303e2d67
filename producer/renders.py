"""Renders: the artifact key of a render request and its enqueueing (after the scene bake it
needs, when the request says so).

A render's job id is ``render-<artifact key>``; an LDC render of a scene whose bake is missing
either fails (``missing_bake: "fail"``, :class:`producer.errors.BakeMissing`) or queues the bake
and waits for its merge job (``missing_bake: "bake"``, an RQ dependency).
"""

from __future__ import annotations

from typing import Any

from redis import Redis
from rq.job import Dependency, Job

from api_schemas.service import ContractPublic, LDCViewParams, RenderRequest, method_needs_bake
from engine import ENGINE_VERSION
from producer.artifacts import artifact_key, read_manifest
from producer.bakes import bake_complete, bake_key, enqueue_bake
from producer.enqueue import enqueue_unique
from producer.errors import BakeMissing, UnknownScene
from producer.names import RENDER_JOB, render_job_id, scene_bake_job_id
from producer.payloads import RenderJobPayload
from producer.queue import ACTIVE_STATUSES, RENDER_TIMEOUT_S, fetch_job, job_retry
from producer.store import ObjectStore

__all__ = ["enqueue_render", "render_artifact_key", "render_params"]


def render_params(req: RenderRequest) -> dict[str, Any]:
    """The artifact parameters of a render: the request without its scene id and without
    ``missing_bake`` (what to do when the bake is missing does not change the image); the bake
    params (and the view params, when not the default) for the methods that read a bake, the
    reference params for ``reference`` (JSON types)."""
    params = req.model_dump(mode="json", exclude={"scene_id", "missing_bake"})
    if params.get("outputs") is None:  # every image (the default): the key of a full artifact stays as it was
        params.pop("outputs", None)
    if params.get("quality") is None:  # planned requests carry the chosen method instead: keys as before
        params.pop("quality", None)
    if method_needs_bake(req.method):
        params.pop("params")  # the LDC methods shade with the bake's settings
        view, default = req.view, LDCViewParams()
        if view.glossy_rays == 0:  # no glossy lobe traced: its filter changes nothing
            params["view"].pop("glossy_filter")
            view = view.model_copy(update={"glossy_filter": default.glossy_filter})
        elif (view.glossy_rays, view.glossy_filter) == (default.glossy_rays, default.glossy_filter):
            params["view"].pop("glossy_rays")  # the default glossy lobes: a supersampled view's key as before
            params["view"].pop("glossy_filter")
        if view == default:  # one sample per pixel (the default): keys as before
            params.pop("view")
    else:
        params.pop("bake")
        params.pop("view")
    return params


def render_artifact_key(req: RenderRequest) -> str:
    """Content key of the render's artifact: (kind, scene, request params, engine version)."""
    return artifact_key("render", {"scene": req.scene_id}, render_params(req), ENGINE_VERSION)


def enqueue_render(
    redis: Redis,
    req: RenderRequest,
    owner: str | None,
    batch_id: str | None = None,
    *,
    store: ObjectStore | None = None,
    timeout: int = RENDER_TIMEOUT_S,
    contract: ContractPublic | None = None,
) -> tuple[str, Job | None]:
    """Queue a render, or find it done or in progress.

    Returns ``(artifact_key, None)`` when the artifact's manifest is in ``store`` (cache hit),
    ``(artifact_key, job)`` otherwise -- the existing job when an identical request is already
    queued or running, else a new one. With ``store=None`` the manifest is not checked (every
    call that finds no active job enqueues one; the job itself returns early when the artifact
    exists). Raises :class:`UnknownScene` when ``store`` is given and holds no such scene.
    """
    key = render_artifact_key(req)

    def cached() -> bool:
        if store is None:
            return False
        return read_manifest(store, key) is not None

    if cached():
        return key, None
    if store is not None and not store.exists(f"scenes/{req.scene_id}.json"):
        raise UnknownScene(f"scene {req.scene_id} does not exist")
    depends_on: Dependency | None = None
    if method_needs_bake(req.method) and store is not None:
        bkey = bake_key(req.scene_id, req.bake)
        if not bake_complete(store, bkey):
            if req.missing_bake == "fail":
                running = fetch_job(redis, scene_bake_job_id(bkey))
                active = running is not None and running.get_status(refresh=False) in ACTIVE_STATUSES
                raise BakeMissing(req.scene_id, bkey, running.id if running is not None and active else None)
            _, merge = enqueue_bake(redis, store, req.scene_id, req.bake, owner)
            if merge is not None:
                depends_on = Dependency(jobs=[merge.id], allow_failure=True)
    payload = RenderJobPayload(request=req, artifact_key=key, contract=contract).model_dump(mode="json")
    meta: dict[str, Any] = {
        "kind": "render",
        "artifact_key": key,
        "owner": owner,
        "batch_id": batch_id,
        "progress": {"fraction": 0.0, "stage": "waiting for the bake" if depends_on else "queued", "eta_s": None},
    }
    if depends_on is not None:
        meta["waits_for_bake"] = True
    job = enqueue_unique(
        redis, "render", RENDER_JOB, payload, render_job_id(key),
        timeout=timeout, meta=meta, retry=job_retry(),
        description=f"render scene {req.scene_id[:12]} ({req.method})", owner=owner, is_cached=cached,
        depends_on=depends_on,
    )
    return key, job
