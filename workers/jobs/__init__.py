"""RQ job functions, enqueued by import path with one JSON-safe dict argument.

This package file stays import-light on purpose: the service and the bake worker's parent
process import names from here without pulling in numba (``render`` imports the engine and
is only imported by the process that runs the job).
"""

RENDER_JOB = "workers.jobs.render.render_job"
"""Import path of the render job function."""

BAKE_PLAN_JOB = "workers.jobs.bake.bake_plan_job"
"""Plans a bake (effect analysis, memory check) and enqueues its missing parts."""
BAKE_LDC_JOB = "workers.jobs.bake.bake_ldc_axis_job"
"""Bakes one LDC axis (a bake part)."""
BAKE_LLF_JOB = "workers.jobs.bake.bake_llf_views_job"
"""Bakes one chunk of LLF directions (a bake part)."""
BAKE_MERGE_JOB = "workers.jobs.bake.bake_merge_job"
"""Verifies a bake's parts and publishes its manifest."""

__all__ = ["BAKE_LDC_JOB", "BAKE_LLF_JOB", "BAKE_MERGE_JOB", "BAKE_PLAN_JOB", "RENDER_JOB"]
