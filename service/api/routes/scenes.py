"""``/v1/scenes``: content-addressed scenes, created from JSON or multipart uploads, or imported
from glTF 2.0 / GLB / OBJ + MTL files (producer/scene_import, docs/scene-import.md)."""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from pathlib import PurePosixPath
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, HTTPException, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from pydantic import ValidationError

from api_schemas.errors import FieldError
from api_schemas.scene import MeshFileObject, Scene
from api_schemas.service import SceneCreate, SceneImportPublic, SceneList, ScenePublic, Sha256
from engine.geometry.meshio import DEFAULT_MAX_MESH_BYTES, SUPPORTED_MESH_TYPES
from producer.artifacts import delete_scene, get_scene, mesh_paths, scene_id_for, sha256_hex, store_scene
from producer.costs import mesh_triangles, remember_mesh_triangles, scene_cost, scene_triangles, size_text
from producer.errors import SceneOutputsInUse
from producer.listings import BadCursor, index_scene, list_scene_page, unindex_scene, unindex_scene_owner
from producer.ownership import ANON_OWNER, remove_bake_owner
from producer.scene_import import IMPORT_FORMATS, ImportOptions, ImportProblem, import_scene, referenced_files
from producer.scene_outputs import delete_scene_outputs
from producer.settings import Settings
from producer.status import ids_in_active_jobs
from producer.store import NotFound, ObjectStore
from service.api.deps import (
    OwnerDep,
    RedisDep,
    SettingsDep,
    StoreDep,
    add_scene_owner,
    remove_scene_owner,
    scene_owners,
    scene_visible,
)
from service.api.errors import ValidationProblem, problem_responses
from service.api.limits import BodyTooLarge, read_multipart

router = APIRouter(prefix="/v1/scenes", tags=["scenes"])

SceneId = Annotated[Sha256, Path(description="Scene id (sha256 hex)")]

SAMPLE_SCENE: dict[str, Any] = {
    "name": "sphere_on_floor",
    "camera": {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0], "fov_y_deg": 40,
               "width": 64, "height": 48},
    "materials": [{"name": "white", "kd": [0.8, 0.8, 0.8]}, {"name": "red", "kd": [0.8, 0.1, 0.1]}],
    "objects": [
        {"type": "sphere", "material": "red", "radius": 0.5, "transform": {"translate": [0, 0.5, 0]}},
        {"type": "plane", "material": "white", "size": [4, 4]},
    ],
    "lights": [{"type": "point", "position": [2, 3, 2], "intensity": [10, 10, 10]}],
}

_MULTIPART_SCHEMA: dict[str, Any] = {
    "type": "object",
    "required": ["scene"],
    "properties": {
        "scene": {
            "type": "string",
            "description": "The scene JSON (a Scene document, or a SceneCreate {\"scene\": ...})",
        },
    },
    "additionalProperties": {
        "type": "string",
        "format": "binary",
        "description": "One file part per mesh_file path of the scene, named by that path. To import a file "
                       "instead, send no 'scene' part but one part named 'gltf', 'glb' or 'obj' (the file) and "
                       "one part per file it names by relative path (.bin buffers, .mtl files), named by that path",
    },
}

# Bodies that are one file to import, by Content-Type (a .gltf must then embed its buffers).
IMPORT_CONTENT_TYPES = {"model/gltf-binary": "glb", "model/gltf+json": "gltf", "model/obj": "obj"}
_IMPORT_BODY_SCHEMA: dict[str, Any] = {"type": "string", "format": "binary"}


# ------------------------------------------------------------------------------ helpers


def limit_errors(scene: Scene, settings: Settings, prefix: str = "scene",
                 meshes: Mapping[str, bytes] | None = None) -> list[FieldError]:
    """What the scene breaks of this server's limits: the camera's pixels, mesh file types, the triangles
    after tessellation (``meshes``: the uploaded mesh files by path, counted from their headers),
    counted before anything is built."""
    errors: list[FieldError] = []
    counts = {path: mesh_triangles(path, data) for path, data in (meshes or {}).items()}
    triangles = scene_triangles(scene, counts)
    if triangles > settings.max_scene_triangles:
        errors.append(FieldError(
            field=f"{prefix}.objects",
            message=f"the scene has {triangles:,} triangles after tessellation, over this server's limit of "
                    f"{settings.max_scene_triangles:,} (IBR_MAX_SCENE_TRIANGLES); building it would need an "
                    f"estimated {size_text(scene_cost(triangles).peak_bytes)}. Use fewer objects or fewer "
                    f"subdivisions / segments",
            type="scene_too_large",
        ))
    cam = scene.camera
    if cam.width * cam.height > settings.max_image_pixels:
        errors.append(FieldError(
            field=f"{prefix}.camera.height",
            message=f"width * height = {cam.width * cam.height} exceeds this server's limit of "
                    f"{settings.max_image_pixels} pixels",
            type="image_too_large",
        ))
    for i, obj in enumerate(scene.objects):
        if isinstance(obj, MeshFileObject):
            ext = PurePosixPath(obj.path).suffix.lower().lstrip(".")
            if ext not in SUPPORTED_MESH_TYPES:
                errors.append(FieldError(
                    field=f"{prefix}.objects.{i}.path",
                    message=f"unsupported mesh file type {('.' + ext) if ext else '(no extension)'!s} in "
                            f"{obj.path!r}; supported: " + ", ".join(f".{t}" for t in SUPPORTED_MESH_TYPES),
                    type="unsupported_mesh_type",
                ))
    return errors


def _first_object_with_path(scene: Scene, path: str) -> int:
    for i, obj in enumerate(scene.objects):
        if isinstance(obj, MeshFileObject) and obj.path == path:
            return i
    return -1


def _parse_scene_json(raw: bytes, bare_allowed: bool) -> Scene:
    """A SceneCreate body, or (multipart ``scene`` part) a bare Scene document."""
    if raw.startswith(b"\xef\xbb\xbf"):
        raw = raw[3:]
    if bare_allowed:
        try:
            doc = json.loads(raw)
        except (ValueError, RecursionError) as exc:
            raise ValidationProblem(
                [FieldError(field="scene", message=f"the scene part is not valid JSON: {exc}", type="json_invalid")]
            ) from None
        if not (isinstance(doc, dict) and set(doc) == {"scene"}):
            try:
                return Scene.model_validate(doc)
            except ValidationError as exc:
                raise ValidationProblem.from_pydantic(exc, Scene, prefix=("scene",)) from None
    try:
        return SceneCreate.model_validate_json(raw).scene
    except ValidationError as exc:
        raise ValidationProblem.from_pydantic(exc, SceneCreate) from None


def _create(store: ObjectStore, scene: Scene, meshes: dict[str, bytes], owner: str | None) -> tuple[ScenePublic, bool]:
    """Store the scene; (public view, created for this owner?)."""
    shas = {p: sha256_hex(meshes[p]) for p in mesh_paths(scene)}
    for path, sha in shas.items():  # the jobs' estimates count them without reading the blobs again
        remember_mesh_triangles(sha, mesh_triangles(path, meshes[path]))
    scene_id = scene_id_for(scene, shas)
    had_marker = owner is not None and scene_visible(store, scene_id, owner)
    public, new_record = store_scene(store, scene, meshes, owner)
    add_scene_owner(store, public.id, owner)  # after the record: a visible scene always exists
    index_scene(store, public, owner)  # after the marker: a listed scene is always visible
    created = new_record if owner is None else (new_record or not had_marker)
    return public.model_copy(update={"links": {"self": f"/v1/scenes/{public.id}",
                                               "document": f"/v1/scenes/{public.id}/document"}}), created


# ------------------------------------------------------------------------------ mesh pre-checks
#
# The worker's loader (engine.geometry.meshio) is the authority on mesh files; these cheap,
# engine-free checks only reject at upload time what would certainly fail there: wrong
# magic, truncation, and face indices outside the vertex range (docs/hard-cases.md #15), with counts.

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _index_problem(faces: np.ndarray, n_vertices: int) -> str | None:
    if faces.size == 0:
        return None
    f = faces.astype(np.int64, copy=False)
    neg = int((f < 0).sum())
    high = int((f >= n_vertices).sum())
    if neg or high:
        affected = int(((f < 0) | (f >= n_vertices)).any(axis=1).sum())
        return (f"{neg + high} face indices out of range 0..{n_vertices - 1} ({neg} negative, {high} too large) "
                f"in {affected} of {len(f)} faces")
    return None


def _check_ply(data: bytes) -> str | None:
    if not (data.startswith(b"ply\n") or data.startswith(b"ply\r\n")):
        return "not a PLY file: missing the 'ply' magic line"
    m = re.search(rb"end_header[ \t]*\r?\n", data[: 1 << 16])
    if m is None:
        return "PLY header has no end_header line (not a PLY file, or truncated)"
    fmt = ""
    elements: list[tuple[str, int, list[tuple[str, str, str | None]]]] = []  # name, count, (prop, type, list count)
    for raw in data[: m.start()].decode("latin-1").splitlines():
        words = raw.split()
        if not words:
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if len(words) == 5 and words[1] == "list":
                elements[-1][2].append((words[4], words[3], words[2]))
            elif len(words) == 3:
                elements[-1][2].append((words[2], words[1], None))
    counts = {name: n for name, n, _ in elements}
    n_vertices = counts.get("vertex", 0)
    body = data[m.end():]
    if fmt == "ascii":
        lines = body.split(b"\n")
        declared = sum(counts.values())
        rows = len([ln for ln in lines if ln.strip()])
        if rows < declared:
            return f"truncated ASCII PLY: the header declares {declared} element rows, the file has {rows}"
        row = 0
        for name, n, props in elements:
            if name == "face" and props and props[0][0] in ("vertex_indices", "vertex_index") and props[0][2]:
                face_rows = [ln.split() for ln in lines[row:row + n]]
                tri = [r[1:4] for r in face_rows if len(r) >= 4 and r[0] == b"3"]
                if len(tri) == n:
                    try:
                        faces = np.array(tri, dtype=np.int64).reshape(-1, 3)
                    except (ValueError, OverflowError):
                        return "ASCII PLY face rows hold non-integer indices"
                    return _index_problem(faces, n_vertices)
                return None
            row += n
        return None
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        return f"unknown PLY format {fmt!r}"
    order = "<" if fmt == "binary_little_endian" else ">"
    offset = 0
    for name, n, props in elements:
        if any(p[2] is not None for p in props):
            if name != "face" or len(props) != 1 or props[0][0] not in ("vertex_indices", "vertex_index"):
                return None  # variable-size rows we do not model: leave it to the worker
            _, itype, ctype = props[0]
            if itype not in _PLY_TYPES or ctype not in _PLY_TYPES:
                return f"PLY face list has an unknown type ({ctype} / {itype})"
            if _PLY_TYPES[itype][0] == "f" or _PLY_TYPES[ctype][0] == "f":
                return None  # float indices: the worker's loader decides
            dt = np.dtype([("n", order + _PLY_TYPES[ctype]), ("i", order + _PLY_TYPES[itype], (3,))])
            need = offset + dt.itemsize * n
            if len(body) < need:
                return None if n == 0 else _ply_truncated(len(body), need, elements)
            table = np.frombuffer(body, dtype=dt, count=n, offset=offset)
            if not np.all(table["n"] == 3):
                return None  # polygons: the worker triangulates and checks them
            return _index_problem(table["i"], n_vertices)
        size = 0
        for _, ptype, _ in props:
            if ptype not in _PLY_TYPES:
                return f"PLY property has an unknown type {ptype!r}"
            size += np.dtype(_PLY_TYPES[ptype]).itemsize
        offset += size * n
        if len(body) < offset:
            return _ply_truncated(len(body), offset, elements)
    return None


def _ply_truncated(have: int, need: int, elements: list[tuple[str, int, Any]]) -> str:
    decl = ", ".join(f"{n} {name}" for name, n, _ in elements)
    return f"truncated binary PLY: the header declares {decl}, needing at least {need} body bytes; the file has {have}"


def _check_obj(data: bytes) -> str | None:
    if b"\x00" in data:
        return "not an OBJ file: it contains binary data (NUL bytes)"
    lines = data.replace(b"\r\n", b"\n").split(b"\n")
    total = sum(1 for ln in lines if ln[:2] == b"v " or ln[:2] == b"v\t")
    seen = 0
    bad = zero = affected = faces = 0
    for ln in lines:
        s = ln.lstrip()
        if s[:2] in (b"v ", b"v\t"):
            seen += 1
        elif s[:2] in (b"f ", b"f\t"):
            faces += 1
            face_bad = False
            for tok in s.split()[1:]:
                head = tok.split(b"/", 1)[0]
                try:
                    idx = int(head)
                except ValueError:
                    bad += 1
                    face_bad = True
                    continue
                if idx == 0:
                    zero += 1
                    face_bad = True
                elif (idx < 0 and seen + idx < 0) or idx > total:
                    bad += 1
                    face_bad = True
            affected += face_bad
    if bad or zero:
        return (f"{bad + zero} OBJ face indices out of range 1..{total} ({zero} zero; OBJ indices start at 1) "
                f"in {affected} of {faces} faces")
    return None


def _check_stl(data: bytes) -> str | None:
    if len(data) >= 84:
        count = int.from_bytes(data[80:84], "little")
        if len(data) == 84 + 50 * count:
            return None
    if data.lstrip()[:5].lower() == b"solid" and b"\x00" not in data:
        return None if b"endsolid" in data[-4096:].lower() else "truncated ASCII STL: no 'endsolid' at the end"
    if len(data) >= 84:
        count = int.from_bytes(data[80:84], "little")
        return (f"not a valid STL file: {len(data)} bytes, but a binary STL of {count} triangles needs "
                f"{84 + 50 * count} (truncated?) and it is not ASCII STL")
    return "not a valid STL file: too short"


def _check_glb(data: bytes) -> str | None:
    if len(data) < 12 or data[:4] != b"glTF":
        return "not a GLB file: missing the 'glTF' magic"
    version = int.from_bytes(data[4:8], "little")
    length = int.from_bytes(data[8:12], "little")
    if version != 2:
        return f"GLB version {version} is not supported (only 2)"
    if length != len(data):
        return f"GLB header declares {length} bytes, the file has {len(data)} (truncated?)"
    return None


def _check_gltf(data: bytes) -> str | None:
    try:
        doc = json.loads(data)
    except (ValueError, RecursionError) as exc:
        return f"not a glTF file: invalid JSON ({exc})"
    if not isinstance(doc, dict):
        return "not a glTF file: the top level is not a JSON object"
    for i, buf in enumerate(doc.get("buffers") or []):
        uri = buf.get("uri") if isinstance(buf, dict) else None
        if isinstance(uri, str) and not uri.startswith("data:"):
            return (f"buffers.{i} references the external file {uri[:100]!r}; uploads must be self-contained: "
                    "embed buffers as data: URIs or upload a .glb")
    return None


_CHECKS = {"ply": _check_ply, "obj": _check_obj, "stl": _check_stl, "glb": _check_glb, "gltf": _check_gltf}


def mesh_problem(path: str, data: bytes) -> str | None:
    """Why the worker would certainly refuse this mesh file, or None."""
    if not data:
        return "the file is empty"
    ext = PurePosixPath(path).suffix.lower().lstrip(".")
    check = _CHECKS.get(ext)
    if check is None:
        return f"unsupported mesh file type .{ext}"
    return check(data)


# ------------------------------------------------------------------------------ imports


def _no_import_options(options: ImportOptions) -> None:
    given = [k for k in ("width", "height", "name") if getattr(options, k) is not None]
    if given:
        raise ValidationProblem([FieldError(
            field=given[0], message=f"{given[0]} applies to imported files (glTF, GLB, OBJ) only; a scene document "
                                    "sets its camera and name itself", type="import_only")])


async def _import_parts(import_parts: list[Any], parts: list[Any], options: ImportOptions, response: Response,
                        store: ObjectStore, owner: str | None, settings: Settings) -> SceneImportPublic:
    if len(import_parts) != 1:
        raise ValidationProblem([FieldError(
            field=import_parts[1].name, message="one file to import per request; found parts "
                                                + ", ".join(repr(p.name) for p in import_parts),
            type="duplicate_part")])
    main = import_parts[0]
    files: dict[str, bytes] = {}
    errors: list[FieldError] = []
    for part in parts:
        if part is main:
            continue
        if part.name in files:
            errors.append(FieldError(field=f"files.{part.name}", message=f"file part {part.name!r} sent twice",
                                     type="duplicate_part"))
        files[part.name] = part.data
    if errors:
        raise ValidationProblem(errors)
    source = PurePosixPath(main.filename).name if main.filename else f"scene.{main.name}"
    return await _import_and_store(main.name, main.data, files, source, options, response, store, owner, settings)


def _convert(fmt: str, data: bytes, files: dict[str, bytes], source: str, options: ImportOptions,
             settings: Settings) -> tuple[Scene, dict[str, bytes], list[dict[str, Any]]]:
    """Everything checked before anything is stored: the conversion, the parts, the limits, the blobs."""
    try:
        imported = import_scene(fmt, data, files, options, source)
    except ImportProblem as exc:
        raise ValidationProblem([FieldError(field=where, message=f"{source}: {message}", type="invalid_import")
                                 for where, message in exc.errors]) from None
    named = set(referenced_files(fmt, data))
    extra = sorted(set(files) - named)
    errors = limit_errors(imported.scene, settings, meshes=imported.meshes)
    if extra:
        errors.append(FieldError(
            field="files", message="file parts the imported file does not name: "
                                   + ", ".join(repr(e) for e in extra[:20])
                                   + ". Name each part by the relative path the file uses for it",
            type="unexpected_part"))
    for path, blob in imported.meshes.items():
        if len(blob) > DEFAULT_MAX_MESH_BYTES:
            errors.append(FieldError(
                field=f"meshes.{path}", type="mesh_too_large",
                message=f"{source}: the mesh converts to a {len(blob)}-byte file, over the workers' "
                        f"{DEFAULT_MAX_MESH_BYTES}-byte limit per mesh file"))
            continue
        problem = mesh_problem(path, blob)
        if problem is not None:  # the importer wrote it: a bug, but never store what a worker refuses
            errors.append(FieldError(field=f"meshes.{path}", message=problem, type="invalid_mesh"))
    if errors:
        raise ValidationProblem(errors)
    return imported.scene, imported.meshes, imported.warnings


async def _import_and_store(fmt: str, data: bytes, files: dict[str, bytes], source: str, options: ImportOptions,
                            response: Response, store: ObjectStore, owner: str | None,
                            settings: Settings) -> SceneImportPublic:
    scene, meshes, warnings = await run_in_threadpool(_convert, fmt, data, files, source, options, settings)
    public, created = await run_in_threadpool(_create, store, scene, meshes, owner)
    if created:
        response.headers["Location"] = f"/v1/scenes/{public.id}"
    else:
        response.status_code = 200
    return SceneImportPublic.model_validate(
        {**public.model_dump(), "import_format": fmt, "import_warnings": warnings})


# ------------------------------------------------------------------------------ routes


@router.post(
    "",
    response_model=ScenePublic | SceneImportPublic,
    status_code=201,
    responses={
        200: {"model": ScenePublic, "description": "The same content was already stored by this key"},
        **problem_responses(400, 401, 413, 422, 429, 503),
    },
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {
                "application/json": {
                    "schema": {"$ref": "#/components/schemas/SceneCreate"},
                    "examples": {"sphere": {"summary": "A sphere on a floor", "value": {"scene": SAMPLE_SCENE}}},
                },
                "multipart/form-data": {"schema": _MULTIPART_SCHEMA},
                **{t: {"schema": _IMPORT_BODY_SCHEMA} for t in IMPORT_CONTENT_TYPES},
            },
        }
    },
)
async def create_scene(
    request: Request, response: Response, store: StoreDep, owner: OwnerDep, settings: SettingsDep,
    width: Annotated[int | None, Query(ge=1, le=16384, description="Imports only: image width of the "
                                       "imported camera (default: from its aspect ratio and the height)")] = None,
    height: Annotated[int | None, Query(ge=1, le=16384, description="Imports only: image height of the "
                                        "imported camera (default 480, or from the width)")] = None,
    name: Annotated[str | None, Query(min_length=1, max_length=128, description="Imports only: the scene's "
                                      "name (default: the file's)")] = None,
) -> ScenePublic | SceneImportPublic:
    """Store a scene (JSON, or multipart with its mesh files), or import one from a glTF 2.0 / GLB / OBJ + MTL
    file (docs/scene-import.md); 201 when new, 200 when already stored. An import answers with
    ``import_warnings``: every feature of the file that was left out or approximated."""
    ctype = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    options = ImportOptions(width=width, height=height, name=name)
    meshes: dict[str, bytes] = {}
    if ctype in IMPORT_CONTENT_TYPES:
        fmt = IMPORT_CONTENT_TYPES[ctype]
        body = await request.body()
        if len(body) > settings.max_upload_bytes:  # one uploaded file, as a multipart part would be
            raise BodyTooLarge(f"the {fmt} file of {len(body)} bytes exceeds the {settings.max_upload_bytes}-byte "
                               "limit per file", field=fmt)
        return await _import_and_store(fmt, body, {}, f"scene.{fmt}", options, response, store, owner, settings)
    if ctype == "multipart/form-data":
        parts = await read_multipart(
            request,
            max_part_bytes=settings.max_upload_bytes,
            max_parts=settings.max_upload_files + 1,
            field_limits={"scene": settings.json_limit_bytes},
        )
        scene_parts = [p for p in parts if p.name == "scene"]
        import_parts = [p for p in parts if p.name in IMPORT_FORMATS]
        if import_parts and not scene_parts:
            return await _import_parts(import_parts, parts, options, response, store, owner, settings)
        if import_parts:
            raise ValidationProblem([FieldError(
                field=import_parts[0].name,
                message="send either a 'scene' part (a scene document) or one file to import, not both",
                type="duplicate_part")])
        if len(scene_parts) != 1:
            raise ValidationProblem([FieldError(
                field="scene",
                message="exactly one part named 'scene' (the scene JSON) is required"
                        + (f"; found {len(scene_parts)}" if scene_parts else ""),
                type="missing" if not scene_parts else "duplicate_part",
            )])
        scene = await run_in_threadpool(_parse_scene_json, scene_parts[0].data, True)
        needed = mesh_paths(scene)
        errors = []
        seen: set[str] = set()
        for part in parts:
            if part.name == "scene":
                continue
            if part.name in seen:
                errors.append(FieldError(field=f"files.{part.name}", message=f"file part {part.name!r} sent twice",
                                         type="duplicate_part"))
            seen.add(part.name)
            meshes[part.name] = part.data
        errors = limit_errors(scene, settings, meshes={p: meshes[p] for p in needed if p in meshes}) + errors
        extra = sorted(set(meshes) - set(needed))
        if extra:
            errors.append(FieldError(
                field="files",
                message="file parts not referenced by any mesh_file path of the scene: "
                        + ", ".join(repr(e) for e in extra[:20])
                        + (f" ... ({len(extra)} in all)" if len(extra) > 20 else "")
                        + ". Name each file part by the mesh_file path it provides",
                type="unexpected_part",
            ))
        for path in needed:
            if path not in meshes:
                errors.append(FieldError(
                    field=f"scene.objects.{_first_object_with_path(scene, path)}.path",
                    message=f"no file part named {path!r}: upload the mesh as a part with that name",
                    type="missing_file",
                ))
        if not errors:
            for path in needed:
                problem = await run_in_threadpool(mesh_problem, path, meshes[path])
                if problem is not None:
                    errors.append(FieldError(field=f"files.{path}", message=problem, type="invalid_mesh"))
        if errors:
            raise ValidationProblem(errors)
        _no_import_options(options)
    elif ctype == "application/json" or ctype.endswith("+json") or ctype == "":
        _no_import_options(options)
        raw = await request.body()
        scene = await run_in_threadpool(_parse_scene_json, raw, False)
        errors = limit_errors(scene, settings)
        for path in mesh_paths(scene):
            errors.append(FieldError(
                field=f"scene.objects.{_first_object_with_path(scene, path)}.path",
                message=f"mesh file {path!r} must be uploaded: send multipart/form-data with a 'scene' part "
                        "and one file part per mesh_file path",
                type="missing_file",
            ))
        if errors:
            raise ValidationProblem(errors)
    else:
        raise ValidationProblem(
            [FieldError(field="", message=f"unsupported Content-Type {ctype!r}; use application/json, "
                                          "multipart/form-data or, to import a file, "
                                          + ", ".join(IMPORT_CONTENT_TYPES), type="content_type")],
            status=415,
        )
    public, created = await run_in_threadpool(_create, store, scene, meshes, owner)
    if created:
        response.headers["Location"] = f"/v1/scenes/{public.id}"
    else:
        response.status_code = 200
    return public


@router.get("", response_model=SceneList, responses=problem_responses(401, 422, 429, 503))
def list_all_scenes(
    store: StoreDep,
    owner: OwnerDep,
    limit: Annotated[int, Query(ge=1, le=1000, description="Scenes per page at most")] = 100,
    cursor: Annotated[str | None, Query(max_length=160, description="The next_cursor of the previous page")] = None,
) -> SceneList:
    """The scenes this API key stored, oldest first, a page at a time: follow ``next_cursor``
    until it is null. Reads an index and small summaries: the time does not depend on how many
    scenes the store holds or how large they are."""
    try:
        items, nxt = list_scene_page(store, owner, limit, cursor)
    except BadCursor as exc:
        raise ValidationProblem([FieldError(field="query.cursor", message=str(exc), type="invalid_cursor")]) from None
    return SceneList(items=items, next_cursor=nxt)


@router.get("/{scene_id}", response_model=ScenePublic, responses=problem_responses(401, 404, 422, 429, 503))
def read_scene(scene_id: SceneId, store: StoreDep, owner: OwnerDep) -> ScenePublic:
    """One stored scene."""
    if not scene_visible(store, scene_id, owner):
        raise NotFound(scene_id)
    _, _, public = get_scene(store, scene_id)
    return public.model_copy(update={"links": {"self": f"/v1/scenes/{public.id}",
                                               "document": f"/v1/scenes/{public.id}/document"}})


@router.get("/{scene_id}/document", response_model=Scene, response_model_exclude_none=True,
            responses=problem_responses(401, 404, 422, 429, 503))
def read_scene_document(scene_id: SceneId, store: StoreDep, owner: OwnerDep) -> Scene:
    """The scene itself (the JSON document as stored, mesh files referenced by path): what a client
    needs to derive cameras or requests from a stored scene. Posting it again with the same mesh
    files gives the same id."""
    if not scene_visible(store, scene_id, owner):
        raise NotFound(scene_id)
    scene, _, _ = get_scene(store, scene_id)
    return scene


@router.delete(
    "/{scene_id}", status_code=204, response_class=Response,
    responses=problem_responses(401, 404, 409, 422, 429, 503),
)
def remove_scene(scene_id: SceneId, store: StoreDep, redis: RedisDep, owner: OwnerDep) -> Response:
    """Delete a scene (409 while a queued or running job uses it). The last owner's delete also
    removes the scene's LDC bakes, walkthroughs and walkthrough bakes."""
    if not scene_visible(store, scene_id, owner) or not store.exists(f"scenes/{scene_id}.json"):
        raise NotFound(scene_id)
    owners = set(scene_owners(store, scene_id))
    last = owner is None or owners <= {owner}
    if last:  # checks every job of the scene and its outputs first; nothing changes on 409
        try:
            outs = delete_scene_outputs(redis, store, scene_id)
        except SceneOutputsInUse as exc:
            raise HTTPException(409, str(exc)) from None
        for bake_key, _params in outs.ldc_bakes:  # who held those bakes
            remove_bake_owner(store, bake_key, None)
    elif scene_id in ids_in_active_jobs(redis, ("scene_id", "scene")):
        raise HTTPException(409, f"scene {scene_id} is used by a queued or running job; cancel it or wait")
    if owner is None:
        for who in owners:  # auth off: one namespace, delete for everybody
            if who != ANON_OWNER:
                unindex_scene_owner(store, scene_id, who)
            store.delete(f"scene-owners/{scene_id}/{who}")
    else:
        unindex_scene_owner(store, scene_id, owner)  # before the marker: a listed scene is always visible
        remove_scene_owner(store, scene_id, owner)
    if not scene_owners(store, scene_id):
        unindex_scene(store, scene_id)
        try:
            delete_scene(store, scene_id)
        except NotFound:
            pass  # deleted concurrently
    return Response(status_code=204)


__all__ = ["SAMPLE_SCENE", "mesh_problem", "router"]
