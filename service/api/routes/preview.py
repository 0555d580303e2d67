"""The browser preview page (issue 7): static files at ``/preview/``, ``/`` redirects there,
plus the few API endpoints only the page needs (``/v1/preview/...``).

No build step: ``service/static/{index.html,app.js,app.css}`` are served as they are.
``/preview/sample-cameras.json`` lists the shipped sample scenes' cameras by scene name,
because the API stores scenes without offering their JSON back: the page starts a sample
scene from its own camera and any other scene from a default camera (see the page's help).

``/v1/preview/capabilities`` tells the page what this API can do, read from the API itself:
the render methods the ``RenderRequest`` model accepts (each candidate name is validated by
the model, so a name the API refuses is never offered) and which resources are routed
(bakes, datasets, relights, walkthroughs). LDC methods are offered only when the scene bake
routes exist too: without them no bake can be made or watched.

``/v1/preview/compare`` computes the LRMS of one render artifact against another (the
difference view) and ``/v1/preview/compare/heatmap.png`` its false-colour error map;
``/v1/preview/artifacts/{key}/image.png?exposure=`` re-exposes a render from its linear
``radiance.exr``; ``/v1/preview/artifacts/{key}/provenance.png`` colours the LDC methods'
provenance codes. All of it is numpy + OpenImageIO: this process
never imports numba or ``engine`` (``engine/__init__`` imports numba), so the formulas of
``engine.metrics.lrms`` / ``error_heatmap`` and ``engine.imageio.tonemap_srgb`` are restated
here and tested against them (tests/service/api/test_preview_api.py).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import threading
from collections import OrderedDict
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, get_args

import numpy as np
from fastapi import APIRouter, HTTPException, Query, Request, Response
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, JSONResponse, RedirectResponse
from pydantic import ValidationError

from api_schemas.common import FrozenModel
from api_schemas.errors import FieldError
from api_schemas.service import ArtifactManifest, RenderRequest, Sha256
from producer.artifacts import read_blob, read_manifest
from producer.store import NotFound, ObjectStore
from service.api.deps import OwnerDep, StoreDep, scene_visible
from service.api.errors import ValidationProblem, problem_responses

router = APIRouter()

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
_FILES = {
    "index.html": "text/html; charset=utf-8",
    "app.js": "text/javascript; charset=utf-8",
    "app.css": "text/css; charset=utf-8",
}
_HEADERS = {"Cache-Control": "no-cache"}

PIVOTS: dict[str, list[float]] = {"cornell_box": [278.0, 273.0, 279.6]}
"""Orbit centres for samples whose camera looks at a point right in front of the eye."""


@lru_cache(maxsize=1)
def sample_cameras() -> dict[str, dict[str, Any]]:
    """Scene name -> {"camera": the sample's camera, "pivot": the point to orbit around, and when the
    sample has them "view_space" and "animation": {"start", "end"}}."""
    try:
        from samples import SCENES_DIR
    except ImportError:  # deployed without the samples package
        return {}
    out: dict[str, dict[str, Any]] = {}
    for path in sorted(SCENES_DIR.glob("*.json")):
        doc = json.loads(path.read_text())
        cam = doc.get("camera")
        name = doc.get("name") or path.stem
        if isinstance(cam, dict):
            entry: dict[str, Any] = {"camera": cam, "pivot": PIVOTS.get(str(name), cam.get("look_at"))}
            # for the Walkthroughs panel: where the viewer may move, and the animation's time range
            if isinstance(doc.get("view_space"), dict):
                entry["view_space"] = doc["view_space"]
            anim = doc.get("animation")
            if isinstance(anim, dict) and "start" in anim and "end" in anim:
                entry["animation"] = {"start": anim["start"], "end": anim["end"]}
            out[str(name)] = entry
    return out


def _to_page(request: Request) -> RedirectResponse:
    query = request.url.query
    return RedirectResponse("/preview/" + (f"?{query}" if query else ""), status_code=307)


@router.get("/", include_in_schema=False)
def root(request: Request) -> RedirectResponse:
    return _to_page(request)


@router.get("/preview", include_in_schema=False)
def preview_no_slash(request: Request) -> RedirectResponse:
    return _to_page(request)


@router.get("/preview/sample-cameras.json", include_in_schema=False)
def cameras() -> JSONResponse:
    return JSONResponse(sample_cameras(), headers=_HEADERS)


@router.get("/preview/", include_in_schema=False)
def index() -> FileResponse:
    return static_file("index.html")


@router.get("/preview/{name}", include_in_schema=False)
def static_file(name: str) -> FileResponse:
    media_type = _FILES.get(name)
    if media_type is None:
        raise HTTPException(404, f"no file {name}")
    return FileResponse(STATIC_DIR / name, media_type=media_type, headers=_HEADERS)


# ------------------------------------------------------------------------------ capabilities

MAX_K_PROBE = 32
"""Largest ``ldc+ibrt:k`` generation count probed against the model."""


class MethodInfo(FrozenModel):
    name: str
    """``reference``, ``ldc``, ``ldc+llf`` or ``ldc+ibrt`` (then ``k`` picks the generations)."""
    needs_bake: bool
    k: list[int] = []
    """For ``ldc+ibrt``: the generation counts the API accepts (sent as ``ldc+ibrt:<k>``)."""


class Capabilities(FrozenModel):
    """What this API serves, for the preview page (it shows only what exists)."""

    methods: list[MethodInfo]
    bakes: bool
    """Scene bakes can be requested and watched (``/v1/scenes/{scene_id}/bakes``)."""
    datasets: bool
    relights: bool
    walkthroughs: bool
    compare: bool = True
    walkthrough_options: dict[str, list[str]] = {}
    """When walkthroughs are routed: the values the walkthrough request accepts for ``quality`` and ``fill``."""
    provenance: dict[int, tuple[str, str]] = {}
    """Provenance code -> (name, CSS colour) of ``/v1/preview/artifacts/{key}/provenance.png``."""
    paths: list[str] = []
    """The ``/v1`` paths of the app's OpenAPI document the flags above were read from."""


def _accepted(method: str) -> bool:
    try:
        RenderRequest.model_validate({"scene_id": "0" * 64, "method": method})
    except ValidationError:
        return False
    return True


@lru_cache(maxsize=1)
def _accepted_methods() -> tuple[tuple[str, tuple[int, ...]], ...]:
    out: list[tuple[str, tuple[int, ...]]] = [(m, ()) for m in ("reference", "ldc", "ldc+llf") if _accepted(m)]
    ks = tuple(k for k in range(MAX_K_PROBE + 1) if _accepted(f"ldc+ibrt:{k}"))
    if ks:
        out.append(("ldc+ibrt", ks))
    return tuple(out)


@lru_cache(maxsize=1)
def _walkthrough_options() -> dict[str, list[str]]:
    """``quality`` and ``fill`` choices of the walkthrough request model (empty without it)."""
    try:
        from api_schemas.walkthrough import WalkthroughRequest, WalkthroughSettings
    except ImportError:
        return {}
    out: dict[str, list[str]] = {}
    for name, model, field in (("quality", WalkthroughSettings, "quality"), ("fill", WalkthroughRequest, "fill")):
        info = model.model_fields.get(field)
        values = [str(v) for v in get_args(info.annotation)] if info is not None else []
        if values:
            out[name] = values
    return out


def capabilities_of(paths: list[str]) -> Capabilities:
    """Capabilities given the app's routed paths (the render methods come from the model)."""
    bakes = any(p.startswith("/v1/scenes/{scene_id}/bakes") for p in paths)
    walkthroughs = "/v1/walkthroughs" in paths and any(p.startswith("/v1/walkthroughs/{key}/frames") for p in paths)
    methods = [MethodInfo(name=m, needs_bake=m != "reference", k=list(ks)) for m, ks in _accepted_methods()
               if m == "reference" or bakes]
    return Capabilities(
        methods=methods,
        bakes=bakes,
        datasets=any(p.startswith("/v1/datasets") for p in paths),
        relights="/v1/relights" in paths,
        walkthroughs=walkthroughs,
        walkthrough_options=_walkthrough_options() if walkthroughs else {},
        provenance={code: (name, "#{:02x}{:02x}{:02x}".format(*rgb)) for code, (name, rgb) in PROVENANCE.items()},
        paths=paths,
    )


@router.get("/v1/preview/capabilities", response_model=Capabilities, tags=["preview"])
def capabilities(request: Request) -> Capabilities:
    """Render methods the API accepts and the resources it routes (read from the app's OpenAPI document)."""
    # the OpenAPI document lists every routed path (app.routes may hold lazily included routers)
    paths = sorted(p for p in request.app.openapi().get("paths", {}) if p.startswith("/v1/"))
    return capabilities_of(paths)


# ------------------------------------------------------------------------------ images (numpy + OpenImageIO)

REC709 = (0.2126, 0.7152, 0.0722)
VIRIDIS = np.array([
    (0.2670, 0.0049, 0.3294), (0.2823, 0.0950, 0.4173), (0.2788, 0.1755, 0.4834), (0.2590, 0.2515, 0.5247),
    (0.2297, 0.3224, 0.5457), (0.1994, 0.3876, 0.5546), (0.1727, 0.4488, 0.5579), (0.1490, 0.5081, 0.5573),
    (0.1276, 0.5669, 0.5506), (0.1206, 0.6258, 0.5335), (0.1579, 0.6838, 0.5017), (0.2461, 0.7389, 0.4520),
    (0.3692, 0.7889, 0.3829), (0.5160, 0.8312, 0.2943), (0.6785, 0.8637, 0.1895), (0.8456, 0.8873, 0.0997),
    (0.9932, 0.9062, 0.1439)], dtype=np.float64)
"""Viridis at 17 points, the palette of ``engine.metrics.error_heatmap`` (display values)."""


def read_image(data: bytes, suffix: str = ".exr") -> np.ndarray:
    """Decode an image (EXR, PNG; any channel count) to float32 ``(h, w, c)``: EXR values as stored,
    8-bit PNG values as their integer codes 0..255 (no transfer function, no normalisation)."""
    import OpenImageIO as oiio

    with tempfile.TemporaryDirectory(prefix="ibr-preview-") as tmp:
        path = os.path.join(tmp, "in" + suffix)
        with open(path, "wb") as f:
            f.write(data)
        inp = oiio.ImageInput.open(path)
        if inp is None:
            raise ValueError(f"cannot read the image: {oiio.geterror()}")
        try:
            spec = inp.spec()
            fmt = "float" if suffix == ".exr" else "uint8"
            arr = inp.read_image(0, 0, 0, spec.nchannels, fmt)
        finally:
            inp.close()
    if arr is None:
        raise ValueError("cannot decode the image")
    return np.asarray(arr, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)


def png_bytes(rgb8: np.ndarray) -> bytes:
    """Encode ``(h, w, c)`` uint8 as PNG."""
    import OpenImageIO as oiio

    h, w, c = rgb8.shape
    with tempfile.TemporaryDirectory(prefix="ibr-preview-") as tmp:
        path = os.path.join(tmp, "out.png")
        out = oiio.ImageOutput.create(path)
        if out is None:
            raise RuntimeError(f"no PNG writer: {oiio.geterror()}")
        spec = oiio.ImageSpec(w, h, c, "uint8")
        spec.attribute("png:compressionLevel", 3)
        if not out.open(path, spec) or not out.write_image(np.ascontiguousarray(rgb8)):
            err = out.geterror()
            out.close()
            raise RuntimeError(f"PNG encoding failed: {err}")
        out.close()
        with open(path, "rb") as f:
            return f.read()


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """Exact sRGB OETF (``engine.imageio.srgb_encode``)."""
    x64 = np.asarray(x, dtype=np.float64)
    power = 1.055 * np.power(np.maximum(x64, 0.0031308), 1.0 / 2.4) - 0.055
    return np.where(x64 <= 0.0031308, 12.92 * x64, power)


def to_srgb8(linear: np.ndarray, exposure_stops: float) -> np.ndarray:
    """The PNG display transform of ``engine.imageio.write_image`` at an exposure, 8-bit:
    ``rint(255 srgb_encode(clip(x 2^e, 0, 1)))``; 4 channels are associated alpha, un-premultiplied
    for the PNG's straight alpha (fully transparent pixels carry no colour); 1 channel becomes grey RGB."""
    x = linear.astype(np.float64)
    colour = x[..., :3] if x.shape[2] >= 3 else np.repeat(x[..., :1], 3, axis=2)
    alpha = np.clip(x[..., 3:4], 0.0, 1.0) if x.shape[2] == 4 else None
    if alpha is not None:
        colour = np.where(alpha > 0, colour / np.where(alpha > 0, alpha, 1.0), 0.0)
    enc = srgb_encode(np.clip(colour * 2.0**exposure_stops, 0.0, 1.0))
    if alpha is not None:
        enc = np.concatenate([enc, alpha], axis=2)
    out: np.ndarray = np.rint(enc * 255.0).astype(np.uint8)
    return out


def luminance(img: np.ndarray) -> np.ndarray:
    """Rec.709 luminance in float64 (1 channel: the value itself; alpha ignored)."""
    x = img.astype(np.float64, copy=False)
    if x.shape[2] == 1:
        return x[..., 0]
    return REC709[0] * x[..., 0] + REC709[1] * x[..., 1] + REC709[2] * x[..., 2]


def coverage_mask(ref: np.ndarray) -> np.ndarray:
    """The reference's covered pixels: alpha > 0 for 4 channels, else every pixel."""
    if ref.shape[2] == 4:
        mask: np.ndarray = ref[..., 3] > 0
        return mask
    return np.ones(ref.shape[:2], dtype=bool)


def lrms(test: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> float:
    """``RMS(Y_test - Y_ref) / mean(Y_ref)`` over ``mask`` (``engine.metrics.lrms``): 0 for identical
    luminance under a black reference, inf for any difference there."""
    y_t, y_r = luminance(test)[mask], luminance(ref)[mask]
    mean = float(np.mean(y_r))
    rms = math.sqrt(float(np.mean(np.square(y_t - y_r))))
    if mean == 0.0:
        return 0.0 if rms == 0.0 else math.inf
    return rms / mean


def heatmap(test: np.ndarray, ref: np.ndarray, mask: np.ndarray, scale: float | None = None) -> np.ndarray:
    """Viridis map of ``|Y_test - Y_ref| / s`` (``s`` = ``scale`` or the mean reference luminance),
    clipped to [0, 1], black outside ``mask``: ``engine.metrics.error_heatmap`` as display values, 8-bit."""
    y_t, y_r = luminance(test), luminance(ref)
    diff = np.abs(y_t - y_r)
    s = float(np.mean(y_r[mask])) if scale is None else scale
    v = (diff > 0).astype(np.float64) if s == 0.0 else np.clip(diff / s, 0.0, 1.0)
    pos = v * (len(VIRIDIS) - 1)
    lo = np.minimum(np.floor(pos).astype(np.intp), len(VIRIDIS) - 2)
    frac = (pos - lo)[..., None]
    rgb = VIRIDIS[lo] * (1.0 - frac) + VIRIDIS[lo + 1] * frac
    rgb[~mask] = 0.0
    out: np.ndarray = np.rint(rgb * 255.0).astype(np.uint8)
    return out


class _Radiance:
    """Small LRU of decoded ``radiance.exr`` by artifact key (artifacts are immutable; visibility is
    still checked on every request before the cache is consulted)."""

    def __init__(self, size: int = 8) -> None:
        self.size = size
        self.items: OrderedDict[tuple[str, str], np.ndarray] = OrderedDict()
        self.lock = threading.Lock()

    def get(self, store: ObjectStore, key: str, blob: str = "radiance.exr") -> np.ndarray:
        with self.lock:
            hit = self.items.get((key, blob))
            if hit is not None:
                self.items.move_to_end((key, blob))
                return hit
        img: np.ndarray = read_image(read_blob(store, key, blob))  # ChecksumMismatch -> 404 corrupt
        img.setflags(write=False)
        with self.lock:
            self.items[(key, blob)] = img
            while len(self.items) > self.size:
                self.items.popitem(last=False)
        return img


RADIANCE = _Radiance()


def visible_render(store: ObjectStore, key: str, owner: str | None, field: str = "key") -> ArtifactManifest:
    """A render artifact (a manifest naming a scene) this owner may see, else 404."""
    manifest = read_manifest(store, key)
    if manifest is None:
        raise NotFound(f"no artifact {key} ({field})")
    scene_id = manifest.inputs.get("scene")
    if scene_id is None or (owner is not None and not scene_visible(store, scene_id, owner)):
        raise NotFound(f"no artifact {key} ({field})")
    if not any(b.name == "radiance.exr" for b in manifest.blobs):
        raise ValidationProblem([FieldError(field=field, message=f"artifact {key} has no radiance.exr "
                                            f"(a {manifest.kind} artifact, not a render)", type="not_a_render")])
    return manifest


class Comparison(FrozenModel):
    """LRMS of a render against a reference render (same size), over the reference's covered pixels."""

    test: Sha256
    ref: Sha256
    lrms: float | None
    """``RMS(Y_test - Y_ref) / mean(Y_ref)`` (Rec.709 luminance); None when infinite (black reference)."""
    rms: float
    mean_ref_luminance: float
    fraction_over_5pct: float
    """Share of pixels with ``|Y_test - Y_ref| > 0.05 mean(Y_ref)``."""
    n_pixels: int
    width: int
    height: int
    links: dict[str, str] = {}


TestKey = Annotated[Sha256, Query(description="Artifact key of the render to judge")]
RefKey = Annotated[Sha256, Query(description="Artifact key of the reference render")]


def _pair(store: ObjectStore, owner: str | None, test: str, ref: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    visible_render(store, test, owner, "query.test")
    visible_render(store, ref, owner, "query.ref")
    t, r = RADIANCE.get(store, test), RADIANCE.get(store, ref)
    if t.shape[:2] != r.shape[:2]:
        raise ValidationProblem([FieldError(
            field="query.test", message=f"image is {t.shape[1]} x {t.shape[0]} but the reference is "
            f"{r.shape[1]} x {r.shape[0]}: compare renders of the same size", type="size_mismatch")])
    mask = coverage_mask(r)
    if not mask.any():
        raise ValidationProblem([FieldError(field="query.ref", message="the reference covers no pixel",
                                            type="empty_mask")])
    return t, r, mask


def _compare(store: ObjectStore, owner: str | None, test: str, ref: str) -> Comparison:
    t, r, mask = _pair(store, owner, test, ref)
    y_t, y_r = luminance(t)[mask], luminance(r)[mask]
    mean = float(np.mean(y_r))
    value = lrms(t, r, mask)
    return Comparison(
        test=test, ref=ref, lrms=value if math.isfinite(value) else None,
        rms=math.sqrt(float(np.mean(np.square(y_t - y_r)))), mean_ref_luminance=mean,
        fraction_over_5pct=float(np.count_nonzero(np.abs(y_t - y_r) > 0.05 * mean)) / y_r.size,
        n_pixels=int(y_r.size), width=int(r.shape[1]), height=int(r.shape[0]),
        links={"heatmap": f"/v1/preview/compare/heatmap.png?test={test}&ref={ref}"},
    )


_ERRORS = problem_responses(401, 404, 422, 429, 503)
_PNG: dict[int | str, dict[str, Any]] = {
    200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}}}, "description": "PNG"}}


@router.get("/v1/preview/compare", response_model=Comparison, tags=["preview"], responses=_ERRORS)
async def compare(store: StoreDep, owner: OwnerDep, test: TestKey, ref: RefKey) -> Comparison:
    """LRMS of render ``test`` against render ``ref`` (both artifacts' ``radiance.exr``)."""
    return await run_in_threadpool(_compare, store, owner, test, ref)


@router.get("/v1/preview/compare/heatmap.png", response_class=Response, tags=["preview"],
            responses={**_PNG, **_ERRORS})
async def compare_heatmap(
    store: StoreDep, owner: OwnerDep, test: TestKey, ref: RefKey,
    scale: Annotated[float | None, Query(gt=0, le=1e30, description="Error shown at full scale (default: the "
                                         "mean reference luminance, so yellow = 100 % relative error)")] = None,
) -> Response:
    """False-colour map of the luminance error of ``test`` against ``ref`` (viridis, black outside coverage)."""
    def run() -> bytes:
        t, r, mask = _pair(store, owner, test, ref)
        return png_bytes(heatmap(t, r, mask, scale))

    return Response(await run_in_threadpool(run), media_type="image/png",
                    headers={"Cache-Control": "private, max-age=31536000, immutable"})


@router.get("/v1/preview/artifacts/{key}/image.png", response_class=Response, tags=["preview"],
            responses={**_PNG, **_ERRORS})
async def exposed_image(
    store: StoreDep, owner: OwnerDep, key: Annotated[Sha256, PathParam(description="Render artifact key")],
    exposure: Annotated[float, Query(ge=-20, le=20, allow_inf_nan=False,
                                     description="Exposure in stops applied to the linear radiance")] = 0.0,
) -> Response:
    """The render's sRGB preview at an exposure: ``srgb(clip(radiance * 2^exposure, 0, 1))``."""
    def run() -> bytes:
        visible_render(store, key, owner, "path.key")
        if exposure == 0.0:
            return read_blob(store, key, "preview.png")
        return png_bytes(to_srgb8(RADIANCE.get(store, key), exposure))

    return Response(await run_in_threadpool(run), media_type="image/png",
                    headers={"Cache-Control": "private, max-age=31536000, immutable"})


PROVENANCE = {0: ("background", (32, 32, 32)), 1: ("warped", (120, 144, 156)), 2: ("hole-filled", (255, 152, 0)),
              3: ("gathered", (33, 150, 243)), 4: ("traced", (233, 30, 99))}
"""Provenance code (the LDC methods' ``provenance.png``, workers/jobs/render.py) -> name, display colour."""
_UNKNOWN = (255, 0, 255)


def provenance_rgb(codes: np.ndarray) -> np.ndarray:
    """Colour ``(h, w)`` provenance codes (unknown codes magenta)."""
    lut = np.tile(np.array(_UNKNOWN, dtype=np.uint8), (256, 1))
    for code, (_, rgb) in PROVENANCE.items():
        lut[code] = rgb
    out: np.ndarray = lut[np.clip(codes, 0, 255).astype(np.intp)]
    return out


@router.get("/v1/preview/artifacts/{key}/provenance.png", response_class=Response, tags=["preview"],
            responses={**_PNG, **_ERRORS})
async def provenance_image(
    store: StoreDep, owner: OwnerDep, key: Annotated[Sha256, PathParam(description="Render artifact key")],
) -> Response:
    """The LDC render's provenance in colour (``/v1/preview/capabilities`` lists the colours); 404 for a
    render without provenance (the reference renderer)."""
    def run() -> bytes:
        manifest = visible_render(store, key, owner, "path.key")
        if not any(b.name == "provenance.png" for b in manifest.blobs):
            raise NotFound(f"artifact {key} has no provenance (method {manifest.params.get('method', '?')})")
        codes = read_image(read_blob(store, key, "provenance.png"), ".png")
        return png_bytes(provenance_rgb(np.rint(codes[..., 0]).astype(np.int64)))

    return Response(await run_in_threadpool(run), media_type="image/png",
                    headers={"Cache-Control": "private, max-age=31536000, immutable"})
