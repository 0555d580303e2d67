"""Turn a validated ``api_schemas.Scene`` into the engine's runtime scene.

This is the one place where schema types meet engine types: primitives are
tessellated, mesh files loaded and validated (with their reports kept for the
job result), transforms applied, and materials / lights flattened to arrays.
:func:`light_rows` converts schema lights, a scene's or a relight request's, to the
engine's light rows.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from api_schemas.datasets import RelightEnvironmentLight
from api_schemas.scene import (
    BoxObject,
    Camera,
    CylinderObject,
    DirectionalLightFields,
    DiskObject,
    InlineMeshObject,
    MeshFileObject,
    OrthographicCamera,
    PlaneObject,
    PointLightFields,
    RectLightFields,
    Scene,
    SceneObject,
    SphereObject,
    scene_hash,
)
from engine.errors import InvalidInputError, MeshValidationError
from engine.geometry import meshio, primitives
from engine.geometry.mesh import TriMesh
from engine.scene import (
    CameraParams,
    LightTable,
    MaterialTable,
    RuntimeScene,
    SceneObjectPart,
    build_runtime_scene,
)
from engine.walkthrough.animation import AnimatedScene, LightTrack, TransformTrack

# The uploaded image of an environment light, linear RGB (H, W, 3).
EnvironmentImage = Callable[[RelightEnvironmentLight], np.ndarray]
SchemaLight = PointLightFields | DirectionalLightFields | RectLightFields | RelightEnvironmentLight

# Resolves a mesh_file path to (bytes, file type); lets the service serve uploads
# from the object store while the CLI reads from a directory.
MeshResolver = Callable[[str], tuple[bytes, str]]


@dataclass
class LoadedScene:
    """A runtime scene plus what loading it found out."""

    runtime: RuntimeScene
    camera: CameraParams
    scene_hash: str
    mesh_reports: list[dict[str, Any]] = field(default_factory=list)


def _v3(v: tuple[float, float, float]) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


def camera_params(cam: Camera) -> CameraParams:
    """Engine camera parameters from a schema camera."""
    if isinstance(cam, OrthographicCamera):
        return CameraParams("orthographic", _v3(cam.eye), _v3(cam.look_at), _v3(cam.up),
                            cam.width, cam.height, ortho_height=cam.ortho_height)
    return CameraParams("perspective", _v3(cam.eye), _v3(cam.look_at), _v3(cam.up),
                        cam.width, cam.height, fov_y_deg=cam.fov_y_deg)


def light_rows(lights: Sequence[SchemaLight], environment_image: EnvironmentImage | None = None
               ) -> list[dict[str, Any]]:
    """Schema lights -> the engine's light rows, in order: one dict per light with its ``type`` and its
    fields under the schema's names, which are the engine's (``engine.scene.LightTable.from_rows`` reads a
    scene's rows, ``engine.relighting.lights.light_from_dict`` a relight request's). A scene light keeps
    its ``name``; a relight rect light its ``samples`` and ``seed``; an environment light's uploaded map
    becomes ``image``, read by ``environment_image`` (required when there is one)."""
    rows: list[dict[str, Any]] = []
    for light in lights:
        if isinstance(light, RelightEnvironmentLight):
            if environment_image is None:
                raise InvalidInputError("an environment light needs its uploaded image")
            row = light.model_dump(exclude={"image_sha256", "transfer"})
            row["image"] = environment_image(light)
            rows.append(row)
        else:
            rows.append(light.model_dump())
    return rows


def directory_resolver(base_dir: str | Path) -> MeshResolver:
    """Resolve mesh paths inside ``base_dir`` only (the schema already forbids '..' and
    absolute paths; this re-checks after symlink resolution)."""
    root = Path(base_dir).resolve()

    def resolve(rel: str) -> tuple[bytes, str]:
        p = (root / PurePosixPath(rel)).resolve()
        if root not in p.parents and p != root:
            raise MeshValidationError(f"{rel}: path leaves the scene directory", source=rel)
        if not p.is_file():
            raise MeshValidationError(f"{rel}: mesh file not found", source=rel)
        size = p.stat().st_size
        if size > meshio.DEFAULT_MAX_MESH_BYTES:
            raise MeshValidationError(f"{rel}: file is {size} bytes, over the {meshio.DEFAULT_MAX_MESH_BYTES} limit",
                                      source=rel)
        return p.read_bytes(), p.suffix.lower().lstrip(".")

    return resolve


def _object_mesh(obj: SceneObject, resolver: MeshResolver | None, reports: list[dict[str, Any]],
                 index: int) -> TriMesh:
    if isinstance(obj, SphereObject):
        return primitives.sphere(obj.center, obj.radius, obj.subdivisions)
    if isinstance(obj, BoxObject):
        return primitives.box(obj.center, obj.size)
    if isinstance(obj, CylinderObject):
        return primitives.cylinder(obj.center, obj.radius, obj.height, obj.segments, obj.capped)
    if isinstance(obj, PlaneObject):
        return primitives.plane(obj.center, obj.size, obj.segments)
    if isinstance(obj, DiskObject):
        return primitives.disk(obj.center, obj.radius, obj.segments)
    if isinstance(obj, InlineMeshObject):
        mesh, rep = meshio.validate_mesh(np.asarray(obj.vertices, dtype=np.float64),
                                         np.asarray(obj.faces, dtype=np.int64),
                                         None if obj.normals is None else np.asarray(obj.normals, np.float64),
                                         source=f"objects.{index}", on_invalid="clean")
        reports.append(rep.to_dict())
        return mesh
    if isinstance(obj, MeshFileObject):
        if resolver is None:
            raise MeshValidationError(f"objects.{index}.path: no mesh files available to resolve {obj.path!r}",
                                      source=obj.path)
        data, ftype = resolver(obj.path)
        mesh, rep = meshio.load_mesh_bytes(data, file_type=ftype, source=obj.path, on_invalid=obj.on_invalid)
        reports.append(rep.to_dict())
        return mesh
    raise InvalidInputError(f"objects.{index}: unsupported object type {type(obj).__name__}")


def load_scene(scene: Scene, resolver: MeshResolver | None = None) -> LoadedScene:
    """Build the runtime scene. Raises MeshValidationError / InvalidInputError naming the object."""
    mat_index = {m.name: i for i, m in enumerate(scene.materials)}
    materials = MaterialTable.from_rows([m.model_dump() for m in scene.materials])
    parts: list[SceneObjectPart] = []
    reports: list[dict[str, Any]] = []
    for i, obj in enumerate(scene.objects):
        try:
            mesh = _object_mesh(obj, resolver, reports, i)
        except (MeshValidationError, InvalidInputError) as exc:
            if str(exc).startswith("objects."):
                raise
            raise type(exc)(f"objects.{i}: {exc}") from exc
        mesh = mesh.transformed(obj.transform.to_matrix())
        parts.append(SceneObjectPart(obj.name or f"object{i}", mesh, mat_index[obj.material]))
    lights = LightTable.from_rows(light_rows(scene.lights))
    runtime = build_runtime_scene(parts, materials, lights, ambient=_v3(scene.ambient),
                                  background=_v3(scene.background))
    return LoadedScene(runtime, camera_params(scene.camera), scene_hash(scene), reports)


def load_scene_at(scene: Scene, time: float, resolver: MeshResolver | None = None) -> LoadedScene:
    """The runtime scene at animation time ``time`` (``AnimatedScene.scene_at``), with the scene's camera,
    hash and mesh reports. InvalidInputError when the scene has no animation or ``time`` is outside
    ``[animation.start, animation.end]`` (the message names ``time`` and the interval)."""
    if scene.animation is None:
        raise InvalidInputError("time: the scene has no animation, so there is no moment to render")
    loaded = load_scene(scene, resolver)
    animated = load_animated_scene(scene, resolver, loaded=loaded)
    t = animated.check_time(time)
    return LoadedScene(animated.scene_at(t), loaded.camera, loaded.scene_hash, loaded.mesh_reports)


def load_animated_scene(scene: Scene, resolver: MeshResolver | None = None, *,
                        loaded: LoadedScene | None = None) -> AnimatedScene:
    """The scene with its animation, as an engine ``AnimatedScene`` (``scene_at(t)`` gives the
    runtime scene at time t). A scene without ``animation`` is static over [0, 0]. ``loaded``: the
    scene as stored, when the caller has loaded it already (``load_scene`` of the same scene)."""
    if loaded is None:
        loaded = load_scene(scene, resolver)
    rt = loaded.runtime
    parts = [SceneObjectPart(name, _part_mesh(rt, i), int(_part_material(rt, i)))
             for i, name in enumerate(rt.object_names)]
    rows = light_rows(scene.lights)
    anim = scene.animation
    if anim is None:
        return AnimatedScene(parts, rt.materials, rows, ambient=_v3(scene.ambient),
                             background=_v3(scene.background))
    index_of = {o.name: i for i, o in enumerate(scene.objects) if o.name is not None}
    tracks: list[TransformTrack] = []
    local: dict[int, TriMesh] = {}
    for name, frames in anim.objects.items():
        i = index_of[name]
        local[i] = _object_mesh(scene.objects[i], resolver, [], i)
        tracks.append(TransformTrack.from_matrices(i, [f.time for f in frames],
                                                   [f.transform.to_matrix() for f in frames]))
    light_index: dict[str, int] = {}
    for i, lt in enumerate(scene.lights):
        if lt.name is not None:
            light_index.setdefault(lt.name, i)
    light_tracks: list[LightTrack] = []
    for name, lframes in anim.lights.items():
        pos = [(f.time, f.position) for f in lframes if f.position is not None]
        inten = [(f.time, f.intensity) for f in lframes if f.intensity is not None]
        light_tracks.append(LightTrack(
            light_index[name],
            np.array([t for t, _ in pos], dtype=np.float64),
            np.array([p for _, p in pos], dtype=np.float64).reshape(-1, 3),
            np.array([t for t, _ in inten], dtype=np.float64),
            np.array([p for _, p in inten], dtype=np.float64).reshape(-1, 3)))
    return AnimatedScene(parts, rt.materials, rows, ambient=_v3(scene.ambient),
                         background=_v3(scene.background), start=anim.start, end=anim.end,
                         object_tracks=tracks, local_meshes=local, light_tracks=light_tracks)


def _part_mesh(rt: RuntimeScene, i: int) -> TriMesh:
    """Object ``i``'s world-space triangles back out of the runtime triangle soup."""
    sel = np.flatnonzero(rt.tri_object == i)
    v = rt.tri_p[sel].reshape(-1, 3)
    n = rt.tri_n[sel].reshape(-1, 3)
    f = np.arange(v.shape[0], dtype=np.int32).reshape(-1, 3)
    return TriMesh(np.ascontiguousarray(v), f, np.ascontiguousarray(n))


def _part_material(rt: RuntimeScene, i: int) -> int:
    sel = np.flatnonzero(rt.tri_object == i)
    return int(rt.tri_material[sel[0]]) if sel.size else 0
