"""The exceptions of the producer layer that the API turns into HTTP answers.

``service/api/errors.py`` maps each to its status (404, 409, 422); the messages are written for
the API's user (what is wrong, what to do).
"""

from __future__ import annotations

from api_schemas.service import JobPublic

__all__ = [
    "BakeInUse",
    "BakeMissing",
    "CalibrationMissing",
    "ContractUnmet",
    "JobNotCancelable",
    "JobNotFound",
    "SceneOutputsInUse",
    "UnknownScene",
    "WalkthroughCalibrationMissing",
    "WalkthroughInUse",
]


class JobNotFound(LookupError):
    """No job with that id (never existed, or expired from Redis): HTTP 404."""


class JobNotCancelable(RuntimeError):
    """The job already ended (finished / failed / canceled): HTTP 409. ``job`` is its state."""

    def __init__(self, job: JobPublic):
        super().__init__(f"job {job.id} is {job.state}; only queued or started jobs can be canceled")
        self.job = job


class UnknownScene(LookupError):
    """The request names a scene the store does not hold: HTTP 404 / 422."""


class BakeMissing(LookupError):
    """An LDC render (``missing_bake: "fail"``) of a scene whose bake is not complete: HTTP 409.
    ``bake_key`` names the bake; ``job_id`` is its running job, if any."""

    def __init__(self, scene_id: str, bake_key: str, job_id: str | None, note: str = ""):
        running = f" (in progress: job {job_id})" if job_id else ""
        super().__init__(
            f"scene {scene_id} has no complete bake {bake_key}{running}; request it with POST "
            f"/v1/scenes/{scene_id}/bakes (same bake params), or send missing_bake: \"bake\" to queue the "
            f"render after the bake{note}")
        self.scene_id = scene_id
        self.bake_key = bake_key
        self.job_id = job_id


class BakeInUse(RuntimeError):
    """A scene bake cannot be deleted while one of its jobs is queued or running (HTTP 409)."""


class WalkthroughInUse(RuntimeError):
    """A walkthrough cannot be deleted while one of its jobs is queued or running (HTTP 409)."""


class SceneOutputsInUse(RuntimeError):
    """A job of the scene, of one of its bakes or of one of its walkthroughs is queued or running (HTTP 409)."""


class CalibrationMissing(LookupError):
    """A render with ``quality`` on a scene whose bake was never calibrated: HTTP 409, naming the
    calibration to request."""

    def __init__(self, scene_id: str, bake_key: str):
        super().__init__(
            f"scene {scene_id} has no calibration for bake {bake_key}: quality contracts are planned from a "
            f"per-scene calibration; request it with POST /v1/scenes/{scene_id}/calibrations (body: the same "
            "\"bake\" params as the render, optionally \"missing_bake\": \"bake\"), or name a method instead "
            "of quality")
        self.scene_id = scene_id
        self.bake_key = bake_key


class WalkthroughCalibrationMissing(CalibrationMissing):
    """A walkthrough with ``quality`` on a scene whose walkthrough settings were never calibrated (409)."""

    def __init__(self, scene_id: str):
        LookupError.__init__(
            self, f"scene {scene_id} has no walkthrough calibration: walkthrough quality contracts are planned "
                  f"from one; request it with POST /v1/scenes/{scene_id}/walkthrough-calibrations, or name "
                  "\"bake\" and \"fill\" instead of quality")
        self.scene_id = scene_id
        self.bake_key = ""


class ContractUnmet(ValueError):
    """No render setting meets a quality contract and ``on_miss`` is ``fail``: HTTP 422 naming the
    unmet targets (``quality.max_error``, ``quality.max_ms``) and what the scene can do."""

    def __init__(self, unmet: tuple[str, ...], reason: str):
        super().__init__(reason + '; send quality.on_miss: "best_effort" to render the closest setting anyway')
        self.unmet = unmet
