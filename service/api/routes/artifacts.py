"""``/v1/artifacts``: content-addressed results (manifest and images), checksum-verified on read."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Response
from fastapi.responses import StreamingResponse

from api_schemas.service import ArtifactManifest, Sha256
from producer.artifacts import read_blob, read_manifest, stream_blob
from producer.store import NotFound, ObjectStore
from service.api.deps import OwnerDep, StoreDep, scene_visible
from service.api.errors import problem_responses

router = APIRouter(prefix="/v1/artifacts", tags=["artifacts"])

ArtifactKey = Annotated[Sha256, Path(description="Artifact key (sha256 hex)")]

VERIFY_BEFORE_SEND_BYTES = 256 << 20
"""Blobs up to this size are read and verified before the first byte is sent, so a checksum
mismatch is a clean 404. Larger ones stream; a mismatch then truncates the response
(``stream_blob`` holds back the last chunk) and invalidates the artifact."""


def _visible_manifest(store: ObjectStore, key: str, owner: str | None) -> ArtifactManifest:
    manifest = read_manifest(store, key)
    if manifest is None:
        raise NotFound(key)
    if owner is not None:
        scene_id = manifest.inputs.get("scene")
        if scene_id is None or not scene_visible(store, scene_id, owner):
            raise NotFound(key)
    return manifest


def blob_response(store: ObjectStore, key: str, owner: str | None, name: str, media_type: str,
                   ext: str) -> Response:
    manifest = _visible_manifest(store, key, owner)
    info = next((b for b in manifest.blobs if b.name == name), None)
    if info is None:
        raise NotFound(f"{key}/{name}")
    headers = {
        "ETag": f'"{info.sha256}"',
        "Cache-Control": "private, max-age=31536000, immutable",
        "Content-Disposition": f'inline; filename="{key[:16]}.{ext}"',
    }
    if info.size <= VERIFY_BEFORE_SEND_BYTES:
        return Response(read_blob(store, key, name), media_type=media_type, headers=headers)
    info, chunks = stream_blob(store, key, name)
    headers["Content-Length"] = str(info.size)
    return StreamingResponse(chunks, media_type=media_type, headers=headers)


_ERRORS = problem_responses(401, 404, 422, 429, 503)


@router.get("/{key}", response_model=ArtifactManifest, responses=_ERRORS)
def read_artifact(key: ArtifactKey, store: StoreDep, owner: OwnerDep) -> ArtifactManifest:
    """An artifact's manifest: its blobs with checksums, parameters and the job's result."""
    return _visible_manifest(store, key, owner)


@router.get(
    "/{key}/image.exr",
    response_class=Response,
    responses={200: {"content": {"image/x-exr": {"schema": {"type": "string", "format": "binary"}}},
                     "description": "Linear radiance, float EXR"}, **_ERRORS},
)
def read_image_exr(key: ArtifactKey, store: StoreDep, owner: OwnerDep) -> Response:
    """The rendered radiance as a float OpenEXR image."""
    return blob_response(store, key, owner, "radiance.exr", "image/x-exr", "exr")


@router.get(
    "/{key}/image.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}}},
                     "description": "sRGB preview, 8-bit PNG"}, **_ERRORS},
)
def read_image_png(key: ArtifactKey, store: StoreDep, owner: OwnerDep) -> Response:
    """An sRGB preview of the render as PNG (exposure 0)."""
    return blob_response(store, key, owner, "preview.png", "image/png", "png")


@router.get(
    "/{key}/provenance.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}}},
                     "description": "LDC renders: 8-bit grey PNG, pixel value = provenance code 0..4"}, **_ERRORS},
)
def read_provenance_png(key: ArtifactKey, store: StoreDep, owner: OwnerDep) -> Response:
    """Per-pixel provenance of an LDC render (0 background, 1 warped, 2 hole-filled, 3 gathered, 4 traced)."""
    return blob_response(store, key, owner, "provenance.png", "image/png", "provenance.png")
