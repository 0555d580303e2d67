"""Job payloads: the one JSON argument of each RQ job, validated again by the worker.

The producer builds payloads with these models and enqueues ``model_dump(mode="json")``; the job
function validates the dict before doing any work. ``extra="forbid"``: a payload cannot smuggle
settings in -- in particular not where a worker writes (the object store comes from the worker's
own settings, ``producer.settings``). One model per job function (``producer.names``), named
``<Job>Payload``.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, ValidationError, model_validator

from api_schemas.common import FrozenModel
from api_schemas.datasets import CompositeRequest, DatasetBakeParams, GenerateRequest, RelightRequest
from api_schemas.service import BakeParams, CalibrationRequest, ContractPublic, RenderRequest, Sha256
from api_schemas.walkthrough import WalkthroughCalibrationRequest, WalkthroughSettings

__all__ = [
    "CalibrateJobPayload",
    "CompositeJobPayload",
    "DatasetBakeJobPayload",
    "GenerateJobPayload",
    "InvalidPayload",
    "LDCAxisPart",
    "LDCIndirectPart",
    "LLFViewsPart",
    "RelightJobPayload",
    "RenderJobPayload",
    "SceneBakeJobPayload",
    "SceneBakePartJobPayload",
    "WalkthroughBakeJobPayload",
    "WalkthroughCalibrateJobPayload",
    "WalkthroughChunkJobPayload",
    "WalkthroughVideoJobPayload",
    "describe_validation_error",
]


class InvalidPayload(ValueError):
    """A job payload failed validation: the job fails at once and is never retried."""


class RenderJobPayload(FrozenModel):
    """Payload of ``workers.jobs.render.render_job``."""

    v: Literal[1] = 1
    """Payload format version."""
    request: RenderRequest
    artifact_key: Sha256
    """The key the enqueuer computed; the worker recomputes it and refuses a mismatch."""
    contract: ContractPublic | None = None
    """A request planned from a quality contract: the contract, written into the artifact's result
    with the achieved time (not part of the key: the same image answers the same explicit request)."""


class VerifyJobPayload(FrozenModel):
    """Payload of ``workers.jobs.verify.verify_job``: measure a contract's render against a converged
    reference of the same view."""

    v: Literal[1] = 1
    request: RenderRequest
    """The planned request (method and params as chosen)."""
    artifact_key: Sha256
    """The artifact whose ``radiance.exr`` is measured."""
    contract: ContractPublic


class CalibrateJobPayload(FrozenModel):
    """Payload of ``workers.jobs.calibrate.calibrate_job``."""

    v: Literal[1] = 1
    scene_id: Sha256
    bake_key: Sha256
    key: Sha256
    """The calibration key the enqueuer computed; the worker recomputes it and refuses a mismatch."""
    request: CalibrationRequest


class WalkthroughCalibrateJobPayload(FrozenModel):
    """Payload of ``workers.jobs.calibrate_walkthrough.calibrate_walkthrough_job``."""

    v: Literal[1] = 1
    scene_id: Sha256
    key: Sha256
    """The calibration key the enqueuer computed; the worker recomputes it and refuses a mismatch."""
    request: WalkthroughCalibrationRequest


class SceneBakeJobPayload(FrozenModel):
    """Payload of the scene bake's plan and merge jobs (``workers.jobs.bake``)."""

    v: Literal[1] = 1
    scene_id: Sha256
    bake_key: Sha256
    """The key the enqueuer computed; the worker recomputes it and refuses a mismatch."""
    params: BakeParams


class LDCAxisPart(FrozenModel):
    name: str
    kind: Literal["ldc_axis"]
    axis: Annotated[int, Field(ge=0, le=2)]


class LDCIndirectPart(FrozenModel):
    """Chunk ``chunk`` of ``chunks`` of an LDC axis's indirect pass: samples
    ``[chunk * n // chunks, (chunk + 1) * n // chunks)`` of the axis's n samples (n is known once the
    axis is baked, so the job computes its range at run time)."""

    name: str
    kind: Literal["ldc_indirect"]
    axis: Annotated[int, Field(ge=0, le=2)]
    chunk: Annotated[int, Field(ge=0)]
    chunks: Annotated[int, Field(ge=1)]

    @model_validator(mode="after")
    def _range(self) -> LDCIndirectPart:
        if self.chunk >= self.chunks:
            raise ValueError("chunk must be < chunks")
        return self


class LLFViewsPart(FrozenModel):
    name: str
    kind: Literal["llf_views"]
    start: Annotated[int, Field(ge=0)]
    stop: Annotated[int, Field(ge=1)]

    @model_validator(mode="after")
    def _range(self) -> LLFViewsPart:
        if self.stop <= self.start:
            raise ValueError("stop must be > start")
        return self


class SceneBakePartJobPayload(SceneBakeJobPayload):
    """Payload of a scene bake part job: the bake's payload plus the part and its artifact key."""

    part: LDCAxisPart | LDCIndirectPart | LLFViewsPart = Field(discriminator="kind")
    part_key: Sha256


class DatasetBakeJobPayload(FrozenModel):
    """Payload of ``workers.jobs.datasets.bake_job``."""

    v: Literal[1] = 1
    dataset_id: Sha256
    params: DatasetBakeParams
    artifact_key: Sha256


class RelightJobPayload(FrozenModel):
    """Payload of ``workers.jobs.datasets.relight_job``."""

    v: Literal[1] = 1
    request: RelightRequest
    artifact_key: Sha256


class GenerateJobPayload(FrozenModel):
    """Payload of ``workers.jobs.datasets.generate_job``."""

    v: Literal[1] = 1
    request: GenerateRequest
    artifact_key: Sha256
    owner: str | None = None
    """Who asked (the generated dataset gets this owner's marker, and every other requester's)."""


class CompositeJobPayload(FrozenModel):
    """Payload of ``workers.jobs.datasets.composite_job``."""

    v: Literal[1] = 1
    request: CompositeRequest
    artifact_key: Sha256


class WalkthroughBakeJobPayload(FrozenModel):
    """Payload of ``workers.jobs.walkthrough.walkthrough_bake_job``."""

    v: Literal[1] = 1
    scene_id: Sha256
    bake_key: Sha256
    settings: WalkthroughSettings


class WalkthroughChunkJobPayload(FrozenModel):
    """Payload of ``workers.jobs.walkthrough.walkthrough_chunk_job``."""

    v: Literal[1] = 1
    walkthrough_key: Sha256
    index: Annotated[int, Field(ge=0)]
    start: Annotated[int, Field(ge=0)]
    stop: Annotated[int, Field(ge=1)]
    chunk_key: Sha256
    bake_key: Sha256 | None
    """None: the frames are path-traced (``WalkthroughRequest.path_traced``)."""


class WalkthroughVideoJobPayload(FrozenModel):
    """Payload of ``workers.jobs.walkthrough.walkthrough_video_job``."""

    v: Literal[1] = 1
    walkthrough_key: Sha256
    bake_key: Sha256 | None


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
