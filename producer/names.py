"""Job names: the import paths RQ stores in every queued job, and the job ids.

RQ enqueues a job by the dotted path of its function (``workers.jobs.render.render_job``) and
imports it in the worker; the paths below are the only place the producer names a job body, so a
job function never moves without this file (and an alias at the old path) changing with it.

Job ids are deterministic (``<kind>-<artifact key>``): identical requests share one job.
"""

from __future__ import annotations

__all__ = [
    "CALIBRATE_JOB",
    "CALIBRATE_WALKTHROUGH_JOB",
    "COMPOSITE_JOB",
    "COMPOSITE_KIND",
    "DATASET_BAKE_JOB",
    "DATASET_BAKE_KIND",
    "GENERATE_JOB",
    "GENERATE_KIND",
    "RELIGHT_JOB",
    "RELIGHT_KIND",
    "RENDER_JOB",
    "VERIFY_JOB",
    "SCENE_BAKE_LDC_JOB",
    "SCENE_BAKE_INDIRECT_JOB",
    "SCENE_BAKE_LLF_JOB",
    "SCENE_BAKE_MERGE_JOB",
    "SCENE_BAKE_PLAN_JOB",
    "WALKTHROUGH_BAKE_JOB",
    "WALKTHROUGH_CHUNK_JOB",
    "WALKTHROUGH_VIDEO_JOB",
    "calibrate_job_id",
    "calibrate_walkthrough_job_id",
    "dataset_job_id",
    "render_job_id",
    "scene_bake_job_id",
    "scene_bake_part_job_id",
    "scene_bake_plan_job_id",
    "verify_job_id",
    "walkthrough_bake_job_id",
    "walkthrough_chunk_job_id",
    "walkthrough_video_job_id",
]

# ------------------------------------------------------------------------------------ job functions

RENDER_JOB = "workers.jobs.render.render_job"
"""Renders one image of a stored scene (``render`` queue)."""
VERIFY_JOB = "workers.jobs.verify.verify_job"
"""Measures a quality contract's render against a converged reference of its view (``render`` queue)."""

SCENE_BAKE_PLAN_JOB = "workers.jobs.bake.bake_plan_job"
"""Plans a scene bake (effect analysis, memory check) and enqueues its missing parts."""
SCENE_BAKE_LDC_JOB = "workers.jobs.bake.bake_ldc_axis_job"
"""Bakes one LDC axis (a scene bake part)."""
SCENE_BAKE_INDIRECT_JOB = "workers.jobs.bake.bake_ldc_indirect_job"
"""Path-traces the indirect light of one chunk of an LDC axis's samples (a scene bake part)."""
SCENE_BAKE_LLF_JOB = "workers.jobs.bake.bake_llf_views_job"
"""Bakes one chunk of LLF directions (a scene bake part)."""
SCENE_BAKE_MERGE_JOB = "workers.jobs.bake.bake_merge_job"
"""Verifies a scene bake's parts and publishes its manifest."""

CALIBRATE_JOB = "workers.jobs.calibrate.calibrate_job"
"""Calibrates a scene's render settings for quality contracts (``bake`` queue)."""
CALIBRATE_WALKTHROUGH_JOB = "workers.jobs.calibrate_walkthrough.calibrate_walkthrough_job"
"""Calibrates a scene's walkthrough settings for quality contracts (``bake`` queue)."""
DATASET_BAKE_JOB = "workers.jobs.datasets.bake_job"
"""Bakes an illumination dataset for relighting (``bake`` queue)."""
RELIGHT_JOB = "workers.jobs.datasets.relight_job"
"""Relights a baked dataset (``render`` queue)."""
GENERATE_JOB = "workers.jobs.datasets.generate_job"
"""Generates an illumination dataset from a stored scene (``bake`` queue)."""
COMPOSITE_JOB = "workers.jobs.datasets.composite_job"
"""Composites a relit object into a background plate (``render`` queue)."""

WALKTHROUGH_BAKE_JOB = "workers.jobs.walkthrough.walkthrough_bake_job"
"""Bakes a walkthrough's base range images (``bake`` queue)."""
WALKTHROUGH_CHUNK_JOB = "workers.jobs.walkthrough.walkthrough_chunk_job"
"""Renders a chunk of a walkthrough's frames (``render`` queue)."""
WALKTHROUGH_VIDEO_JOB = "workers.jobs.walkthrough.walkthrough_video_job"
"""Encodes a walkthrough's video and publishes its manifest (``render`` queue)."""

# ------------------------------------------------------------------------------------ dataset job kinds

DATASET_BAKE_KIND = "relight-bake"
RELIGHT_KIND = "relight"
GENERATE_KIND = "dataset-generation"
COMPOSITE_KIND = "composite"
"""Artifact kinds of the dataset jobs; each is also the prefix of its job id."""

# ------------------------------------------------------------------------------------ job ids


def render_job_id(key: str) -> str:
    return f"render-{key}"


def verify_job_id(key: str) -> str:
    """The verification of a contract's render artifact ``key``."""
    return f"verify-{key}"


def scene_bake_job_id(key: str) -> str:
    """A scene bake's own (merge) job: the one clients follow and renders depend on."""
    return f"bake-{key}"


def scene_bake_plan_job_id(key: str) -> str:
    return f"bake-plan-{key}"


def scene_bake_part_job_id(part_key: str) -> str:
    return f"bake-part-{part_key}"


def calibrate_job_id(key: str) -> str:
    return f"calibrate-{key}"


def calibrate_walkthrough_job_id(key: str) -> str:
    return f"wtcalibrate-{key}"


def walkthrough_bake_job_id(bake_key: str) -> str:
    return f"wtbake-{bake_key}"


def walkthrough_chunk_job_id(chunk_key: str) -> str:
    return f"wtchunk-{chunk_key}"


def walkthrough_video_job_id(walkthrough_key: str) -> str:
    return f"walkthrough-{walkthrough_key}"


def dataset_job_id(kind: str, key: str) -> str:
    """``relight-<key>``, ``relight-bake-<key>``, ``dataset-generation-<key>``, ``composite-<key>``."""
    return f"{kind}-{key}"
