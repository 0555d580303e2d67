"""Calibrations of a scene for quality contracts, and the planning of a render request with one.

A calibration measures, on a few probe views of a scene, every candidate render setting's error
against a converged image and its time, and fits the per-scene model of :mod:`engine.quality`
(the job: ``workers/jobs/calibrate.py``, on the ``bake`` queue after the bake it calibrates).

Store: ``calibrations/<scene_id>/<bake_key>.json`` holds the model of that scene and bake (the
latest calibration of it: a new one replaces it), ``{"key", "params", "model"}``. It is removed with
the scene. Job id ``calibrate-<key>``, ``key = artifact_key("calibration", {"scene", "bake"},
params, ENGINE_VERSION)``: identical requests share one job. ``calibrations/<scene_id>/served/<bake_key>.json``
holds what renders planned from that calibration measured (their time; with ``verify``, their error):
running correction factors per setting (:func:`record_served`), which :func:`plan_render` applies.

:func:`plan_render` runs in the API when a request with ``quality`` arrives: it reads the model,
plans (``engine.quality.plan``) and returns the request with the chosen method and params (its
artifact key is that of the same explicit request, so the cache is shared) and the contract the
answer states.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from redis import Redis
from rq.job import Dependency, Job

from api_schemas.service import (
    CalibrationPublic,
    CalibrationRequest,
    ContractPublic,
    LDCViewParams,
    ReferenceRenderParams,
    RenderRequest,
)
from engine import ENGINE_VERSION
from engine.quality import (
    Plan,
    SceneModel,
    Setting,
    adaptive_scale,
    apply_corrections,
    correction_factor,
    correction_key,
    fold_observation,
    plan,
)
from producer.artifacts import artifact_key, get_scene
from producer.bakes import bake_complete, bake_key, enqueue_bake
from producer.costs import render_cost, stored_scene
from producer.enqueue import enqueue_unique
from producer.errors import BakeMissing, CalibrationMissing, ContractUnmet, UnknownScene
from producer.names import CALIBRATE_JOB, VERIFY_JOB, calibrate_job_id, render_job_id, scene_bake_job_id, verify_job_id
from producer.payloads import VerifyJobPayload
from producer.queue import ACTIVE_STATUSES, BAKE_TIMEOUT_S, fetch_job, job_retry
from producer.status import job_public
from producer.store import NotFound, ObjectStore

__all__ = [
    "calibration_key",
    "calibration_status",
    "VERIFY_TIMEOUT_S",
    "enqueue_calibration",
    "enqueue_verification",
    "model_path",
    "plan_render",
    "read_calibration",
    "fold_into_document",
    "read_json_object",
    "read_served",
    "read_verification",
    "record_served",
    "served_path",
    "verification_path",
    "verification_status",
    "write_calibration",
    "write_verification",
]


def calibration_key(scene_id: str, bkey: str, req: CalibrationRequest) -> str:
    return artifact_key("calibration", {"scene": scene_id, "bake": bkey}, req.params.model_dump(mode="json"),
                        ENGINE_VERSION)


def model_path(scene_id: str, bkey: str) -> str:
    return f"calibrations/{scene_id}/{bkey}.json"


def read_calibration(store: ObjectStore, scene_id: str, bkey: str) -> dict[str, Any] | None:
    """The stored calibration document ``{"key", "params", "model"}`` of a scene's bake, or None."""
    doc = read_json_object(store, model_path(scene_id, bkey))
    return doc if doc is not None and doc.get("model", {}).get("engine_version") == ENGINE_VERSION else None


def read_json_object(store: ObjectStore, key: str) -> dict[str, Any] | None:
    """The JSON object stored at ``key``; None when there is none."""
    try:
        doc = json.loads(store.get_bytes(key))
    except NotFound:
        return None
    return doc if isinstance(doc, dict) else None


def write_calibration(store: ObjectStore, scene_id: str, bkey: str, key: str, params: dict[str, Any],
                      model: SceneModel) -> None:
    doc = {"key": key, "params": params, "model": model.to_json()}
    store.put_bytes(model_path(scene_id, bkey), json.dumps(doc, sort_keys=True).encode(), "application/json")


def enqueue_calibration(redis: Redis, store: ObjectStore, scene_id: str, req: CalibrationRequest,
                        owner: str | None) -> tuple[str, str, Job | None]:
    """Queue a calibration: ``(key, bake key, None)`` when the stored one has the same key,
    else ``(key, bake key, job)``. A missing bake: :class:`BakeMissing` with ``missing_bake: "fail"``,
    else the bake is queued and the calibration waits for it."""
    if not store.exists(f"scenes/{scene_id}.json"):
        raise UnknownScene(f"scene {scene_id} does not exist")
    bkey = bake_key(scene_id, req.bake)
    key = calibration_key(scene_id, bkey, req)

    def cached() -> bool:
        doc = read_calibration(store, scene_id, bkey)
        return doc is not None and doc.get("key") == key

    if cached():
        return key, bkey, None
    depends_on: Dependency | None = None
    if not bake_complete(store, bkey):
        if req.missing_bake == "fail":
            running = fetch_job(redis, scene_bake_job_id(bkey))
            active = running is not None and running.get_status(refresh=False) in ACTIVE_STATUSES
            raise BakeMissing(scene_id, bkey, running.id if running is not None and active else None)
        _, merge = enqueue_bake(redis, store, scene_id, req.bake, owner)
        if merge is not None:
            depends_on = Dependency(jobs=[merge.id], allow_failure=True)
    payload = {"v": 1, "scene_id": scene_id, "bake_key": bkey, "key": key, "request": req.model_dump(mode="json")}
    meta: dict[str, Any] = {"kind": "bake", "scene_id": scene_id, "bake_key": bkey, "owner": owner,
                            "progress": {"fraction": 0.0, "stage": "waiting for the bake" if depends_on else "queued",
                                         "eta_s": None}}
    job = enqueue_unique(redis, "bake", CALIBRATE_JOB, payload, calibrate_job_id(key), timeout=BAKE_TIMEOUT_S,
                         meta=meta, retry=job_retry(), description=f"calibrate scene {scene_id[:12]}", owner=owner,
                         is_cached=cached, depends_on=depends_on)
    return key, bkey, job


def calibration_status(redis: Redis, store: ObjectStore, scene_id: str, bkey: str, key: str | None = None,
                       cached: bool = False) -> CalibrationPublic:
    """The calibration of ``scene_id``'s bake ``bkey``: the stored model (``finished``), else the job
    ``calibrate-<key>`` when ``key`` is given, else ``missing``."""
    doc = read_calibration(store, scene_id, bkey)
    links = {"self": f"/v1/scenes/{scene_id}/calibrations/{bkey}"}
    job = fetch_job(redis, calibrate_job_id(key)) if key is not None else None
    if doc is not None and (key is None or doc.get("key") == key):
        return CalibrationPublic(scene_id=scene_id, bake_key=bkey, key=doc["key"], state="finished", cached=cached,
                                 job=job_public(job) if job is not None else None, model=doc["model"], links=links)
    if job is None or key is None:
        return CalibrationPublic(scene_id=scene_id, bake_key=bkey, key=key or "0" * 64, state="missing", links=links)
    pub = job_public(job)
    links["job"] = f"/v1/jobs/{job.id}"
    state = {"queued": "queued", "started": "running", "finished": "finished", "failed": "failed",
             "canceled": "failed"}[pub.state]
    return CalibrationPublic(scene_id=scene_id, bake_key=bkey, key=key, state=state,  # type: ignore[arg-type]
                             job=pub, links=links)


# ------------------------------------------------------------------------------------ served renders


def served_path(scene_id: str, bkey: str) -> str:
    """Where what served renders measured is kept, beside the calibration it corrects."""
    return f"calibrations/{scene_id}/served/{bkey}.json"


def read_served(store: ObjectStore, scene_id: str, bkey: str, key: str) -> dict[str, Any]:
    """The corrections served renders measured for the calibration ``key`` of a scene's bake:
    ``{"time": {setting: {"log", "n"}}, "error": {...}}`` (``engine.quality.fold_observation``);
    empty when there are none or they were measured against another calibration (a new one starts
    afresh)."""
    doc = read_json_object(store, served_path(scene_id, bkey))
    if doc is None or doc.get("key") != key or doc.get("engine_version") != ENGINE_VERSION:
        return {}
    return {k: doc.get(k) or {} for k in ("time", "error")}


def record_served(store: ObjectStore, scene_id: str, contract: dict[str, Any], *, achieved_ms: float | None = None,
                  measured_error: float | None = None) -> dict[str, Any] | None:
    """Fold what a render planned from ``contract`` (``ContractPublic`` as JSON) measured into its
    calibration's corrections: ``achieved_ms`` (the render's time) against ``predicted_ms``,
    ``measured_error`` (``verify``) against the error the answer estimated (the adaptive reference:
    its estimate times the scale; else the prediction), each made raw again with the factor the plan
    applied (``contract.calibration.corrections``). The planner then multiplies its predictions by
    the running factors (``engine.quality.apply_corrections``). Read, fold, write: two workers
    folding at the same moment can lose one observation, which a running mean can afford. Returns
    the document written, or None when there was nothing to fold."""
    cal = contract.get("calibration") or {}
    bkey, key = cal.get("bake_key"), cal.get("key")
    if not bkey or not key:
        return None
    applied = cal.get("corrections") or {}
    setting = correction_key(str(contract.get("method")), contract.get("params"), contract.get("view"))
    obs: dict[str, float] = {}
    if achieved_ms is not None and float(contract.get("predicted_ms") or 0) > 0 and achieved_ms > 0:
        obs["time"] = achieved_ms / float(contract["predicted_ms"]) * float(applied.get("time", 1.0))
    estimated = contract.get("estimated_error")
    if measured_error is not None and estimated is not None and float(estimated) > 0 and measured_error > 0:
        obs["error"] = measured_error / float(estimated) * float(applied.get("error", 1.0))
    if not obs:
        return None
    return fold_into_document(store, served_path(scene_id, bkey), key, read_served(store, scene_id, bkey, key),
                              setting, obs)


def fold_into_document(store: ObjectStore, path: str, key: str, current: Mapping[str, Any], setting: str,
                       obs: Mapping[str, float]) -> dict[str, Any]:
    """Fold the observations ``obs`` (kind -> measured-over-predicted ratio) of ``setting`` into the
    corrections ``current`` (``{kind: {setting: {"log", "n"}}}``, measured against calibration
    ``key``) and write them to ``path``; returns the document written. Served renders' and served
    walkthroughs' corrections are kept this way."""
    doc: dict[str, Any] = {"key": key, "engine_version": ENGINE_VERSION, **current}
    for kind, ratio in obs.items():
        table = dict(doc.get(kind) or {})
        table[setting] = fold_observation(table.get(setting), ratio)
        doc[kind] = table
    store.put_bytes(path, json.dumps(doc, sort_keys=True).encode(), "application/json")
    return doc


# ------------------------------------------------------------------------------------ planning


def _pixels(store: ObjectStore, req: RenderRequest) -> tuple[int, int]:
    cam = req.camera
    if cam is None:
        scene, _, _ = get_scene(store, req.scene_id)
        cam = scene.camera
    return cam.width, cam.height


def _request_for(req: RenderRequest, model: SceneModel, setting: Setting) -> RenderRequest:
    update: dict[str, Any] = {"method": setting.method, "quality": None}
    params = model.setting_params(setting)
    if params is not None:
        update["params"] = ReferenceRenderParams(**params)
    if setting.view is not None:
        update["view"] = LDCViewParams(**setting.view)
    return req.model_copy(update=update)


def plan_render(redis: Redis, store: ObjectStore, req: RenderRequest, max_render_bytes: int | None = None, *,
                error_margin: float = 1.0, time_margin: float = 1.0) -> tuple[RenderRequest, ContractPublic]:
    """The request with the planner's method and params, and the contract to state.

    Raises :class:`CalibrationMissing` (409) when the scene's bake ``req.bake`` was never
    calibrated; :class:`ContractUnmet` (422) when no setting meets the targets and
    ``on_miss`` is ``fail``; :class:`BakeMissing` (409, the ``missing_bake`` rule) when the bake is
    missing, ``missing_bake`` is ``fail`` and only a setting that needs the bake would meet them.
    ``max_render_bytes``: settings whose estimated memory (``producer.costs.render_cost``, what the
    render route refuses by) exceeds it are not candidates.
    ``error_margin`` / ``time_margin``: the safety margins of ``engine.quality.plan``."""
    q = req.quality
    assert q is not None
    bkey = bake_key(req.scene_id, req.bake)
    doc = read_calibration(store, req.scene_id, bkey)
    if doc is None:
        raise CalibrationMissing(req.scene_id, bkey)
    served = read_served(store, req.scene_id, bkey, str(doc.get("key")))
    model = apply_corrections(SceneModel.from_json(doc["model"]), served)
    width, height = _pixels(store, req)
    _, triangles = stored_scene(store, req.scene_id)
    ready = bake_complete(store, bkey)
    best_effort = q.on_miss == "best_effort"
    allow_bake = ready or req.missing_bake == "bake"

    def allowed(s: Setting) -> bool:
        return max_render_bytes is None or \
            render_cost(_request_for(req, model, s), width, height, triangles).peak_bytes <= max_render_bytes

    margins = {"error_margin": error_margin, "time_margin": time_margin}
    p = plan(model, width * height, max_error=q.max_error, max_ms=q.max_ms, best_effort=best_effort,
             bake_ready=ready, allow_bake=allow_bake, allowed=allowed, error_margin=error_margin,
             time_margin=time_margin)
    if not ready and not allow_bake and not p.met:
        with_bake = plan(model, width * height, max_error=q.max_error, max_ms=q.max_ms, bake_ready=False,
                         allowed=allowed, error_margin=error_margin, time_margin=time_margin)
        if with_bake.met and with_bake.choice is not None:
            running = fetch_job(redis, scene_bake_job_id(bkey))
            active = running is not None and running.get_status(refresh=False) in ACTIVE_STATUSES
            raise BakeMissing(req.scene_id, bkey, running.id if running is not None and active else None,
                              note=f"; the contract would be met by {with_bake.choice.setting.name} from that bake "
                                   f"(what renders now cannot: {p.reason})")
    if p.choice is None:
        raise ContractUnmet(p.unmet, p.reason + _excluded_note(model))
    return _planned(req, model, doc, p, width, height, ready, allow_bake, margins, served)


def _excluded_note(model: SceneModel) -> str:
    if not model.excluded:
        return ""
    return "; excluded on this scene: " + "; ".join(f"{m}: {why}" for m, why in sorted(model.excluded.items()))


def _planned(req: RenderRequest, model: SceneModel, doc: dict[str, Any], p: Plan, width: int, height: int,
             ready: bool, allow_bake: bool, margins: dict[str, float],
             served: dict[str, Any]) -> tuple[RenderRequest, ContractPublic]:
    q = req.quality
    choice = p.choice
    assert q is not None and choice is not None and p.rule is not None
    setting = choice.setting
    params = model.setting_params(setting)
    if setting.adaptive:  # the render estimates its own error once it has run
        assert model.adaptive is not None
        estimate: dict[str, Any] = {"estimated_error_source": "render",
                                    "error_scale": adaptive_scale(model, choice.error)}
    else:
        estimate = {"estimated_error": choice.error, "estimated_error_source": "calibration"}
    planned = _request_for(req, model, setting)
    if setting.needs_bake:
        bake = "ready" if ready else "waited"
    else:
        bake = "not_needed" if ready or allow_bake else "best_available_now"
    contract = ContractPublic(
        max_error=q.max_error, max_ms=q.max_ms, on_miss=q.on_miss, rule=p.rule, met=p.met, unmet=list(p.unmet),
        reason=p.reason, method=setting.method, params=params, view=setting.view, width=width, height=height,
        predicted_error=choice.error, predicted_ms=choice.render_ms, predicted_bake_ms=choice.bake_ms,
        bake=bake, excluded=dict(model.excluded), planned_for=dict(p.planned_for),  # type: ignore[arg-type]
        margins={"error": margins["error_margin"], "time": margins["time_margin"]}, verify=q.verify, **estimate,
        calibration={"key": doc["key"], "bake_key": model.bake_key, "created_at": model.created_at,
                     "cost_s": model.cost_s, "probes": model.probe.get("views"),
                     "corrections": {kind: correction_factor(served, kind,
                                                             correction_key(setting.method, params, setting.view))
                                     for kind in ("time", "error")},
                     "url": f"/v1/scenes/{req.scene_id}/calibrations/{model.bake_key}"})
    return planned, contract


# ------------------------------------------------------------------------------------ verification

VERIFY_TIMEOUT_S = 300
"""The verification job's timeout: the converged reference is capped in time below it
(``workers.jobs.verify.VERIFY_MAX_MS``)."""


def verification_path(scene_id: str, key: str) -> str:
    """Where the measurement of artifact ``key`` is kept: with the scene's calibrations, so that it
    goes with the scene (``producer.scene_outputs``) and outlives the job's result."""
    return f"calibrations/{scene_id}/verified/{key}.json"


def read_verification(store: ObjectStore, scene_id: str, key: str) -> dict[str, Any] | None:
    """The stored measurement of artifact ``key`` (the verification job's result), or None."""
    doc = read_json_object(store, verification_path(scene_id, key))
    return doc if doc is not None and doc.get("engine_version") == ENGINE_VERSION else None


def write_verification(store: ObjectStore, scene_id: str, key: str, result: dict[str, Any]) -> None:
    doc = {**result, "engine_version": ENGINE_VERSION}
    store.put_bytes(verification_path(scene_id, key), json.dumps(doc, sort_keys=True).encode(), "application/json")


def enqueue_verification(redis: Redis, store: ObjectStore, planned: RenderRequest, key: str,
                         contract: ContractPublic, owner: str | None) -> Job | None:
    """Queue the measurement of artifact ``key`` (the render of ``planned``) against a converged
    reference of its view, after the render's job when it is still running. One job per artifact
    (``verify-<key>``): the same contract asked again finds it, running or finished. None when the
    measurement exists already (stored by the job: :func:`verification_status` reads it)."""
    if read_verification(store, planned.scene_id, key) is not None:
        return None
    render = fetch_job(redis, render_job_id(key))
    depends_on = None
    if render is not None and render.get_status(refresh=False) in ACTIVE_STATUSES:
        depends_on = Dependency(jobs=[render.id], allow_failure=True)
    payload = VerifyJobPayload(request=planned, artifact_key=key, contract=contract).model_dump(mode="json")
    meta: dict[str, Any] = {"kind": "verify", "artifact_key": key, "owner": owner,
                            "progress": {"fraction": 0.0, "stage": "waiting for the render" if depends_on else "queued",
                                         "eta_s": None}}
    return enqueue_unique(redis, "render", VERIFY_JOB, payload, verify_job_id(key), timeout=VERIFY_TIMEOUT_S,
                          meta=meta, retry=job_retry(), description=f"verify render {key[:12]}", owner=owner,
                          is_cached=lambda: read_verification(store, planned.scene_id, key) is not None,
                          depends_on=depends_on)


def verification_status(redis: Redis, store: ObjectStore, scene_id: str, key: str) -> dict[str, Any] | None:
    """``contract.verification`` of artifact ``key``: its job's id, URL and state, and once finished
    the measurement (kept in the store, so it outlives the job's result); None when there is
    neither a job nor a measurement."""
    job = fetch_job(redis, verify_job_id(key))
    stored = read_verification(store, scene_id, key)
    if job is None and stored is None:
        return None
    out: dict[str, Any] = {"job_id": verify_job_id(key), "url": f"/v1/jobs/{verify_job_id(key)}"}
    pub = job_public(job) if job is not None else None
    if stored is not None:
        out["state"] = "finished"
        out.update({k: v for k, v in stored.items() if k not in ("artifact_key", "engine_version")})
        if pub is None:
            out["url"] = None  # the job's record expired; the measurement is here
    else:
        assert pub is not None
        out["state"] = pub.state
        if pub.state == "finished" and pub.result:
            out.update({k: v for k, v in pub.result.items() if k != "artifact_key"})
        elif pub.error:
            out["error"] = pub.error
    return out
