"""Scene description: the JSON document every renderer, baker and job receives.

Conventions (see ``docs/scene-format.md``): world space is right-handed with y up, in
any length unit; colours are linear RGB; a point light has intensity in W/sr, a
directional light irradiance, a rectangular light and an emissive material radiance.

Variants are chosen by a ``type`` field (Mitsuba 3 style dictionaries) through pydantic
discriminated unions. Every check reports a location that names the offending field:
single-model checks at the field (``camera.look_at``), cross-references at the Scene
level (``objects.3.material``, ``animation.objects.foo``).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from typing import TYPE_CHECKING, Annotated, Any, Literal, Self

import numpy as np
import numpy.typing as npt
from pydantic import (
    BeforeValidator,
    Field,
    StringConstraints,
    field_validator,
    model_validator,
)
from pydantic_core import InitErrorDetails, PydanticCustomError

from api_schemas.common import (
    RGB,
    FiniteFloat,
    FrozenModel,
    Loc,
    Name,
    NonNegativeFloat,
    PositiveFloat,
    PositiveVec3,
    StrictBool,
    Vec3,
    error_at,
    ndarray_to_list,
    numpy_scalar,
    raise_errors,
    unit_vector,
)

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

__all__ = [
    "MAX_IMAGE_PIXELS",
    "MAX_LIGHTS",
    "MAX_MATERIALS",
    "MAX_MESH_FACES",
    "MAX_MESH_VERTICES",
    "MAX_OBJECTS",
    "MAX_SCENE_BYTES",
    "Animation",
    "BoxObject",
    "BoxViewSpace",
    "Camera",
    "CylinderObject",
    "DirectionalLight",
    "DirectionalLightFields",
    "DiskObject",
    "InlineMeshObject",
    "Light",
    "LightKeyframe",
    "Material",
    "MeshFileObject",
    "OrthographicCamera",
    "PerspectiveCamera",
    "PlaneObject",
    "PathViewSpace",
    "PointLight",
    "PointLightFields",
    "PolygonViewSpace",
    "RectLight",
    "RectLightFields",
    "Scene",
    "SceneFileTooLargeError",
    "SceneObject",
    "SphereObject",
    "Transform",
    "TransformKeyframe",
    "ViewSpace",
    "canonical_scene_json",
    "load_scene_file",
    "load_scene_json",
    "scene_hash",
    "scene_json_schema",
]

MAX_IMAGE_PIXELS = 64_000_000
MAX_OBJECTS = 10_000
MAX_LIGHTS = 4096
# More materials than objects could never all be used.
MAX_MATERIALS = 10_000
MAX_MESH_VERTICES = 5_000_000
MAX_MESH_FACES = 10_000_000
MAX_KEYFRAMES = 100_000
MAX_VIEW_SPACE_POINTS = 10_000
MAX_POLYGON_VERTICES = 1000
MAX_SCENE_BYTES = 64 * 1024 * 1024

# Relative tolerances; all checks are scale-free (a scene at 1e-3 or 1e3 behaves alike).
_PARALLEL_TOL = 1e-9  # |cross| of two unit vectors below this counts as parallel
_COINCIDENT_TOL = 1e-12  # |a - b| <= tol * max(|a|, |b|) counts as the same point
_ENERGY_TOL = 1e-6
_MIN_SCALE = 1e-12
_SINGULAR_TOL = 1e-12  # |det| / product of column norms (Hadamard ratio)


def _cross(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float, float]:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _parallel(a: tuple[float, float, float], b: tuple[float, float, float]) -> bool:
    """a and b are unit vectors."""
    return math.hypot(*_cross(a, b)) <= _PARALLEL_TOL


def _fmt(v: float) -> str:
    return f"{v:.9g}"


# --------------------------------------------------------------------------- cameras

Resolution = Annotated[int, Field(strict=True, ge=1, le=16384), BeforeValidator(numpy_scalar)]


def _view_errors(eye: Vec3, look_at: Vec3, up: Vec3, width: int, height: int) -> list[InitErrorDetails]:
    errors: list[InitErrorDetails] = []
    forward: tuple[float, float, float] | None = None
    d = tuple(l - e for l, e in zip(look_at, eye, strict=True))
    span = max(max(abs(c) for c in eye), max(abs(c) for c in look_at))
    if not all(math.isfinite(c) for c in d):
        errors.append(error_at(("look_at",), "view_direction", "look_at - eye overflows", look_at))
    elif max(abs(c) for c in d) <= _COINCIDENT_TOL * span:
        errors.append(error_at(("look_at",), "view_direction", "look_at must differ from eye", look_at))
    else:
        forward = unit_vector(d)
    up_unit = unit_vector(up)
    if up_unit is None:
        errors.append(error_at(("up",), "up_vector", "up must be a nonzero vector", up))
    elif forward is not None and _parallel(forward, up_unit):
        errors.append(
            error_at(("up",), "up_vector", "up must not be parallel to the view direction look_at - eye", up)
        )
    if width * height > MAX_IMAGE_PIXELS:
        errors.append(
            error_at(
                ("height",),
                "image_too_large",
                f"width * height = {width * height} exceeds {MAX_IMAGE_PIXELS} pixels",
                height,
            )
        )
    return errors


class PerspectiveCamera(FrozenModel):
    """Pinhole camera looking from ``eye`` toward ``look_at``; square pixels."""

    type: Literal["perspective"] = "perspective"
    eye: Vec3
    """Centre of projection, world space."""
    look_at: Vec3
    """A point on the optical axis, world space; must differ from eye."""
    up: Vec3 = (0.0, 1.0, 0.0)
    """World-space up hint; must not be parallel to look_at - eye."""
    fov_y_deg: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, lt=180)] = 45.0
    """Full vertical field of view in degrees, in the open interval (0, 180)."""
    width: Resolution
    """Image width in pixels, 1..16384 (width * height <= 64e6)."""
    height: Resolution
    """Image height in pixels, 1..16384."""

    @model_validator(mode="after")
    def _check_view(self) -> Self:
        raise_errors(
            type(self).__name__, _view_errors(self.eye, self.look_at, self.up, self.width, self.height)
        )
        return self

    @property
    def aspect(self) -> float:
        return self.width / self.height


class OrthographicCamera(FrozenModel):
    """Parallel projection along look_at - eye; the view is ``ortho_height`` world units tall."""

    type: Literal["orthographic"] = "orthographic"
    eye: Vec3
    """Centre of the image plane, world space."""
    look_at: Vec3
    """A point on the viewing axis, world space; must differ from eye."""
    up: Vec3 = (0.0, 1.0, 0.0)
    """World-space up hint; must not be parallel to look_at - eye."""
    ortho_height: PositiveFloat
    """Height of the view in world units; the width follows from the aspect ratio."""
    width: Resolution
    """Image width in pixels, 1..16384 (width * height <= 64e6)."""
    height: Resolution
    """Image height in pixels, 1..16384."""

    @model_validator(mode="after")
    def _check_view(self) -> Self:
        raise_errors(
            type(self).__name__, _view_errors(self.eye, self.look_at, self.up, self.width, self.height)
        )
        return self

    @property
    def aspect(self) -> float:
        return self.width / self.height


Camera = Annotated[PerspectiveCamera | OrthographicCamera, Field(discriminator="type")]


# --------------------------------------------------------------------------- materials

Exponent = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=1e7)]


class Material(FrozenModel):
    """Phong-family material (docs/algorithms.md, "Shared conventions").

    Per channel ``kd + ks + kr + kg <= 1`` so that no material creates energy.
    """

    name: Name
    """Unique within the scene; objects refer to it by this name."""
    kd: RGB = (0.8, 0.8, 0.8)
    """Diffuse albedo; BRDF kd / pi."""
    ks: RGB = (0.0, 0.0, 0.0)
    """Specular highlight weight of the energy-normalised Phong lobe (n + 2) / (2 pi) cos^n."""
    shininess: Exponent = 0.0
    """Phong exponent n of the highlight lobe (0 is a valid, wide lobe)."""
    kr: RGB = (0.0, 0.0, 0.0)
    """Ideal mirror reflectance."""
    kg: RGB = (0.0, 0.0, 0.0)
    """Glossy (fuzzy) reflectance of the environment."""
    gloss_exponent: Exponent = 0.0
    """Phong exponent of the glossy reflection lobe; >= 1 whenever kg > 0."""
    emission: RGB = (0.0, 0.0, 0.0)
    """Radiance the surface shows to camera and mirror/glossy rays (linear RGB). It does not
    light other surfaces: declare a light (e.g. a rect light at the same place) for that."""

    @model_validator(mode="after")
    def _check_coefficients(self) -> Self:
        errors: list[InitErrorDetails] = []
        problems = []
        for c, channel in enumerate("rgb"):
            parts = (self.kd[c], self.ks[c], self.kr[c], self.kg[c])
            # any coefficient above 1 already breaks the budget; checking it first also keeps
            # fsum away from values near 1e308, whose sum overflows (a 500 instead of a 422)
            total = max(parts) if max(parts) > 1 + _ENERGY_TOL else math.fsum(parts)
            if total > 1 + _ENERGY_TOL:
                terms = " + ".join(_fmt(p) for p in parts)
                problems.append(f"channel {channel}: kd + ks + kr + kg = {terms} = {_fmt(total)} > 1")
        if problems:
            message = "energy conservation violated, " + "; ".join(problems)
            errors.append(error_at((), "energy_conservation", message, None))
        # A model validator, not a field validator: the default exponent 0 must be caught too.
        if self.is_glossy and self.gloss_exponent < 1:
            errors.append(
                error_at(
                    ("gloss_exponent",),
                    "gloss_exponent",
                    f"gloss_exponent must be >= 1 when kg > 0 (got {_fmt(self.gloss_exponent)})",
                    self.gloss_exponent,
                )
            )
        raise_errors("Material", errors)
        return self

    @property
    def has_highlight(self) -> bool:
        """ks is nonzero in some channel."""
        return max(self.ks) > 0

    @property
    def is_mirror(self) -> bool:
        """kr is nonzero in some channel."""
        return max(self.kr) > 0

    @property
    def is_glossy(self) -> bool:
        """kg is nonzero in some channel."""
        return max(self.kg) > 0

    @property
    def is_diffuse(self) -> bool:
        """Only kd and emission are nonzero: shading is view-independent."""
        return not (self.has_highlight or self.is_mirror or self.is_glossy)


# --------------------------------------------------------------------------- transforms

Quaternion = tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat]
MatrixRow = tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat]
Matrix4 = tuple[MatrixRow, MatrixRow, MatrixRow, MatrixRow]


class Transform(FrozenModel):
    """Local-to-world transform ``T @ R @ S`` (scale first, then rotate, then translate),
    or an explicit 4x4 ``matrix``."""

    translate: Vec3 = (0.0, 0.0, 0.0)
    """Translation."""
    rotate_deg: Vec3 | None = None
    """Euler angles in degrees, extrinsic x then y then z (scipy ``from_euler("xyz")``)."""
    quaternion: Quaternion | None = None
    """Rotation as (x, y, z, w); normalised on use, must be nonzero."""
    scale: Vec3 = (1.0, 1.0, 1.0)
    """Per-axis scale, each |s| >= 1e-12. Negative values mirror (flip handedness)."""
    matrix: Matrix4 | None = None
    """Row-major 4x4 affine matrix (last row 0 0 0 1, invertible); excludes the other fields."""

    @model_validator(mode="after")
    def _check(self) -> Self:
        errors: list[InitErrorDetails] = []
        if self.rotate_deg is not None and self.quaternion is not None:
            errors.append(
                error_at(
                    ("quaternion",),
                    "rotation_conflict",
                    "give at most one of rotate_deg and quaternion",
                    self.quaternion,
                )
            )
        if self.quaternion is not None:
            if max(abs(c) for c in self.quaternion) == 0:
                errors.append(
                    error_at(
                        ("quaternion",), "zero_quaternion", "quaternion must be nonzero", self.quaternion
                    )
                )
        small = [i for i, s in enumerate(self.scale) if abs(s) < _MIN_SCALE]
        if small:
            errors.append(
                error_at(
                    ("scale",),
                    "degenerate_scale",
                    f"scale components {small} have |s| < {_MIN_SCALE:g}",
                    self.scale,
                )
            )
        if self.matrix is not None:
            others = [
                n
                for n, set_ in (
                    ("translate", self.translate != (0.0, 0.0, 0.0)),
                    ("rotate_deg", self.rotate_deg is not None),
                    ("quaternion", self.quaternion is not None),
                    ("scale", self.scale != (1.0, 1.0, 1.0)),
                )
                if set_
            ]
            if others:
                errors.append(
                    error_at(
                        ("matrix",),
                        "matrix_conflict",
                        f"matrix excludes {', '.join(others)}; fold them into the matrix",
                        self.matrix,
                    )
                )
            if self.matrix[3] != (0.0, 0.0, 0.0, 1.0):
                errors.append(
                    error_at(
                        ("matrix",),
                        "matrix_not_affine",
                        "the last row of matrix must be [0, 0, 0, 1]",
                        self.matrix,
                    )
                )
            else:
                linear = np.array(self.matrix, dtype=np.float64)[:3, :3]
                # Scale each column to unit max-norm first so neither tiny nor huge units
                # overflow or underflow the determinant.
                col_max = np.abs(linear).max(axis=0)
                if np.any(col_max == 0):
                    ratio = 0.0
                else:
                    cols = linear / col_max
                    ratio = abs(float(np.linalg.det(cols))) / float(np.prod(np.linalg.norm(cols, axis=0)))
                if ratio < _SINGULAR_TOL:
                    errors.append(
                        error_at(
                            ("matrix",),
                            "singular_matrix",
                            "matrix must be invertible (it is singular)",
                            self.matrix,
                        )
                    )
        raise_errors("Transform", errors)
        return self

    def rotation(self) -> Rotation | None:
        """The rotation part as a scipy Rotation, or None when no rotation is given."""
        # deferred on purpose: only the workers build matrices; the models load without scipy (ibr-client)
        from scipy.spatial.transform import Rotation

        if self.quaternion is not None:
            q = np.asarray(self.quaternion, dtype=np.float64)
            return Rotation.from_quat(q / np.abs(q).max())  # pre-scaled: tiny quaternions stay valid
        if self.rotate_deg is not None:
            return Rotation.from_euler("xyz", self.rotate_deg, degrees=True)
        return None

    def to_matrix(self) -> npt.NDArray[np.float64]:
        """World-from-local matrix, ``(4, 4) float64``: ``T @ R @ S`` or ``matrix``."""
        if self.matrix is not None:
            return np.array(self.matrix, dtype=np.float64)
        m = np.eye(4, dtype=np.float64)
        rot = self.rotation()
        r = np.eye(3) if rot is None else rot.as_matrix()
        m[:3, :3] = r * np.asarray(self.scale, dtype=np.float64)[None, :]
        m[:3, 3] = self.translate
        return m


# --------------------------------------------------------------------------- objects


_DRIVE = re.compile(r"^[A-Za-z]:")


def _path_problem(path: str) -> str | None:
    if path == "":
        return "must not be empty"
    if "\x00" in path:
        return "must not contain NUL characters"
    if "\\" in path:
        return "must use '/' as separator (backslash found)"
    if path.startswith("/"):
        return "must be relative (it is absolute)"
    if _DRIVE.match(path):
        return "must be relative (it starts with a drive letter)"
    if ".." in path.split("/"):
        return "must not contain '..' components"
    return None


class MeshFileObject(FrozenModel):
    """Triangle mesh read from a file (PLY, OBJ, ...) relative to the scene's base directory."""

    type: Literal["mesh_file"] = "mesh_file"
    path: Annotated[str, Field(max_length=4096)]
    """Relative POSIX path, no '..' components; resolved by the loader."""
    on_invalid: Literal["reject", "clean"] = "reject"
    """What the loader does with degenerate or non-finite data: fail, or drop the bad faces."""
    name: Name | None = None
    """Optional name, unique among the scene's objects; animation tracks refer to it."""
    material: Name
    """Name of a material of the scene."""
    transform: Transform = Transform()
    """Local-to-world transform applied to the shape."""

    @field_validator("path")
    @classmethod
    def _safe_path(cls, value: str) -> str:
        problem = _path_problem(value)
        if problem is not None:
            raise PydanticCustomError("unsafe_path", f"path {value!r} {problem}")
        return value


_Index = Annotated[int, Field(strict=True)]


class InlineMeshObject(FrozenModel):
    """Triangle mesh given inline. Faces are counter-clockwise seen from the front."""

    type: Literal["mesh"] = "mesh"
    vertices: Annotated[
        list[Vec3], BeforeValidator(ndarray_to_list), Field(min_length=3, max_length=MAX_MESH_VERTICES)
    ]
    """Vertex positions, local space."""
    faces: Annotated[
        list[tuple[_Index, _Index, _Index]],
        BeforeValidator(ndarray_to_list),
        Field(min_length=1, max_length=MAX_MESH_FACES),
    ]
    """Triangles as three 0-based vertex indices."""
    normals: Annotated[list[Vec3] | None, BeforeValidator(ndarray_to_list)] = None
    """Optional per-vertex normals (nonzero, same count as vertices); normalised on use."""
    name: Name | None = None
    """Optional name, unique among the scene's objects; animation tracks refer to it."""
    material: Name
    """Name of a material of the scene."""
    transform: Transform = Transform()
    """Local-to-world transform applied to the shape."""

    @model_validator(mode="after")
    def _check_arrays(self) -> Self:
        errors: list[InitErrorDetails] = []
        n = len(self.vertices)
        bad = _bad_indices(self.faces, n)
        if bad is not None:
            count, (i, j, value) = bad
            errors.append(
                error_at(
                    ("faces",),
                    "face_index_out_of_range",
                    f"{count} face {'index' if count == 1 else 'indices'} out of range [0, {n}) "
                    f"(first: faces.{i}.{j} = {value})",
                    None,
                )
            )
        if self.normals is not None:
            if len(self.normals) != n:
                errors.append(
                    error_at(
                        ("normals",),
                        "normals_length",
                        f"normals has {len(self.normals)} entries, vertices has {n}",
                        None,
                    )
                )
            else:
                zero = np.flatnonzero(~np.any(np.asarray(self.normals, dtype=np.float64) != 0, axis=1))
                if zero.size:
                    errors.append(
                        error_at(
                            ("normals",),
                            "zero_normal",
                            f"{zero.size} normals are zero vectors (first: normals.{int(zero[0])})",
                            None,
                        )
                    )
        raise_errors("InlineMeshObject", errors)
        return self


def _bad_indices(faces: list[tuple[int, int, int]], n: int) -> tuple[int, tuple[int, int, int]] | None:
    """Count of indices outside [0, n) and the first one as (face, corner, value)."""
    try:
        f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    except OverflowError:  # an index beyond int64: certainly bad, count in Python
        flat = [(i, j, v) for i, face in enumerate(faces) for j, v in enumerate(face) if not 0 <= v < n]
        return len(flat), flat[0]
    mask = (f < 0) | (f >= n)
    count = int(mask.sum())
    if count == 0:
        return None
    i, j = (int(x) for x in np.argwhere(mask)[0])
    return count, (i, j, int(f[i, j]))


Segments = Annotated[int, Field(strict=True, ge=3, le=4096), BeforeValidator(numpy_scalar)]


class SphereObject(FrozenModel):
    """Sphere, tessellated as an icosphere."""

    type: Literal["sphere"] = "sphere"
    center: Vec3 = (0.0, 0.0, 0.0)
    """Centre, local space."""
    radius: PositiveFloat
    """Radius (> 0)."""
    subdivisions: Annotated[int, Field(strict=True, ge=0, le=8), BeforeValidator(numpy_scalar)] = 5
    """Icosphere subdivision levels, 0..8 (20 * 4^k triangles)."""
    name: Name | None = None
    """Optional name, unique among the scene's objects; animation tracks refer to it."""
    material: Name
    """Name of a material of the scene."""
    transform: Transform = Transform()
    """Local-to-world transform applied to the shape."""


class BoxObject(FrozenModel):
    """Axis-aligned box (in local space)."""

    type: Literal["box"] = "box"
    center: Vec3 = (0.0, 0.0, 0.0)
    """Centre, local space."""
    size: PositiveVec3
    """Edge lengths along x, y, z (each > 0)."""
    name: Name | None = None
    """Optional name, unique among the scene's objects; animation tracks refer to it."""
    material: Name
    """Name of a material of the scene."""
    transform: Transform = Transform()
    """Local-to-world transform applied to the shape."""


class CylinderObject(FrozenModel):
    """Cylinder with its axis along local y, centred at ``center``."""

    type: Literal["cylinder"] = "cylinder"
    center: Vec3 = (0.0, 0.0, 0.0)
    """Centre of the axis, local space."""
    radius: PositiveFloat
    """Radius (> 0)."""
    height: PositiveFloat
    """Length along y (> 0); the cylinder spans center.y +- height / 2."""
    segments: Segments = 64
    """Facets around the axis, 3..4096."""
    capped: StrictBool = True
    """Close both ends with disks."""
    name: Name | None = None
    """Optional name, unique among the scene's objects; animation tracks refer to it."""
    material: Name
    """Name of a material of the scene."""
    transform: Transform = Transform()
    """Local-to-world transform applied to the shape."""


class PlaneObject(FrozenModel):
    """Rectangle in the local xz plane, front face toward +y."""

    type: Literal["plane"] = "plane"
    center: Vec3 = (0.0, 0.0, 0.0)
    """Centre, local space."""
    size: tuple[PositiveFloat, PositiveFloat]
    """Extent along x and z (each > 0)."""
    segments: Annotated[int, Field(strict=True, ge=1, le=1024), BeforeValidator(numpy_scalar)] = 1
    """Subdivisions per side, 1..1024."""
    name: Name | None = None
    """Optional name, unique among the scene's objects; animation tracks refer to it."""
    material: Name
    """Name of a material of the scene."""
    transform: Transform = Transform()
    """Local-to-world transform applied to the shape."""


class DiskObject(FrozenModel):
    """Disk in the local xz plane, front face toward +y."""

    type: Literal["disk"] = "disk"
    center: Vec3 = (0.0, 0.0, 0.0)
    """Centre, local space."""
    radius: PositiveFloat
    """Radius (> 0)."""
    segments: Segments = 64
    """Facets around the rim, 3..4096."""
    name: Name | None = None
    """Optional name, unique among the scene's objects; animation tracks refer to it."""
    material: Name
    """Name of a material of the scene."""
    transform: Transform = Transform()
    """Local-to-world transform applied to the shape."""


SceneObject = Annotated[
    MeshFileObject | InlineMeshObject | SphereObject | BoxObject | CylinderObject | PlaneObject | DiskObject,
    Field(discriminator="type"),
]


# --------------------------------------------------------------------------- lights
#
# One light model: the ``*LightFields`` bases hold each kind's fields and checks; the scene's lights
# add a ``name`` (animation tracks refer to it), a relight request's lights (``api_schemas.datasets``)
# add defaults and, for a rect light, its sampling. ``workers.scene_loader.light_rows`` is the one
# conversion of either to the engine's lights.


class PointLightFields(FrozenModel):
    """Isotropic point light: irradiance I cos(theta) / d^2."""

    type: Literal["point"] = "point"
    position: Vec3
    """Position, world space."""
    intensity: RGB
    """Radiant intensity per channel, W/sr."""


class DirectionalLightFields(FrozenModel):
    """Light from infinitely far away, arriving along ``direction``."""

    type: Literal["directional"] = "directional"
    direction: Vec3
    """Direction the light travels (from the light toward the scene); nonzero, normalised on use."""
    irradiance: RGB
    """Irradiance on a surface perpendicular to the direction, W/m^2 per channel."""

    @field_validator("direction")
    @classmethod
    def _nonzero(cls, value: Vec3) -> Vec3:
        if unit_vector(value) is None:
            raise PydanticCustomError("zero_vector", "direction must be a nonzero vector")
        return value


class RectLightFields(FrozenModel):
    """Parallelogram area light with corners corner, corner + edge_u, corner + edge_v,
    corner + edge_u + edge_v; emits toward cross(edge_u, edge_v) (both sides if two_sided)."""

    type: Literal["rect"] = "rect"
    corner: Vec3
    """One corner, world space."""
    edge_u: Vec3
    """First edge from the corner; nonzero."""
    edge_v: Vec3
    """Second edge from the corner; nonzero and not parallel to edge_u."""
    radiance: RGB
    """Emitted radiance per channel, W/(m^2 sr)."""
    two_sided: StrictBool = False
    """Emit from both faces."""

    @model_validator(mode="after")
    def _check_edges(self) -> Self:
        errors: list[InitErrorDetails] = []
        u = unit_vector(self.edge_u)
        v = unit_vector(self.edge_v)
        if u is None:
            errors.append(
                error_at(("edge_u",), "zero_vector", "edge_u must be a nonzero vector", self.edge_u)
            )
        if v is None:
            errors.append(
                error_at(("edge_v",), "zero_vector", "edge_v must be a nonzero vector", self.edge_v)
            )
        if u is not None and v is not None and _parallel(u, v):
            errors.append(
                error_at(("edge_v",), "parallel_edges", "edge_v must not be parallel to edge_u", self.edge_v)
            )
        raise_errors(type(self).__name__, errors)
        return self


class PointLight(PointLightFields):
    """Isotropic point light: irradiance I cos(theta) / d^2."""

    name: Name | None = None
    """Optional name, unique among the scene's lights; animation tracks refer to it."""


class DirectionalLight(DirectionalLightFields):
    """Light from infinitely far away, arriving along ``direction``."""

    name: Name | None = None
    """Optional name, unique among the scene's lights; animation tracks refer to it."""


class RectLight(RectLightFields):
    """Parallelogram area light with corners corner, corner + edge_u, corner + edge_v,
    corner + edge_u + edge_v; emits toward cross(edge_u, edge_v) (both sides if two_sided)."""

    name: Name | None = None
    """Optional name, unique among the scene's lights; animation tracks refer to it."""


Light = Annotated[PointLight | DirectionalLight | RectLight, Field(discriminator="type")]


# --------------------------------------------------------------------------- animation


class TransformKeyframe(FrozenModel):
    """An object's transform at ``time``; it replaces the object's own transform."""

    time: FiniteFloat
    """Time of the keyframe, in [animation.start, animation.end]."""
    transform: Transform
    """Local-to-world transform at that time."""


class LightKeyframe(FrozenModel):
    """A light's state at ``time``: new position and/or new emission."""

    time: FiniteFloat
    """Time of the keyframe, in [animation.start, animation.end]."""
    position: Vec3 | None = None
    """Point light: its position; rect light: its corner. Not allowed for directional lights."""
    intensity: RGB | None = None
    """Replaces the light's emission: intensity (point), irradiance (directional), radiance (rect)."""

    @model_validator(mode="after")
    def _not_empty(self) -> Self:
        if self.position is None and self.intensity is None:
            raise_errors(
                "LightKeyframe",
                [
                    error_at(
                        (), "empty_keyframe", "a light keyframe needs position or intensity (or both)", None
                    )
                ],
            )
        return self


class Animation(FrozenModel):
    """Keyframed motion over [start, end]; between keyframes values are interpolated,
    outside the first/last keyframe they are held."""

    start: FiniteFloat
    """Start time."""
    end: FiniteFloat
    """End time (> start)."""
    objects: dict[
        Name, Annotated[list[TransformKeyframe], Field(min_length=1, max_length=MAX_KEYFRAMES)]
    ] = {}
    """Tracks keyed by object name; keyframes strictly increasing in time."""
    lights: dict[Name, Annotated[list[LightKeyframe], Field(min_length=1, max_length=MAX_KEYFRAMES)]] = {}
    """Tracks keyed by light name; keyframes strictly increasing in time."""

    @model_validator(mode="after")
    def _check_times(self) -> Self:
        errors: list[InitErrorDetails] = []
        if not self.end > self.start:
            errors.append(
                error_at(
                    ("end",),
                    "empty_interval",
                    f"end ({_fmt(self.end)}) must be greater than start ({_fmt(self.start)})",
                    self.end,
                )
            )
        tracks: list[tuple[str, str, list[float]]] = [
            ("objects", k, [f.time for f in v]) for k, v in self.objects.items()
        ]
        tracks += [("lights", k, [f.time for f in v]) for k, v in self.lights.items()]
        for group, key, times in tracks:
            previous: float | None = None
            for i, time in enumerate(times):
                loc = (group, key, i, "time")
                if not self.start <= time <= self.end:
                    errors.append(
                        error_at(
                            loc,
                            "keyframe_time",
                            f"time {_fmt(time)} is outside [start, end] = "
                            f"[{_fmt(self.start)}, {_fmt(self.end)}]",
                            time,
                        )
                    )
                if previous is not None and not time > previous:
                    errors.append(
                        error_at(
                            loc,
                            "keyframe_order",
                            f"keyframe times must increase strictly: {_fmt(time)} follows {_fmt(previous)}",
                            time,
                        )
                    )
                previous = time
        raise_errors("Animation", errors)
        return self


# --------------------------------------------------------------------------- view space


def _span(points: list[tuple[float, ...]]) -> float:
    return max((abs(c) for p in points for c in p), default=0.0)


def _no_room(loc: Loc, message: str, value: Any) -> InitErrorDetails:
    return error_at(loc, "view_space_empty", "the view space has no room: " + message, value)


class PathViewSpace(FrozenModel):
    """The viewer moves along a polyline (within ``radius`` of it)."""

    type: Literal["path"] = "path"
    points: Annotated[list[Vec3], Field(min_length=2, max_length=MAX_VIEW_SPACE_POINTS)]
    """Polyline vertices, world space (eye positions); at least 2, total length > 0."""
    radius: NonNegativeFloat = 0.0
    """How far the eye may leave the polyline (0: exactly on it)."""

    @model_validator(mode="after")
    def _check_length(self) -> Self:
        pts = np.asarray(self.points, dtype=np.float64)
        scale = max(_span(list(self.points)), 1e-300)
        length = float(np.sum(np.linalg.norm(np.diff(pts / scale, axis=0), axis=1))) * scale
        if not length > _COINCIDENT_TOL * scale and not self.radius > _COINCIDENT_TOL * scale:
            raise_errors("PathViewSpace", [_no_room(("points",), "all path points coincide and radius is 0", None)])
        return self

    def distance(self, point: Vec3) -> float:
        """How far ``point`` lies outside the view space (0 inside)."""
        p = np.asarray(point, dtype=np.float64)
        pts = np.asarray(self.points, dtype=np.float64)
        a, b = pts[:-1], pts[1:]
        ab = b - a
        den = np.einsum("ij,ij->i", ab, ab)
        u = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.where(den > 0, den, 1.0), 0.0, 1.0)
        d = float(np.min(np.linalg.norm(p - (a + u[:, None] * ab), axis=1)))
        return max(0.0, d - self.radius)

    def bounds(self) -> tuple[Vec3, Vec3]:
        pts = np.asarray(self.points, dtype=np.float64)
        lo, hi = pts.min(axis=0) - self.radius, pts.max(axis=0) + self.radius
        return (float(lo[0]), float(lo[1]), float(lo[2])), (float(hi[0]), float(hi[1]), float(hi[2]))


class BoxViewSpace(FrozenModel):
    """The viewer moves inside an axis-aligned box (flat boxes, e.g. min.y == max.y at eye height, are fine)."""

    type: Literal["box"] = "box"
    min: Vec3
    """Lower corner, world space."""
    max: Vec3
    """Upper corner, world space; max >= min per axis and the box is not a single point."""

    @model_validator(mode="after")
    def _check_box(self) -> Self:
        errors: list[InitErrorDetails] = []
        bad = [f"{'xyz'[k]}: max {_fmt(self.max[k])} < min {_fmt(self.min[k])}" for k in range(3)
               if self.max[k] < self.min[k]]
        if bad:
            errors.append(error_at(("max",), "view_space_order", "max must be >= min on every axis (" +
                                   "; ".join(bad) + ")", self.max))
        else:
            scale = _span([self.min, self.max])
            if max(self.max[k] - self.min[k] for k in range(3)) <= _COINCIDENT_TOL * scale:
                errors.append(_no_room(("max",), "min and max are the same point", self.max))
        raise_errors("BoxViewSpace", errors)
        return self

    def distance(self, point: Vec3) -> float:
        """How far ``point`` lies outside the view space (0 inside)."""
        p = np.asarray(point, dtype=np.float64)
        return float(np.linalg.norm(p - np.clip(p, self.min, self.max)))

    def bounds(self) -> tuple[Vec3, Vec3]:
        return self.min, self.max


Vec2 = tuple[FiniteFloat, FiniteFloat]


def _segments_cross(a: Any, b: Any, c: Any, d: Any) -> bool:
    """Proper intersection of the open segments ab and cd (2D)."""

    def orient(p: Any, q: Any, r: Any) -> float:
        return float((q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]))

    o1, o2, o3, o4 = orient(a, b, c), orient(a, b, d), orient(c, d, a), orient(c, d, b)
    return (o1 > 0) != (o2 > 0) and (o3 > 0) != (o4 > 0) and 0 not in (o1, o2, o3, o4)


class PolygonViewSpace(FrozenModel):
    """The viewer moves inside a simple polygon in the horizontal plane y = ``eye_height``."""

    type: Literal["polygon"] = "polygon"
    vertices: Annotated[list[Vec2], Field(min_length=3, max_length=MAX_POLYGON_VERTICES)]
    """Polygon corners as [x, z] pairs, in order (either orientation); no self-intersections."""
    eye_height: FiniteFloat
    """y coordinate of the eye, world space."""

    @model_validator(mode="after")
    def _check_polygon(self) -> Self:
        v = np.asarray(self.vertices, dtype=np.float64)
        scale = max(_span(list(self.vertices)), 1e-300)
        w = v / scale
        area = 0.5 * abs(float(np.sum(w[:, 0] * np.roll(w[:, 1], -1) - np.roll(w[:, 0], -1) * w[:, 1])))
        errors: list[InitErrorDetails] = []
        if not area > 1e-12:
            errors.append(_no_room(("vertices",), "the polygon has zero area", None))
        else:
            n = len(w)
            for i in range(n):
                for j in range(i + 2, n):
                    if i == 0 and j == n - 1:
                        continue  # adjacent through the closing edge
                    if _segments_cross(w[i], w[(i + 1) % n], w[j], w[(j + 1) % n]):
                        errors.append(error_at(("vertices",), "self_intersection",
                                               f"the polygon intersects itself (edge {i}-{(i + 1) % n} crosses "
                                               f"edge {j}-{(j + 1) % n})", None))
                        break
                if errors:
                    break
        raise_errors("PolygonViewSpace", errors)
        return self

    def distance(self, point: Vec3) -> float:
        """How far ``point`` lies outside the view space (the polygon at eye height; 0 inside)."""
        x, y, z = (float(c) for c in point)
        v = np.asarray(self.vertices, dtype=np.float64)
        w = np.roll(v, -1, axis=0)
        inside = False
        for (x0, z0), (x1, z1) in zip(v, w, strict=True):
            if (z0 > z) != (z1 > z) and x < x0 + (z - z0) * (x1 - x0) / (z1 - z0):
                inside = not inside
        dy = y - self.eye_height
        if inside:
            return abs(dy)
        q = np.array([x, z])
        ab = w - v
        den = np.einsum("ij,ij->i", ab, ab)
        u = np.clip(np.einsum("ij,ij->i", q - v, ab) / np.where(den > 0, den, 1.0), 0.0, 1.0)
        dxz = float(np.min(np.linalg.norm(q - (v + u[:, None] * ab), axis=1)))
        return math.hypot(dxz, dy)

    def bounds(self) -> tuple[Vec3, Vec3]:
        v = np.asarray(self.vertices, dtype=np.float64)
        lo, hi = v.min(axis=0), v.max(axis=0)
        return (float(lo[0]), self.eye_height, float(lo[1])), (float(hi[0]), self.eye_height, float(hi[1]))


ViewSpace = Annotated[PathViewSpace | BoxViewSpace | PolygonViewSpace, Field(discriminator="type")]


# --------------------------------------------------------------------------- scene


class Scene(FrozenModel):
    """A complete scene: camera, materials, objects, lights and optional animation.

    An empty scene (no objects, no lights) is valid and renders the background.
    """

    schema_version: Literal[1] = 1
    """Format version; bumped on incompatible changes."""
    name: Annotated[str, StringConstraints(min_length=1, max_length=128)] = "untitled"
    """Human-readable name."""
    camera: Camera
    """The view to render."""
    materials: Annotated[list[Material], Field(max_length=MAX_MATERIALS)] = []
    """Materials, unique by name."""
    objects: Annotated[list[SceneObject], Field(max_length=MAX_OBJECTS)] = []
    """Shapes; each names its material."""
    lights: Annotated[list[Light], Field(max_length=MAX_LIGHTS)] = []
    """Light sources: the only things that illuminate (emissive materials are only seen)."""
    ambient: RGB = (0.0, 0.0, 0.0)
    """Ambient radiance; adds kd * ambient at every visible surface."""
    background: RGB = (0.0, 0.0, 0.0)
    """Radiance of rays that leave the scene."""
    animation: Animation | None = None
    """Optional keyframed animation of named objects and lights."""
    view_space: ViewSpace | None = None
    """Optional region the viewer of a walkthrough may move in (docs/walkthrough.md)."""

    @field_validator("schema_version", mode="before")
    @classmethod
    def _integer_version(cls, value: Any) -> Any:
        # Literal[1] alone would take JSON true and 1.0 (both == 1).
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise PydanticCustomError("schema_version", "schema_version must be the integer 1")
        return int(value)

    @model_validator(mode="after")
    def _check_references(self) -> Self:
        errors: list[InitErrorDetails] = []
        errors += _duplicates("materials", [m.name for m in self.materials], "material")
        errors += _duplicates("objects", [o.name for o in self.objects], "object")
        errors += _duplicates("lights", [light.name for light in self.lights], "light")
        known = {m.name for m in self.materials}
        for i, obj in enumerate(self.objects):
            if obj.material not in known:
                errors.append(
                    error_at(
                        ("objects", i, "material"),
                        "unknown_material",
                        f"unknown material {obj.material!r}; "
                        f"defined: {_listing(m.name for m in self.materials)}",
                        obj.material,
                    )
                )
        if self.animation is not None:
            object_names = {o.name for o in self.objects if o.name is not None}
            for key in self.animation.objects:
                if key not in object_names:
                    errors.append(
                        error_at(
                            ("animation", "objects", key),
                            "unknown_object",
                            f"no object named {key!r}; named objects: {_listing(sorted(object_names))}",
                            key,
                        )
                    )
            lights_by_name: dict[str, Light] = {}
            for light in self.lights:  # first definition wins, as in the duplicate check
                if light.name is not None:
                    lights_by_name.setdefault(light.name, light)
            for key, frames in self.animation.lights.items():
                target = lights_by_name.get(key)
                if target is None:
                    errors.append(
                        error_at(
                            ("animation", "lights", key),
                            "unknown_light",
                            f"no light named {key!r}; named lights: {_listing(sorted(lights_by_name))}",
                            key,
                        )
                    )
                elif isinstance(target, DirectionalLight):
                    for i, frame in enumerate(frames):
                        if frame.position is not None:
                            errors.append(
                                error_at(
                                    ("animation", "lights", key, i, "position"),
                                    "directional_position",
                                    f"{key!r} is a directional light: it has no position to animate",
                                    frame.position,
                                )
                            )
        raise_errors("Scene", errors)
        return self

    def material_index(self) -> dict[str, int]:
        """Material name -> index in ``materials`` (the material id used by renderers)."""
        return {m.name: i for i, m in enumerate(self.materials)}


def _listing(names: Any, limit: int = 10) -> str:
    names = list(names)
    if not names:
        return "none"
    shown = ", ".join(repr(n) for n in names[:limit])
    return shown + (f", ... ({len(names)} in all)" if len(names) > limit else "")


def _duplicates(field: str, names: list[str | None], what: str) -> list[InitErrorDetails]:
    first: dict[str, int] = {}
    errors: list[InitErrorDetails] = []
    for i, name in enumerate(names):
        if name is None:
            continue
        if name in first:
            errors.append(
                error_at(
                    (field, i, "name"),
                    "duplicate_name",
                    f"duplicate {what} name {name!r} (first used by {field}.{first[name]})",
                    name,
                )
            )
        else:
            first[name] = i
    return errors


# --------------------------------------------------------------------------- helpers


class SceneFileTooLargeError(ValueError):
    """A scene document exceeds MAX_SCENE_BYTES."""


_BOM = b"\xef\xbb\xbf"


def load_scene_json(data: str | bytes | bytearray) -> Scene:
    """Parse and validate a scene document (UTF-8 JSON).

    Raises pydantic.ValidationError for invalid JSON or an invalid scene, and
    SceneFileTooLargeError beyond MAX_SCENE_BYTES.
    """
    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else bytes(data)
    if len(raw) > MAX_SCENE_BYTES:
        raise SceneFileTooLargeError(f"scene document is {len(raw)} bytes, the limit is {MAX_SCENE_BYTES}")
    if raw.startswith(_BOM):  # editors on Windows add one; JSON parsers need not accept it
        raw = raw[len(_BOM) :]
    return Scene.model_validate_json(raw)


def load_scene_file(path: str | os.PathLike[str]) -> Scene:
    """Read and validate a scene file (UTF-8 JSON, at most MAX_SCENE_BYTES)."""
    with open(path, "rb") as f:
        # Read one byte past the cap instead of trusting stat(): pipes and growing files.
        raw = f.read(MAX_SCENE_BYTES + 1)
    if len(raw) > MAX_SCENE_BYTES:
        raise SceneFileTooLargeError(f"scene file {os.fspath(path)!r} exceeds {MAX_SCENE_BYTES} bytes")
    return load_scene_json(raw)


def scene_json_schema() -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of a scene document."""
    return Scene.model_json_schema()


_ADDITIVE_FIELDS = ("view_space",)


def canonical_scene_json(scene: Scene) -> str:
    """Compact JSON with sorted keys and every field (defaults included).

    Equal scenes give equal text whatever the key order or omitted defaults of the
    document they were parsed from.
    """
    doc = scene.model_dump(mode="json")
    # Fields added after version 1 shipped are left out while unset, so the hash of every
    # scene written before them stays what it was.
    for key in _ADDITIVE_FIELDS:
        if doc.get(key) is None:
            doc.pop(key, None)
    return json.dumps(
        doc,
        sort_keys=True,
        separators=(",", ":"),
        ensure_ascii=True,
        allow_nan=False,
    )


def scene_hash(scene: Scene) -> str:
    """SHA-256 (hex) of :func:`canonical_scene_json`; a cache key for bakes and renders."""
    return hashlib.sha256(canonical_scene_json(scene).encode("ascii")).hexdigest()
