"""Scene import: glTF 2.0 (``.gltf`` + buffers, ``.glb``) and OBJ + MTL -> a scene and its mesh blobs.

The result is exactly what a user could upload by hand (``POST /v1/scenes`` multipart): a
:class:`~api_schemas.scene.Scene` whose meshes are ``mesh_file`` objects, and one binary PLY
per mesh, so the workers read imported scenes like any other. What maps exactly, what is
approximated and what is left out is in docs/scene-import.md; every feature left out or
approximated is reported in ``warnings`` (never dropped silently). Invalid input raises
:class:`ImportProblem`, whose errors name the part (``accessors[3].count``, ``box.obj:12``).
Runs in the API process: numpy and the standard library, no numba, no network.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import ValidationError

from api_schemas.scene import Scene
from producer.scene_import.common import ImportOptions, ImportProblem
from producer.scene_import.gltf import gltf_companions, import_gltf
from producer.scene_import.obj import import_obj, obj_companions

__all__ = ["IMPORT_FORMATS", "ImportOptions", "ImportProblem", "ImportedScene", "companions", "import_scene",
           "referenced_files"]

ImportFormat = Literal["gltf", "glb", "obj"]
IMPORT_FORMATS: tuple[str, ...] = ("gltf", "glb", "obj")


@dataclass(frozen=True)
class ImportedScene:
    scene: Scene
    meshes: dict[str, bytes]
    """Mesh blob (binary PLY) by the ``mesh_file`` path the scene gives it."""
    warnings: list[dict[str, Any]]
    """One entry per unsupported or approximated feature: feature, message, count, where."""


def import_scene(fmt: str, data: bytes, files: Mapping[str, bytes] | None = None,
                 options: ImportOptions | None = None, source: str | None = None) -> ImportedScene:
    """Convert one file (``fmt`` gltf, glb or obj); ``files`` holds the other files of the upload
    by the relative path the main file uses for them (glTF buffers, MTL files)."""
    files = files or {}
    options = options or ImportOptions()
    src = source or f"scene.{fmt}"
    if not data:
        raise ImportProblem([(fmt, "the file is empty")])
    if fmt in ("gltf", "glb"):
        doc, meshes, warnings = import_gltf(data, fmt == "glb", files, options, src)
    elif fmt == "obj":
        doc, meshes, warnings = import_obj(data, files, options, src)
    else:
        raise ImportProblem([("format", f"unknown import format {fmt!r}; one of {', '.join(IMPORT_FORMATS)}")])
    try:
        scene = Scene.model_validate(doc)
    except ValidationError as exc:
        errs = exc.errors(include_url=False)
        raise ImportProblem([("converted scene." + ".".join(str(p) for p in e["loc"]), e["msg"])
                             for e in errs[:20]]) from None
    return ImportedScene(scene=scene, meshes=meshes, warnings=warnings.as_list())


def companions(fmt: str, data: bytes) -> list[str]:
    """The other files of an upload the main file names by relative path (glTF buffers, MTL files)."""
    if fmt == "gltf":
        return gltf_companions(data)
    if fmt == "obj":
        return obj_companions(data)
    return []


def referenced_files(fmt: str, data: bytes) -> list[str]:
    """Every file the main file names by relative path: :func:`companions` plus a glTF's images,
    which may come along but are not read (textures are ignored)."""
    return gltf_companions(data, images=True) if fmt == "gltf" else companions(fmt, data)
