"""The verification job: measure a quality contract's render against a converged reference of the
same view (``quality.verify``, ``docs/quality-contracts.md``).

``verify_job(payload)`` runs on the ``render`` queue after the render it measures:

1. read the artifact's ``radiance.exr`` (the route makes sure the request asked for it);
2. render the converged reference of the same view: the adaptive reference (``engine/progressive.py``)
   with the scene's reference settings from its calibration, told :data:`VERIFY_MAX_ERROR` (in the
   contract's metric, through the calibrated ``error_scale``), capped at :data:`VERIFY_CAP_SPP`
   samples per pixel and :data:`VERIFY_MAX_MS` milliseconds, with a seed of its own so its noise is
   independent of the image's;
3. the LRMS of the image against it over the contract's pixels (``ReferenceRenderer.error_region``),
   with the reference's own estimated error removed in quadrature.

Returns ``measured_error``, ``measured_error_raw``, ``reference_error``, ``met`` (against the
contract's ``max_error``, None without one), ``verify_ms`` (the reference's render time: what the
measurement cost) and the reference's ``adaptive`` report; the same is stored with the scene's
calibrations (``producer.calibrations.write_verification``), where answers read it after the job's
result expires, and the measured error is folded into the calibration's corrections
(``producer.calibrations.record_served``: the planner's error prediction for that setting follows it).
"""

from __future__ import annotations

import math
import time
from typing import Any

from pydantic import ValidationError
from rq import get_current_job

from engine.imageio import decode_image
from engine.metrics import lrms
from engine.quality import SceneModel, adaptive_scale
from engine.reference import ReferenceParams
from producer.artifacts import read_blob, read_manifest
from producer.calibrations import read_calibration, write_verification
from producer.payloads import InvalidPayload, VerifyJobPayload, describe_validation_error
from workers.jobs.common import ProgressReporter, fold_served, json_safe, load_stored_scene, worker_store
from workers.jobs.render import renderer_cache
from workers.scene_loader import camera_params

__all__ = ["VERIFY_CAP_SPP", "VERIFY_MAX_ERROR", "VERIFY_MAX_MS", "VERIFY_SEED", "verify_job"]

VERIFY_MAX_ERROR = 0.005
"""The converged reference's target (the contract's metric): 0.5 %, a tenth of a typical target."""
VERIFY_CAP_SPP = 4096
"""Most samples per pixel of the converged reference."""
VERIFY_MAX_MS = 240_000.0
"""Most render time of the converged reference (below the job's timeout,
``producer.calibrations.VERIFY_TIMEOUT_S``); a reference stopped by it reports the error it reached."""
VERIFY_SEED = 104_729
"""The converged reference's seed (renders use 0, calibration ground truths 7919)."""

def verify_job(payload: dict[str, Any]) -> dict[str, Any]:
    """Measure one contract's render (see the module docstring)."""
    try:
        p = VerifyJobPayload.model_validate(payload)
    except ValidationError as exc:
        raise InvalidPayload(f"invalid verification job payload: {describe_validation_error(exc)}") from None
    store = worker_store()
    progress = ProgressReporter(get_current_job())
    progress.report(0.0, "reading the image", force=True)
    manifest = read_manifest(store, p.artifact_key)
    if manifest is None:
        raise RuntimeError(f"artifact {p.artifact_key} does not exist (its render failed or was removed): "
                           "nothing to verify")
    image, _ = decode_image("radiance.exr", read_blob(store, p.artifact_key, "radiance.exr"))
    con = p.contract
    doc = read_calibration(store, p.request.scene_id, str(con.calibration.get("bake_key", "")))
    if doc is None:
        raise RuntimeError("the scene's calibration is gone: the converged reference's settings come from it")
    model = SceneModel.from_json(doc["model"])
    scale = adaptive_scale(model, VERIFY_MAX_ERROR)
    entry, _ = renderer_cache().get_or_load(p.request.scene_id, lambda: load_stored_scene(store, p.request.scene_id))
    camera = camera_params(p.request.camera) if p.request.camera is not None else entry.loaded.camera
    params = ReferenceParams(**{**model.reference_request_params(VERIFY_CAP_SPP, min(0.99, VERIFY_MAX_ERROR / scale),
                                                                 VERIFY_MAX_MS), "seed": VERIFY_SEED})
    progress.report(0.05, "converged reference", force=True)
    t0 = time.perf_counter()
    out = entry.renderer.render(camera, params, lambda f, _s: progress.report(0.05 + 0.9 * f, "converged reference"))
    verify_ms = 1000.0 * (time.perf_counter() - t0)
    if image.shape[:2] != out.radiance.shape[:2]:
        raise RuntimeError(f"the image is {image.shape[1]} x {image.shape[0]}, the view {camera.width} x "
                           f"{camera.height}")
    mask = out.error_region  # the progressive render's own: its estimate and this LRMS share the pixels
    if mask is None:
        mask = entry.renderer.error_region(camera, out.object_id, out.depth, params.max_depth)
    raw = float(lrms(image[..., :3], out.radiance, mask if mask.any() else None))
    ref_err = scale * float((out.adaptive or {}).get("estimated_error", 0.0))
    measured = math.sqrt(max(raw * raw - ref_err * ref_err, 0.0))
    progress.report(1.0, "done", force=True, check=False)
    result: dict[str, Any] = json_safe({
        "artifact_key": p.artifact_key, "measured_error": measured, "measured_error_raw": raw,
        "reference_error": ref_err, "met": None if con.max_error is None else measured <= con.max_error,
        "verify_ms": verify_ms, "reference": {"params": params.to_dict(), "adaptive": out.adaptive}})
    write_verification(store, p.request.scene_id, p.artifact_key, result)
    # the answer's estimate of this image's error (the adaptive reference's is in the render's result)
    served = manifest.result.get("contract") or con.model_dump(mode="json")
    fold_served(store, p.request.scene_id, served, measured_error=measured)
    return result
