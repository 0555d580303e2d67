"""Illumination datasets in the object store: validated image blobs and dataset documents.

Imported by the API process, so it never imports numba: images are decoded with OpenImageIO
directly (the same library ``engine.imageio`` wraps). An upload is checked from its header (pixels,
channels, decoded size as float32 against a budget) before any pixel is decoded, and its statistics
are gathered a band of rows at a time (:func:`scan_image`), so a small compressed file declaring
gigabytes of pixels costs the API nothing. The dataset jobs' artifact keys are here too
(their names and payloads are in ``producer.names`` and ``producer.payloads``).

Key layout (next to docs/service-design.md's):

- ``blobs/<sha256>``: an uploaded file (image, depth map, mask, environment map, plate), by content;
- ``blob-info/<sha256>.json``: its header facts and pixel statistics, written after the blob once
  it decoded as an image (its presence means "received and readable");
- ``blob-owners/<sha256>/<owner>``: an API key that sent those bytes itself; only such a key sees
  the file or may name it (``producer.ownership``; knowing a hash grants nothing);
- ``dataset-pending/<id>.json``: a manifest whose files are being uploaded separately;
- ``datasets/<id>.json``: ``{"manifest", "files", "width", "height", "created_at", "source"}``,
  written LAST (its presence commits the dataset);
- ``dataset-owners/<id>/<owner>``: one empty marker per API key that stored the dataset (``_``
  with auth off; ``producer.ownership``).

A dataset id is the sha256 of the canonical JSON of its manifest with every file's sha256 filled
in (:func:`dataset_id_for`). Nothing half-stored is visible: blobs are content-addressed and
unreferenced until a document names them, and the document is checked completely before it is
written.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import tempfile
import threading
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np
from pydantic import ValidationError

from api_schemas.datasets import (
    CompositeRequest,
    DatasetBakeParams,
    DatasetFileInfo,
    DatasetManifest,
    DatasetPublic,
    FileUploadPublic,
    GenerateRequest,
    MissingFile,
    RelightEnvironmentLight,
    RelightRequest,
    parse_transfer,
)
from api_schemas.errors import FieldError, format_error_details
from engine import ENGINE_VERSION
from producer.artifacts import artifact_key, blob_key, canonical_json, put_blob_unless_intact, sha256_hex
from producer.listings import page_index
from producer.names import COMPOSITE_KIND, DATASET_BAKE_KIND, GENERATE_KIND, RELIGHT_KIND
from producer.ownership import (
    ANON_OWNER,
    DATASET_OWNERS_PREFIX,
    add_blob_owner,
    add_dataset_owner,
    blob_visible,
    dataset_index_prefix,
    dataset_owners,
    dataset_visible,
    remove_dataset_owner,
    stamp,
)
from producer.store import ChecksumMismatch, NotFound, ObjectStore

__all__ = [
    "DatasetInvalid",
    "bake_artifact_key",
    "composite_artifact_key",
    "composite_inputs",
    "generate_artifact_key",
    "manifest_errors",
    "relight_artifact_key",
    "relight_inputs",
    "FileProblem",
    "ImageFile",
    "blob_info",
    "commit_dataset",
    "dataset_id_for",
    "dataset_key",
    "ImageTooLarge",
    "decode_image",
    "decode_slots",
    "decoded_size",
    "owned_blob_info",
    "scan_image",
    "delete_dataset",
    "fill_shas",
    "get_dataset",
    "linearise",
    "list_dataset_page",
    "list_datasets",
    "rebuild_dataset_index",
    "missing_files",
    "put_pending",
    "read_file_blob",
    "read_pending",
    "sniff_extension",
    "store_file",
]

log = logging.getLogger(__name__)

_SHA256 = re.compile(r"[0-9a-f]{64}")
_MIB = 1 << 20
_INTEGER_TYPES = {"uint8", "int8", "uint16", "int16", "uint", "int", "uint32", "int32"}

# magic bytes -> (extension OpenImageIO picks its reader by, format label)
_MAGIC: tuple[tuple[bytes, str], ...] = (
    (b"\x76\x2f\x31\x01", ".exr"),
    (b"\x89PNG\r\n\x1a\n", ".png"),
    (b"II*\x00", ".tif"),
    (b"MM\x00*", ".tif"),
    (b"#?RADIANCE", ".hdr"),
    (b"#?RGBE", ".hdr"),
    (b"\xff\xd8\xff", ".jpg"),
)
SUPPORTED_FORMATS = "OpenEXR, Radiance HDR, PNG, TIFF, JPEG"


class FileProblem(ValueError):
    """An uploaded file is not a usable image (the message says why, without the file name)."""


class DatasetInvalid(ValueError):
    """A dataset cannot be stored; ``errors`` names each field or file (HTTP 422)."""

    def __init__(self, errors: Sequence[FieldError], status: int = 422):
        super().__init__("; ".join(f"{e['field']}: {e['message']}" for e in errors))
        self.errors = list(errors)
        self.status = status


# ------------------------------------------------------------------------------ keys


def _require_sha(value: str, what: str) -> str:
    if not isinstance(value, str) or _SHA256.fullmatch(value) is None:
        raise NotFound(f"{what} {value!r}")
    return value


def dataset_key(dataset_id: str) -> str:
    return f"datasets/{_require_sha(dataset_id, 'dataset')}.json"


def _pending_key(dataset_id: str) -> str:
    return f"dataset-pending/{_require_sha(dataset_id, 'dataset')}.json"


def _info_key(sha: str) -> str:
    return f"blob-info/{_require_sha(sha, 'file')}.json"


def _now() -> datetime:
    return datetime.now(UTC)


# ------------------------------------------------------------------------------ images


@dataclass(frozen=True)
class ImageFile:
    """A decoded image: ``pixels`` (h, w, c) float32 as stored (integer files scaled to [0, 1],
    not linearised) and its header facts."""

    pixels: np.ndarray
    width: int
    height: int
    channels: int
    format: str
    pixel_type: str

    @property
    def is_integer(self) -> bool:
        return self.pixel_type in _INTEGER_TYPES


def sniff_extension(data: bytes) -> str | None:
    for magic, ext in _MAGIC:
        if data.startswith(magic):
            return ext
    return None


class ImageTooLarge(FileProblem):
    """The header declares an image whose decoded size is over the configured budget."""


_SCAN_CHUNK_BYTES = 8 << 20
"""Decoded bytes (float32) per band of rows :func:`scan_image` reads at a time."""
_DECODE_SLOTS: dict[int, threading.BoundedSemaphore] = {}
_DECODE_SLOTS_LOCK = threading.Lock()


def decode_slots(n: int) -> threading.BoundedSemaphore:
    """The process-wide semaphore bounding concurrent image validations to ``n`` (one per ``n``)."""
    with _DECODE_SLOTS_LOCK:
        return _DECODE_SLOTS.setdefault(n, threading.BoundedSemaphore(n))


def decoded_size(width: int, height: int, channels: int, bytes_per_channel: int = 4) -> int:
    """Bytes an image takes decoded: at least float32 per channel (wider native types count as such)."""
    return width * height * channels * max(4, bytes_per_channel)


@contextmanager
def _open_image(data: bytes, max_pixels: int, max_decoded_bytes: int | None) -> Iterator[tuple[Any, ImageFile]]:
    """Open an image file's bytes with OpenImageIO and check its header: (ImageInput, header facts
    with empty pixels). Nothing past the header is decoded here. Raises :class:`FileProblem`
    (:class:`ImageTooLarge` over ``max_pixels`` or ``max_decoded_bytes``)."""
    import OpenImageIO as oiio  # deferred on purpose: only uploads decode images; the API starts without it

    if not data:
        raise FileProblem("the file is empty")
    ext = sniff_extension(data)
    if ext is None:
        raise FileProblem(f"not an image in a supported format ({SUPPORTED_FORMATS}): unrecognised file signature")
    fd, path = tempfile.mkstemp(suffix=ext, prefix="ibr-upload-")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        inp = oiio.ImageInput.open(path)
        if inp is None:
            raise FileProblem(f"cannot read the image: {_oiio_error(oiio.geterror(), path)}")
        try:
            spec = inp.spec()
            w, h, c = int(spec.width), int(spec.height), int(spec.nchannels)
            if w < 1 or h < 1 or c < 1:
                raise FileProblem(f"the header declares an empty image ({w}x{h}, {c} channels)")
            if int(spec.depth) != 1 or spec.deep:
                raise FileProblem("volume and deep images are not supported")
            if w * h > max_pixels:
                raise ImageTooLarge(f"the header declares {w}x{h} = {w * h} pixels, more than this server's limit "
                                    f"of {max_pixels}")
            if c > 16:
                raise FileProblem(f"the header declares {c} channels; at most 16 are supported")
            size = decoded_size(w, h, c, int(spec.format.size()))
            if max_decoded_bytes is not None and size > max_decoded_bytes:
                raise ImageTooLarge(
                    f"the header declares {w}x{h} pixels x {c} channels: {size} bytes ({size / _MIB:.1f} MiB) "
                    f"decoded as float32, over this server's limit of {max_decoded_bytes} bytes "
                    f"({max_decoded_bytes / _MIB:.1f} MiB) per file")
            header = ImageFile(np.zeros((0, 0, 0), np.float32), w, h, c, str(inp.format_name()), str(spec.format))
            yield inp, header
            if inp.has_error:
                raise FileProblem(f"cannot read the pixels (truncated or corrupt?): "
                                  f"{_oiio_error(inp.geterror(), path)}")
        finally:
            inp.close()
    finally:
        try:
            os.unlink(path)
        except OSError:
            pass


def decode_image(data: bytes, *, max_pixels: int, header_only: bool = False,
                 max_decoded_bytes: int | None = None) -> ImageFile:
    """Decode an image file's bytes with OpenImageIO. The declared resolution is checked against
    ``max_pixels`` (and the decoded size against ``max_decoded_bytes``) before any pixel is read
    (docs/hard-cases.md #16). Raises :class:`FileProblem`."""
    import OpenImageIO as oiio

    with _open_image(data, max_pixels, max_decoded_bytes) as (inp, header):
        if header_only:
            return header
        w, h, c = header.width, header.height, header.channels
        raw = inp.read_image(0, 0, 0, c, oiio.FLOAT)
        if raw is None or inp.has_error:
            raise FileProblem(f"cannot read the pixels (truncated or corrupt?): {_oiio_error(inp.geterror(), '')}")
        pixels = np.array(raw, dtype=np.float32).reshape(h, w, c)
    return ImageFile(pixels, w, h, c, header.format, header.pixel_type)


def scan_image(data: bytes, *, max_pixels: int, max_decoded_bytes: int | None = None
               ) -> tuple[ImageFile, dict[str, int]]:
    """Header facts (empty pixels) and pixel statistics (``n_nonfinite``, ``n_negative``) of an
    image file, decoded a band of rows (or of tiles) at a time: beyond the file and whatever its
    reader buffers, at most ``_SCAN_CHUNK_BYTES`` of float pixels are held at once. Raises
    :class:`FileProblem`."""
    import OpenImageIO as oiio

    with _open_image(data, max_pixels, max_decoded_bytes) as (inp, header):
        spec = inp.spec()
        w, h, c = header.width, header.height, header.channels
        tile_h = int(spec.tile_height) if int(spec.tile_width) > 0 else 0
        rows = max(1, _SCAN_CHUNK_BYTES // (w * c * 4))
        if tile_h:
            rows = max(tile_h, rows // tile_h * tile_h)
        x0, y_first, z0 = int(spec.x), int(spec.y), int(spec.z)
        n_nonfinite = n_negative = 0
        for y0 in range(y_first, y_first + h, rows):
            y1 = min(y0 + rows, y_first + h)
            if tile_h:
                raw = inp.read_tiles(0, 0, x0, x0 + w, y0, y1, z0, z0 + 1, 0, c, oiio.FLOAT)
            else:
                raw = inp.read_scanlines(0, 0, y0, y1, z0, 0, c, oiio.FLOAT)
            if raw is None or inp.has_error:
                raise FileProblem(f"cannot read the pixels (truncated or corrupt?): "
                                  f"{_oiio_error(inp.geterror(), '')}")
            band = np.asarray(raw, dtype=np.float32)
            finite = np.isfinite(band)
            n_nonfinite += int(band.size - np.count_nonzero(finite))
            n_negative += int(np.count_nonzero(np.where(finite, band, 0.0) < 0))
            del raw, band, finite
    return header, {"n_nonfinite": n_nonfinite, "n_negative": n_negative}


def _oiio_error(msg: str, path: str) -> str:
    text = (msg or "unknown error").strip().splitlines()[0] if (msg or "").strip() else "unknown error"
    if path:
        text = text.replace(path, "<file>")
    return re.sub(r"/\S*ibr-upload-\S*", "<file>", text)[:300]


def linearise(img: ImageFile, transfer: str) -> np.ndarray:
    """(h, w, 3) float32 linear RGB: grey is repeated, alpha dropped; integer files decoded with
    ``transfer`` (``srgb``, ``linear``, ``gamma:<g>``), float files taken as linear."""
    px = img.pixels
    rgb = np.repeat(px[:, :, :1], 3, axis=2) if px.shape[2] < 3 else px[:, :, :3]
    rgb = np.ascontiguousarray(rgb, dtype=np.float32)
    if not img.is_integer:
        return rgb
    kind, g = parse_transfer(transfer)
    v = rgb.astype(np.float64)
    if kind == "srgb":
        v = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    elif kind == "gamma":
        v = np.power(v, g)
    return v.astype(np.float32)


# ------------------------------------------------------------------------------ file blobs


def blob_info(store: ObjectStore, sha: str) -> dict[str, Any] | None:
    """The stored facts of a received file, or None when it was not received (or not an image)."""
    try:
        raw = store.get_bytes(_info_key(sha))
    except NotFound:
        return None
    try:
        info: dict[str, Any] = json.loads(raw)
        FileUploadPublic.model_validate({k: info[k] for k in FileUploadPublic.model_fields})
    except (ValueError, KeyError, TypeError):
        log.error("file %s: unreadable info record deleted", sha)
        store.delete(_info_key(sha))
        return None
    if not store.exists(blob_key(sha)):
        store.delete(_info_key(sha))
        return None
    return info


def owned_blob_info(store: ObjectStore, sha: str, owner: str | None) -> dict[str, Any] | None:
    """:func:`blob_info` of a file ``owner`` uploaded itself (any file with auth off); None otherwise,
    exactly as for a file nobody uploaded: knowing a hash grants nothing."""
    if not blob_visible(store, sha, owner):
        return None
    return blob_info(store, sha)


def store_file(store: ObjectStore, data: bytes, *, max_pixels: int, expected_sha: str | None = None,
               owner: str | None = None, max_decoded_bytes: int | None = None) -> dict[str, Any]:
    """Validate ``data`` as an image and store it under its sha256 (blob first, then its info
    record), recording ``owner`` as one who sent it. Returns the info record. The header is
    checked against ``max_pixels`` and ``max_decoded_bytes`` before any pixel is decoded, and the
    statistics are gathered a band of rows at a time (:func:`scan_image`). Raises
    :class:`FileProblem`; nothing is stored then."""
    sha = sha256_hex(data)
    if expected_sha is not None and sha != expected_sha:
        raise FileProblem(f"the content's sha256 is {sha}, not {expected_sha} as the URL / manifest says")
    existing = blob_info(store, sha)
    if existing is not None:
        put_blob_unless_intact(store, sha, data)  # a stored copy that went bad is replaced by these bytes
        add_blob_owner(store, sha, owner)  # the bytes were sent: proof of possession
        return existing
    img, stats = scan_image(data, max_pixels=max_pixels, max_decoded_bytes=max_decoded_bytes)
    info: dict[str, Any] = {"sha256": sha, "size": len(data), "width": img.width, "height": img.height,
                            "channels": img.channels, "format": img.format, "pixel_type": img.pixel_type,
                            **stats}
    put_blob_unless_intact(store, sha, data)
    store.put_bytes(_info_key(sha), canonical_json(info).encode(), "application/json")
    add_blob_owner(store, sha, owner)
    return info


def read_file_blob(store: ObjectStore, sha: str) -> bytes:
    """A stored file's bytes, verified (a corrupt blob is deleted with its info record and raises
    ChecksumMismatch: upload it again)."""
    data = store.get_bytes(blob_key(sha))
    if sha256_hex(data) != sha:
        log.error("blob %s does not match its checksum; deleted", sha)
        store.delete(blob_key(sha))
        store.delete(_info_key(sha))
        raise ChecksumMismatch(f"file {sha}: stored copy is corrupt and was removed; upload it again")
    return data


# ------------------------------------------------------------------------------ manifests


def fill_shas(manifest: DatasetManifest, shas: Mapping[str, str]) -> DatasetManifest:
    """The manifest with the sha256 of every file named in ``shas`` filled in."""
    doc = manifest.model_dump(mode="json")
    for img in doc["images"]:
        if img["file"] in shas:
            img["sha256"] = shas[img["file"]]
    for part in ("geometry", "mask"):
        ref = doc.get(part)
        if isinstance(ref, dict) and "file" in ref and ref["file"] in shas:
            ref["sha256"] = shas[ref["file"]]
    return DatasetManifest.model_validate(doc)


def dataset_id_for(manifest: DatasetManifest) -> str:
    """sha256 of the canonical JSON of the manifest; every file must have its sha256."""
    unset = [f for f, _, sha, _ in manifest.file_refs() if sha is None]
    if unset:
        raise ValueError(f"file sha256 not set for {unset[:5]}")
    return hashlib.sha256(canonical_json(manifest.model_dump(mode="json")).encode("utf-8")).hexdigest()


def missing_files(store: ObjectStore, manifest: DatasetManifest, dataset_id: str, owner: str | None = None
                  ) -> tuple[list[MissingFile], int]:
    """Files of the manifest ``owner`` has not sent yet (one entry per distinct sha256; a file
    another key sent counts as missing), and the count received."""
    missing: list[MissingFile] = []
    seen: set[str] = set()
    received = 0
    for field, name, sha, _ in manifest.file_refs():
        assert sha is not None
        if sha in seen:
            continue
        seen.add(sha)
        if owned_blob_info(store, sha, owner) is None:
            missing.append(MissingFile(field=field, name=name, sha256=sha,
                                       upload_url=f"/v1/datasets/uploads/{sha}"))
        else:
            received += 1
    return missing, received


def put_pending(store: ObjectStore, manifest: DatasetManifest, dataset_id: str) -> None:
    if not store.exists(_pending_key(dataset_id)):
        doc = {"manifest": manifest.model_dump(mode="json"), "created_at": _now().isoformat()}
        store.put_bytes(_pending_key(dataset_id), canonical_json(doc).encode(), "application/json")


def read_pending(store: ObjectStore, dataset_id: str) -> DatasetManifest | None:
    try:
        raw = store.get_bytes(_pending_key(dataset_id))
    except NotFound:
        return None
    try:
        manifest = DatasetManifest.model_validate(json.loads(raw)["manifest"])
        ok = dataset_id_for(manifest) == dataset_id
    except (ValueError, KeyError, TypeError):
        ok = False
    if not ok:
        store.delete(_pending_key(dataset_id))
        return None
    return manifest


# ------------------------------------------------------------------------------ commit


def _check_files(store: ObjectStore, manifest: DatasetManifest, owner: str | None
                 ) -> tuple[list[DatasetFileInfo], int, int]:
    """Cross-file checks; DatasetInvalid naming every bad file (409 for a file ``owner`` has not
    uploaded itself). Returns (files, width, height)."""
    errors: list[FieldError] = []
    cam = manifest.camera
    width, height = cam.width, cam.height
    files: list[DatasetFileInfo] = []
    missing: list[FieldError] = []
    for field, name, sha, role in manifest.file_refs():
        assert sha is not None
        info = owned_blob_info(store, sha, owner)
        if info is None:
            missing.append(FieldError(field=f"{field}.file",
                                      message=f"file {name!r} (sha256 {sha}) has not been uploaded",
                                      type="missing_file"))
            continue
        where = f"files.{name}"
        w, h = int(info["width"]), int(info["height"])
        if (w, h) != (width, height):
            errors.append(FieldError(field=where, message=f"{role} {name!r} is {w}x{h} but the camera (and every "
                                     f"image of the dataset) is {width}x{height}", type="wrong_size"))
        if role == "image":
            if info["n_nonfinite"]:
                errors.append(FieldError(field=where, message=f"image {name!r} holds {info['n_nonfinite']} NaN/Inf "
                                         "sample(s)", type="non_finite"))
            if info["n_negative"]:
                errors.append(FieldError(field=where, message=f"image {name!r} holds {info['n_negative']} negative "
                                         "sample(s); radiance must be >= 0", type="negative"))
        elif role == "depth":
            if info["pixel_type"] in _INTEGER_TYPES:
                errors.append(FieldError(field=where, message=f"depth map {name!r} is a {info['pixel_type']} "
                                         "image; depth must be a float image (EXR, float TIFF, HDR) in world units",
                                         type="depth_not_float"))
        files.append(DatasetFileInfo(field=field, name=name, sha256=sha, size=int(info["size"]), width=w, height=h,
                                     pixel_type=str(info["pixel_type"])))
    if missing:
        raise DatasetInvalid(missing, status=409)
    if errors:
        raise DatasetInvalid(errors)
    return files, width, height


def _public(dataset_id: str, doc: Mapping[str, Any]) -> DatasetPublic:
    manifest = DatasetManifest.model_validate(doc["manifest"])
    return DatasetPublic(
        id=dataset_id,
        name=manifest.name,
        created_at=doc["created_at"],
        n_images=len(manifest.images),
        width=int(doc["width"]),
        height=int(doc["height"]),
        distant=manifest.distant,
        transfer=manifest.transfer,
        geometry=manifest.geometry.type,
        has_mask=manifest.mask is not None,
        total_bytes=sum(int(f["size"]) for f in doc["files"]),
        manifest=manifest,
        source=dict(doc.get("source") or {"kind": "upload"}),
        links={"self": f"/v1/datasets/{dataset_id}", "bake": f"/v1/datasets/{dataset_id}/bake"},
    )


def commit_dataset(store: ObjectStore, manifest: DatasetManifest, owner: str | None,
                   source: Mapping[str, Any] | None = None, *, scene_exists: bool | None = None,
                   add_owner: bool = True) -> tuple[DatasetPublic, bool]:
    """Check every file of the manifest (received from ``owner``, same size as the camera, finite,
    >= 0, depth a float image) and write the dataset document LAST; add ``owner``'s marker. A key
    joins a dataset stored already only by sending its files too. Returns (public view, new
    document?). DatasetInvalid (status 409 when files are missing, 422 otherwise)."""
    dataset_id = dataset_id_for(manifest)
    existing = _read_doc(store, dataset_id)
    if existing is not None:
        if add_owner and not dataset_visible(store, dataset_id, owner):
            _check_files(store, manifest, owner)  # 409 naming the files this key has not sent
        _index(store, dataset_id, existing)  # idempotent: the entry's name depends only on the document
        if add_owner:
            add_dataset_owner(store, dataset_id, owner)
        store.delete(_pending_key(dataset_id))
        return _public(dataset_id, existing), False
    if manifest.geometry.type == "scene":
        present = scene_exists if scene_exists is not None else store.exists(
            f"scenes/{manifest.geometry.scene_id}.json")
        if not present:
            raise DatasetInvalid([FieldError(field="geometry.scene_id", message=f"no stored scene "
                                             f"{manifest.geometry.scene_id}", type="unknown_scene")])
    files, width, height = _check_files(store, manifest, owner)
    doc = {"manifest": manifest.model_dump(mode="json"), "files": [f.model_dump(mode="json") for f in files],
           "width": width, "height": height, "created_at": _now().isoformat(),
           "source": dict(source or {"kind": "upload"})}
    store.put_bytes(dataset_key(dataset_id), canonical_json(doc).encode("utf-8"), "application/json")
    _index(store, dataset_id, doc)
    if add_owner:
        add_dataset_owner(store, dataset_id, owner)
    store.delete(_pending_key(dataset_id))
    return _public(dataset_id, doc), True


def _all_entry(dataset_id: str, doc: Mapping[str, Any]) -> str:
    """The dataset's entry in the index of every dataset: named by when it was stored."""
    return f"{dataset_index_prefix(None)}{stamp(datetime.fromisoformat(str(doc['created_at'])))}-{dataset_id}"


def _index(store: ObjectStore, dataset_id: str, doc: Mapping[str, Any]) -> None:
    store.put_bytes(_all_entry(dataset_id, doc), b"", "text/plain")


def _read_doc(store: ObjectStore, dataset_id: str) -> dict[str, Any] | None:
    try:
        raw = store.get_bytes(dataset_key(dataset_id))
    except NotFound:
        return None
    try:
        doc: dict[str, Any] = json.loads(raw)
        manifest = DatasetManifest.model_validate(doc["manifest"])
        if dataset_id_for(manifest) != dataset_id:
            raise ValueError("content does not hash to its id")
        _public(dataset_id, doc)
    except (ValueError, KeyError, TypeError) as exc:  # ValidationError is a ValueError
        log.error("dataset %s: stored document corrupt (%s); deleted", dataset_id, exc)
        store.delete(dataset_key(dataset_id))
        raise ChecksumMismatch(f"dataset {dataset_id}: stored document is corrupt and was removed; "
                               "upload it again") from None
    return doc


def get_dataset(store: ObjectStore, dataset_id: str) -> tuple[DatasetManifest, DatasetPublic]:
    """(canonical manifest, public view); NotFound when absent."""
    doc = _read_doc(store, _require_sha(dataset_id, "dataset"))
    if doc is None:
        raise NotFound(f"dataset {dataset_id}")
    public = _public(dataset_id, doc)
    return public.manifest, public


def list_dataset_page(store: ObjectStore, owner: str | None, limit: int, cursor: str | None = None
                      ) -> tuple[list[DatasetPublic], str | None]:
    """One page of the datasets ``owner`` holds (every dataset with owner None), oldest first (by
    when ``owner`` first held it; by when it was stored with auth off), and the cursor of the next
    page (None after the last): reads ``owner``'s dataset index (``dataset_index_prefix``) and the
    documents of this page only. An entry whose dataset is gone (deleted, or its document found
    corrupt) is removed. ``producer.listings.BadCursor`` for a cursor no listing returned."""

    def load(ids: list[str]) -> list[DatasetPublic | None]:
        out: list[DatasetPublic | None] = []
        for did in ids:
            try:
                doc = _read_doc(store, did)
            except ChecksumMismatch:
                doc = None
            out.append(_public(did, doc) if doc is not None else None)
        return out

    return page_index(store, dataset_index_prefix(owner), limit, cursor, load)


def list_datasets(store: ObjectStore, owner: str | None) -> list[DatasetPublic]:
    """Every dataset ``owner`` holds, oldest first (all pages of ``list_dataset_page``)."""
    out: list[DatasetPublic] = []
    cursor: str | None = None
    while True:
        page, cursor = list_dataset_page(store, owner, 1000, cursor)
        out += page
        if cursor is None:
            return out


def rebuild_dataset_index(store: ObjectStore) -> int:
    """Index every stored dataset for its holders (the markers ``dataset-owners/<id>/<owner>``) and
    for everybody, each at the time it was stored: what a store written before the index needs
    once; idempotent. Returns how many datasets were indexed."""
    holders: dict[str, list[str]] = {}
    for key in store.list(DATASET_OWNERS_PREFIX):
        did, _, who = key[len(DATASET_OWNERS_PREFIX):].partition("/")
        holders.setdefault(did, []).append(who)
    n = 0
    for did, held_by in holders.items():
        try:
            doc = _read_doc(store, did) if _SHA256.fullmatch(did) else None
        except ChecksumMismatch:
            doc = None
        if doc is None:
            continue
        _index(store, did, doc)
        for w in held_by:
            add_dataset_owner(store, did, None if w == ANON_OWNER else w,
                              since=datetime.fromisoformat(str(doc["created_at"])))
        n += 1
    return n


def delete_dataset(store: ObjectStore, dataset_id: str, owner: str | None) -> None:
    """Remove ``owner``'s marker (every marker with auth off); the document goes with the last
    marker (its entry in the index of every dataset first). Blobs stay (content-addressed,
    possibly shared). NotFound when not visible."""
    if not dataset_visible(store, dataset_id, owner) or not store.exists(dataset_key(dataset_id)):
        raise NotFound(f"dataset {dataset_id}")
    for who in dataset_owners(store, dataset_id) if owner is None else [owner]:
        remove_dataset_owner(store, dataset_id, who)
    if not dataset_owners(store, dataset_id):
        try:
            doc = _read_doc(store, dataset_id)
        except ChecksumMismatch:
            doc = None  # removed as corrupt: its index entry goes at the next listing
        if doc is not None:
            store.delete(_all_entry(dataset_id, doc))
        store.delete(dataset_key(dataset_id))


def manifest_errors(exc: ValidationError, prefix: str = "") -> list[FieldError]:
    """A manifest's validation errors as field errors (``images.2.intensity.0``)."""
    out = format_error_details(exc.errors(include_url=False), DatasetManifest)
    if prefix:
        out = [FieldError(field=f"{prefix}.{e['field']}" if e["field"] else prefix, message=e["message"],
                          type=e["type"]) for e in out]
    return out


# ------------------------------------------------------------------------------ artifact keys of the dataset jobs


def bake_artifact_key(dataset_id: str, params: DatasetBakeParams) -> str:
    return artifact_key(DATASET_BAKE_KIND, {"dataset": dataset_id}, params.model_dump(mode="json"), ENGINE_VERSION)


def _relight_inputs(req: RelightRequest | CompositeRequest, dataset_ids: Mapping[str, str]) -> dict[str, str]:
    inputs = dict(dataset_ids)
    for role, did in dataset_ids.items():
        inputs[f"bake.{role}"] = bake_artifact_key(did, req.bake)
    for i, light in enumerate(req.lights):
        if isinstance(light, RelightEnvironmentLight):
            inputs[f"environment.{i}"] = light.image_sha256
    return inputs


def relight_inputs(req: RelightRequest) -> tuple[dict[str, str], dict[str, Any]]:
    """(artifact inputs, artifact params) of a relight: the dataset, its bake and environment maps
    are inputs (content hashes), the rest of the request is params."""
    params = req.model_dump(mode="json")
    params.pop("dataset_id")
    return _relight_inputs(req, {"dataset": req.dataset_id}), params


def relight_artifact_key(req: RelightRequest) -> str:
    inputs, params = relight_inputs(req)
    return artifact_key(RELIGHT_KIND, inputs, params, ENGINE_VERSION)


def composite_artifact_key(req: CompositeRequest) -> str:
    inputs, params = composite_inputs(req)
    return artifact_key(COMPOSITE_KIND, inputs, params, ENGINE_VERSION)


def composite_inputs(req: CompositeRequest) -> tuple[dict[str, str], dict[str, Any]]:
    """(artifact inputs, artifact params) of a composite: content hashes are inputs."""
    params = req.model_dump(mode="json")
    inputs = _relight_inputs(req, {"dataset": req.object_dataset_id, "background": req.background_dataset_id})
    inputs["plate"] = req.plate_sha256
    inputs["object_mask"] = req.object_mask_sha256
    if req.active_region_sha256 is not None:
        inputs["active_region"] = req.active_region_sha256
    for role in ("object_dataset_id", "background_dataset_id", "plate_sha256", "object_mask_sha256",
                 "active_region_sha256"):
        params.pop(role)
    return inputs, params


def generate_artifact_key(req: GenerateRequest) -> str:
    params = req.model_dump(mode="json")
    params.pop("scene_id")
    return artifact_key(GENERATE_KIND, {"scene": req.scene_id}, params, ENGINE_VERSION)
