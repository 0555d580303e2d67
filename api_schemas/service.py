"""Request / response models of the HTTP API, shared by the service and the workers.

Resources: scenes (content-addressed), jobs (RQ), renders (a render request creates or
reuses a job whose result is an artifact), artifacts (content-addressed blobs + a
manifest), batches (many requests in one call). Errors are RFC 9457 problem details.

Workers validate job payloads with these same models before doing any work. The render methods
and the reference renderer's parameters come from the registry ``engine.methods`` (pure Python:
the API process imports it, and no numba).
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    Field,
    StringConstraints,
    ValidationInfo,
    WithJsonSchema,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from api_schemas.common import FiniteFloat, FrozenModel, error_at, raise_errors
from api_schemas.scene import Camera, Scene
from engine.errors import InvalidInputError
from engine.methods import (
    GLOSSY_FILTER,
    GLOSSY_RAYS,
    IBRT_GENERATIONS,
    METHODS,
    REFERENCE,
    SUPERSAMPLE,
    Param,
    allowed_forms,
    method_pattern,
    parse_method,
)
from engine.methods import method_needs_bake as method_needs_bake  # for the routes and job dispatch

Sha256 = Annotated[str, StringConstraints(pattern=r"^[0-9a-f]{64}$")]
"""Lower-case hex sha256: scene ids, blob checksums and artifact keys."""

JobId = Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9_-]{1,128}$")]

MAX_IBRT_GENERATIONS = IBRT_GENERATIONS.high
METHOD_PATTERN = method_pattern()
"""``^(reference|ldc|ldc\\+llf|ldc\\+ibrt:[0-8])$``, from the registry (``engine.methods``)."""


def _check_method(value: str) -> str:
    try:
        parse_method(value)
    except InvalidInputError:
        raise PydanticCustomError(
            "render_method", "method must be " + allowed_forms() + ", got '{value}'",
            {"max_k": MAX_IBRT_GENERATIONS, "value": value[:40]},
        ) from None
    return value


RenderMethod = Annotated[
    str,
    AfterValidator(_check_method),
    WithJsonSchema({"type": "string", "pattern": METHOD_PATTERN,
                    "description": " | ".join(m.form for m in METHODS) + "".join(
                        f" ({m.arg.name} = {m.arg.range_text} reflection generations)"
                        for m in METHODS if m.arg is not None)}),
]
"""A render method of the registry ``engine.methods`` (its module docstring has the table):
``reference`` (the ray tracer), or a method that renders from the scene's bake: ``ldc`` (warp of
the layered depth cube only), ``ldc+llf`` (plus highlights and light-field gather), ``ldc+ibrt:k``
(plus k generations of image-based ray tracing through the LDC ending in a gather, k = 0..8).
Validated through the registry, kept as sent (the string is part of the artifact key)."""

JobState = Literal["queued", "started", "finished", "failed", "canceled"]


# ------------------------------------------------------------------------------ scenes


class SceneCreate(FrozenModel):
    """Body of ``POST /v1/scenes`` (JSON). Mesh files go in a multipart request instead:
    part ``scene`` (this JSON) and one file part per ``mesh_file`` path, named by that path."""

    scene: Scene


class MeshBlob(FrozenModel):
    path: str
    """The ``mesh_file`` path used in the scene (metadata only)."""
    sha256: Sha256
    size: int


class ScenePublic(FrozenModel):
    """A stored scene. ``id`` hashes the canonical scene JSON together with its mesh blobs,
    so equal content always gets the same id."""

    id: Sha256
    name: str
    created_at: datetime
    n_objects: int
    n_lights: int
    meshes: list[MeshBlob] = []
    links: dict[str, str] = {}


class ImportWarning(FrozenModel):
    """A feature of an imported file that was left out or approximated (docs/scene-import.md)."""

    feature: str
    """What: ``textures``, ``spot_as_point``, ``animations``, ``cameras_beyond_first``, ..."""
    message: str
    """What the import did with it."""
    count: int
    """How many places of the file have it."""
    where: list[str]
    """The first (at most 10) of those places, named as in the file (``materials[2].normalTexture``)."""


class SceneImportPublic(ScenePublic):
    """A scene stored from an imported glTF / GLB / OBJ file: the stored scene, plus what the
    conversion left out or approximated. Only the answer to the import carries these."""

    import_format: Literal["gltf", "glb", "obj"]
    import_warnings: list[ImportWarning] = []


class SceneList(FrozenModel):
    items: list[ScenePublic]
    next_cursor: str | None = None
    """Pass as ``cursor`` for the next page; null on the last page."""


# ------------------------------------------------------------------------------ renders


def _ref(name: str) -> Param:
    return REFERENCE.param(name)


def _int_default(name: str) -> int:
    """The default of the registry's integer reference parameter ``name``."""
    d = _ref(name).default
    assert isinstance(d, int), name
    return d


def _bounds(p: Param) -> Any:
    return Field(ge=p.low, le=p.high, description=p.doc)


def _number_in(p: Param) -> AfterValidator:
    """An optional float parameter of the registry: its range (open or closed bounds) checked with a
    message naming the whole range."""

    def check(value: Any) -> Any:
        if value is not None and not p.contains(value):
            raise PydanticCustomError("param_range", "{name} must be a number in {range}, got {value}",
                                      {"name": p.name, "range": p.range_text, "value": value})
        return value

    return AfterValidator(check)


def _number_doc(p: Param) -> Any:
    """The float parameter's description and range in the JSON schema; left out of dumps when not
    set (or set to its default), so a request without it dumps (and hashes into its artifact key)
    as before it existed."""
    bounds: dict[str, Any] = {"exclusiveMinimum" if p.low_open else "minimum": p.low,
                              "exclusiveMaximum" if p.high_open else "maximum": p.high}
    return Field(description=p.doc, json_schema_extra=bounds, exclude_if=lambda v: v is None or v == p.default)


class ReferenceRenderParams(FrozenModel):
    """Settings of the reference renderer (see docs/reference-renderer.md)."""

    # ranges, defaults and meanings: the registry entry engine.methods.REFERENCE (tests/engine/test_methods.py
    # checks that these fields are exactly its parameters)

    spp: Annotated[int, _bounds(_ref("spp"))] = _int_default("spp")
    max_depth: Annotated[int, _bounds(_ref("max_depth"))] = _int_default("max_depth")
    glossy_samples: Annotated[int, _bounds(_ref("glossy_samples"))] = _int_default("glossy_samples")
    area_light_samples: Annotated[int, _bounds(_ref("area_light_samples"))] = _int_default("area_light_samples")
    indirect_samples: Annotated[int, _bounds(_ref("indirect_samples"))] = _int_default("indirect_samples")
    indirect_bounces: Annotated[int, _bounds(_ref("indirect_bounces"))] = _int_default("indirect_bounces")
    seed: Annotated[int, _bounds(_ref("seed"))] = _int_default("seed")
    max_error: Annotated[FiniteFloat | None, _number_in(_ref("max_error")), _number_doc(_ref("max_error"))] = None
    max_ms: Annotated[FiniteFloat | None, _number_in(_ref("max_ms")), _number_doc(_ref("max_ms"))] = None
    light_paths: Annotated[FiniteFloat, _number_in(_ref("light_paths")), _number_doc(_ref("light_paths"))] = float(
        _ref("light_paths").default or 0.0)


Antialias = Literal["edges", "uniform"]
"""Where an LDC view supersamples (``engine.methods.ANTIALIAS_MODES``)."""


class LDCViewParams(FrozenModel):
    """How an LDC method (``ldc``, ``ldc+llf``, ``ldc+ibrt:k``) renders the view from its bake: its
    antialiasing (docs/ldc.md, *Antialiasing*). The defaults render one sample per pixel."""

    supersample: Annotated[int, _bounds(SUPERSAMPLE)] = int(SUPERSAMPLE.default or 1)
    antialias: Antialias = "edges"
    """``edges``: the s x s sub-pixel samples only in the pixels at an edge of the one-sample image
    (silhouettes, depth jumps, shadow and light borders; the other pixels are the one-sample image's);
    ``uniform``: in every pixel (s^2 the work). No effect at ``supersample`` 1."""
    glossy_rays: Annotated[int, _bounds(GLOSSY_RAYS)] | Literal["auto"] = "auto"
    """n image-based rays traced through each glossy pixel's lobe, followed through k mirror bounces to the
    lights, instead of gathering the lobe from the light field (``ldc+ibrt:k`` with k >= 1 only; docs/ldc.md,
    *Traced glossy reflections*): a glossy surface then shows lights seen in mirrors. 0: gathered. ``auto``
    (the default): 16 rays where a glossy surface may see a rect light in a mirror (the scene has glossy and
    mirror surfaces and rect lights) and the method traces rays, else 0."""
    glossy_filter: Annotated[int, _bounds(GLOSSY_FILTER)] = int(GLOSSY_FILTER.default or 0)
    """With ``glossy_rays``: the radius in pixels over which the traced glossy term is averaged among the
    pixels of the same surface (0: not filtered; the rays' noise against a little blur)."""


class LLFRenderParams(FrozenModel):
    """Reference-renderer settings used for the outgoing radiance stored in the light field."""

    spp: Annotated[int, Field(ge=1, le=64)] = 1
    max_depth: Annotated[int, Field(ge=0, le=16)] = 4
    glossy_samples: Annotated[int, Field(ge=1, le=256)] = 8
    area_light_samples: Annotated[int, Field(ge=1, le=256)] = 4
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0


LLFMode = Literal["auto", "always", "never"]

IndirectMode = Literal["auto", "off"]

IndirectSampling = Literal["fixed", "adaptive"]

IndirectCaustics = Literal["photons", "paths"]

INDIRECT_RANGES: dict[str, tuple[float, float]] = {
    "noise": (0.001, 0.5), "min_paths": (2, 65536), "max_paths": (2, 65536), "bounces": (1, 16),
    "round_paths": (1, 256), "stride": (1, 8), "caustic_photons": (1024, 1 << 26), "caustic_radius": (0.0005, 0.1)}
"""Allowed ranges of the indirect settings: those of ``engine.newviews.indirect.IndirectParams.RANGES``
(the API process imports no numba, so they are repeated here; tests/workers/test_indirect_parts.py
checks that they agree, and the worker re-validates with the engine's own class)."""

MAX_INDIRECT_CHUNKS = 256
"""Most indirect chunk jobs per LDC axis."""


def _in_range(name: str) -> AfterValidator:
    """The field's range as an ``[lo, hi]`` check whose message names the whole range."""
    lo, hi = INDIRECT_RANGES[name]

    def check(value: Any) -> Any:
        if not lo <= value <= hi:
            raise PydanticCustomError("indirect_range", "indirect {name} must be in [{lo}, {hi}], got {value}",
                                      {"name": name, "lo": lo, "hi": hi, "value": value})
        return value

    return AfterValidator(check)


def _range_doc(name: str, doc: str) -> Any:
    lo, hi = INDIRECT_RANGES[name]
    return Field(description=doc, json_schema_extra={"minimum": lo, "maximum": hi})


class IndirectBakeParams(FrozenModel):
    """Indirect diffuse light (interreflection, colour bleeding) of the LDC samples, path traced at
    bake time to a noise target per sample side (``engine/newviews/indirect.py``), and in the light
    field's radiance when the bake has one.

    The pass runs as ``chunks`` jobs per LDC axis (each a contiguous run of the axis's samples,
    after that axis's direct-lit part); the result does not depend on the split."""

    mode: IndirectMode = "auto"
    """``auto``: bake indirect light when the effect analysis says it can arrive (the plan says why
    not otherwise, and nothing is paid); ``off``: direct light only."""
    sampling: IndirectSampling = "fixed"
    """``fixed``: every sample side traces the same number of paths, sized from ``noise``:
    ``(0.32 / noise)^2`` rounded to a power of two (0.02 -> 256, 0.014 -> 512, 0.03 -> 128) within
    ``min_paths`` .. ``max_paths``. ``adaptive``: a pilot of ``min_paths`` paths per side sizes that
    side's estimate for ``noise`` relative to its brightness. At equal view error the fixed count
    bakes in 0.43-0.63x the time on the sample scenes (docs/accuracy/gi.md, "Sampling the indirect
    pass"), so it is the default."""
    noise: Annotated[float, _in_range("noise"), _range_doc("noise", "noise level that sizes the paths per side")] = 0.02
    """The noise level asked for: ``fixed`` sizes its path count from it; ``adaptive`` takes it as
    the target relative standard error of each sample side's radiance (luminance), 0.02 = 2 % of its
    brightness. Either way the bake reports the achieved relative standard errors."""
    min_paths: Annotated[int, _in_range("min_paths"), _range_doc("min_paths", "fewest paths per side")] = 64
    """The fewest paths a sample side traces (a multiple of ``round_paths``, at least two rounds: the
    error is estimated from the spread of the round means); ``adaptive``: the pilot, which sizes the
    side's estimate, a fresh set of at least as many paths (a side never stops on the paths it
    reports, which would bias it low where bright paths are rare: light reaching it through mirrors)."""
    max_paths: Annotated[int, _in_range("max_paths"), _range_doc("max_paths", "most paths per side")] = 1024
    """Most paths one sample side traces (the cost bound, >= ``min_paths``; ``adaptive``: pilot
    included; equal to ``min_paths``: that count in either sampler)."""
    bounces: Annotated[int, _in_range("bounces"), _range_doc("bounces", "diffuse bounces per path")] = 3
    """Diffuse vertices per path (1: one bounce, the colour bleeding; more: higher interreflection)."""
    round_paths: Annotated[int, _in_range("round_paths"), _range_doc("round_paths", "paths per round")] = 8
    """Paths per side per round, a power of two (a stratified block of the side's sample sequence)."""
    stride: Annotated[int, _in_range("stride"), _range_doc("stride", "LDC pixels between traced samples")] = 1
    """Path-trace every ``stride``-th LDC pixel in each direction and give the samples in between the
    interpolation of their traced neighbours on the same surface (a sample with none is traced):
    about 1 / stride^2 of the indirect pass's cost, the direct light (shadow borders) still at the
    LDC's full resolution. Indirect light varies slowly over a surface, so a fine LDC at stride 2
    costs about what the LDC at half its resolution costs at stride 1
    (docs/accuracy/gi.md)."""
    caustics: IndirectCaustics = "photons"
    """How light that reaches a diffuse surface through mirror or glossy surfaces (a caustic) is
    found: ``photons``, a caustic photon map traced from the rect lights through the scene's mirror
    and glossy surfaces (``engine/caustics.py``; built only when the scene has both), or ``paths``,
    the indirect paths alone, which find it rarely and noisily. On the mirror / glossy Cornell box
    the photon map takes the view error away from the caustics' speckles (docs/accuracy/gi.md,
    "Caustics from a photon map")."""
    caustic_photons: Annotated[int, _in_range("caustic_photons"),
                               _range_doc("caustic_photons", "photons aimed at mirror / glossy surfaces")] = 1 << 20
    """Photons aimed at the mirror and glossy surfaces (each chunk job traces the same map; ~0.5 s
    per million on the sample scenes)."""
    caustic_radius: Annotated[float, _in_range("caustic_radius"),
                              _range_doc("caustic_radius", "photon kernel radius, fraction of the diagonal")] = 0.01
    """The photon kernel's radius as a fraction of the scene's bounding-box diagonal: larger is
    smoother and blurs a caustic's edges over that distance."""
    chunks: Annotated[int, Field(ge=1, le=MAX_INDIRECT_CHUNKS)] = 4
    """Jobs per LDC axis for the indirect pass (the unit of parallelism across bake workers)."""

    @model_validator(mode="after")
    def _consistent(self) -> IndirectBakeParams:
        r = self.round_paths
        if r & (r - 1):
            raise PydanticCustomError("indirect_round_paths", "indirect round_paths must be a power of two "
                                      "(1, 2, 4, ..., 256), got {value}", {"value": r})
        if self.min_paths % r or self.min_paths < 2 * r:
            raise PydanticCustomError(
                "indirect_min_paths", "indirect min_paths must be a multiple of round_paths ({round}) and at "
                "least {low}, got {value}", {"round": r, "low": 2 * r, "value": self.min_paths})
        if self.max_paths < self.min_paths:
            raise PydanticCustomError(
                "indirect_max_paths", "indirect max_paths ({max}) must be at least min_paths ({min})",
                {"max": self.max_paths, "min": self.min_paths})
        return self


class BakeParams(FrozenModel):
    """What a bake computes: the layered depth cube (LDC) and, when the scene has glossy or mirror
    materials (the effect analysis decides; ``llf`` overrides), the layered light field (LLF).

    Bakes are split into parts for the ``bake`` queue: one per LDC axis and one per chunk of
    ``llf_chunk`` LLF directions."""

    ldc_resolution: Annotated[int, Field(ge=8, le=4096)] = 256
    """LDC pixels along the longest side of the scene's bounding box (each of the 3 axes)."""
    max_layers: Annotated[int, Field(ge=1, le=256)] = 32
    """Surface crossings kept per LDC pixel (deeper ones are dropped and counted)."""
    area_light_samples: Annotated[int, Field(ge=1, le=1024)] = 16
    """Samples per rect light for the baked diffuse shading (g x g grid, g = round(sqrt(n)))."""
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    llf: LLFMode = "auto"
    """``auto``: bake the light field only when the effect analysis finds glossy or mirror
    materials; ``always``: bake it anyway; ``never``: never (``ldc+llf`` renders then fail)."""
    llf_f: Annotated[int, Field(ge=1, le=16)] = 4
    """Octahedron subdivision: 4 f^2 + 2 directions (f = 4: 66, 8: 258, 16: 1026)."""
    llf_resolution: Annotated[int, Field(ge=4, le=512)] = 64
    """Pixels along the longest side of each LLF view (parallel projection)."""
    llf_chunk: Annotated[int, Field(ge=1, le=1026)] = 16
    """LLF directions per bake job (the unit of parallelism across bake workers)."""
    llf_params: LLFRenderParams = LLFRenderParams()
    indirect: IndirectBakeParams = IndirectBakeParams()
    """Indirect light (on by default: without it a closed room misses a large share of its light,
    ~40 % in a Cornell box); ``{"mode": "off"}`` bakes direct light only."""


MissingBake = Literal["fail", "bake"]

RenderOutput = Literal["preview", "radiance", "depth", "normal", "object_id", "material_id", "provenance"]
"""One image of a render's artifact: ``preview`` (preview.png, 8-bit sRGB), ``radiance``
(radiance.exr, linear float), the AOVs ``depth``, ``normal``, ``object_id``, ``material_id``
(``<name>.exr``) and, for the LDC methods, ``provenance`` (provenance.png)."""

RENDER_OUTPUTS: tuple[str, ...] = ("preview", "radiance", "depth", "normal", "object_id", "material_id",
                                   "provenance")
"""Every :data:`RenderOutput`, in the canonical order (the order of a normalised ``outputs`` list)."""


def _check_outputs(value: list[str] | None) -> list[str] | None:
    if value is None:
        return None
    if not value:
        raise PydanticCustomError(
            "render_outputs_empty",
            "outputs must name at least one of {allowed} (or be left out for all of them)",
            {"allowed": ", ".join(RENDER_OUTPUTS)},
        )
    present = set(value)
    return [name for name in RENDER_OUTPUTS if name in present]  # canonical: same set, same artifact key


RenderOutputs = Annotated[list[RenderOutput] | None, AfterValidator(_check_outputs)]


MAX_CONTRACT_MS = 600_000.0
"""The largest ``quality.max_ms``: the render job's timeout (``producer.queue.RENDER_TIMEOUT_S``, in
ms; the API process's schema cannot import the producer, tests/api_schemas/test_quality_schema.py
checks that they agree)."""

QualityMiss = Literal["fail", "best_effort"]


class QualityContract(FrozenModel):
    """A quality contract instead of a method (``docs/quality-contracts.md``): the planner picks the
    method and its settings from the scene's calibration, the cheapest that meets ``max_error``,
    the most accurate within ``max_ms``, or with both the cheapest meeting the error within the
    time."""

    max_error: float | None = None
    """Largest LRMS against the converged image of the same view, in (0, 1): 0.05 is 5 %."""
    max_ms: float | None = None
    """Largest render time in the worker, in milliseconds, in (0, 600000] (the render job's timeout)."""
    on_miss: QualityMiss = "fail"
    """When no setting meets every target: ``fail`` answers 422 saying what the scene can do;
    ``best_effort`` renders the closest setting and marks the answer as not meeting the contract."""
    verify: bool = False
    """Also measure the error: a follow-up job renders a converged reference of the same view (the
    adaptive reference at a tight error, capped in samples and time) and reports the LRMS of the image
    against it in ``contract.verification``, at the caller's cost (its time is reported). The image's
    ``radiance`` output is then always made (the measurement reads it)."""

    @model_validator(mode="after")
    def _ranges(self) -> QualityContract:
        from engine.quality import check_targets

        problems = check_targets(self.max_error, self.max_ms, MAX_CONTRACT_MS)
        if problems:
            raise PydanticCustomError("quality_range", "{message}",
                                      {"message": "; ".join(message for _, message in problems)})
        return self


class RenderRequest(FrozenModel):
    """Body of ``POST /v1/renders``: a view of a stored scene by a method, or by a quality
    contract (``quality``) that lets the planner pick the method."""

    scene_id: Sha256
    camera: Camera | None = None
    """Overrides the scene's camera; None renders the scene's own view."""
    method: RenderMethod = "reference"
    params: ReferenceRenderParams = ReferenceRenderParams()
    """Reference renderer settings (method ``reference`` only; the LDC methods render from the bake
    and use its settings)."""
    bake: BakeParams = BakeParams()
    """Which bake of the scene an LDC method renders from (ignored by ``reference``)."""
    view: LDCViewParams = LDCViewParams()
    """How an LDC method renders the view (antialiasing); methods that render from a bake only."""
    missing_bake: MissingBake = "fail"
    """When the bake does not exist yet: ``fail`` answers 409 naming the bake to request;
    ``bake`` requests it and queues the render to run when it is done (the answer says so)."""
    outputs: RenderOutputs = None
    """Which images the artifact holds; None (the default): all of them (``provenance`` only for the
    LDC methods). An interactive client asks for what it shows, e.g. ``["preview"]`` or
    ``["preview", "radiance"]``: the job encodes and stores only those (a 512x512 LDC view saves
    most of its encode time). The list is normalised (order, duplicates) and is part of the
    artifact key; a request with a subset is answered from the full artifact when that exists."""
    quality: QualityContract | None = None
    """An error target and / or a time budget instead of a method: the API plans the request from the
    scene's calibration (``POST /v1/scenes/{id}/calibrations``) before it is queued, and the answer's
    ``contract`` says what was chosen and why. Explicit ``method`` or ``params`` with ``quality`` are
    422 (the planner chooses them); ``bake`` and ``missing_bake`` still say which bake the LDC
    methods may use and whether to wait for it."""
    time: Annotated[FiniteFloat | None, Field(exclude_if=lambda v: v is None)] = None
    """Animation time of an animated scene (one with ``animation``): the image is the scene at that
    moment (objects and lights keyframed to it), inside ``[animation.start, animation.end]``, else 422
    naming the interval. Method ``reference`` only: the LDC methods render from the bake of the scene
    as stored and a quality contract plans from that bake's calibration, so ``time`` with either is
    422; ``time`` on a scene without animation is 422 (there is no moment to choose). Leave it out to
    render the scene as stored (each object at its own ``transform``, the lights as written): a
    request without it has the artifact key it always had, one with it a key of its own per time."""

    @field_validator("time")
    @classmethod
    def _time_without_sign_of_zero(cls, value: float | None) -> float | None:
        return None if value is None else value + 0.0  # -0.0 -> 0.0: one moment, one artifact key

    @model_validator(mode="after")
    def _time_renders_the_scene(self) -> RenderRequest:
        if self.time is None:
            return self
        if self.quality is not None:
            raise_errors("RenderRequest", [error_at(
                ("time",), "time_with_quality", "time renders an animated scene at that moment with method "
                "'reference'; a quality contract plans from the calibration of the scene as stored: leave out time "
                "or quality", self.time)])
        if method_needs_bake(self.method):
            raise_errors("RenderRequest", [error_at(
                ("time",), "time_with_bake", f"time renders an animated scene at that moment, which method "
                f"'{self.method}' cannot: it renders from the bake of the scene as stored; use method 'reference' "
                "or leave out time", self.time)])
        return self

    @model_validator(mode="after")
    def _view_is_for_the_ldc_methods(self) -> RenderRequest:
        # a view at the default is no request (a job payload carries every field): only another one is refused
        if self.view != LDCViewParams() and self.quality is None and not method_needs_bake(self.method):
            raise_errors("RenderRequest", [error_at(
                ("view",), "view_with_reference", f"view sets how the LDC methods render from a bake; method "
                f"'{self.method}' takes its settings in params: leave out view", self.view.model_dump())])
        if self.view.glossy_rays not in (0, "auto") and self.quality is None and \
                not (parse_method(self.method).ibrt_generations or 0):
            raise_errors("RenderRequest", [error_at(
                ("view", "glossy_rays"), "glossy_rays_untraced", f"glossy_rays traces image-based rays: it needs "
                f"method 'ldc+ibrt:k' with k >= 1, got '{self.method}'", self.view.glossy_rays)])
        return self

    @model_validator(mode="after")
    def _quality_chooses_the_method(self) -> RenderRequest:
        if self.quality is None:
            return self
        explicit = sorted({"method", "params"} & self.model_fields_set)
        if self.view != LDCViewParams():
            explicit.append("view")
        if explicit:
            raise PydanticCustomError(
                "quality_with_method",
                "quality lets the planner choose the method and its settings: leave out {fields}, or leave out "
                "quality to choose them yourself", {"fields": " and ".join(explicit)})
        if self.outputs is not None and "provenance" in self.outputs:
            raise PydanticCustomError(
                "quality_outputs", "'provenance' exists for the LDC methods only, and with quality the planner "
                "may choose 'reference': leave it out of outputs", {})
        return self

    @field_validator("outputs")
    @classmethod
    def _outputs_fit_method(cls, value: list[str] | None, info: ValidationInfo) -> list[str] | None:
        method = info.data.get("method")
        if value is not None and "provenance" in value and method is not None and not method_needs_bake(method):
            raise PydanticCustomError(
                "render_outputs_method",
                "'provenance' exists for the LDC methods only (method is '{method}'); allowed for "
                "'reference': {allowed}",
                {"method": method, "allowed": ", ".join(n for n in RENDER_OUTPUTS if n != "provenance")},
            )
        return value


class RenderPublic(FrozenModel):
    """Answer to a render request: the artifact when cached, else the job computing it."""

    artifact_key: Sha256
    status: Literal["cached", "queued", "running", "finished", "failed"]
    job: JobPublic | None = None
    artifact: ArtifactManifest | None = None
    bake: BakePublic | None = None
    """LDC methods: the bake the render reads (with ``missing_bake: "bake"``, the bake it waits for)."""
    contract: ContractPublic | None = None
    """Requests with ``quality``: the plan chosen, its predicted error and time, the achieved time."""
    links: dict[str, str] = {}


ContractRule = Literal["cheapest_meeting_error", "most_accurate_within_time", "cheapest_meeting_error_within_time",
                       "most_accurate_within_time_error_unmet", "best_effort_most_accurate", "best_effort_fastest"]


class ContractPublic(FrozenModel):
    """What a quality contract got: the setting the planner chose, by which rule, what it predicts
    and what the render achieved."""

    max_error: float | None = None
    max_ms: float | None = None
    on_miss: QualityMiss = "fail"
    rule: ContractRule
    """``cheapest_meeting_error`` (max_error alone), ``most_accurate_within_time`` (max_ms alone),
    ``cheapest_meeting_error_within_time`` (both, met), ``most_accurate_within_time_error_unmet``
    (both: the error is not reachable within the time), ``best_effort_most_accurate`` /
    ``best_effort_fastest`` (``on_miss: best_effort`` and a target no setting meets)."""
    met: bool
    """The chosen setting is predicted to meet every target."""
    unmet: list[str] = []
    """The targets it is predicted to miss (``max_error``, ``max_ms``), with ``reason``."""
    reason: str = ""
    method: str
    params: dict[str, Any] | None = None
    """The reference renderer's settings when the method is ``reference``."""
    view: dict[str, Any] | None = None
    """An LDC method's antialiasing when the plan chose one (``RenderRequest.view``: ``supersample``,
    ``antialias``); None: one sample per pixel, or the reference."""
    width: int
    height: int
    predicted_error: float
    """LRMS against the converged image of the view, from the scene's calibration."""
    predicted_ms: float
    """Render time in the worker (the renderer's call, without queueing, loading and encoding)."""
    predicted_bake_ms: float = 0.0
    """The bake's cost when the plan waits for a bake that is not made yet (part of the cost ranked)."""
    achieved_ms: float | None = None
    """The render's measured time in the worker, once it has run."""
    estimated_error: float | None = None
    """The estimated achieved error (LRMS against the converged image, as ``predicted_error``): for
    the adaptive reference the render's own estimate (``result.adaptive.estimated_error``) times
    ``error_scale``, once it has run; for every other setting the calibrated prediction, which is
    all that is known without a converged render (``estimated_error_source`` says which)."""
    estimated_error_source: Literal["render", "calibration"] | None = None
    """``render``: estimated by the render itself (the adaptive reference); ``calibration``: the
    calibration's prediction for this setting."""
    error_scale: float | None = None
    """The adaptive reference only: the contract's error over the render's own estimate, measured at
    calibration (the render estimates over the whole image, the contract leaves out the pixels next to
    emitters); the render is told ``planned_for.max_error / error_scale``."""
    planned_for: dict[str, float] = {}
    """The targets the choice was planned against: the request's times the safety margins
    (``margins``), or the request's own when no setting keeps the margin (``reason`` says so)."""
    margins: dict[str, float] = {}
    """The server's safety margins (``IBR_CONTRACT_ERROR_MARGIN``, ``IBR_CONTRACT_TIME_MARGIN``)."""
    verify: bool = False
    verification: dict[str, Any] | None = None
    """With ``verify``: the verification job (``job_id``, ``url``, ``state``) and, once it has finished,
    ``measured_error`` (LRMS of the image against the converged reference, that reference's own
    estimated noise removed in quadrature), ``measured_error_raw``, ``reference_error`` (the converged
    reference's estimated error), ``met`` and ``verify_ms`` (what the measurement cost)."""
    bake: Literal["not_needed", "ready", "waited", "best_available_now"]
    """``ready``: the LDC bake was in the store; ``waited``: it was queued and the render waits for it;
    ``best_available_now``: the bake is missing and ``missing_bake`` is ``fail``, so only the settings
    that render now were considered; ``not_needed``: the chosen method needs no bake (whether the bake
    exists or, with ``missing_bake: "bake"``, waiting for it would have cost more)."""
    excluded: dict[str, str] = {}
    """Methods the calibration excluded on this scene, and why."""
    calibration: dict[str, Any] = {}
    """Which calibration planned it: its key, when it was made, what it cost."""


# ------------------------------------------------------------------------------ calibrations


class CalibrationParams(FrozenModel):
    """How a scene is calibrated for quality contracts (``docs/quality-contracts.md``): probe views
    near the scene's camera, each rendered by every candidate and by a ground truth."""

    probes: Annotated[int, Field(ge=1, le=8)] = 4
    """Probe views (the scene's camera turned about its up axis; never the camera itself). The model
    keeps the worst probe's error, so more probes cover more of the views callers ask for."""
    size: Annotated[int, Field(ge=16, le=512)] = 64
    """Longest side of the probe images, in pixels (the aspect ratio is the scene camera's)."""
    time_scale: Annotated[int, Field(ge=2, le=8)] = 4
    """The LDC methods are also timed at ``size x time_scale`` (their time's per-pixel part)."""
    truth_spp: Annotated[int, Field(ge=16, le=4096)] = 256
    """Samples per pixel of the ground truth (its remaining noise is removed from the fits)."""
    ibrt_ks: Annotated[list[Annotated[int, Field(ge=1, le=MAX_IBRT_GENERATIONS)]],
                       Field(min_length=1, max_length=8)] = [1, 2, 4]
    """The ``ldc+ibrt:k`` generations calibrated (on scenes with mirrors)."""


class CalibrationRequest(FrozenModel):
    """Body of ``POST /v1/scenes/{scene_id}/calibrations``."""

    bake: BakeParams = BakeParams()
    """The bake whose LDC methods are calibrated (the bake render requests name)."""
    params: CalibrationParams = CalibrationParams()
    missing_bake: MissingBake = "fail"
    """When the bake does not exist: ``fail`` (409) or ``bake`` (queue it; the calibration runs after it)."""


CalibrationState = Literal["queued", "running", "finished", "failed", "missing"]


class CalibrationPublic(FrozenModel):
    """A scene's calibration for one bake: the job making it, then the fitted model."""

    scene_id: Sha256
    bake_key: Sha256
    key: Sha256
    """Content key of the calibration (scene, bake, calibration params, engine version)."""
    state: CalibrationState
    cached: bool = False
    job: JobPublic | None = None
    model: dict[str, Any] | None = None
    """The fitted model (``engine.quality.SceneModel``): per method its error and time fit, the
    excluded methods and why, the bake's cost and ``cost_s``, what the calibration took."""
    links: dict[str, str] = {}


# ------------------------------------------------------------------------------ bakes


BakePartState = Literal["queued", "started", "finished", "failed", "canceled", "missing"]


class BakePart(FrozenModel):
    """One unit of a bake: an LDC axis, a chunk of an axis's indirect pass or a chunk of LLF
    directions, its own artifact and job."""

    name: str
    """``ldc-axis-0`` .. ``ldc-axis-2``, ``ldc-indirect-<axis>-<i>``, ``llf-views-<first>-<last>``."""
    kind: Literal["ldc_axis", "ldc_indirect", "llf_views"]
    key: Sha256
    """Artifact key of the part (content-addressed: the bake's key + the part's name)."""
    state: BakePartState
    """``finished`` when the part's artifact is in the store; ``missing`` when neither the
    artifact nor a job exists (it is redone by the next request of the bake)."""
    progress: Annotated[float, Field(ge=0.0, le=1.0)] = 0.0
    weight: float = 1.0
    """Estimated share of the bake's work (for the aggregated progress)."""
    job_id: str | None = None
    error: str | None = None


BakeState = Literal["queued", "running", "finished", "failed", "canceled", "missing"]


class BakePublic(FrozenModel):
    """A bake of a scene: its parts, their states and the aggregated progress."""

    key: Sha256
    scene_id: Sha256
    params: BakeParams
    state: BakeState
    cached: bool = False
    """True when the request found the bake already in the store."""
    progress: JobProgress = Field(default_factory=lambda: JobProgress())
    plan: dict[str, Any] | None = None
    """The effect analysis and what it made the bake do (LLF or not, visibility bits, sizes)."""
    parts: list[BakePart] = []
    job: JobPublic | None = None
    """The bake's merge job (``bake-<key>``): finishes when the manifest is published."""
    error: str | None = None
    artifact: ArtifactManifest | None = None
    links: dict[str, str] = {}


class BakeList(FrozenModel):
    items: list[BakePublic]


# ------------------------------------------------------------------------------ jobs


class JobProgress(FrozenModel):
    fraction: Annotated[float, Field(ge=0.0, le=1.0)] = 0.0
    stage: str = ""
    eta_s: float | None = None


class JobPublic(FrozenModel):
    id: JobId
    kind: Literal["render", "bake"]
    state: JobState
    progress: JobProgress = JobProgress()
    created_at: datetime | None = None
    started_at: datetime | None = None
    ended_at: datetime | None = None
    error: str | None = None
    """Why a job failed, in words a user can act on."""
    result: dict[str, Any] | None = None
    """Small JSON result (artifact key, timings); arrays never travel through Redis."""
    batch_id: str | None = None
    links: dict[str, str] = {}


class JobList(FrozenModel):
    items: list[JobPublic]
    next_cursor: str | None = None
    """Pass as ``cursor`` for the next page; null on the last page."""


# ------------------------------------------------------------------------------ artifacts


class BlobInfo(FrozenModel):
    name: str
    sha256: Sha256
    size: int
    content_type: str


class ArtifactManifest(FrozenModel):
    """The commit record of an artifact, written after all its blobs.

    ``key`` = sha256 of the canonical JSON of (kind, inputs, params, engine_version)."""

    key: Sha256
    kind: str
    inputs: dict[str, str]
    params: dict[str, Any]
    engine_version: str
    blobs: list[BlobInfo]
    result: dict[str, Any] = {}
    created_at: datetime


# ------------------------------------------------------------------------------ batches


class BatchRequest(FrozenModel):
    """Many scenes and / or render requests in one call (``POST /v1/batches``)."""

    scenes: Annotated[list[SceneCreate], Field(max_length=1000)] = []
    renders: Annotated[list[RenderRequest], Field(max_length=10000)] = []


class BatchPublic(FrozenModel):
    id: JobId
    scene_ids: list[Sha256] = []
    renders: list[RenderPublic] = []
    progress: JobProgress = JobProgress()
    counts: dict[str, int] = {}
    """Jobs per state, plus ``cached`` for renders served from the store."""


# ------------------------------------------------------------------------------ errors


class ProblemField(FrozenModel):
    field: str
    """Dot-joined location, e.g. ``scene.objects.2.radius`` ('' = the whole body)."""
    message: str
    type: str


class Problem(FrozenModel):
    """RFC 9457 problem details (``application/problem+json``)."""

    type: str = "about:blank"
    title: str
    status: int
    detail: str = ""
    errors: list[ProblemField] = []
    """One entry per invalid field, e.g. ``{"field": "scene.objects.2.radius", ...}``."""


RenderPublic.model_rebuild()
CalibrationPublic.model_rebuild()
BakePublic.model_rebuild()
