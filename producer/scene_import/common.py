"""What the glTF and OBJ importers share: errors, warnings, mesh blobs, material and camera mapping.

Numpy and the standard library only: the API process runs the conversion and never loads numba.
"""

from __future__ import annotations

import math
import re
import urllib.parse
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from api_schemas.scene import MAX_LIGHTS, MAX_MATERIALS, MAX_MESH_FACES, MAX_MESH_VERTICES, MAX_OBJECTS

__all__ = [
    "DEFAULT_HEIGHT",
    "ImportOptions",
    "ImportProblem",
    "MeshData",
    "SceneBuilder",
    "Warnings",
    "companion_uri_problem",
    "pbr_material",
    "ply_bytes",
]

DEFAULT_HEIGHT = 480
"""Image height of an imported camera when the request names none."""
MAX_SHININESS = 1e4
"""Phong exponent given to the smoothest surfaces (roughness 0 would be infinite)."""
MIRROR_EXPONENT = 1e4
"""A metal whose exponent reaches this reflects its surroundings as a mirror (kr), not a glossy lobe."""
_MAX_WARNING_PLACES = 10


class ImportProblem(Exception):
    """The file cannot be imported: ``errors`` holds (field, message) pairs naming the part."""

    def __init__(self, errors: list[tuple[str, str]]) -> None:
        super().__init__("; ".join(f"{f}: {m}" for f, m in errors))
        self.errors = errors


def fail(where: str, message: str) -> ImportProblem:
    return ImportProblem([(where, message)])


@dataclass
class ImportOptions:
    width: int | None = None
    height: int | None = None
    name: str | None = None


@dataclass
class _Warning:
    feature: str
    message: str
    where: list[str] = field(default_factory=list)
    count: int = 0


class Warnings:
    """Unsupported or approximated features, one entry per feature with the places it occurs."""

    def __init__(self) -> None:
        self._by_feature: dict[str, _Warning] = {}

    def add(self, feature: str, where: str, message: str) -> None:
        w = self._by_feature.setdefault(feature, _Warning(feature, message))
        w.count += 1
        if len(w.where) < _MAX_WARNING_PLACES:
            w.where.append(where)

    def as_list(self) -> list[dict[str, Any]]:
        return [{"feature": w.feature, "message": w.message, "count": w.count, "where": list(w.where)}
                for w in self._by_feature.values()]

    def features(self) -> set[str]:
        return set(self._by_feature)


_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")


def companion_uri_problem(uri: str) -> str | None:
    """Why ``uri`` does not name another file of the same upload (None when it does)."""
    if not uri:
        return "is empty"
    if _SCHEME.match(uri):
        return f"{uri[:60]!r} is a URL ({uri.split(':', 1)[0]}:); only files of the upload (relative paths) " \
               "and data: URIs are read, nothing is fetched"
    path = urllib.parse.unquote(uri)
    if "\x00" in path:
        return "contains a NUL character"
    if path.startswith(("/", "\\")) or re.match(r"^[A-Za-z]:", path):
        return f"{uri[:60]!r} is an absolute path; only files of the upload (relative paths) are read"
    if "\\" in path:
        return f"{uri[:60]!r} uses '\\' as separator"
    if ".." in path.split("/"):
        return f"{uri[:60]!r} leaves the upload ('..'); only files of the upload are read"
    return None


# --------------------------------------------------------------------------- mesh blobs


@dataclass
class MeshData:
    """One triangle mesh in local space: float64 positions, optional normals, int64 faces."""

    positions: npt.NDArray[np.float64]
    faces: npt.NDArray[np.int64]
    normals: npt.NDArray[np.float64] | None = None


def ply_bytes(mesh: MeshData, comment: str) -> bytes:
    """Binary little-endian PLY: double positions, float normals when given, uint triangle indices.

    The form a user would upload by hand; the API's PLY pre-check and the worker's loader read it."""
    n, m = len(mesh.positions), len(mesh.faces)
    props = ["property double x", "property double y", "property double z"]
    vdt: list[tuple[str, str]] = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if mesh.normals is not None:
        props += ["property float nx", "property float ny", "property float nz"]
        vdt += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    safe_comment = re.sub(r"[^\x20-\x7e]", "?", comment)[:200]
    header = "\n".join(["ply", "format binary_little_endian 1.0", f"comment {safe_comment}",
                        f"element vertex {n}", *props, f"element face {m}",
                        "property list uchar uint vertex_indices", "end_header"]) + "\n"
    verts = np.zeros(n, dtype=vdt)
    for k, axis in enumerate("xyz"):
        verts[axis] = mesh.positions[:, k]
    if mesh.normals is not None:
        for k, axis in enumerate(("nx", "ny", "nz")):
            verts[axis] = mesh.normals[:, k]
    faces = np.zeros(m, dtype=[("n", "u1"), ("i", "<u4", (3,))])
    faces["n"] = 3
    faces["i"] = mesh.faces
    return header.encode("ascii") + verts.tobytes() + faces.tobytes()


# --------------------------------------------------------------------------- materials


def _rgb(values: Any) -> tuple[float, float, float]:
    return (float(values[0]), float(values[1]), float(values[2]))


def roughness_to_exponent(roughness: float) -> float:
    """Phong exponent of the lobe a GGX roughness r resembles: alpha = r^2, Blinn-Phong
    n_b = 2 / alpha^2 - 2, and the Phong lobe around the mirror direction is about 4x wider
    than the Blinn-Phong lobe around the normal: n = n_b / 4."""
    alpha2 = max(roughness, 0.0) ** 4
    if alpha2 * 2 * (MAX_SHININESS + 0.5) <= 1:
        return MAX_SHININESS
    return max(0.0, 1.0 / (2.0 * alpha2) - 0.5)


def pbr_material(name: str, base: tuple[float, float, float], metallic: float, roughness: float,
                 f0: tuple[float, float, float], emission: tuple[float, float, float]) -> dict[str, Any]:
    """A metallic-roughness material as the project's Phong-family material (docs/scene-import.md).

    Diffuse ``kd = base (1 - metallic) (1 - max f0)``; the dielectric specular ``(1 - metallic) f0``
    goes to the highlight lobe ``ks``; the metal specular ``metallic * base`` is split evenly
    between ``ks`` (what it reflects of the lights) and ``kg`` / ``kr`` (what it reflects of the
    scene), since the schema counts those as two lobes of one energy budget. Fresnel is taken at
    normal incidence."""
    m = min(max(metallic, 0.0), 1.0)
    c = tuple(min(max(v, 0.0), 1.0) for v in base)
    f = tuple(min(max(v, 0.0), 1.0) for v in f0)
    n = roughness_to_exponent(min(max(roughness, 0.0), 1.0))
    fmax = max(f)
    kd = [c[i] * (1 - m) * (1 - fmax) for i in range(3)]
    ks = [(1 - m) * f[i] for i in range(3)]
    env = [0.0, 0.0, 0.0]
    metal = [m * c[i] for i in range(3)]
    if n >= 1.0:
        for i in range(3):
            ks[i] += metal[i] / 2
            env[i] = metal[i] / 2
    else:
        for i in range(3):
            ks[i] += metal[i]
    doc: dict[str, Any] = {"name": name, "kd": _clean(kd), "ks": _clean(ks),
                           "shininess": float(n) if max(ks) > 0 else 0.0,
                           "emission": _clean(list(emission))}
    if max(env) > 0:
        if n >= MIRROR_EXPONENT:
            doc["kr"] = _clean(env)
        else:
            doc["kg"] = _clean(env)
            doc["gloss_exponent"] = float(n)
    return doc


def _clean(v: list[float]) -> list[float]:
    return [float(round(x, 12)) if abs(x) > 1e-15 else 0.0 for x in v]


def phong_material(name: str, kd: tuple[float, float, float], ks: tuple[float, float, float], shininess: float,
                   kr: tuple[float, float, float], emission: tuple[float, float, float], where: str,
                   warnings: Warnings) -> dict[str, Any]:
    """An MTL material; channels whose kd + ks + kr exceed 1 are scaled down (with a warning)."""
    total = max(kd[i] + ks[i] + kr[i] for i in range(3))
    scale = 1.0
    if total > 1.0:
        scale = (1.0 - 1e-9) / total
        warnings.add("energy_scaled", where,
                     "Kd + Ks (+ mirror) exceed 1 in some channel: the coefficients were scaled down so the "
                     "material reflects at most the light it receives")
    doc: dict[str, Any] = {
        "name": name,
        "kd": _clean([v * scale for v in kd]),
        "ks": _clean([v * scale for v in ks]),
        "shininess": float(min(max(shininess, 0.0), 1e7)) if max(ks) > 0 else 0.0,
        "emission": _clean(list(emission)),
    }
    if max(kr) > 0:
        doc["kr"] = _clean([v * scale for v in kr])
    return doc


# --------------------------------------------------------------------------- the scene


_NAME_BAD = re.compile(r"[^A-Za-z0-9_.-]+")


def safe_name(raw: Any, fallback: str) -> str:
    text = raw if isinstance(raw, str) else ""
    text = _NAME_BAD.sub("_", text).strip("_")[:48]
    return text or fallback


class SceneBuilder:
    """Collects materials, mesh blobs, objects, lights and the camera; enforces the scene limits."""

    def __init__(self, source: str, warnings: Warnings) -> None:
        self.source = source
        self.warnings = warnings
        self.materials: list[dict[str, Any]] = []
        self._material_names: set[str] = set()
        self._object_names: set[str] = set()
        self._light_names: set[str] = set()
        self.objects: list[dict[str, Any]] = []
        self.lights: list[dict[str, Any]] = []
        self.meshes: dict[str, bytes] = {}
        self._mesh_faces: dict[str, int] = {}
        self.mesh_data: dict[str, MeshData] = {}
        self.total_vertices = 0
        self.total_faces = 0
        self.instanced_faces = 0
        self.camera: dict[str, Any] | None = None
        self._lo = np.full(3, np.inf)
        self._hi = np.full(3, -np.inf)

    def unique(self, name: str, taken: set[str]) -> str:
        out, k = name, 2
        while out in taken:
            out = f"{name[:56]}.{k}"
            k += 1
        taken.add(out)
        return out

    def add_material(self, doc: dict[str, Any], where: str) -> str:
        if len(self.materials) >= MAX_MATERIALS:
            raise fail(where, f"more than {MAX_MATERIALS} materials (the scene limit)")
        doc = dict(doc)
        doc["name"] = self.unique(doc["name"], self._material_names)
        self.materials.append(doc)
        return str(doc["name"])

    def add_mesh(self, mesh: MeshData, stem: str, where: str) -> str:
        """Store one mesh blob; returns its path."""
        nv, nf = len(mesh.positions), len(mesh.faces)
        if nv > MAX_MESH_VERTICES or nf > MAX_MESH_FACES:
            raise fail(where, f"{nv} vertices and {nf} triangles exceed the per-mesh limits "
                              f"({MAX_MESH_VERTICES} vertices, {MAX_MESH_FACES} triangles)")
        self.total_vertices += nv
        self.total_faces += nf
        if self.total_faces > MAX_MESH_FACES or self.total_vertices > MAX_MESH_VERTICES:
            raise fail(where, f"the file holds more than {MAX_MESH_FACES} triangles or {MAX_MESH_VERTICES} "
                              "vertices in all (the scene limits)")
        path = f"meshes/{len(self.meshes):04d}_{safe_name(stem, 'mesh')}.ply"
        self.meshes[path] = ply_bytes(mesh, f"imported from {self.source} ({where})")
        self._mesh_faces[path] = nf
        self.mesh_data[path] = mesh
        return path

    def add_object(self, path: str, material: str, world: npt.NDArray[np.float64] | None, name: str,
                   where: str) -> None:
        if len(self.objects) >= MAX_OBJECTS:
            raise fail(where, f"more than {MAX_OBJECTS} mesh instances (the scene's object limit)")
        self.instanced_faces += self._mesh_faces[path]
        if self.instanced_faces > MAX_MESH_FACES:
            raise fail(where, f"the scene's mesh instances hold more than {MAX_MESH_FACES} triangles in all")
        obj: dict[str, Any] = {"type": "mesh_file", "path": path, "material": material,
                               "name": self.unique(safe_name(name, f"object_{len(self.objects)}"),
                                                   self._object_names)}
        pts = self.mesh_data[path].positions
        if world is not None and not np.array_equal(world, np.eye(4)):
            obj["transform"] = {"matrix": [[float(x) for x in row] for row in world]}
            pts = pts @ world[:3, :3].T + world[:3, 3]
        if len(pts):
            self._lo = np.minimum(self._lo, pts.min(axis=0))
            self._hi = np.maximum(self._hi, pts.max(axis=0))
        self.objects.append(obj)

    def add_light(self, doc: dict[str, Any], where: str) -> None:
        if len(self.lights) >= MAX_LIGHTS:
            raise fail(where, f"more than {MAX_LIGHTS} lights (the scene limit)")
        doc = dict(doc)
        doc["name"] = self.unique(safe_name(doc.get("name"), f"light_{len(self.lights)}"), self._light_names)
        self.lights.append(doc)

    def bounds(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None:
        if not np.all(np.isfinite(self._lo)):
            return None
        return self._lo.copy(), self._hi.copy()

    def emissive_rect_lights(self, emissive: dict[str, tuple[float, float, float]]) -> None:
        """Each emissive object whose triangles form one flat parallelogram also becomes a rect light
        (the project's emission is only seen); other emissive objects are listed in a warning."""
        for obj in list(self.objects):
            radiance = emissive.get(obj["material"])
            if radiance is None:
                continue
            where = f"objects {obj['name']}"
            mesh = self.mesh_data[obj["path"]]
            pts = mesh.positions
            faces = mesh.faces
            if "transform" in obj:
                mat = np.asarray(obj["transform"]["matrix"], dtype=np.float64)
                pts = pts @ mat[:3, :3].T + mat[:3, 3]
                if np.linalg.det(mat[:3, :3]) < 0:  # a mirroring transform turns the front side clockwise
                    faces = faces[:, ::-1]
            rect = _parallelogram(pts, faces)
            if rect is None:
                self.warnings.add("emission_not_a_light", where,
                                  "an emissive surface that is not one flat parallelogram is seen (its emission) "
                                  "but lights nothing: only parallelograms become rect lights")
                continue
            corner, eu, ev = rect
            self.warnings.add("emission_as_rect_light", where,
                              "an emissive parallelogram became a rect light of the same radiance, emitting "
                              "on its front side, so that it lights the scene")
            self.add_light({"type": "rect", "name": f"{obj['name']}_light", "corner": corner, "edge_u": eu,
                            "edge_v": ev, "radiance": list(radiance)}, where)
        if not self.lights and self.objects:
            self.warnings.add("no_lights", self.source, "the file has no light the project can use (glTF viewers "
                                                        "often add an environment): the scene renders black until "
                                                        "lights are added to its document")

    def default_camera(self, aspect: float | None, options: ImportOptions) -> dict[str, Any]:
        """A perspective camera looking along -z at the scene's bounds, the whole front in view."""
        width, height = resolution(aspect or 4 / 3, options)
        fov = 45.0
        b = self.bounds()
        if b is None:
            lo, hi = np.array([-1.0, -1.0, -1.0]), np.array([1.0, 1.0, 1.0])
        else:
            lo, hi = b
        centre = (lo + hi) / 2
        half = np.maximum((hi - lo) / 2, 1e-6 * max(1.0, float(np.abs(centre).max())))
        t = math.tan(math.radians(fov) / 2)
        dist = max(half[1], half[0] * height / width) / t * 1.1 + half[2]
        eye = centre + np.array([0.0, 0.0, dist])
        return {"type": "perspective", "eye": [float(x) for x in eye], "look_at": [float(x) for x in centre],
                "up": [0.0, 1.0, 0.0], "fov_y_deg": fov, "width": width, "height": height}


def resolution(aspect: float, options: ImportOptions) -> tuple[int, int]:
    """(width, height): the request's, else derived from the camera's aspect ratio."""
    aspect = aspect if math.isfinite(aspect) and aspect > 0 else 4 / 3
    if options.width and options.height:
        return options.width, options.height
    if options.width:
        return options.width, max(1, min(16384, round(options.width / aspect)))
    height = options.height or DEFAULT_HEIGHT
    return max(1, min(16384, round(height * aspect))), height


def _parallelogram(pts: npt.NDArray[np.float64], faces: npt.NDArray[np.int64]
                   ) -> tuple[list[float], list[float], list[float]] | None:
    """(corner, edge_u, edge_v) when the triangles cover exactly one flat parallelogram, oriented so
    that cross(edge_u, edge_v) is the triangles' front side."""
    used = np.unique(faces.reshape(-1))
    uniq = np.unique(pts[used], axis=0)
    if len(uniq) != 4:
        return None
    a = pts[faces[:, 1]] - pts[faces[:, 0]]
    b = pts[faces[:, 2]] - pts[faces[:, 0]]
    cr = np.cross(a, b)
    area = float(np.linalg.norm(cr, axis=1).sum()) / 2
    normal = cr.sum(axis=0)
    nn = float(np.linalg.norm(normal))
    if nn == 0 or area == 0:
        return None
    normal /= nn
    p0 = uniq[0]
    # the vertex opposite p0 is the one whose sum with p0 equals the sum of the other two
    for k in (1, 2, 3):
        others = [uniq[j] for j in (1, 2, 3) if j != k]
        diag_gap = np.linalg.norm(p0 + uniq[k] - others[0] - others[1])
        scale = float(np.abs(uniq - p0).max())
        if diag_gap <= 1e-6 * scale:
            eu, ev = others[0] - p0, others[1] - p0
            cross = np.cross(eu, ev)
            rect_area = float(np.linalg.norm(cross))
            if rect_area == 0 or abs(rect_area - area) > 1e-6 * rect_area:
                return None  # not flat, or the triangles do not cover it once
            if float(np.dot(cross, normal)) < 0:
                eu, ev = ev, eu
            return ([float(x) for x in p0], [float(x) for x in eu], [float(x) for x in ev])
    return None
