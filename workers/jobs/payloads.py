"""Job payloads: the one JSON argument of each RQ job, validated again by the worker.

The service builds payloads with these models and enqueues ``model_dump(mode="json")``;
the job function validates the dict before doing any work. ``extra="forbid"``: a payload
cannot smuggle settings in -- in particular not where a worker writes (the object store
comes from the worker's own settings, ``workers/settings.py``).
"""

from __future__ import annotations

from typing import Literal

from pydantic import ValidationError

from api_schemas.common import FrozenModel
from api_schemas.service import RenderRequest, Sha256

__all__ = ["InvalidPayload", "RenderJobPayload", "describe_validation_error"]


class InvalidPayload(ValueError):
    """A job payload failed validation: the job fails at once and is never retried."""


class RenderJobPayload(FrozenModel):
    """Payload of ``workers.jobs.render.render_job``."""

    v: Literal[1] = 1
    """Payload format version."""
    request: RenderRequest
    artifact_key: Sha256
    """The key the enqueuer computed; the worker recomputes it and refuses a mismatch."""


def describe_validation_error(exc: ValidationError, limit: int = 5) -> str:
    """One line naming the fields: ``request.params.spp: Input should be ... ; ...``."""
    parts = []
    for err in exc.errors()[:limit]:
        loc = ".".join(str(p) for p in err.get("loc", ())) or "(payload)"
        parts.append(f"{loc}: {err.get('msg', 'invalid')}")
    more = exc.error_count() - limit
    if more > 0:
        parts.append(f"... and {more} more")
    return "; ".join(parts)
