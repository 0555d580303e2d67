"""Walkthrough calibrations of a scene, and the planning of a walkthrough request with ``quality``.

A walkthrough calibration (the job: ``workers/jobs/calibrate_walkthrough.py``, ``bake`` queue)
bakes each calibrated preset (unless its bake is stored), renders a few probe frames from it with
each calibrated fill and converged, and fits :class:`engine.walkthrough.quality.WalkthroughModel`.

Store: ``calibrations/<scene_id>/walkthrough.json`` holds the scene's latest walkthrough model
``{"key", "params", "model"}`` (a new calibration replaces it; removed with the scene), and
``calibrations/<scene_id>/walkthrough-served.json`` what the frames of walkthroughs planned from it
took (:func:`record_served_walkthrough`): per setting a running time correction the planner applies
(``engine.quality.correction_factor``), as served renders correct a render calibration. Job id
``wtcalibrate-<key>``, ``key = artifact_key("walkthrough-calibration", {"scene"}, params,
ENGINE_VERSION)``: identical requests share one job.

:func:`plan_walkthrough_request` runs in the API when a walkthrough with ``quality`` arrives: it
plans (``engine.walkthrough.quality.plan_walkthrough``) and returns the request with the chosen
bake preset and fill, or path-traced frames (its key is that of the same explicit request, so the
two share frames), and
the contract to state. The contract is kept beside the request (:func:`contract_key`) so that the
walkthrough's status keeps stating it.
"""

from __future__ import annotations

import json
import math
import statistics
from typing import Any

from redis import Redis
from rq.job import Job

from api_schemas.walkthrough import (
    WalkthroughCalibrationPublic,
    WalkthroughCalibrationRequest,
    WalkthroughContractPublic,
    WalkthroughPublic,
    WalkthroughRequest,
    WalkthroughSettings,
)
from engine import ENGINE_VERSION
from engine.walkthrough.quality import (
    WalkthroughModel,
    apply_time_corrections,
    path_setting_name,
    plan_walkthrough,
    setting_name,
    time_key,
)
from producer.artifacts import artifact_key, read_manifest
from producer.calibrations import fold_into_document, read_json_object
from producer.enqueue import enqueue_unique
from producer.errors import ContractUnmet, UnknownScene, WalkthroughCalibrationMissing
from producer.names import CALIBRATE_WALKTHROUGH_JOB, calibrate_walkthrough_job_id
from producer.queue import BAKE_TIMEOUT_S, fetch_job, job_retry
from producer.status import job_public
from producer.store import NotFound, ObjectStore
from producer.walkthroughs import contract_key

__all__ = [
    "enqueue_walkthrough_calibration",
    "plan_walkthrough_request",
    "read_contract",
    "read_served_walkthroughs",
    "read_walkthrough_calibration",
    "record_served_walkthrough",
    "walkthrough_calibration_key",
    "walkthrough_calibration_path",
    "walkthrough_calibration_status",
    "with_contract",
    "write_contract",
    "write_walkthrough_calibration",
]


def walkthrough_calibration_key(scene_id: str, req: WalkthroughCalibrationRequest) -> str:
    return artifact_key("walkthrough-calibration", {"scene": scene_id}, req.params.model_dump(mode="json"),
                        ENGINE_VERSION)


def walkthrough_calibration_path(scene_id: str) -> str:
    return f"calibrations/{scene_id}/walkthrough.json"


def read_walkthrough_calibration(store: ObjectStore, scene_id: str) -> dict[str, Any] | None:
    """The stored walkthrough calibration ``{"key", "params", "model"}`` of a scene (of this engine
    version), or None."""
    doc = read_json_object(store, walkthrough_calibration_path(scene_id))
    return doc if doc is not None and doc.get("model", {}).get("engine_version") == ENGINE_VERSION else None


def write_walkthrough_calibration(store: ObjectStore, scene_id: str, key: str, params: dict[str, Any],
                                  model: WalkthroughModel) -> None:
    doc = {"key": key, "params": params, "model": model.to_json()}
    store.put_bytes(walkthrough_calibration_path(scene_id), json.dumps(doc, sort_keys=True).encode(),
                    "application/json")


def enqueue_walkthrough_calibration(redis: Redis, store: ObjectStore, scene_id: str,
                                    req: WalkthroughCalibrationRequest, owner: str | None) -> tuple[str, Job | None]:
    """Queue a walkthrough calibration: ``(key, None)`` when the stored one has the same key, else
    ``(key, job)``."""
    if not store.exists(f"scenes/{scene_id}.json"):
        raise UnknownScene(f"scene {scene_id} does not exist")
    key = walkthrough_calibration_key(scene_id, req)

    def cached() -> bool:
        doc = read_walkthrough_calibration(store, scene_id)
        return doc is not None and doc.get("key") == key

    if cached():
        return key, None
    payload = {"v": 1, "scene_id": scene_id, "key": key, "request": req.model_dump(mode="json")}
    meta: dict[str, Any] = {"kind": "walkthrough-calibration", "scene_id": scene_id, "owner": owner,
                            "progress": {"fraction": 0.0, "stage": "queued", "eta_s": None}}
    job = enqueue_unique(redis, "bake", CALIBRATE_WALKTHROUGH_JOB, payload, calibrate_walkthrough_job_id(key),
                         timeout=BAKE_TIMEOUT_S, meta=meta, retry=job_retry(),
                         description=f"calibrate walkthroughs of scene {scene_id[:12]}", owner=owner,
                         is_cached=cached)
    return key, job


def walkthrough_calibration_status(redis: Redis, store: ObjectStore, scene_id: str, key: str | None = None,
                                   cached: bool = False) -> WalkthroughCalibrationPublic:
    """The scene's walkthrough calibration: the stored model (``finished``), else the job
    ``wtcalibrate-<key>`` when ``key`` is given, else ``missing``."""
    doc = read_walkthrough_calibration(store, scene_id)
    links = {"self": f"/v1/scenes/{scene_id}/walkthrough-calibrations"}
    job = fetch_job(redis, calibrate_walkthrough_job_id(key)) if key is not None else None
    if doc is not None and (key is None or doc.get("key") == key):
        return WalkthroughCalibrationPublic(scene_id=scene_id, key=doc["key"], state="finished", cached=cached,
                                            job=job_public(job) if job is not None else None, model=doc["model"],
                                            links=links)
    if job is None or key is None:
        return WalkthroughCalibrationPublic(scene_id=scene_id, key=key or "0" * 64, state="missing", links=links)
    pub = job_public(job)
    links["job"] = f"/v1/jobs/{job.id}"
    state = {"queued": "queued", "started": "running", "finished": "finished", "failed": "failed",
             "canceled": "failed"}[pub.state]
    return WalkthroughCalibrationPublic(scene_id=scene_id, key=key, state=state, job=pub,  # type: ignore[arg-type]
                                        links=links)


# ------------------------------------------------------------------------------------ planning


def plan_walkthrough_request(store: ObjectStore, req: WalkthroughRequest, *, error_margin: float = 1.0,
                             time_margin: float = 1.0) -> tuple[WalkthroughRequest, WalkthroughContractPublic]:
    """The request with the planner's bake preset and fill, and the contract to state.

    Raises :class:`WalkthroughCalibrationMissing` (409) when the scene's walkthrough settings were
    never calibrated, :class:`ContractUnmet` (422) when no setting meets the targets and ``on_miss``
    is ``fail``. ``error_margin``: the flat margin for fits without a calibrated one;
    ``time_margin``: the time budget's safety margin."""
    q = req.quality
    assert q is not None
    doc = read_walkthrough_calibration(store, req.scene_id)
    if doc is None:
        raise WalkthroughCalibrationMissing(req.scene_id)
    model = WalkthroughModel.from_json(doc["model"])
    model, applied = apply_time_corrections(model, read_served_walkthroughs(store, req.scene_id, doc["key"]))
    cam = req.frames[0].camera
    ready = {preset for preset, bkey in model.bake_keys.items() if read_manifest(store, bkey) is not None}
    p = plan_walkthrough(model, cam.width * cam.height, len(req.frames), max_error=q.max_error, max_ms=q.max_ms,
                         best_effort=q.on_miss == "best_effort", bakes_ready=ready, flat_margin=error_margin,
                         time_margin=time_margin)
    if p.choice is None or p.rule is None:
        raise ContractUnmet(p.unmet, p.reason)
    c = p.choice
    if c.path_noise is not None:
        asked = req.model_dump(mode="json", exclude={"bake", "fill", "quality"})
        # a time budget bounds each frame's paths too: a frame that needs more paths than its probes did
        # stops at the budget, above the noise target (its estimate says by how much), instead of late
        budget = {} if q.max_ms is None else {"max_ms": q.max_ms}
        planned = WalkthroughRequest.model_validate({**asked, "path_traced": {"noise": c.path_noise, **budget}})
        setting: dict[str, Any] = {"preset": None, "fill": None, "path_noise": c.path_noise, "bake": "none"}
    else:
        planned = req.model_copy(update={"bake": WalkthroughSettings.model_validate({"quality": c.preset}),
                                         "fill": c.fill, "quality": None})
        setting = {"preset": c.preset, "fill": c.fill, "bake": "ready" if c.preset in ready else "waited"}
    contract = WalkthroughContractPublic(
        max_error=q.max_error, max_ms=q.max_ms, on_miss=q.on_miss, rule=p.rule, met=p.met, unmet=list(p.unmet),
        reason=p.reason, frames=len(req.frames), **setting,
        width=cam.width, height=cam.height, predicted_error=c.error, predicted_frame_ms=c.frame_ms,
        predicted_bake_ms=c.bake_ms, predicted_total_ms=c.total_ms, estimated_error=c.error,
        planned_for=dict(p.planned_for),
        excluded=dict(model.excluded),
        calibration={"key": doc["key"], "created_at": model.created_at, "cost_s": model.cost_s,
                     "time_corrections": applied,
                     "probes": model.probe.get("frames"), "url": f"/v1/scenes/{req.scene_id}/walkthrough-calibrations"})
    return planned, contract


def write_contract(store: ObjectStore, wkey: str, contract: WalkthroughContractPublic) -> None:
    store.put_bytes(contract_key(wkey), contract.model_dump_json().encode(), "application/json")


def read_contract(store: ObjectStore, wkey: str) -> WalkthroughContractPublic | None:
    try:
        return WalkthroughContractPublic.model_validate_json(store.get_bytes(contract_key(wkey)))
    except NotFound:
        return None


def with_contract(store: ObjectStore, pub: WalkthroughPublic) -> WalkthroughPublic:
    """``pub`` with the contract its walkthrough was asked with (none: ``pub`` itself); once the
    walkthrough is finished, with the frames' achieved render times (``median`` and ``max``) and, for
    path-traced frames, their own estimates of their error."""
    contract = read_contract(store, pub.key)
    if contract is None:
        return pub
    manifest = read_manifest(store, pub.key) if pub.status == "finished" and contract.achieved_frame_ms is None \
        else None
    if manifest is not None:
        ms: list[float] = []
        est: list[float] = []
        for k in manifest.result.get("chunks", []):
            m = read_manifest(store, k)
            ms += [] if m is None else [float(x) for x in m.result.get("frame_ms", [])]
            est += [] if m is None else [float(x) for x in m.result.get("estimated_error", [])]
        if ms:
            update: dict[str, Any] = {"achieved_frame_ms": {"median": statistics.median(ms), "max": max(ms)}}
            if est:  # path-traced frames: each frame's own estimate of its LRMS
                update["achieved_estimated_error"] = {"median": statistics.median(est), "max": max(est)}
            contract = contract.model_copy(update=update)
            # a finished walkthrough's frames never change: kept, so later answers read no chunk manifest
            write_contract(store, pub.key, contract)
    return pub.model_copy(update={"contract": contract})


# ------------------------------------------------------------------------------------ served walkthroughs


def served_walkthroughs_path(scene_id: str) -> str:
    return f"calibrations/{scene_id}/walkthrough-served.json"


def read_served_walkthroughs(store: ObjectStore, scene_id: str, key: str) -> dict[str, Any]:
    """What the frames of walkthroughs planned from the walkthrough calibration ``key`` took:
    ``{"time": {setting: {"log", "n"}}}`` (``engine.quality.fold_observation``); empty when none, or
    when they were measured against another calibration (a new one starts afresh)."""
    doc = read_json_object(store, served_walkthroughs_path(scene_id))
    if doc is None or doc.get("key") != key or doc.get("engine_version") != ENGINE_VERSION:
        return {}
    return {"time": doc.get("time") or {}}


def _steady_frame_ms(chunk_frame_ms: list[list[float]]) -> list[float]:
    """The frame times of every chunk but each chunk's first frame: the first frame a chunk job
    renders also loads the kernels into its process (measured at ~0.27 s on the test room against
    ~9 ms for the others), which the model, calibrated after an untimed frame, leaves out."""
    return [ms for chunk in chunk_frame_ms for ms in chunk[1:]]


def record_served_walkthrough(store: ObjectStore, scene_id: str, contract: WalkthroughContractPublic,
                              chunk_frame_ms: list[list[float]]) -> dict[str, Any] | None:
    """Fold what the frames of a walkthrough planned from ``contract`` took into the corrections of
    the calibration that planned it: the slowest frame (each chunk's first left out,
    :func:`_steady_frame_ms`) against the predicted frame time, made raw again with the factor the
    plan applied (``calibration.time_corrections``), since the model predicts the slowest frame
    (``max_ms`` bounds every frame). Read, fold, write, as ``producer.calibrations.record_served``.
    Returns the document written, or None when there was nothing to fold."""
    key = contract.calibration.get("key")
    setting = time_key(path_setting_name(contract.path_noise) if contract.path_noise is not None
                       else setting_name(str(contract.preset), str(contract.fill)))
    steady = _steady_frame_ms(chunk_frame_ms)
    if not key or not steady or contract.predicted_frame_ms <= 0:
        return None
    applied = float((contract.calibration.get("time_corrections") or {}).get(setting, 1.0))
    ratio = max(steady) / contract.predicted_frame_ms * applied
    if not (ratio > 0 and math.isfinite(ratio)):
        return None
    return fold_into_document(store, served_walkthroughs_path(scene_id), str(key),
                              read_served_walkthroughs(store, scene_id, str(key)), setting, {"time": ratio})
