"""Render methods: the one registry of what a render request's ``method`` may name.

Every entry documents itself, the way Mitsuba 3's plugins open with a table of their parameters:
its wire name, the parameters it takes (with ranges and defaults), the bake it renders from and
what its cost grows with. The request schema (``api_schemas.service``), the routes and job
dispatch (through ``method_needs_bake``), the preview page's capability list and the LDC renderer
(``engine.newviews.renderer``) all read this module; pure Python, so the API process imports it
without numba.

=================  ==================  ===========  ==============================================
wire form          parameters          bake         renders
=================  ==================  ===========  ==============================================
``reference``      the request's       none         the ray tracer (``engine.reference``): ground
                   ``params``                       truth, cost per pixel and sample
``ldc``            none                LDC          warp of the layered depth cube, holes filled
                                                    by image-based rays, highlights; no reflections
``ldc+llf``        none                LDC + LLF    ``ldc`` + mirror and glossy reflections
                                                    gathered from the layered light field
``ldc+ibrt:k``     ``k`` in 0..8       LDC + LLF    ``ldc+llf`` with the mirror term traced through
                                                    the LDC for k generations (k = 0 is ``ldc+llf``)
=================  ==================  ===========  ==============================================

The LDC methods share the view settings of the request's ``view``: ``supersample`` s in 1..4
(:data:`SUPERSAMPLE`) and ``antialias`` (:data:`ANTIALIAS_MODES`): ``edges`` traces s x s
sub-pixel rays only in the pixels at an edge of the one-sample image (silhouettes, depth jumps,
shadow and light borders), ``uniform`` in every pixel (s^2 the work).

The LLF is baked only for scenes with glossy or mirror materials (the effect analysis decides,
``BakeParams.llf`` overrides); a scene without them renders ``ldc+llf`` from the LDC alone.

A method string is parsed strictly: the parameter of ``ldc+ibrt:k`` is written in canonical
decimal (``ldc+ibrt:3``, not ``03``, ``+3`` or `` 3``), so every accepted string is the one
:attr:`MethodSpec.wire` gives back. That matters beyond tidiness: the string is hashed into the
artifact key as sent, so two spellings of one render would be two cache entries.
"""

from __future__ import annotations

import math
import operator
import re
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal, SupportsFloat, SupportsIndex

from engine.errors import InvalidInputError

__all__ = [
    "LDC",
    "LDC_IBRT",
    "LDC_LLF",
    "MAX_RENDER_MS",
    "METHODS",
    "REFERENCE",
    "IBRT_GENERATIONS",
    "ANTIALIAS_MODES",
    "SUPERSAMPLE",
    "BakePart",
    "Method",
    "MethodSpec",
    "Param",
    "allowed_forms",
    "get_method",
    "method_needs_bake",
    "method_pattern",
    "parse_method",
    "wire_names",
]

BakePart = Literal["LDC", "LLF"]
"""A part of a scene bake: the layered depth cube (geometry + view-independent radiance) or the
layered light field (outgoing radiance by direction, for reflections)."""


@dataclass(frozen=True)
class Param:
    """A parameter of a method: an integer with ``low <= value <= high`` (``kind`` "int"), or a
    number (``kind`` "float") between ``low`` and ``high``, each bound excluded when
    ``low_open`` / ``high_open``. ``default`` is used when the value is not given; a float
    parameter may default to None: optional, not set unless given."""

    name: str
    default: int | float | None
    low: int | float
    high: int | float
    doc: str
    kind: Literal["int", "float"] = "int"
    low_open: bool = False
    high_open: bool = False

    def __post_init__(self) -> None:
        if self.kind == "int" and (self.low_open or self.high_open):
            raise ValueError(f"parameter {self.name}: an integer parameter has closed bounds")
        if self.default is None:
            if self.kind != "float":
                raise ValueError(f"parameter {self.name}: only a float parameter may be optional")
        elif not self.contains(self.default):
            raise ValueError(f"parameter {self.name}: default {self.default} outside {self.range_text}")

    @property
    def optional(self) -> bool:
        """Not set unless given (default None)."""
        return self.default is None

    def contains(self, value: float) -> bool:
        """``value`` lies in the parameter's range (bounds as the parameter says)."""
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return bool(above and below)

    def check(self, value: object, what: str | None = None) -> int | float:
        """``value`` in range, else :class:`InvalidInputError` naming the range. An int parameter
        takes an int or a numpy integer (not a bool or a float), a float one any finite real number
        but a bool."""
        if self.kind == "float":
            ok = (isinstance(value, (int, float, SupportsFloat)) and not isinstance(value, bool)
                  and math.isfinite(float(value)) and self.contains(float(value)))  # type: ignore[arg-type]
            if not ok:
                raise InvalidInputError(f"{what or self.name} must be a number in {self.range_text}, got {value!r}")
            return float(value)  # type: ignore[arg-type]
        v = operator.index(value) if isinstance(value, SupportsIndex) and not isinstance(value, bool) else None
        if v is None or not self.low <= v <= self.high:
            raise InvalidInputError(f"{what or self.name} must be an integer in [{self.low}, {self.high}], "
                                    f"got {value!r}")
        return v

    @property
    def range_text(self) -> str:
        """``1..4096`` (integers), ``(0, 1)`` or ``(0, 600000]`` (numbers, brackets for included bounds)."""
        if self.kind == "int":
            return f"{self.low}..{self.high}"
        return f"{'(' if self.low_open else '['}{self.low:g}, {self.high:g}{')' if self.high_open else ']'}"


@dataclass(frozen=True)
class Method:
    """One registry entry.

    ``name`` is the wire name, or with an ``arg`` the name before ``:<arg>`` (``ldc+ibrt`` is sent
    as ``ldc+ibrt:k``). ``arg`` is the parameter carried in the method string itself; ``params``
    are the settings of the request's ``params`` object (``reference`` only: the LDC methods take
    their settings from the bake). ``bake`` names the bake parts the method renders from (empty:
    none). ``gathers`` says the view-dependent pass gathers reflections from the LLF. ``cost``
    names what the render time grows with."""

    name: str
    summary: str
    bake: tuple[BakePart, ...]
    cost: str
    arg: Param | None = None
    params: tuple[Param, ...] = ()
    gathers: bool = False

    @property
    def form(self) -> str:
        """How the method is written on the wire: ``ldc`` or ``ldc+ibrt:k``."""
        return self.name if self.arg is None else f"{self.name}:{self.arg.name}"

    @property
    def needs_bake(self) -> bool:
        return bool(self.bake)

    def param(self, name: str) -> Param:
        """The ``params`` entry ``name`` (KeyError if the method has none of that name)."""
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(f"method {self.name!r} has no parameter {name!r}")

    def spec(self, arg: object = None) -> MethodSpec:
        """This method with its string parameter (checked against its range; ``None``: the
        default); :class:`InvalidInputError` for a parameter the method does not take."""
        if self.arg is None:
            if arg is not None:
                raise InvalidInputError(f"method {self.name!r} takes no parameter, got {arg!r}")
            return MethodSpec(self, None)
        value = self.arg.default if arg is None else self.arg.check(arg, f"{self.name}'s {self.arg.name}")
        return MethodSpec(self, value)

    def wire_names(self) -> Iterator[str]:
        """Every string that names this method on the wire."""
        if self.arg is None:
            yield self.name
        else:
            for k in range(self.arg.low, self.arg.high + 1):
                yield f"{self.name}:{k}"


@dataclass(frozen=True)
class MethodSpec:
    """A parsed method string: the registry entry and the value of its string parameter."""

    method: Method
    arg: int | None = None

    @property
    def name(self) -> str:
        """The registry name (``ldc+ibrt`` for ``ldc+ibrt:3``)."""
        return self.method.name

    @property
    def wire(self) -> str:
        """The canonical method string (``parse_method(s).wire == s`` for every accepted ``s``)."""
        return self.method.name if self.arg is None else f"{self.method.name}:{self.arg}"

    @property
    def needs_bake(self) -> bool:
        return self.method.needs_bake

    @property
    def bake(self) -> tuple[BakePart, ...]:
        return self.method.bake

    @property
    def gathers(self) -> bool:
        """The view-dependent pass gathers mirror and glossy reflections from the LLF."""
        return self.method.gathers

    @property
    def ibrt_generations(self) -> int:
        """Mirror generations traced through the LDC (0 for every method but ``ldc+ibrt:k``)."""
        return self.arg if self.method is LDC_IBRT and self.arg is not None else 0


# ------------------------------------------------------------------------------ the methods

MAX_RENDER_MS = 600_000.0
"""Largest time budget of a reference render (``max_ms``): the render job's timeout,
``producer.queue.RENDER_TIMEOUT_S`` (tests/engine/test_progressive.py checks they agree)."""

REFERENCE = Method(
    name="reference",
    summary="The ray tracer (Embree + numba): ground truth, rendered from the scene's triangles.",
    bake=(),
    cost="pixels x spp camera rays, each with one shadow ray per point light and area_light_samples per rect "
         "light, glossy_samples rays at the first glossy hit and one mirror ray per mirror hit (to max_depth), "
         "plus indirect_samples paths of indirect_bounces bounces per pixel; no bake, no precomputation.",
    params=(
        Param("spp", 4, 1, 4096, "antialiasing samples per pixel (scrambled Sobol points, box filter); with "
              "max_error or max_ms, the most any pixel gets"),
        Param("max_depth", 4, 0, 64, "mirror / glossy recursion depth"),
        Param("glossy_samples", 16, 1, 4096, "samples of the glossy lobe at the first glossy bounce of a chain"),
        Param("area_light_samples", 16, 1, 4096, "shadow rays per rectangular light per shading point "
              "(g x g jittered grid, g = round(sqrt(n)))"),
        Param("indirect_samples", 0, 0, 65536, "indirect diffuse paths per pixel (0: direct lighting only)"),
        Param("indirect_bounces", 2, 1, 64, "diffuse bounces per indirect path"),
        Param("seed", 0, 0, 2**31 - 1, "random seed"),
        Param("max_error", None, 0.0, 1.0, "progressive, adaptive render until the estimated LRMS against the "
              "converged image is at most this (spp is then the cap per pixel); not set: spp samples per pixel",
              kind="float", low_open=True, high_open=True),
        Param("max_ms", None, 0.0, MAX_RENDER_MS, "progressive render that stops when this many milliseconds "
              "of render time are spent (alone or with max_error); not set: no time budget",
              kind="float", low_open=True),
        Param("light_paths", 1.0, 0.0, 64.0, "light paths per camera sample for the caustics seen on diffuse "
              "surfaces (light through mirror / glossy surfaces, traced from the lights and joined to the camera; "
              "pinhole cameras with indirect paths only); 0: the camera's paths find that light too (noisier)",
              kind="float"),
    ),
)

LDC = Method(
    name="ldc",
    summary="Warp of the layered depth cube: holes and silhouettes by image-based rays, Phong highlights; "
            "no reflections (everything the LDC alone holds).",
    bake=("LDC",),
    cost="per view: every LDC sample warped (grows with ldc_resolution^2 x layers, not with the image), one "
         "image-based ray per hole and silhouette pixel, highlights on glossy pixels; the bake once per scene "
         "and bake parameters.",
)

LDC_LLF = Method(
    name="ldc+llf",
    summary="ldc plus mirror (3-direction cone) and glossy (lobe) reflections gathered from the layered "
            "light field.",
    bake=("LDC", "LLF"),
    cost="ldc + one light-field gather per glossy or mirror pixel (grows with the reflective pixels and the "
         "lobe's LLF directions); the LLF bake renders 4 f^2 + 2 views with the reference renderer.",
    gathers=True,
)

IBRT_GENERATIONS = Param("k", 1, 0, 8, "reflection generations traced through the LDC (0: the same image as "
                         "ldc+llf)")
"""The ``k`` of ``ldc+ibrt:k``."""

LDC_IBRT = Method(
    name="ldc+ibrt",
    summary="ldc+llf with the mirror term traced through the LDC for k generations (image-based ray "
            "tracing), the last ending in the light-field gather; glossy terms are gathered, or traced "
            "through k + 1 generations where a glossy surface may see a rect light in a mirror "
            "(view.glossy_rays).",
    bake=("LDC", "LLF"),
    cost="ldc+llf + k image-based rays per mirror pixel, each hit shaded (diffuse, highlights, glossy "
         "gather): grows about linearly with k on mirror pixels only; traced glossy lobes add their rays "
         "(16 per glossy pixel by default where they are traced).",
    arg=IBRT_GENERATIONS,
    gathers=True,
)

SUPERSAMPLE = Param("supersample", 1, 1, 4, "s: s x s samples per pixel on a regular sub-pixel grid, box-filtered "
                    "(1: one sample per pixel, no antialiasing)")
"""The LDC methods' antialiasing factor (``engine.newviews.renderer.LDCViewRenderer.render``)."""

GLOSSY_RAYS = Param("glossy_rays", 0, 0, 256, "n: image-based rays traced per glossy pixel through its lobe, "
                    "followed through mirrors to the lights (ldc+ibrt:k with k >= 1; 0: the lobe is gathered from "
                    "the light field)")
"""The LDC views' traced glossy lobe (``engine.newviews.renderer.LDCViewRenderer.render``)."""

GLOSSY_RAYS_AUTO = 16
"""``glossy_rays="auto"`` (the default): this many rays where a glossy surface may see a rect light in
a mirror (the scene has glossy and mirror surfaces and rect lights; ``ldc+ibrt:k``, k >= 1), else 0
(the light field's gather holds everything else the lobe sees)."""


def auto_glossy_rays(glossy: bool, mirror: bool, rect_light: bool) -> int:
    """The rays per glossy pixel ``glossy_rays="auto"`` traces in a scene with (or without) glossy and
    mirror surfaces and rect lights: :data:`GLOSSY_RAYS_AUTO` when it has all three, else 0. The
    renderer decides from the materials its triangles use, the API prices a request from the scene's."""
    return GLOSSY_RAYS_AUTO if glossy and mirror and rect_light else 0

GLOSSY_FILTER = Param("glossy_filter", 3, 0, 8, "radius in pixels over which the traced glossy term is averaged "
                      "among the pixels of the same surface (0: not filtered)")
"""The filter of the traced glossy term (``glossy_rays``)."""

ANTIALIAS_MODES: tuple[str, ...] = ("edges", "uniform")
"""Where the LDC methods supersample: ``edges`` only the pixels at an edge of the one-sample image
(the default: on the sample scenes it reaches uniform supersampling's error at a fraction of its
time, docs/ldc.md), ``uniform`` every pixel."""

METHODS: tuple[Method, ...] = (REFERENCE, LDC, LDC_LLF, LDC_IBRT)
"""Every render method, in the order they are offered (``reference`` is the request's default)."""

_BY_NAME = {m.name: m for m in METHODS}
_ARG = re.compile(r"0|[1-9][0-9]{0,8}")  # canonical decimal (the string round-trips), short enough for int()


def get_method(name: str) -> Method:
    """The registry entry called ``name`` (``ldc+ibrt``, not ``ldc+ibrt:3``)."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise InvalidInputError(f"no render method {name!r}; methods: {allowed_forms()}") from None


def allowed_forms(*, needs_bake: bool | None = None) -> str:
    """The accepted method strings in words: ``'reference', 'ldc', 'ldc+llf' or 'ldc+ibrt:k' with
    k in 0..8`` (``needs_bake``: only the methods that do, or do not, render from a bake)."""
    chosen = [m for m in METHODS if needs_bake is None or m.needs_bake == needs_bake]
    forms = [f"'{m.form}'" for m in chosen]
    text = ", ".join(forms[:-1]) + f" or {forms[-1]}" if len(forms) > 1 else forms[0]
    ranges = [f"{m.arg.name} in {m.arg.range_text}" for m in chosen if m.arg is not None]
    return text + (" with " + ", ".join(ranges) if ranges else "")


def _int_alternatives(low: int, high: int) -> str:
    if 0 <= low <= high <= 9:
        return f"[{low}-{high}]" if high > low else str(low)
    return "(?:" + "|".join(str(k) for k in range(low, high + 1)) + ")"


def method_pattern() -> str:
    """A regular expression (JSON Schema ``pattern``) matching exactly the accepted method strings."""
    alts = [re.escape(m.name) if m.arg is None else f"{re.escape(m.name)}:{_int_alternatives(m.arg.low, m.arg.high)}"
            for m in METHODS]
    return "^(" + "|".join(alts) + ")$"


def wire_names() -> list[str]:
    """Every accepted method string, in registry order."""
    return [s for m in METHODS for s in m.wire_names()]


def parse_method(method: object) -> MethodSpec:
    """Parse a method string as sent on the wire (``reference``, ``ldc``, ``ldc+llf``, ``ldc+ibrt:k``).

    Raises :class:`InvalidInputError` (a ``ValueError``) naming the allowed forms for anything
    else, including non-canonical spellings (``ldc+ibrt:03``) and a missing ``:k``."""
    if not isinstance(method, str):
        raise InvalidInputError(f"method must be a string: {allowed_forms()}; got {method!r}")
    name, sep, arg = method.partition(":")
    entry = _BY_NAME.get(name)
    if entry is None or bool(sep) != (entry.arg is not None):
        raise InvalidInputError(f"method must be {allowed_forms()}, got {method[:40]!r}")
    if entry.arg is None:
        return MethodSpec(entry, None)
    p = entry.arg
    if _ARG.fullmatch(arg) is None or not p.low <= int(arg) <= p.high:
        raise InvalidInputError(f"method {method[:40]!r}: {p.name} must be an integer in {p.range_text} written "
                                f"in plain decimal (e.g. '{entry.name}:{p.default}'); methods: {allowed_forms()}")
    return entry.spec(int(arg))


def method_needs_bake(method: str) -> bool:
    """True when ``method`` renders from a scene bake (every method but ``reference``); for a
    string the request model has validated (an unknown name raises :class:`InvalidInputError`)."""
    return parse_method(method).needs_bake
