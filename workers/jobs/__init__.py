"""RQ job functions, enqueued by import path with one JSON-safe dict argument.

This package file stays import-light on purpose: the service and the bake worker's parent
process import names from here without pulling in numba (``render`` imports the engine and
is only imported by the process that runs the job).
"""

RENDER_JOB = "workers.jobs.render.render_job"
"""Import path of the render job function."""

__all__ = ["RENDER_JOB"]
