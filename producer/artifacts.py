"""What lives where in the object store: content-addressed artifacts, scenes and blobs.

Key layout (see docs/service-design.md):

- ``blobs/<sha256>``: uploaded mesh files, by content. User-supplied file names never
  become keys; they are only metadata inside scene documents.
- ``scenes/<scene_id>.json``: ``{"scene", "meshes": [{"path", "sha256", "size"}],
  "created_at", "owner"}``, written after its blobs.
- ``scene-summaries/<scene_id>.json``: the scene's public view (``ScenePublic``: name, counts,
  mesh list), a few hundred bytes whatever the scene's size, written after the document and
  removed before it: what scene listings read (``producer.listings``).
- ``artifacts/<key>/<name>``: an artifact's blobs; ``artifacts/<key>/manifest.json``
  (an ``ArtifactManifest`` with each blob's sha256) is written LAST and commits the
  artifact. No manifest = no artifact.

Integrity: every read is checked against a recorded sha256. A bad artifact blob removes
the manifest (so the artifact is absent and gets rebaked) and raises ChecksumMismatch;
bad bytes are never returned.

Canonical JSON for keys: ``sort_keys=True, separators=(",", ":")``, ``allow_nan=False``.
Numbers are rendered by ``json`` (shortest round-trip ``repr`` for floats), so a value's
TYPE matters: ``1`` and ``1.0`` give different keys. Params must therefore come from
``model.model_dump(mode="json")`` of a pydantic model, whose field types are fixed, never
from hand-built dicts. A type difference can only cause a cache miss, never a wrong hit.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from pathlib import PurePosixPath
from typing import Any

from pydantic import ValidationError

from api_schemas.scene import MeshFileObject, Scene, canonical_scene_json
from api_schemas.service import ArtifactManifest, BlobInfo, MeshBlob, ScenePublic
from producer.store import DEFAULT_CHUNK, ChecksumMismatch, NotFound, ObjectStore, StoreError

__all__ = [
    "MANIFEST_NAME",
    "MeshResolver",
    "artifact_key",
    "artifact_prefix",
    "blob_key",
    "blob_reader",
    "canonical_json",
    "delete_artifact",
    "delete_scene",
    "get_scene",
    "list_scenes",
    "manifest_key",
    "mesh_paths",
    "put_blob_unless_intact",
    "put_scene",
    "read_blob",
    "read_manifest",
    "scene_id_for",
    "scene_key",
    "scene_summary_key",
    "read_scene_summary",
    "write_scene_summary",
    "sha256_hex",
    "store_scene",
    "stream_blob",
    "write_artifact",
]

log = logging.getLogger(__name__)

MANIFEST_NAME = "manifest.json"
_SHA256 = re.compile(r"[0-9a-f]{64}")
_BLOB_NAME = re.compile(r"[A-Za-z0-9._-]{1,255}")

MeshResolver = Callable[[str], tuple[bytes, str]]
"""Same shape as ``workers.scene_loader.MeshResolver`` (not imported: the producer never imports
the worker runtime)."""


# ------------------------------------------------------------------------------ helpers


def canonical_json(obj: Any) -> str:
    """Compact JSON with sorted keys, non-ASCII kept as is, NaN/Inf rejected (ValueError)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def _canonical_ascii(obj: Any) -> str:
    # the settings of api_schemas.scene.canonical_scene_json, for scene ids
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _require_sha(value: str, what: str) -> str:
    if not isinstance(value, str) or _SHA256.fullmatch(value) is None:
        raise ValueError(f"{what} must be 64 lower-case hex characters, got {value!r}")
    return value


def artifact_prefix(key: str) -> str:
    return f"artifacts/{_require_sha(key, 'artifact key')}/"


def manifest_key(key: str) -> str:
    return artifact_prefix(key) + MANIFEST_NAME


def blob_key(sha256: str) -> str:
    return f"blobs/{_require_sha(sha256, 'blob sha256')}"


def scene_key(scene_id: str) -> str:
    return f"scenes/{_require_sha(scene_id, 'scene id')}.json"


def scene_summary_key(scene_id: str) -> str:
    return f"scene-summaries/{_require_sha(scene_id, 'scene id')}.json"


def _now() -> datetime:
    return datetime.now(UTC)


# ------------------------------------------------------------------------------ artifacts


def artifact_key(kind: str, inputs: Mapping[str, str], params: Mapping[str, Any], engine_version: str) -> str:
    """sha256 of the canonical JSON of ``{"kind", "inputs", "params", "engine_version"}``.

    ``inputs`` maps roles to content hashes (``{"scene": scene_id}``); ``params`` must be
    JSON data from ``model_dump(mode="json")`` (see the module docstring). Raises
    ValueError for anything not representable as canonical JSON (NaN, sets, objects)."""
    if not isinstance(kind, str) or not kind:
        raise ValueError("artifact kind must be a non-empty string")
    if not isinstance(engine_version, str) or not engine_version:
        raise ValueError("engine_version must be a non-empty string")
    for role, value in inputs.items():
        if not isinstance(role, str) or not isinstance(value, str):
            raise ValueError(f"artifact inputs must map str -> str, got {role!r}: {value!r}")
    doc = {"kind": kind, "inputs": dict(inputs), "params": dict(params), "engine_version": engine_version}
    try:
        text = canonical_json(doc)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"artifact params are not canonical JSON data: {exc}") from exc
    # surrogatepass: a lone surrogate (legal in a Python str from JSON) still gets a distinct key
    return hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest()


def write_artifact(
    store: ObjectStore,
    key: str,
    kind: str,
    inputs: Mapping[str, str],
    params: Mapping[str, Any],
    engine_version: str,
    blobs: Mapping[str, tuple[bytes, str]],
    result: Mapping[str, Any],
    *,
    max_workers: int = 1,
) -> ArtifactManifest:
    """Write every blob (``name -> (bytes, content_type)``), then the manifest.

    With ``max_workers > 1`` the blob writes run concurrently on that many threads (their fsyncs
    or S3 round trips overlap), started in the order of ``blobs`` (put what a client waits for
    first); the manifest is still written only after every blob write has returned, and not at
    all when one failed (its error is raised once the others finished).

    ``key`` must equal ``artifact_key(kind, inputs, params, engine_version)`` (ValueError
    otherwise: publishing content under another request's key would serve wrong results).
    If the artifact is already committed its manifest is returned and nothing is
    written (first commit wins: a retried or duplicate job never rewrites blobs a
    published manifest vouches for). Everything is validated and serialized before the
    first write, so bad input writes nothing."""
    expected = artifact_key(kind, inputs, params, engine_version)
    if key != expected:
        raise ValueError(f"artifact key {key!r} does not match its inputs (expected {expected})")
    if isinstance(max_workers, bool) or not isinstance(max_workers, int) or max_workers < 1:
        raise ValueError(f"max_workers must be an int >= 1, got {max_workers!r}")
    infos: list[BlobInfo] = []
    for name in sorted(blobs):
        if _BLOB_NAME.fullmatch(name) is None or name in (".", "..", MANIFEST_NAME):
            raise ValueError(f"invalid artifact blob name {name!r}")
        data, content_type = blobs[name]
        infos.append(BlobInfo(name=name, sha256=sha256_hex(data), size=len(data), content_type=content_type))
    try:
        manifest = ArtifactManifest(
            key=key,
            kind=kind,
            inputs=dict(inputs),
            params=dict(params),
            engine_version=engine_version,
            blobs=infos,
            result=dict(result),
            created_at=_now(),
        )
        manifest_bytes = manifest.model_dump_json().encode("utf-8")
        canonical_json(manifest.result)  # JSON-safe and finite
    except (ValidationError, TypeError, ValueError) as exc:
        raise ValueError(f"artifact {key}: manifest cannot be serialized: {exc}") from exc

    existing = read_manifest(store, key)
    if existing is not None:
        return existing
    prefix = artifact_prefix(key)
    if max_workers > 1 and len(infos) > 1:
        with ThreadPoolExecutor(min(max_workers, len(infos)), thread_name_prefix="ibr-artifact") as pool:
            by_name = {info.name: info for info in infos}
            futures = [pool.submit(store.put_bytes, prefix + name, blobs[name][0], by_name[name].content_type)
                       for name in blobs]
            for future in futures:
                future.result()  # re-raises a failed write; leaving the block waits for the rest
    else:
        for info in infos:
            store.put_bytes(prefix + info.name, blobs[info.name][0], info.content_type)
    store.put_bytes(manifest_key(key), manifest_bytes, "application/json")
    return manifest


def read_manifest(store: ObjectStore, key: str) -> ArtifactManifest | None:
    """The committed manifest, or None when the artifact is absent.

    An unparsable manifest, or one recorded under another key, is corrupt: it is deleted
    and None returned (the artifact gets recomputed)."""
    mkey = manifest_key(key)
    try:
        data = store.get_bytes(mkey)
    except NotFound:
        return None
    try:
        manifest = ArtifactManifest.model_validate_json(data)
    except ValidationError as exc:
        log.warning("artifact %s: unreadable manifest deleted (%s)", key, exc.errors()[:1])
        store.delete(mkey)
        return None
    if manifest.key != key:
        log.warning("artifact %s: manifest names key %s; deleted", key, manifest.key)
        store.delete(mkey)
        return None
    return manifest


def _invalidate(store: ObjectStore, key: str, name: str, why: str) -> ChecksumMismatch:
    log.error("artifact %s: blob %s %s; manifest deleted so the artifact is recomputed", key, name, why)
    store.delete(manifest_key(key))
    return ChecksumMismatch(f"artifact {key}: blob {name!r} {why}; the artifact was invalidated")


def _blob_info(store: ObjectStore, key: str, name: str) -> BlobInfo:
    manifest = read_manifest(store, key)
    if manifest is None:
        raise NotFound(f"artifact {key}")
    for info in manifest.blobs:
        if info.name == name:
            return info
    raise NotFound(f"artifact {key} has no blob {name!r}")


def read_blob(store: ObjectStore, key: str, name: str) -> bytes:
    """A committed artifact's blob, verified against the manifest's sha256 and size.

    NotFound when the artifact (manifest) or the name is absent. A missing or altered
    blob deletes the manifest and raises ChecksumMismatch."""
    info = _blob_info(store, key, name)
    try:
        data = store.get_bytes(artifact_prefix(key) + name)
    except NotFound:
        raise _invalidate(store, key, name, "is missing") from None
    if len(data) != info.size or sha256_hex(data) != info.sha256:
        raise _invalidate(store, key, name, "does not match its checksum")
    return data


def stream_blob(
    store: ObjectStore, key: str, name: str, chunk: int = DEFAULT_CHUNK
) -> tuple[BlobInfo, Iterator[bytes]]:
    """``(info, chunks)`` of a committed artifact's blob, for large downloads.

    NotFound / a missing blob are raised by this call, before any chunk. The bytes are
    hashed while streaming and the LAST chunk is held back until the whole blob has
    matched ``info.sha256``: on a mismatch the manifest is deleted and ChecksumMismatch
    raised instead, so a client never receives a complete copy of bad bytes (with
    ``Content-Length: info.size`` it sees a truncated response)."""
    info = _blob_info(store, key, name)
    try:
        chunks = store.open_stream(artifact_prefix(key) + name, chunk)
    except NotFound:
        raise _invalidate(store, key, name, "is missing") from None

    def verified() -> Iterator[bytes]:
        digest = hashlib.sha256()
        size = 0
        pending: bytes | None = None
        for block in chunks:
            digest.update(block)
            size += len(block)
            if pending is not None:
                yield pending
            pending = block
        if size != info.size or digest.hexdigest() != info.sha256:
            raise _invalidate(store, key, name, "does not match its checksum")
        if pending is not None:
            yield pending

    return info, verified()


def delete_artifact(store: ObjectStore, key: str) -> None:
    """Manifest first (the artifact is absent from then on), then its blobs. Idempotent."""
    store.delete(manifest_key(key))
    for k in store.list(artifact_prefix(key)):
        store.delete(k)


# ------------------------------------------------------------------------------ scenes


def mesh_paths(scene: Scene) -> list[str]:
    """The distinct ``mesh_file`` paths a scene references, sorted: the uploads it needs."""
    return sorted({obj.path for obj in scene.objects if isinstance(obj, MeshFileObject)})


def _scene_id(scene_text: str, mesh_shas: Mapping[str, str]) -> str:
    h = hashlib.sha256(scene_text.encode("ascii"))
    h.update(b"\n")
    h.update(_canonical_ascii(sorted([p, s] for p, s in mesh_shas.items())).encode("ascii"))
    return h.hexdigest()


def scene_id_for(scene: Scene, mesh_shas: Mapping[str, str]) -> str:
    """sha256 of ``canonical_scene_json(scene)``, a newline, and the canonical JSON of the
    sorted ``[path, sha256]`` pairs of its mesh files: equal content, equal id."""
    return _scene_id(canonical_scene_json(scene), mesh_shas)


def _public(scene_id: str, doc: Mapping[str, Any]) -> ScenePublic:
    scene = doc["scene"]
    return ScenePublic(
        id=scene_id,
        name=scene.get("name", "untitled"),
        created_at=doc["created_at"],
        n_objects=len(scene.get("objects", [])),
        n_lights=len(scene.get("lights", [])),
        meshes=[MeshBlob.model_validate(m) for m in doc["meshes"]],
    )


def store_scene(
    store: ObjectStore, scene: Scene, meshes: Mapping[str, bytes], owner: str | None
) -> tuple[ScenePublic, bool]:
    """:func:`put_scene`, also saying whether the scene was new (True) or already stored.

    Only the mesh files the scene references are stored (each under ``blobs/<sha256>``,
    skipped when an intact copy is stored); other entries of ``meshes`` are ignored. A
    referenced path missing from ``meshes`` raises ValueError before anything is written.
    An existing scene keeps its document (first owner and ``created_at``), but blobs that
    are missing or fail their checksum are written again, so uploading again repairs a
    scene whose blob was found corrupt, or went bad before any reader found out. Its
    summary (``scene_summary_key``) is written after the document (again when missing)."""
    paths = mesh_paths(scene)
    missing = [p for p in paths if p not in meshes]
    if missing:
        raise ValueError(f"mesh files referenced by the scene but not supplied: {missing!r}")
    shas = {p: sha256_hex(meshes[p]) for p in paths}
    scene_text = canonical_scene_json(scene)
    scene_id = _scene_id(scene_text, shas)

    written: set[str] = set()
    for p in paths:
        sha = shas[p]
        if sha not in written:
            put_blob_unless_intact(store, sha, meshes[p])
        written.add(sha)

    try:
        existing = _read_scene_doc(store, scene_id)
    except ChecksumMismatch:
        existing = None  # the corrupt document was removed: write a good one
    if existing is not None:
        public = _public(scene_id, existing)
        if read_scene_summary(store, scene_id) is None:  # stored before summaries existed, or lost
            write_scene_summary(store, public)
        return public, False
    doc: dict[str, Any] = {
        "scene": json.loads(scene_text),
        "meshes": [{"path": p, "sha256": shas[p], "size": len(meshes[p])} for p in paths],
        "created_at": _now().isoformat(),
        "owner": owner,
    }
    store.put_bytes(scene_key(scene_id), _canonical_ascii(doc).encode("ascii"), "application/json")
    public = _public(scene_id, doc)
    write_scene_summary(store, public)
    return public, True


def put_blob_unless_intact(store: ObjectStore, sha: str, data: bytes) -> bool:
    """Write ``blobs/<sha>`` unless a copy that matches its checksum is stored: an upload of the
    same bytes replaces a stored blob that went bad (before a reader found it out). True when
    written."""
    bkey = blob_key(sha)
    try:
        if sha256_hex(store.get_bytes(bkey)) == sha:
            return False
        log.error("blob %s does not match its checksum; replaced by the uploaded bytes", sha)
    except NotFound:
        pass
    store.put_bytes(bkey, data)
    return True


def write_scene_summary(store: ObjectStore, public: ScenePublic) -> None:
    # ASCII JSON like the document: a mesh path may hold a lone surrogate (escaped, never encoded)
    doc = public.model_dump(mode="json", exclude={"links"})
    store.put_bytes(scene_summary_key(public.id), _canonical_ascii(doc).encode("ascii"), "application/json")


def read_scene_summary(store: ObjectStore, scene_id: str) -> ScenePublic | None:
    """The scene's stored public view, or None when the scene (or its summary) is absent. An
    unreadable summary, or one of another scene, is removed (the next upload writes it again)."""
    skey = scene_summary_key(scene_id)
    try:
        raw = store.get_bytes(skey)
    except NotFound:
        return None
    try:
        public: ScenePublic | None = ScenePublic.model_validate(json.loads(raw))
    except (ValueError, TypeError):  # ValidationError is a ValueError
        public = None
    if public is None or public.id != scene_id:
        log.error("scene %s: unreadable summary removed", scene_id)
        store.delete(skey)
        return None
    return public


def put_scene(store: ObjectStore, scene: Scene, meshes: Mapping[str, bytes], owner: str | None) -> ScenePublic:
    """Store a scene's mesh blobs, then its document (last); return its public view."""
    return store_scene(store, scene, meshes, owner)[0]


def _read_scene_doc(store: ObjectStore, scene_id: str) -> dict[str, Any] | None:
    """The verified scene document, or None when absent. A document that does not parse
    or does not hash to its id is deleted (a re-upload recreates it) and raises
    ChecksumMismatch."""
    skey = scene_key(scene_id)
    try:
        raw = store.get_bytes(skey)
    except NotFound:
        return None
    problem = ""
    try:
        doc = json.loads(raw)
        pairs = {m["path"]: m["sha256"] for m in doc["meshes"]}
        if _scene_id(_canonical_ascii(doc["scene"]), pairs) != scene_id:
            problem = "content does not hash to its id"
        _public(scene_id, doc)  # the fields the id does not cover must parse too
    except (ValueError, TypeError, KeyError, AttributeError) as exc:  # ValidationError is a ValueError
        problem = f"unreadable ({exc})"
    if problem:
        log.error("scene %s: stored document %s; deleted", scene_id, problem)
        store.delete(scene_summary_key(scene_id))  # summary first: listings never show a scene without a document
        store.delete(skey)
        raise ChecksumMismatch(f"scene {scene_id}: stored document is corrupt and was removed; upload it again")
    result: dict[str, Any] = doc
    return result


def get_scene(store: ObjectStore, scene_id: str) -> tuple[Scene, dict[str, str], ScenePublic]:
    """``(scene, {mesh path: blob sha256}, public view)``; NotFound when absent.

    The document is verified against its id (ChecksumMismatch, see ``_read_scene_doc``)."""
    if not isinstance(scene_id, str) or _SHA256.fullmatch(scene_id) is None:
        raise NotFound(f"scene {scene_id!r}")
    doc = _read_scene_doc(store, scene_id)
    if doc is None:
        raise NotFound(f"scene {scene_id}")
    try:
        scene = Scene.model_validate(doc["scene"])
    except ValidationError as exc:
        raise StoreError(f"scene {scene_id}: stored scene does not validate against the current schema: {exc}") from exc
    return scene, {m["path"]: m["sha256"] for m in doc["meshes"]}, _public(scene_id, doc)


def list_scenes(store: ObjectStore, owner: str | None = None) -> list[ScenePublic]:
    """Stored scenes (of ``owner`` when given), oldest first.

    Reads every scene document: for maintenance and tests; the API's listing reads a page of
    the per-owner index and the scenes' summaries instead (``producer.listings``). Unreadable
    documents are skipped (``get_scene`` removes them)."""
    out: list[ScenePublic] = []
    for key in store.list("scenes/"):
        scene_id = key[len("scenes/") : -len(".json")] if key.endswith(".json") else ""
        if _SHA256.fullmatch(scene_id) is None:
            continue
        try:
            doc = json.loads(store.get_bytes(key))
            if owner is not None and doc.get("owner") != owner:
                continue
            out.append(_public(scene_id, doc))
        except NotFound:
            continue  # deleted meanwhile
        except (ValueError, TypeError, KeyError, AttributeError) as exc:
            log.error("scene %s: unreadable document skipped (%s)", scene_id, exc)
    out.sort(key=lambda s: (s.created_at, s.id))
    return out


def delete_scene(store: ObjectStore, scene_id: str) -> None:
    """Remove a scene's document; NotFound when absent.

    Its blobs stay: blobs are content-addressed and may be shared by other scenes (a
    garbage collector that knows every scene's blobs may remove unreferenced ones)."""
    if not isinstance(scene_id, str) or _SHA256.fullmatch(scene_id) is None:
        raise NotFound(f"scene {scene_id!r}")
    skey = scene_key(scene_id)
    if not store.exists(skey):
        raise NotFound(f"scene {scene_id}")
    store.delete(scene_summary_key(scene_id))
    store.delete(skey)


def blob_reader(store: ObjectStore, mesh_shas: Mapping[str, str]) -> MeshResolver:
    """A ``MeshResolver`` for ``workers.scene_loader.load_scene``: a scene's mesh path ->
    ``(bytes, file type from the path's extension)``, read from ``blobs/<sha256>`` and
    verified. A path outside ``mesh_shas`` or a missing blob raises NotFound; a blob
    whose bytes do not match its name is deleted (a re-upload restores it) and raises
    ChecksumMismatch."""
    shas = dict(mesh_shas)

    def resolve(path: str) -> tuple[bytes, str]:
        sha = shas.get(path)
        if sha is None:
            raise NotFound(f"mesh file {path!r} is not part of this scene")
        bkey = blob_key(sha)
        data = store.get_bytes(bkey)
        if sha256_hex(data) != sha:
            log.error("blob %s (mesh %r) does not match its checksum; deleted", sha, path)
            store.delete(bkey)
            raise ChecksumMismatch(f"mesh file {path!r}: stored blob is corrupt and was removed; upload it again")
        return data, PurePosixPath(path).suffix.lower().lstrip(".")

    return resolve
