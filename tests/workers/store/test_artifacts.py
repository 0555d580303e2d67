"""Artifacts and scenes on top of the object store, on both backends: content-addressed
keys, blobs-then-manifest commit, checksum verification (docs/hard-cases.md #23), scenes with
deduplicated mesh blobs, and hostile upload names (docs/hard-cases.md #17)."""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from api_schemas.scene import Material, MeshFileObject, PerspectiveCamera, Scene, SceneObject, SphereObject
from api_schemas.service import ArtifactManifest
from producer import artifacts as art
from producer.store import ChecksumMismatch, LocalStore, NotFound, ObjectStore, StoreUnavailable
from producer.store.s3 import S3Store
from samples import SAMPLES_DIR, sample_path

ENGINE = "0.1.0"
SCENE_ID = "ab" * 32
PARAMS: dict[str, Any] = {"spp": 4, "max_depth": 4, "exposure": 0.5, "camera": {"eye": [0.0, 1.0, 2.5]}}
BLOBS = {
    "radiance.exr": (b"\x76\x2f\x31\x01" + bytes(range(256)) * 40, "image/x-exr"),
    "preview.png": (b"\x89PNG\r\n\x1a\n" + b"pixels" * 100, "image/png"),
}


def _key(**overrides: Any) -> str:
    args: dict[str, Any] = {"kind": "render", "inputs": {"scene": SCENE_ID}, "params": PARAMS, "engine_version": ENGINE}
    args.update(overrides)
    return art.artifact_key(**args)


def _write(store: ObjectStore, result: dict[str, Any] | None = None) -> ArtifactManifest:
    return art.write_artifact(
        store, _key(), "render", {"scene": SCENE_ID}, PARAMS, ENGINE, BLOBS, result or {"timings": {"total": 1.5}}
    )


class Recording:
    """Wraps a store and records every write / delete in order; can fail chosen puts."""

    def __init__(self, inner: ObjectStore, fail_put: Callable[[str], bool] = lambda key: False) -> None:
        self.inner, self.fail_put = inner, fail_put
        self.puts: list[str] = []
        self.deletes: list[str] = []

    def put_bytes(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        if self.fail_put(key):
            raise StoreUnavailable(f"injected failure writing {key}")
        self.puts.append(key)
        self.inner.put_bytes(key, data, content_type)

    def delete(self, key: str) -> None:
        self.deletes.append(key)
        self.inner.delete(key)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


@pytest.fixture
def raw_write(any_store: ObjectStore, request: pytest.FixtureRequest) -> Callable[[str, bytes], None]:
    """Overwrite an object behind the store's back (a file on disk / an S3 object)."""
    if isinstance(any_store, LocalStore):
        root = any_store.root

        def write_file(key: str, data: bytes) -> None:
            (root / key).write_bytes(data)

        return write_file
    assert isinstance(any_store, S3Store)
    client = request.getfixturevalue("s3_client")
    bucket, prefix = any_store.bucket, any_store.prefix

    def write_object(key: str, data: bytes) -> None:
        client.put_object(Bucket=bucket, Key=prefix + key, Body=data)

    return write_object


# ------------------------------------------------------------------------------ artifact keys


def test_artifact_key_is_the_documented_hash() -> None:
    """Pinned against a literal: a change of the canonical form would silently orphan
    every stored artifact, so it must show up here."""
    text = (
        '{"engine_version":"0.1.0","inputs":{"scene":"' + SCENE_ID + '"},"kind":"render",'
        '"params":{"camera":{"eye":[0.0,1.0,2.5]},"exposure":0.5,"max_depth":4,"spp":4}}'
    )
    assert _key() == hashlib.sha256(text.encode()).hexdigest()
    assert re.fullmatch(r"[0-9a-f]{64}", _key())


def test_artifact_key_ignores_dict_order() -> None:
    shuffled = {"camera": {"eye": [0.0, 1.0, 2.5]}, "spp": 4, "exposure": 0.5, "max_depth": 4}
    assert _key(params=shuffled) == _key()
    assert _key(params=dict(reversed(list(PARAMS.items())))) == _key()


@pytest.mark.parametrize(
    "change",
    [
        {"kind": "bake"},
        {"inputs": {"scene": "cd" * 32}},
        {"inputs": {"dataset": SCENE_ID}},
        {"inputs": {"scene": SCENE_ID, "lights": "ef" * 32}},
        {"params": {**PARAMS, "spp": 5}},
        {"params": {**PARAMS, "exposure": 0.5000000000000001}},
        {"params": {**PARAMS, "spp": 4.0}},  # documented: types matter (params come from model_dump)
        {"params": {**PARAMS, "camera": {"eye": [0.0, 1.0, 2.6]}}},
        {"params": {**PARAMS, "extra": None}},
        {"engine_version": "0.1.1"},
    ],
)
def test_artifact_key_changes_with_every_input(change: dict[str, Any]) -> None:
    assert _key(**change) != _key()


def test_artifact_key_unicode_is_kept_and_stable() -> None:
    assert _key(params={"label": "caf\u00e9"}) == _key(params={"label": "caf\u00e9"})
    assert _key(params={"label": "caf\u00e9"}) != _key(params={"label": "cafe"})
    assert _key(params={"label": "\ud800"}) != _key(params={"label": "\ud801"})  # lone surrogates


@pytest.mark.parametrize(
    "bad",
    [
        {"params": {"x": float("nan")}},
        {"params": {"x": float("inf")}},
        {"params": {"x": {1, 2}}},
        {"params": {"x": object()}},
        {"inputs": {"scene": 3}},
        {"kind": ""},
        {"engine_version": ""},
    ],
)
def test_artifact_key_rejects_non_canonical_input(bad: dict[str, Any]) -> None:
    with pytest.raises(ValueError):
        _key(**bad)


# ------------------------------------------------------------------------------ writing and reading


def test_write_then_read(any_store: ObjectStore) -> None:
    written = _write(any_store)
    key = _key()
    assert written.key == key and written.kind == "render" and written.engine_version == ENGINE
    assert [b.name for b in written.blobs] == sorted(BLOBS)
    for info in written.blobs:
        data, ctype = BLOBS[info.name]
        assert (info.sha256, info.size, info.content_type) == (hashlib.sha256(data).hexdigest(), len(data), ctype)
        assert art.read_blob(any_store, key, info.name) == data
    assert art.read_manifest(any_store, key) == written
    assert any_store.list("") == sorted(
        [f"artifacts/{key}/manifest.json", f"artifacts/{key}/radiance.exr", f"artifacts/{key}/preview.png"]
    )
    with pytest.raises(NotFound):
        art.read_blob(any_store, key, "other.exr")
    with pytest.raises(NotFound):
        art.read_blob(any_store, "0" * 64, "preview.png")
    assert art.read_manifest(any_store, "0" * 64) is None


def test_blobs_are_written_before_the_manifest(any_store: ObjectStore) -> None:
    rec = Recording(any_store)
    _write(rec)
    assert len(rec.puts) == 3 and rec.puts[-1].endswith("/manifest.json")


@pytest.mark.parametrize("fail_on", ["manifest.json", "radiance.exr"])
def test_a_failed_write_publishes_no_artifact(any_store: ObjectStore, fail_on: str) -> None:
    rec = Recording(any_store, fail_put=lambda key: key.endswith(fail_on))
    with pytest.raises(StoreUnavailable):
        _write(rec)
    assert art.read_manifest(any_store, _key()) is None
    with pytest.raises(NotFound):
        art.read_blob(any_store, _key(), "preview.png")
    _write(any_store)  # the retry succeeds and commits
    assert art.read_blob(any_store, _key(), "preview.png") == BLOBS["preview.png"][0]


@pytest.mark.parametrize(
    "bad",
    [
        {"key": "0" * 64},
        {"blobs": {"../escape": (b"x", "text/plain")}},
        {"blobs": {"a/b": (b"x", "text/plain")}},
        {"blobs": {"manifest.json": (b"x", "application/json")}},
        {"blobs": {"": (b"x", "text/plain")}},
        {"result": {"t": float("nan")}},
        {"result": {"t": object()}},
    ],
)
def test_bad_artifact_writes_nothing(any_store: ObjectStore, bad: dict[str, Any]) -> None:
    args: dict[str, Any] = {
        "key": _key(),
        "kind": "render",
        "inputs": {"scene": SCENE_ID},
        "params": PARAMS,
        "engine_version": ENGINE,
        "blobs": BLOBS,
        "result": {},
    }
    args.update(bad)
    with pytest.raises(ValueError):
        art.write_artifact(any_store, **args)
    assert any_store.list("") == []


def test_committed_artifact_is_not_rewritten(any_store: ObjectStore) -> None:
    first = _write(any_store, {"n": 1})
    rec = Recording(any_store)
    again = _write(rec, {"n": 2})
    assert again == first and rec.puts == []


def test_unparsable_manifest_is_deleted(any_store: ObjectStore, raw_write: Callable[[str, bytes], None]) -> None:
    _write(any_store)
    mkey = art.manifest_key(_key())
    raw_write(mkey, b'{"key": "truncated')
    assert art.read_manifest(any_store, _key()) is None
    assert not any_store.exists(mkey)


def test_manifest_of_another_key_is_deleted(any_store: ObjectStore) -> None:
    manifest = _write(any_store)
    other = "1" * 64
    any_store.put_bytes(art.manifest_key(other), manifest.model_dump_json().encode())
    assert art.read_manifest(any_store, other) is None
    assert not any_store.exists(art.manifest_key(other))
    assert art.read_manifest(any_store, _key()) == manifest


def _flip_one_byte(data: bytes) -> bytes:
    return data[:100] + bytes([data[100] ^ 0x01]) + data[101:]


@pytest.mark.parametrize("corruption", ["same_size", "truncated", "missing"])
def test_corrupt_blob_is_never_served_and_gets_rebaked(
    any_store: ObjectStore, raw_write: Callable[[str, bytes], None], corruption: str
) -> None:
    """docs/hard-cases.md #23."""
    _write(any_store)
    key = _key()
    bkey = f"artifacts/{key}/radiance.exr"
    good = BLOBS["radiance.exr"][0]
    if corruption == "missing":
        any_store.delete(bkey)
    else:
        raw_write(bkey, _flip_one_byte(good) if corruption == "same_size" else good[:-10])
    assert art.read_blob(any_store, key, "preview.png") == BLOBS["preview.png"][0]  # others still fine
    with pytest.raises(ChecksumMismatch):
        art.read_blob(any_store, key, "radiance.exr")
    assert art.read_manifest(any_store, key) is None  # absent now, so the job runs again
    with pytest.raises(NotFound):
        art.read_blob(any_store, key, "radiance.exr")
    _write(any_store)  # the rebake
    assert art.read_blob(any_store, key, "radiance.exr") == good


def test_stream_blob_verifies_and_holds_back_the_last_chunk(
    any_store: ObjectStore, raw_write: Callable[[str, bytes], None]
) -> None:
    _write(any_store)
    key = _key()
    good = BLOBS["radiance.exr"][0]
    info, chunks = art.stream_blob(any_store, key, "radiance.exr", chunk=1000)
    assert info.size == len(good)
    assert b"".join(chunks) == good

    raw_write(f"artifacts/{key}/radiance.exr", _flip_one_byte(good))
    received = bytearray()
    _, chunks = art.stream_blob(any_store, key, "radiance.exr", chunk=1000)
    with pytest.raises(ChecksumMismatch):
        for block in chunks:
            received += block
    assert 0 < len(received) < len(good)  # a client never gets a complete bad copy
    assert art.read_manifest(any_store, key) is None


def test_stream_blob_of_missing_things(any_store: ObjectStore) -> None:
    with pytest.raises(NotFound):
        art.stream_blob(any_store, _key(), "radiance.exr")
    _write(any_store)
    any_store.delete(f"artifacts/{_key()}/preview.png")
    with pytest.raises(ChecksumMismatch):
        art.stream_blob(any_store, _key(), "preview.png")  # raised by the call, before any byte
    assert art.read_manifest(any_store, _key()) is None


def test_delete_artifact_removes_manifest_first(any_store: ObjectStore) -> None:
    _write(any_store)
    rec = Recording(any_store)
    art.delete_artifact(rec, _key())
    assert rec.deletes[0].endswith("/manifest.json") and len(rec.deletes) >= 3
    assert any_store.list("") == []
    art.delete_artifact(any_store, _key())  # idempotent


def test_malformed_artifact_keys_are_rejected(any_store: ObjectStore) -> None:
    for bad in ["../x", "AB" * 32, "a" * 63, ""]:
        with pytest.raises(ValueError):
            art.read_manifest(any_store, bad)
        with pytest.raises(ValueError):
            art.read_blob(any_store, bad, "x")


# ------------------------------------------------------------------------------ scenes

CAMERA = PerspectiveCamera(eye=(0.0, 1.0, 4.0), look_at=(0.0, 0.0, 0.0), width=16, height=16)
MESH_A = b"ply\nformat ascii 1.0\nelement vertex 0\n" + b"a" * 200
MESH_B = b"o B\n" + b"v 0 0 0\n" * 30


def _scene(paths: list[str], name: str = "test scene") -> Scene:
    objects: list[SceneObject] = [MeshFileObject(path=p, material="m", name=f"o{i}") for i, p in enumerate(paths)]
    objects.append(SphereObject(radius=0.5, material="m"))
    return Scene(name=name, camera=CAMERA, materials=[Material(name="m")], objects=objects)


def _blob_keys(store: ObjectStore) -> list[str]:
    return store.list("blobs/")


def test_put_and_get_scene(any_store: ObjectStore) -> None:
    scene = _scene(["meshes/a.ply", "meshes/b.OBJ", "meshes/copy_of_a.ply"])
    meshes = {"meshes/a.ply": MESH_A, "meshes/b.OBJ": MESH_B, "meshes/copy_of_a.ply": MESH_A}
    public = art.put_scene(any_store, scene, meshes, owner="alice")
    sha_a, sha_b = hashlib.sha256(MESH_A).hexdigest(), hashlib.sha256(MESH_B).hexdigest()
    assert public.id == art.scene_id_for(
        scene, {"meshes/a.ply": sha_a, "meshes/b.OBJ": sha_b, "meshes/copy_of_a.ply": sha_a}
    )
    assert (public.name, public.n_objects, public.n_lights) == ("test scene", 4, 0)
    assert [(m.path, m.sha256, m.size) for m in public.meshes] == [
        ("meshes/a.ply", sha_a, len(MESH_A)),
        ("meshes/b.OBJ", sha_b, len(MESH_B)),
        ("meshes/copy_of_a.ply", sha_a, len(MESH_A)),
    ]
    assert _blob_keys(any_store) == sorted([f"blobs/{sha_a}", f"blobs/{sha_b}"])  # deduplicated
    assert any_store.list("scenes/") == [f"scenes/{public.id}.json"]

    got, shas, public2 = art.get_scene(any_store, public.id)
    assert got == scene and public2 == public
    assert shas == {"meshes/a.ply": sha_a, "meshes/b.OBJ": sha_b, "meshes/copy_of_a.ply": sha_a}
    resolve = art.blob_reader(any_store, shas)
    assert resolve("meshes/a.ply") == (MESH_A, "ply")
    assert resolve("meshes/b.OBJ") == (MESH_B, "obj")
    with pytest.raises(NotFound):
        resolve("meshes/not_in_scene.ply")


def test_scene_blobs_are_written_first_and_not_rewritten(any_store: ObjectStore) -> None:
    scene = _scene(["a.ply", "b.obj"])
    rec = Recording(any_store)
    first = art.put_scene(rec, scene, {"a.ply": MESH_A, "b.obj": MESH_B}, owner=None)
    assert [k.split("/")[0] for k in rec.puts] == ["blobs", "blobs", "scenes", "scene-summaries"]
    other = _scene(["c.ply"], name="shares a blob")
    rec2 = Recording(any_store)
    art.put_scene(rec2, other, {"c.ply": MESH_A}, owner=None)
    assert [k.split("/")[0] for k in rec2.puts] == ["scenes", "scene-summaries"]  # MESH_A already stored
    rec3 = Recording(any_store)
    again, created = art.store_scene(rec3, scene, {"a.ply": MESH_A, "b.obj": MESH_B}, owner="bob")
    assert rec3.puts == [] and not created
    assert again == first  # first upload's created_at is kept


def test_scene_id_is_stable_and_content_sensitive() -> None:
    shas = {"a.ply": "1" * 64}
    scene = _scene(["a.ply"])
    doc = json.loads(scene.model_dump_json())
    reordered = Scene.model_validate_json(json.dumps(dict(reversed(list(doc.items())))))
    minimal = Scene.model_validate(
        {
            "name": "test scene",
            "camera": {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0, 0], "width": 16, "height": 16},
            "materials": [{"name": "m"}],
            "objects": [
                {"type": "mesh_file", "path": "a.ply", "material": "m", "name": "o0"},
                {"type": "sphere", "radius": 0.5, "material": "m"},
            ],
        }
    )
    assert art.scene_id_for(reordered, shas) == art.scene_id_for(scene, shas) == art.scene_id_for(minimal, shas)
    assert art.scene_id_for(scene, {"a.ply": "2" * 64}) != art.scene_id_for(scene, shas)
    assert art.scene_id_for(_scene(["a.ply"], name="other"), shas) != art.scene_id_for(scene, shas)
    assert art.scene_id_for(_scene(["b.ply"]), {"b.ply": "1" * 64}) != art.scene_id_for(scene, shas)


def test_scene_without_mesh_files(any_store: ObjectStore) -> None:
    scene = _scene([])
    public = art.put_scene(any_store, scene, {"unused.ply": MESH_A}, owner=None)
    assert public.meshes == [] and _blob_keys(any_store) == []  # unreferenced uploads are not kept
    assert art.get_scene(any_store, public.id)[0] == scene


def test_missing_mesh_upload_writes_nothing(any_store: ObjectStore) -> None:
    with pytest.raises(ValueError, match="b.obj"):
        art.put_scene(any_store, _scene(["a.ply", "b.obj"]), {"a.ply": MESH_A}, owner=None)
    assert any_store.list("") == []


def test_get_list_delete_scenes(any_store: ObjectStore) -> None:
    with pytest.raises(NotFound):
        art.get_scene(any_store, "0" * 64)
    with pytest.raises(NotFound):
        art.get_scene(any_store, "../../etc/passwd")
    a = art.put_scene(any_store, _scene(["a.ply"], name="a"), {"a.ply": MESH_A}, owner="alice")
    b = art.put_scene(any_store, _scene(["b.ply"], name="b"), {"b.ply": MESH_A}, owner="bob")
    c = art.put_scene(any_store, _scene([], name="c"), {}, owner=None)
    assert [s.id for s in art.list_scenes(any_store)] == [a.id, b.id, c.id]  # oldest first
    assert art.list_scenes(any_store, owner="bob") == [b]
    assert art.list_scenes(any_store, owner="carol") == []
    art.delete_scene(any_store, a.id)
    with pytest.raises(NotFound):
        art.get_scene(any_store, a.id)
    with pytest.raises(NotFound):
        art.delete_scene(any_store, a.id)
    assert [s.id for s in art.list_scenes(any_store)] == [b.id, c.id]
    assert _blob_keys(any_store) == [f"blobs/{hashlib.sha256(MESH_A).hexdigest()}"]  # still used by b


def test_corrupt_scene_document_is_removed_and_reupload_repairs(
    any_store: ObjectStore, raw_write: Callable[[str, bytes], None]
) -> None:
    scene = _scene(["a.ply"])
    public = art.put_scene(any_store, scene, {"a.ply": MESH_A}, owner=None)
    skey = art.scene_key(public.id)
    raw = any_store.get_bytes(skey)
    raw_write(skey, raw.replace(b'"test scene"', b'"tost scene"'))  # parses, but does not hash to its id
    with pytest.raises(ChecksumMismatch):
        art.get_scene(any_store, public.id)
    assert not any_store.exists(skey)
    assert art.put_scene(any_store, scene, {"a.ply": MESH_A}, owner=None).id == public.id
    raw_write(skey, b"\x00garbage")
    assert art.list_scenes(any_store) == []  # skipped, not fatal
    with pytest.raises(ChecksumMismatch):
        art.get_scene(any_store, public.id)


def test_corrupt_mesh_blob_is_removed_and_reupload_repairs(
    any_store: ObjectStore, raw_write: Callable[[str, bytes], None]
) -> None:
    scene = _scene(["a.ply"])
    public = art.put_scene(any_store, scene, {"a.ply": MESH_A}, owner=None)
    _, shas, _ = art.get_scene(any_store, public.id)
    raw_write(art.blob_key(shas["a.ply"]), _flip_one_byte(MESH_A))
    with pytest.raises(ChecksumMismatch):
        art.blob_reader(any_store, shas)("a.ply")
    assert not any_store.exists(art.blob_key(shas["a.ply"]))
    art.put_scene(any_store, scene, {"a.ply": MESH_A}, owner=None)  # the same upload again
    assert art.blob_reader(any_store, shas)("a.ply") == (MESH_A, "ply")


@pytest.mark.parametrize("corruption", ["same_size", "truncated", "empty"])
def test_reupload_replaces_a_corrupt_blob_nobody_read_yet(
    any_store: ObjectStore, raw_write: Callable[[str, bytes], None], corruption: str
) -> None:
    """A stored mesh blob that went bad before any reader checked it: uploading the same scene (or
    any scene with the same file) again writes the good bytes over it."""
    scene = _scene(["a.ply"])
    public = art.put_scene(any_store, scene, {"a.ply": MESH_A}, owner=None)
    bkey = art.blob_key(hashlib.sha256(MESH_A).hexdigest())
    bad = {"same_size": _flip_one_byte(MESH_A), "truncated": MESH_A[:-7], "empty": b""}[corruption]
    raw_write(bkey, bad)
    rec = Recording(any_store)
    again, created = art.store_scene(rec, scene, {"a.ply": MESH_A}, owner=None)
    assert again.id == public.id and not created
    assert rec.puts == [bkey] and any_store.get_bytes(bkey) == MESH_A
    other = _scene(["b/a.ply"], name="another scene with the same file")
    raw_write(bkey, bad)
    art.put_scene(any_store, other, {"b/a.ply": MESH_A}, owner=None)
    assert any_store.get_bytes(bkey) == MESH_A
    rec = Recording(any_store)  # an intact blob is not written again
    art.store_scene(rec, scene, {"a.ply": MESH_A}, owner=None)
    assert rec.puts == []


HOSTILE_NAMES = ["../../x", "C:\\..\\x", "a\x00b.ply", "/etc/passwd", "..", "blobs/../../y", "\ud800.obj"]
_OUR_KEYS = re.compile(r"blobs/[0-9a-f]{64}|scenes/[0-9a-f]{64}\.json|scene-summaries/[0-9a-f]{64}\.json")


def test_hostile_upload_names_only_become_metadata(any_store: ObjectStore, tmp_path: Path) -> None:
    """docs/hard-cases.md #17 at the storage level. The schema rejects these paths, so the scene is
    built with model_construct: even then the store writes only ``blobs/<sha256>`` and
    ``scenes/<id>.json`` under its root."""
    objects = [MeshFileObject.model_construct(path=p, material="m") for p in HOSTILE_NAMES]
    scene = Scene.model_construct(camera=CAMERA, materials=[Material(name="m")], objects=objects)
    meshes = {p: MESH_A + p.encode("utf-8", "surrogatepass") for p in HOSTILE_NAMES}
    public = art.put_scene(any_store, scene, meshes, owner=None)

    keys = any_store.list("")
    assert len(keys) == len(HOSTILE_NAMES) + 2  # the blobs, the document and its summary
    assert all(_OUR_KEYS.fullmatch(k) for k in keys), keys
    assert sorted(m.path for m in public.meshes) == sorted(HOSTILE_NAMES)
    if isinstance(any_store, LocalStore):
        files = [p for p in tmp_path.rglob("*") if p.is_file()]
        outside = [p for p in files if any_store.root not in p.parents]
        assert outside == [], outside
        assert sorted(p.relative_to(any_store.root).as_posix() for p in files) == keys
    # the names resolve (as metadata) to the right content
    doc = json.loads(any_store.get_bytes(f"scenes/{public.id}.json"))
    shas = {m["path"]: m["sha256"] for m in doc["meshes"]}
    resolve = art.blob_reader(any_store, shas)
    assert resolve("../../x") == (meshes["../../x"], "")
    assert resolve("a\x00b.ply") == (meshes["a\x00b.ply"], "ply")


def test_stored_sample_scene_loads_through_the_blob_reader(local_store: LocalStore) -> None:
    """The resolver plugs into workers.scene_loader.load_scene and gives the same
    geometry as reading the sample directory."""
    from api_schemas import load_scene_file
    from workers.scene_loader import directory_resolver, load_scene

    scene = load_scene_file(sample_path("teapot_glossy"))
    paths = art.mesh_paths(scene)
    assert paths == ["meshes/teapot.ply"]
    public = art.put_scene(local_store, scene, {p: (Path(SAMPLES_DIR) / p).read_bytes() for p in paths}, owner=None)
    stored, shas, _ = art.get_scene(local_store, public.id)
    from_store = load_scene(stored, art.blob_reader(local_store, shas))
    from_dir = load_scene(scene, directory_resolver(SAMPLES_DIR))
    assert from_store.runtime.n_triangles == from_dir.runtime.n_triangles > 0
    assert from_store.scene_hash == from_dir.scene_hash
    assert from_store.mesh_reports == from_dir.mesh_reports
