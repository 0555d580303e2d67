"""Request / response models of the HTTP API, shared by the service and the workers.

Resources: scenes (content-addressed), jobs (RQ), renders (a render request creates or
reuses a job whose result is an artifact), artifacts (content-addressed blobs + a
manifest), batches (many requests in one call). Errors are RFC 9457 problem details.

The service never imports the engine; workers validate job payloads with these same
models before doing any work.
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import Field, StringConstraints

from api_schemas.common import FrozenModel
from api_schemas.scene import Camera, Scene

Sha256 = Annotated[str, StringConstraints(pattern=r"^[0-9a-f]{64}$")]
"""Lower-case hex sha256: scene ids, blob checksums and artifact keys."""

JobId = Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9_-]{1,128}$")]

RenderMethod = Literal["reference"]
"""Render methods available now; later issues add ``ldc``, ``ldc+llf``, ``ldc+ibrt:k``."""

JobState = Literal["queued", "started", "finished", "failed", "canceled"]


# ------------------------------------------------------------------------------ scenes


class SceneCreate(FrozenModel):
    """Body of ``POST /v1/scenes`` (JSON). Mesh files go in a multipart request instead:
    part ``scene`` (this JSON) and one file part per ``mesh_file`` path, named by that path."""

    scene: Scene


class MeshBlob(FrozenModel):
    path: str
    """The ``mesh_file`` path used in the scene (metadata only)."""
    sha256: Sha256
    size: int


class ScenePublic(FrozenModel):
    """A stored scene. ``id`` hashes the canonical scene JSON together with its mesh blobs,
    so equal content always gets the same id."""

    id: Sha256
    name: str
    created_at: datetime
    n_objects: int
    n_lights: int
    meshes: list[MeshBlob] = []
    links: dict[str, str] = {}


class SceneList(FrozenModel):
    items: list[ScenePublic]
    total: int


# ------------------------------------------------------------------------------ renders


class ReferenceRenderParams(FrozenModel):
    """Settings of the reference renderer (see docs/reference-renderer.md)."""

    spp: Annotated[int, Field(ge=1, le=4096)] = 4
    max_depth: Annotated[int, Field(ge=0, le=64)] = 4
    glossy_samples: Annotated[int, Field(ge=1, le=4096)] = 16
    area_light_samples: Annotated[int, Field(ge=1, le=4096)] = 16
    indirect_samples: Annotated[int, Field(ge=0, le=65536)] = 0
    indirect_bounces: Annotated[int, Field(ge=1, le=64)] = 2
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0


class RenderRequest(FrozenModel):
    """Body of ``POST /v1/renders``: a view of a stored scene by a method."""

    scene_id: Sha256
    camera: Camera | None = None
    """Overrides the scene's camera; None renders the scene's own view."""
    method: RenderMethod = "reference"
    params: ReferenceRenderParams = ReferenceRenderParams()


class RenderPublic(FrozenModel):
    """Answer to a render request: the artifact when cached, else the job computing it."""

    artifact_key: Sha256
    status: Literal["cached", "queued", "running", "finished", "failed"]
    job: JobPublic | None = None
    artifact: ArtifactManifest | None = None
    links: dict[str, str] = {}


# ------------------------------------------------------------------------------ jobs


class JobProgress(FrozenModel):
    fraction: Annotated[float, Field(ge=0.0, le=1.0)] = 0.0
    stage: str = ""
    eta_s: float | None = None


class JobPublic(FrozenModel):
    id: JobId
    kind: Literal["render", "bake"]
    state: JobState
    progress: JobProgress = JobProgress()
    created_at: datetime | None = None
    started_at: datetime | None = None
    ended_at: datetime | None = None
    error: str | None = None
    """Why a job failed, in words a user can act on."""
    result: dict[str, Any] | None = None
    """Small JSON result (artifact key, timings); arrays never travel through Redis."""
    batch_id: str | None = None
    links: dict[str, str] = {}


class JobList(FrozenModel):
    items: list[JobPublic]


# ------------------------------------------------------------------------------ artifacts


class BlobInfo(FrozenModel):
    name: str
    sha256: Sha256
    size: int
    content_type: str


class ArtifactManifest(FrozenModel):
    """The commit record of an artifact, written after all its blobs.

    ``key`` = sha256 of the canonical JSON of (kind, inputs, params, engine_version)."""

    key: Sha256
    kind: str
    inputs: dict[str, str]
    params: dict[str, Any]
    engine_version: str
    blobs: list[BlobInfo]
    result: dict[str, Any] = {}
    created_at: datetime


# ------------------------------------------------------------------------------ batches


class BatchRequest(FrozenModel):
    """Many scenes and / or render requests in one call (``POST /v1/batches``)."""

    scenes: Annotated[list[SceneCreate], Field(max_length=1000)] = []
    renders: Annotated[list[RenderRequest], Field(max_length=10000)] = []


class BatchPublic(FrozenModel):
    id: JobId
    scene_ids: list[Sha256] = []
    renders: list[RenderPublic] = []
    progress: JobProgress = JobProgress()
    counts: dict[str, int] = {}
    """Jobs per state, plus ``cached`` for renders served from the store."""


# ------------------------------------------------------------------------------ errors


class ProblemField(FrozenModel):
    field: str
    """Dot-joined location, e.g. ``scene.objects.2.radius`` ('' = the whole body)."""
    message: str
    type: str


class Problem(FrozenModel):
    """RFC 9457 problem details (``application/problem+json``)."""

    type: str = "about:blank"
    title: str
    status: int
    detail: str = ""
    errors: list[ProblemField] = []
    """One entry per invalid field, e.g. ``{"field": "scene.objects.2.radius", ...}``."""


RenderPublic.model_rebuild()
