"""Runtime scene: everything a renderer needs, flattened into contiguous arrays.

The runtime scene is built from engine-owned parameter types (no api_schemas
import). Geometry is a triangle soup in world space, stored in float64, plus a
float32 copy *relative to the scene centre* for Embree: Embree intersects in
float32, and recentring keeps a small scene placed 1e4 away from the origin
representable (docs/hard-cases.md #1, #6).

Light order is fixed and shared by every technique (visibility bit i belongs to
light i): point lights, then directional lights, then rectangular lights, each
in the order given.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

from engine.errors import InvalidInputError
from engine.geometry.mesh import TriMesh


def _rgb_array(rows: list[tuple[float, float, float]] | np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(rows, dtype=np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(a)):
        raise InvalidInputError(f"{name}: values must be finite")
    return np.ascontiguousarray(a)


@dataclass(frozen=True)
class MaterialTable:
    """Per-material arrays, indexed by material id.

    kd, ks, kr, kg, emission: (nm, 3) float64; shininess, gloss_exponent: (nm,) float64.
    BRDF (docs/algorithms.md "Shared conventions", materials): kd/pi + ks (n+2)/(2 pi) cos^n(alpha) for light sources;
    kr ideal mirror; kg normalised Phong lobe (exponent gloss_exponent) for the environment.
    """

    names: tuple[str, ...]
    kd: np.ndarray
    ks: np.ndarray
    shininess: np.ndarray
    kr: np.ndarray
    kg: np.ndarray
    gloss_exponent: np.ndarray
    emission: np.ndarray

    @staticmethod
    def from_rows(rows: list[dict]) -> MaterialTable:
        """rows: dicts with name, kd, ks, shininess, kr, kg, gloss_exponent, emission."""
        if not rows:
            rows = [dict(name="__default__", kd=(0.8, 0.8, 0.8), ks=(0, 0, 0), shininess=0.0,
                         kr=(0, 0, 0), kg=(0, 0, 0), gloss_exponent=0.0, emission=(0, 0, 0))]
        return MaterialTable(
            names=tuple(r["name"] for r in rows),
            kd=_rgb_array([r["kd"] for r in rows], "kd"),
            ks=_rgb_array([r["ks"] for r in rows], "ks"),
            shininess=np.asarray([float(r["shininess"]) for r in rows], dtype=np.float64),
            kr=_rgb_array([r["kr"] for r in rows], "kr"),
            kg=_rgb_array([r["kg"] for r in rows], "kg"),
            gloss_exponent=np.asarray([float(r["gloss_exponent"]) for r in rows], dtype=np.float64),
            emission=_rgb_array([r["emission"] for r in rows], "emission"),
        )

    @property
    def count(self) -> int:
        return len(self.names)


@dataclass(frozen=True)
class LightTable:
    """All lights of a scene as arrays, for the renderers' shading kernels, which read a light's row and
    pass it to ``engine.lights``' scalar samplers. Directions are unit vectors (the way light travels).

    Built from rows (:meth:`from_rows`): dicts with the scene format's light fields
    (``api_schemas.scene``'s point, directional and rect lights; ``workers.scene_loader`` converts a
    schema scene). The relighting describes lights as specs instead (``engine.relighting.lights``: the
    same three kinds plus environment maps, expanded into samples for the relight kernel);
    ``engine.relighting.lights.light_table`` builds a LightTable from such specs, so a dataset's
    ground truth is rendered under exactly the lights a relight uses.
    """

    point_position: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    point_intensity: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    dir_direction: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    dir_irradiance: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    rect_corner: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    rect_edge_u: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    rect_edge_v: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    rect_radiance: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    rect_two_sided: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=np.bool_))
    names: tuple[str, ...] = ()

    @property
    def n_point(self) -> int:
        return int(self.point_position.shape[0])

    @property
    def n_directional(self) -> int:
        return int(self.dir_direction.shape[0])

    @property
    def n_rect(self) -> int:
        return int(self.rect_corner.shape[0])

    @property
    def count(self) -> int:
        return self.n_point + self.n_directional + self.n_rect

    def rect_frames(self) -> tuple[np.ndarray, np.ndarray]:
        """Rect lights' unit normals (n_rect, 3), edge_u x edge_v normalised (the side a one-sided
        light emits toward), and areas (n_rect,)."""
        a = np.cross(self.rect_edge_u, self.rect_edge_v).reshape(-1, 3)
        area = np.linalg.norm(a, axis=1)
        return a / np.where(area > 0, area, 1.0)[:, None], area

    @staticmethod
    def from_rows(rows: list[dict]) -> LightTable:
        """rows: dicts with type 'point' | 'directional' | 'rect' and the schema's fields."""
        pts = [r for r in rows if r["type"] == "point"]
        dirs = [r for r in rows if r["type"] == "directional"]
        rects = [r for r in rows if r["type"] == "rect"]
        unknown = [r["type"] for r in rows if r["type"] not in ("point", "directional", "rect")]
        if unknown:
            raise InvalidInputError(f"unknown light type(s): {unknown}")
        d = _rgb_array([r["direction"] for r in dirs], "direction")
        dn = np.linalg.norm(d, axis=1, keepdims=True)
        if np.any(dn == 0):
            raise InvalidInputError("directional light direction must be nonzero")
        ordered = pts + dirs + rects
        return LightTable(
            point_position=_rgb_array([r["position"] for r in pts], "position"),
            point_intensity=_rgb_array([r["intensity"] for r in pts], "intensity"),
            dir_direction=np.ascontiguousarray(d / np.where(dn == 0, 1, dn)),
            dir_irradiance=_rgb_array([r["irradiance"] for r in dirs], "irradiance"),
            rect_corner=_rgb_array([r["corner"] for r in rects], "corner"),
            rect_edge_u=_rgb_array([r["edge_u"] for r in rects], "edge_u"),
            rect_edge_v=_rgb_array([r["edge_v"] for r in rects], "edge_v"),
            rect_radiance=_rgb_array([r["radiance"] for r in rects], "radiance"),
            rect_two_sided=np.asarray([bool(r.get("two_sided", False)) for r in rects], dtype=np.bool_),
            names=tuple(str(r.get("name") or f"light{i}") for i, r in enumerate(ordered)),
        )


@dataclass(frozen=True)
class CameraParams:
    """A pinhole or orthographic camera. Pixel (0, 0) is the top-left corner."""

    kind: str  # "perspective" | "orthographic"
    eye: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float]
    width: int
    height: int
    fov_y_deg: float = 45.0
    ortho_height: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in ("perspective", "orthographic"):
            raise InvalidInputError(f"camera.kind must be perspective or orthographic, got {self.kind!r}")
        if self.width < 1 or self.height < 1:
            raise InvalidInputError("camera width and height must be >= 1")
        if self.kind == "perspective" and not (0.0 < self.fov_y_deg < 180.0):
            raise InvalidInputError("camera.fov_y_deg must be in (0, 180)")
        if self.kind == "orthographic" and not self.ortho_height > 0:
            raise InvalidInputError("camera.ortho_height must be > 0")
        f = np.subtract(self.look_at, self.eye)
        if not np.all(np.isfinite(f)) or np.linalg.norm(f) == 0:
            raise InvalidInputError("camera.look_at must differ from camera.eye")
        if np.linalg.norm(np.cross(f / np.linalg.norm(f), np.asarray(self.up, float))) < 1e-12:
            raise InvalidInputError("camera.up must not be parallel to the view direction")

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(right, up, forward) orthonormal world-space vectors, float64."""
        fwd = np.subtract(self.look_at, self.eye).astype(np.float64)
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, np.asarray(self.up, dtype=np.float64))
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        return right, up, fwd

    def to_dict(self) -> dict:
        return {"kind": self.kind, "eye": list(self.eye), "look_at": list(self.look_at),
                "up": list(self.up), "width": self.width, "height": self.height,
                "fov_y_deg": self.fov_y_deg, "ortho_height": self.ortho_height}


@dataclass(frozen=True)
class SceneObjectPart:
    """One object's world-space mesh and its material index."""

    name: str
    mesh: TriMesh
    material_id: int


@dataclass(frozen=True, eq=False)
class RuntimeScene:
    """Flattened scene. Shapes (nt triangles):

    tri_p: (nt, 3, 3) float64 world-space corners;
    tri_n: (nt, 3, 3) float64 unit shading normals per corner;
    tri_ng: (nt, 3) float64 unit geometric normals (from the winding);
    tri_material: (nt,) int32; tri_object: (nt,) int32;
    tri_local32: (nt, 3, 3) float32 corners relative to ``center`` (Embree's input).
    """

    tri_p: np.ndarray
    tri_n: np.ndarray
    tri_ng: np.ndarray
    tri_material: np.ndarray
    tri_object: np.ndarray
    tri_local32: np.ndarray
    center: np.ndarray
    extent: float
    object_names: tuple[str, ...]
    materials: MaterialTable
    lights: LightTable
    ambient: np.ndarray
    background: np.ndarray

    @property
    def n_triangles(self) -> int:
        return int(self.tri_p.shape[0])

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        if self.n_triangles == 0:
            return np.zeros(3), np.zeros(3)
        return self.tri_p.reshape(-1, 3).min(axis=0), self.tri_p.reshape(-1, 3).max(axis=0)

    def geometry_hash(self) -> str:
        """Identifies the geometry, e.g. to key per-process Embree scene caches."""
        h = hashlib.sha256()
        for a in (self.tri_p, self.tri_material, self.tri_object):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()


def build_runtime_scene(
    parts: list[SceneObjectPart],
    materials: MaterialTable,
    lights: LightTable,
    ambient: tuple[float, float, float] = (0.0, 0.0, 0.0),
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> RuntimeScene:
    """Flatten world-space object meshes into one triangle soup."""
    tri_p, tri_n, mat, obj = [], [], [], []
    for oid, part in enumerate(parts):
        if not (0 <= part.material_id < materials.count):
            raise InvalidInputError(f"object {part.name!r}: material id {part.material_id} out of range")
        m = part.mesh
        tri_p.append(m.vertices[m.faces])
        tri_n.append(m.normals[m.faces])
        mat.append(np.full(m.n_faces, part.material_id, dtype=np.int32))
        obj.append(np.full(m.n_faces, oid, dtype=np.int32))
    if tri_p:
        p = np.ascontiguousarray(np.concatenate(tri_p), dtype=np.float64)
        n = np.ascontiguousarray(np.concatenate(tri_n), dtype=np.float64)
        mats = np.ascontiguousarray(np.concatenate(mat))
        objs = np.ascontiguousarray(np.concatenate(obj))
    else:
        p = np.zeros((0, 3, 3))
        n = np.zeros((0, 3, 3))
        mats = np.zeros(0, dtype=np.int32)
        objs = np.zeros(0, dtype=np.int32)
    if not np.all(np.isfinite(p)) or not np.all(np.isfinite(n)):
        raise InvalidInputError("scene geometry contains non-finite values")
    if p.shape[0]:
        lo, hi = p.reshape(-1, 3).min(axis=0), p.reshape(-1, 3).max(axis=0)
        center = 0.5 * (lo + hi)
        extent = float(np.linalg.norm(hi - lo))
    else:
        center, extent = np.zeros(3), 0.0
    ng = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    ln = np.linalg.norm(ng, axis=1, keepdims=True)
    if np.any(ln == 0):
        raise InvalidInputError(f"{int(np.sum(ln == 0))} degenerate triangles reached the runtime scene")
    ng = ng / ln
    local32 = np.ascontiguousarray((p - center).astype(np.float32))
    return RuntimeScene(
        tri_p=p, tri_n=n, tri_ng=np.ascontiguousarray(ng), tri_material=mats, tri_object=objs,
        tri_local32=local32, center=center, extent=extent,
        object_names=tuple(pt.name for pt in parts), materials=materials, lights=lights,
        ambient=np.asarray(ambient, dtype=np.float64), background=np.asarray(background, dtype=np.float64),
    )
