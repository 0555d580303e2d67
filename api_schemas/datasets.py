"""Illumination datasets and relighting: request / response models of the HTTP API.

An illumination dataset (docs/relighting.md) is K images of one fixed view, image k
lit only by light k, plus the camera and the surface geometry registered to the pixels. The
*manifest* (:class:`DatasetManifest`) describes it; the image, depth and mask files travel as
separate uploads and are referenced by name (and sha256). A dataset id is the sha256 of the
canonical manifest with every file's sha256 filled in, so equal content gets the same id.

Conventions:

- ``images[k].position``: world position of point light k (a light stage), or
  ``images[k].direction``: direction *toward* distant light k (a photometric-stereo rig such as
  DiLiGenT). One kind per dataset.
- ``images[k].intensity``: W/sr for point lights, irradiance for distant lights; three numbers
  > 0 (or one, for grey).
- ``transfer``: how 8- and 16-bit files are linearised (``srgb``, ``linear``, ``gamma:<g>``);
  float files (EXR, HDR, float TIFF) are linear whatever it says.
- ``geometry``: a depth map file (``depth_kind`` "z" along the optical axis or "distance"
  along the pixel's ray), or a stored scene that the worker ray-casts from the camera.
- ``mask``: optional image, object where its first channel > 0.5.

Models are strict (unknown fields are errors, numbers are numbers) like every schema here.
"""

from __future__ import annotations

import re
from datetime import datetime
from typing import Annotated, Any, Literal, Self

from pydantic import BeforeValidator, Field, StringConstraints, field_validator, model_validator
from pydantic_core import InitErrorDetails, PydanticCustomError

from api_schemas.common import (
    RGB,
    FiniteFloat,
    FrozenModel,
    NonNegativeFloat,
    PositiveFloat,
    StrictBool,
    Vec3,
    error_at,
    numpy_scalar,
    raise_errors,
    unit_vector,
)
from api_schemas.scene import (
    DirectionalLightFields,
    OrthographicCamera,
    PerspectiveCamera,
    PointLightFields,
    RectLightFields,
    Resolution,
)
from api_schemas.service import ArtifactManifest, JobPublic, ReferenceRenderParams, Sha256

__all__ = [
    "MAX_DATASET_IMAGES",
    "MAX_DATASET_SAMPLES",
    "MAX_EXPANDED_LIGHTS",
    "DatasetBakeParams",
    "BakeRequest",
    "CompositeRequest",
    "DatasetBakePublic",
    "DatasetCamera",
    "DatasetFileInfo",
    "DatasetImage",
    "DatasetList",
    "DatasetManifest",
    "DatasetPublic",
    "DatasetUploadStatus",
    "DepthGeometry",
    "FileName",
    "FileUploadPublic",
    "GenerateRequest",
    "GenerationPublic",
    "LightPlacement",
    "MaskRef",
    "MissingFile",
    "PinholeCamera",
    "RelightDirectionalLight",
    "RelightEnvironmentLight",
    "RelightLight",
    "RelightPointLight",
    "RelightPublic",
    "RelightRectLight",
    "RelightRequest",
    "SceneGeometry",
    "parse_transfer",
]

MAX_DATASET_IMAGES = 4096
"""Most images in one dataset (the bake keeps every light's values of every pixel)."""

MAX_DATASET_SAMPLES = 1 << 30
"""Most samples (images x width x height x 3) in one dataset: the bake holds the whole stack in
memory as float32 (4 GiB at this limit)."""

FileName = Annotated[str, StringConstraints(min_length=1, max_length=255, pattern=r"^[^\x00-\x1f\x7f]+$")]
"""Name of an uploaded file (the multipart part name): metadata only, never a path. Files are
stored under their sha256."""

_TRANSFER = re.compile(r"^(srgb|linear|gamma:([0-9]+(\.[0-9]+)?))$")
Transfer = Annotated[str, StringConstraints(max_length=32)]


def parse_transfer(value: str) -> tuple[str, float]:
    """``"srgb" -> ("srgb", 0)``, ``"linear" -> ("linear", 1)``, ``"gamma:2.2" -> ("gamma", 2.2)``."""
    m = _TRANSFER.match(value)
    if m is None:
        raise ValueError(f"transfer must be 'srgb', 'linear' or 'gamma:<g>' (e.g. gamma:2.2), got {value!r}")
    if m.group(2) is not None:
        return "gamma", float(m.group(2))
    return m.group(1), 1.0 if m.group(1) == "linear" else 0.0


def _intensity(value: Any) -> Any:
    # one number = grey; kept as a 3-tuple so the canonical manifest (and the id) has one form
    if isinstance(value, bool):
        return value  # rejected by the strict float below
    if isinstance(value, int | float):
        return (value, value, value)
    return value


PositiveRGB = tuple[PositiveFloat, PositiveFloat, PositiveFloat]


# ------------------------------------------------------------------------------ cameras


class PinholeCamera(FrozenModel):
    """A calibrated pinhole camera (OpenCV frame: x right, y down, z forward): intrinsics
    ``fx, fy, cx, cy`` in pixels (pixel centres at integer + 0.5) and an optional pose."""

    type: Literal["pinhole"] = "pinhole"
    fx: PositiveFloat
    """Focal length in pixels along x."""
    fy: PositiveFloat
    """Focal length in pixels along y."""
    cx: FiniteFloat
    """Principal point x in pixels."""
    cy: FiniteFloat
    """Principal point y in pixels."""
    width: Resolution
    """Image width in pixels."""
    height: Resolution
    """Image height in pixels."""
    world_from_camera: tuple[tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat], ...] | None = None
    """4x4 row-major pose (camera -> world, the lights' frame); None = the camera frame is the world."""

    @field_validator("world_from_camera")
    @classmethod
    def _four_rows(cls, value: Any) -> Any:
        if value is not None and len(value) != 4:
            raise PydanticCustomError("matrix_shape", "world_from_camera must have 4 rows of 4 numbers")
        return value


DatasetCamera = Annotated[PerspectiveCamera | OrthographicCamera | PinholeCamera, Field(discriminator="type")]
"""The camera that took the images: the scene format's perspective / orthographic camera, or a
calibrated pinhole camera."""


# ------------------------------------------------------------------------------ manifest


class DatasetImage(FrozenModel):
    """One image of the dataset and the light it was taken under."""

    file: FileName
    """The image's file name (its multipart part name, or the name listed for a separate upload)."""
    sha256: Sha256 | None = None
    """sha256 of the file; required when the files are uploaded separately, checked when given."""
    position: Vec3 | None = None
    """World position of the (point) light; exactly one of position / direction."""
    direction: Vec3 | None = None
    """Direction TOWARD a distant light (need not be unit); exactly one of position / direction."""
    intensity: Annotated[PositiveRGB, BeforeValidator(_intensity)]
    """W/sr (point) or irradiance (distant), per channel, > 0; a single number means grey."""

    @model_validator(mode="after")
    def _one_light(self) -> Self:
        errors: list[InitErrorDetails] = []
        if (self.position is None) == (self.direction is None):
            errors.append(error_at(("position",), "light_kind",
                                   "give exactly one of position (point light) or direction (distant light)",
                                   None))
        if self.direction is not None and unit_vector(self.direction) is None:
            errors.append(error_at(("direction",), "zero_vector", "direction must be a nonzero vector",
                                   self.direction))
        raise_errors("DatasetImage", errors)
        return self


class DepthGeometry(FrozenModel):
    """Surface geometry as a depth map file (float EXR / TIFF / HDR, same size as the images)."""

    type: Literal["depth"] = "depth"
    file: FileName
    sha256: Sha256 | None = None
    depth_kind: Literal["z", "distance"] = "z"
    """``z``: distance along the optical axis; ``distance``: along the pixel's ray. NaN, Inf and
    values <= 0 mark pixels without a surface."""


class SceneGeometry(FrozenModel):
    """Surface geometry from a stored scene: the worker ray-casts it from the dataset camera
    (which must then be a perspective or orthographic camera of the scene format)."""

    type: Literal["scene"] = "scene"
    scene_id: Sha256


Geometry = Annotated[DepthGeometry | SceneGeometry, Field(discriminator="type")]


class MaskRef(FrozenModel):
    """Object mask image (same size): object where the first channel > 0.5."""

    file: FileName
    sha256: Sha256 | None = None


class DatasetManifest(FrozenModel):
    """Everything about a dataset except the pixels (body of ``POST /v1/datasets`` or the
    ``manifest`` part of a multipart upload)."""

    name: Annotated[str, StringConstraints(min_length=1, max_length=128, pattern=r"^[^\x00-\x1f\x7f]+$")] = "untitled"
    images: Annotated[list[DatasetImage], Field(min_length=3, max_length=MAX_DATASET_IMAGES)]
    """The K >= 3 images, each with its light."""
    transfer: Transfer = "srgb"
    """Transfer function of 8/16-bit files: ``srgb``, ``linear`` or ``gamma:<g>`` (0.1 <= g <= 10)."""
    camera: DatasetCamera
    geometry: Geometry
    mask: MaskRef | None = None
    sphere_center: Vec3 | None = None
    """Centre of the sphere the point lights were placed on (the bake's default; None = the
    centroid of the surface points). Ignored for distant lights."""

    @field_validator("transfer")
    @classmethod
    def _transfer(cls, value: str) -> str:
        try:
            kind, g = parse_transfer(value)
        except ValueError as exc:
            raise PydanticCustomError("transfer", str(exc)) from None
        if kind == "gamma" and not (0.1 <= g <= 10.0):
            raise PydanticCustomError("transfer", f"gamma must be in [0.1, 10], got {g}")
        return value

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        errors: list[InitErrorDetails] = []
        distant = self.images[0].direction is not None
        seen_files: dict[str, int] = {}
        seen_lights: dict[tuple[float, ...], int] = {}
        for i, img in enumerate(self.images):
            if (img.direction is not None) != distant:
                errors.append(error_at(("images", i, "position" if distant else "direction"), "mixed_light_kinds",
                                       "all images must use the same light kind: images.0 has a "
                                       f"{'direction (distant light)' if distant else 'position (point light)'}",
                                       None))
            if img.file in seen_files:
                errors.append(error_at(("images", i, "file"), "duplicate_file",
                                       f"file {img.file!r} is already images.{seen_files[img.file]}'s image", img.file))
            seen_files.setdefault(img.file, i)
            v = img.direction if img.direction is not None else img.position
            assert v is not None
            key: tuple[Any, ...] = ("position", *v)
            if img.direction is not None:
                u = unit_vector(v)
                assert u is not None
                key = ("direction", *(round(c, 15) for c in u))
            if key in seen_lights:
                errors.append(error_at(("images", i, "direction" if img.direction is not None else "position"),
                                       "duplicate_light",
                                       f"light duplicates the light of images.{seen_lights[key]}", list(v)))
            seen_lights.setdefault(key, i)
        samples = len(self.images) * self.camera.width * self.camera.height * 3
        if samples > MAX_DATASET_SAMPLES:
            errors.append(error_at(("images",), "dataset_too_large",
                                   f"{len(self.images)} images of {self.camera.width}x{self.camera.height} are "
                                   f"{samples} samples, more than the limit of {MAX_DATASET_SAMPLES}; use fewer "
                                   "images or a lower resolution", None))
        if isinstance(self.geometry, SceneGeometry) and isinstance(self.camera, PinholeCamera):
            errors.append(error_at(("camera", "type"), "camera_kind",
                                   "geometry from a scene needs a perspective or orthographic camera", "pinhole"))
        names = set(seen_files)
        for where, ref in (("geometry", self.geometry), ("mask", self.mask)):
            fname = getattr(ref, "file", None)
            if fname is not None and fname in names:
                errors.append(error_at((where, "file"), "duplicate_file",
                                       f"file {fname!r} is also an image of the dataset", fname))
        raise_errors("DatasetManifest", errors)
        return self

    @property
    def distant(self) -> bool:
        return self.images[0].direction is not None

    def file_refs(self) -> list[tuple[str, str, str | None, str]]:
        """``(field path, file name, sha256 or None, role)`` of every file, in manifest order."""
        out = [(f"images.{i}", img.file, img.sha256, "image") for i, img in enumerate(self.images)]
        if isinstance(self.geometry, DepthGeometry):
            out.append(("geometry", self.geometry.file, self.geometry.sha256, "depth"))
        if self.mask is not None:
            out.append(("mask", self.mask.file, self.mask.sha256, "mask"))
        return out


# ------------------------------------------------------------------------------ stored datasets


class FileUploadPublic(FrozenModel):
    """A stored, validated file (answer of ``PUT /v1/datasets/uploads/{sha256}``)."""

    sha256: Sha256
    size: int
    width: int
    height: int
    channels: int
    format: str
    """OpenImageIO format name: ``openexr``, ``png``, ``tiff``, ``hdr``, ``jpeg``."""
    pixel_type: str
    """``uint8``, ``uint16``, ``half``, ``float``."""


class DatasetFileInfo(FrozenModel):
    field: str
    """Where the manifest names the file (``images.3``, ``geometry``, ``mask``)."""
    name: str
    sha256: Sha256
    size: int
    width: int
    height: int
    pixel_type: str


class DatasetPublic(FrozenModel):
    """A stored (committed) dataset."""

    id: Sha256
    name: str
    created_at: datetime
    n_images: int
    width: int
    height: int
    distant: bool
    transfer: str
    geometry: Literal["depth", "scene"]
    has_mask: bool
    total_bytes: int
    manifest: DatasetManifest
    """The canonical manifest (every file's sha256 filled in): download the files by these."""
    source: dict[str, Any] = {}
    """How the dataset was made: ``{"kind": "upload"}`` or ``{"kind": "generated", "scene_id", ...}``."""
    links: dict[str, str] = {}


class DatasetList(FrozenModel):
    items: list[DatasetPublic]
    next_cursor: str | None = None
    """Pass as ``cursor`` for the next page; null on the last page."""


class MissingFile(FrozenModel):
    field: str
    name: str
    sha256: Sha256
    upload_url: str
    """``PUT`` the file's bytes here."""


class DatasetUploadStatus(FrozenModel):
    """Answer to a manifest sent on its own: which files the server still needs."""

    dataset_id: Sha256
    state: Literal["pending", "committed"]
    missing: list[MissingFile]
    """Files not received yet (a file received once is never asked for again)."""
    received: int
    """Distinct files already stored."""
    links: dict[str, str] = {}


# ------------------------------------------------------------------------------ bake


class DatasetBakeParams(FrozenModel):
    """How a dataset is baked for relighting (``engine.relighting.bake.bake_dataset``)."""

    layout: Literal["pixel_major", "tiled"] = "pixel_major"
    half: StrictBool = True
    """Store float16 where every value keeps float16's precision (else float32)."""
    dedupe_tol_deg: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=10)] = 1e-3
    max_face_radius_deg: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=89)] | None = None
    """Coverage rule: triangles with a larger circumradius are outside coverage; None = automatic."""
    half_rel_floor: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, lt=1)] = 0.0
    compress: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, lt=1)] | None = None
    """Requested relative RMS error of a low-rank compressed store (used only when it meets this
    error and is smaller; the measured error is in the bake's report); None = no compression."""


class BakeRequest(FrozenModel):
    """Body of ``POST /v1/datasets/{id}/bake`` (may be empty: ``{}``)."""

    params: DatasetBakeParams = DatasetBakeParams()


class DatasetBakePublic(FrozenModel):
    dataset_id: Sha256
    artifact_key: Sha256
    status: Literal["cached", "queued", "running", "finished", "failed"]
    job: JobPublic | None = None
    artifact: ArtifactManifest | None = None
    links: dict[str, str] = {}


# ------------------------------------------------------------------------------ generation


class LightPlacement(FrozenModel):
    """Where the generated dataset's point lights go (``engine.relighting.generate.LightPlacement``)."""

    region: Literal["sphere", "hemisphere", "upper_front_quarter"] = "upper_front_quarter"
    """``hemisphere``: elevation >= 0 about ``up``; ``upper_front_quarter`` (the paper's): that half,
    azimuth within +-90 deg of ``front``."""
    layout: Literal["grid", "geodesic"] = "grid"
    """``grid``: rings of constant elevation every ``spacing_deg``; ``geodesic``: a subdivided
    icosahedron (near-uniform)."""
    spacing_deg: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0.5, le=90)] = 10.0
    """Neighbour spacing in degrees."""
    center: Vec3 | None = None
    """Sphere centre; None = the centroid of the visible surface points."""
    radius: PositiveFloat | None = None
    """Sphere radius; None = 1.5 x the distance of the farthest visible surface point."""
    intensity: Annotated[PositiveRGB, BeforeValidator(_intensity)] | None = None
    """W/sr of every light; None = radius^2 (irradiance 1 at the centre)."""
    up: Vec3 = (0.0, 1.0, 0.0)
    """The zenith."""
    front: Vec3 | None = None
    """Azimuth 0 of the placement; None = toward the camera."""

    @model_validator(mode="after")
    def _frame(self) -> Self:
        errors: list[InitErrorDetails] = []
        up = unit_vector(self.up)
        if up is None:
            errors.append(error_at(("up",), "zero_vector", "up must be a nonzero vector", self.up))
        if self.front is not None:
            f = unit_vector(self.front)
            if f is None:
                errors.append(error_at(("front",), "zero_vector", "front must be a nonzero vector", self.front))
            elif up is not None and abs(sum(a * b for a, b in zip(f, up, strict=True))) > 1 - 1e-9:
                errors.append(error_at(("front",), "parallel", "front must not be parallel to up", self.front))
        raise_errors("LightPlacement", errors)
        return self


class GenerateRequest(FrozenModel):
    """Body of ``POST /v1/datasets/generate``: render a stored scene under point lights."""

    scene_id: Sha256
    camera: PerspectiveCamera | OrthographicCamera | None = None
    """Overrides the scene's camera."""
    placement: LightPlacement = LightPlacement()
    params: ReferenceRenderParams = ReferenceRenderParams()
    max_lights: Annotated[int, Field(strict=True, ge=3, le=MAX_DATASET_IMAGES), BeforeValidator(numpy_scalar)] = 512
    """Refuse placements with more lights than this (rendering cost grows with the count)."""
    ground_truth: Annotated[list[RelightLight], Field(max_length=64)] = []
    """For testing: also render the scene under each of these lights alone (the same replacements
    as for the dataset images), to compare relit images with; served at ``links["ground_truth.<i>"]``."""


class GenerationPublic(FrozenModel):
    artifact_key: Sha256
    """Key of the generation job's record; the dataset id is in ``dataset_id`` once finished."""
    status: Literal["cached", "queued", "running", "finished", "failed"]
    dataset_id: Sha256 | None = None
    job: JobPublic | None = None
    artifact: ArtifactManifest | None = None
    """The generation record: ``result`` (dataset id, counts, timings) and the ground-truth blobs."""
    links: dict[str, str] = {}


# ------------------------------------------------------------------------------ relight


class RelightPointLight(PointLightFields):
    """Isotropic point light (near or far, inside or outside the light sphere); the scene's point light
    without a name, intensity 1 by default."""

    intensity: RGB = (1.0, 1.0, 1.0)
    """W/sr per channel."""


class RelightDirectionalLight(DirectionalLightFields):
    """The scene's directional light without a name, irradiance 1 by default."""

    irradiance: RGB = (1.0, 1.0, 1.0)


class RelightRectLight(RectLightFields):
    """Rectangular area light ``corner + a edge_u + b edge_v``, sampled with ``samples`` points: the scene's
    rect light without a name, radiance 1 by default."""

    radiance: RGB = (1.0, 1.0, 1.0)
    samples: Annotated[int, Field(strict=True, ge=1, le=4096), BeforeValidator(numpy_scalar)] = 16
    seed: Annotated[int, Field(strict=True, ge=0, le=2**31 - 1), BeforeValidator(numpy_scalar)] = 0


class RelightEnvironmentLight(FrozenModel):
    """Equirectangular environment map (uploaded with ``PUT /v1/datasets/uploads/{sha256}``; row 0 =
    +y zenith), turned into ``n_lights`` directional lights."""

    type: Literal["environment"] = "environment"
    image_sha256: Sha256
    n_lights: Annotated[int, Field(strict=True, ge=1, le=4096), BeforeValidator(numpy_scalar)] = 64
    method: Literal["downsample", "importance"] = "downsample"
    seed: Annotated[int, Field(strict=True, ge=0, le=2**31 - 1), BeforeValidator(numpy_scalar)] = 0
    scale: NonNegativeFloat = 1.0
    transfer: Transfer = "linear"
    """Transfer function if the map is an 8/16-bit file (float files are linear)."""

    @field_validator("transfer")
    @classmethod
    def _transfer(cls, value: str) -> str:
        try:
            parse_transfer(value)
        except ValueError as exc:
            raise PydanticCustomError("transfer", str(exc)) from None
        return value


RelightLight = Annotated[
    RelightPointLight | RelightDirectionalLight | RelightRectLight | RelightEnvironmentLight,
    Field(discriminator="type"),
]


class RelightRequest(FrozenModel):
    """Body of ``POST /v1/relights``: a baked dataset under new lights (superposed)."""

    dataset_id: Sha256
    lights: Annotated[list[RelightLight], Field(min_length=1, max_length=256)]
    bake: DatasetBakeParams = DatasetBakeParams()
    """Which bake of the dataset to use (it must exist: ``POST /v1/datasets/{id}/bake``)."""
    min_light_distance: NonNegativeFloat | None = None
    """A point light nearer than this to a surface point contributes 0 there (singular); None = auto."""
    exposure_stops: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=-30, le=30)] = 0.0
    """Exposure of the PNG preview (the EXR is always linear, unscaled)."""

    @model_validator(mode="after")
    def _budget(self) -> Self:
        raise_errors("RelightRequest", _light_budget_errors(self.lights))
        return self


MAX_EXPANDED_LIGHTS = 16384
"""Most point / directional lights one request may expand to (rect samples + environment lights)."""


def _expanded(light: Any) -> int:
    if isinstance(light, RelightRectLight):
        return light.samples
    if isinstance(light, RelightEnvironmentLight):
        return light.n_lights
    return 1


def _light_budget_errors(lights: list[Any]) -> list[InitErrorDetails]:
    total = sum(_expanded(light) for light in lights)
    if total <= MAX_EXPANDED_LIGHTS:
        return []
    return [error_at(("lights",), "too_many_lights", f"the lights expand to {total} point / directional lights "
                     f"(rect samples + environment n_lights), more than the limit of {MAX_EXPANDED_LIGHTS}", None)]


class RelightPublic(FrozenModel):
    artifact_key: Sha256
    status: Literal["cached", "queued", "running", "finished", "failed"]
    job: JobPublic | None = None
    artifact: ArtifactManifest | None = None
    links: dict[str, str] = {}


class CompositeRequest(FrozenModel):
    """Body of ``POST /v1/composites`` (paper section 3.3): the object dataset and a background
    dataset (same lights and view, object removed), relit under ``lights``; object pixels from the
    relit object, active-region pixels of the plate scaled by ``I_object / I_background``."""

    object_dataset_id: Sha256
    background_dataset_id: Sha256
    plate_sha256: Sha256
    """The background plate image (uploaded with ``PUT /v1/datasets/uploads/{sha256}``)."""
    plate_transfer: Transfer = "srgb"
    """Transfer function of the plate if it is an 8/16-bit file (float files are linear)."""
    object_mask_sha256: Sha256
    """Object mask image (object where its first channel > 0.5): these pixels come from the relit object."""
    active_region_sha256: Sha256 | None = None
    """Active region mask image (where the object's shadows / interreflections change the plate);
    None = the object mask dilated by ``active_margin_px``."""
    active_margin_px: Annotated[int, Field(strict=True, ge=0, le=4096), BeforeValidator(numpy_scalar)] = 16
    lights: Annotated[list[RelightLight], Field(min_length=1, max_length=256)]
    bake: DatasetBakeParams = DatasetBakeParams()
    eps: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=1)] = 1e-3
    """Near-black guard: both relit images are lifted by eps x the background's mean over the active
    region before the ratio ``I_object / I_background`` is taken."""
    max_ratio: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=1, le=1e6)] = 8.0
    """Clamp of the ratio where the object lights an (almost) black background."""

    @model_validator(mode="after")
    def _budget(self) -> Self:
        raise_errors("CompositeRequest", _light_budget_errors(self.lights))
        return self
    exposure_stops: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=-30, le=30)] = 0.0

    @field_validator("plate_transfer")
    @classmethod
    def _transfer(cls, value: str) -> str:
        try:
            parse_transfer(value)
        except ValueError as exc:
            raise PydanticCustomError("transfer", str(exc)) from None
        return value


GenerateRequest.model_rebuild()
