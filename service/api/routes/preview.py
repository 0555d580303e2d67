"""The browser preview page: static files at ``/preview/``, ``/`` redirects there,
plus the few API endpoints only the page needs (``/v1/preview/...``).

No build step: ``service/static/{index.html,app.js,app.css}`` are served as they are.
``/preview/sample-cameras.json`` lists the shipped sample scenes' cameras by scene name,
because the API stores scenes without offering their JSON back: the page starts a sample
scene from its own camera and any other scene from a default camera (see the page's help).

``/v1/preview/capabilities`` tells the page what this API can do: the render methods of the
registry ``engine.methods`` (the one the request model validates with: name, generations, bake,
cost) and which resources are routed (bakes, datasets, relights, walkthroughs). LDC methods are
offered only when the scene bake routes exist too: without them no bake can be made or watched.

``/v1/preview/compare`` computes the LRMS of one render artifact against another (the
difference view) and ``/v1/preview/compare/heatmap.png`` its false-colour error map;
``/v1/preview/artifacts/{key}/image.png?exposure=`` re-exposes a render from its linear
``radiance.exr``; ``/v1/preview/artifacts/{key}/provenance.png`` colours the LDC methods'
provenance codes. The images are decoded and measured by ``engine.imageio`` and ``engine.metrics``
(numpy + OpenImageIO; neither imports numba, which this process never loads).
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
from typing import Annotated, Any, Literal, get_args

import numpy as np
from fastapi import APIRouter, HTTPException, Query, Request, Response
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, JSONResponse, RedirectResponse

from api_schemas.common import FrozenModel
from api_schemas.errors import FieldError
from api_schemas.service import ArtifactManifest, Sha256
from engine.imageio import decode_image, encode_display
from engine.methods import METHODS, BakePart
from engine.metrics import error_heatmap_display, fraction_over, lrms, luminance
from producer.artifacts import read_blob, read_manifest
from producer.names import GENERATE_KIND, RELIGHT_KIND
from producer.ownership import dataset_visible
from producer.store import NotFound, ObjectStore
from producer.walkthroughs import chunk_key, chunks, read_request
from service.api.deps import OwnerDep, StoreDep, scene_visible
from service.api.errors import LacksPart, MissingResource, ValidationProblem, problem_responses

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

class ParamInfo(FrozenModel):
    """A setting of the request's ``params`` for a method: an integer in ``[low, high]``, or (``kind``
    "float") a number between ``low`` and ``high``, a bound excluded when ``low_open`` / ``high_open``;
    ``default`` None: not set unless given."""

    name: str
    default: int | float | None
    low: int | float
    high: int | float
    doc: str
    kind: Literal["int", "float"] = "int"
    low_open: bool = False
    high_open: bool = False


class MethodInfo(FrozenModel):
    name: str
    """``reference``, ``ldc``, ``ldc+llf`` or ``ldc+ibrt`` (then ``k`` picks the generations)."""
    needs_bake: bool
    k: list[int] = []
    """For ``ldc+ibrt``: the generation counts the API accepts (sent as ``ldc+ibrt:<k>``)."""
    k_default: int | None = None
    """For ``ldc+ibrt``: the generation count to offer first."""
    bake: list[BakePart] = []
    """The bake parts the method renders from (``LDC``, ``LLF``)."""
    params: list[ParamInfo] = []
    """The settings of the request's ``params`` (``reference``: spp, max_depth, ...)."""
    summary: str = ""
    cost: str = ""
    """What the render time grows with."""


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
    """When walkthroughs are routed: the values the walkthrough request accepts for ``quality`` and ``fill``,
    and ``path_noise``, the noise targets of path-traced frames a walkthrough calibration measures by
    default (``path_traced.noise`` takes any in its range)."""
    provenance: dict[int, tuple[str, str]] = {}
    """Provenance code -> (name, CSS colour) of ``/v1/preview/artifacts/{key}/provenance.png``."""
    paths: list[str] = []
    """The ``/v1`` paths of the app's OpenAPI document the flags above were read from."""


@lru_cache(maxsize=1)
def _walkthrough_options() -> dict[str, list[str]]:
    """``quality`` and ``fill`` choices of the walkthrough request model, and the calibration's default
    ``path_noises`` (empty without the models)."""
    try:
        from api_schemas.walkthrough import WalkthroughCalibrationParams, WalkthroughRequest, WalkthroughSettings
    except ImportError:
        return {}
    out: dict[str, list[str]] = {}
    for name, model, field in (("quality", WalkthroughSettings, "quality"), ("fill", WalkthroughRequest, "fill")):
        info = model.model_fields.get(field)
        values = [str(v) for v in get_args(info.annotation)] if info is not None else []
        if values:
            out[name] = values
    out["path_noise"] = [f"{n:g}" for n in WalkthroughCalibrationParams().path_noises]
    return out


def capabilities_of(paths: list[str]) -> Capabilities:
    """Capabilities given the app's routed paths (the render methods come from the registry)."""
    bakes = any(p.startswith("/v1/scenes/{scene_id}/bakes") for p in paths)
    walkthroughs = "/v1/walkthroughs" in paths and any(p.startswith("/v1/walkthroughs/{key}/frames") for p in paths)
    methods = [MethodInfo(name=m.name, needs_bake=m.needs_bake,
                          k=list(range(int(m.arg.low), int(m.arg.high) + 1)) if m.arg is not None else [],
                          k_default=int(m.arg.default) if m.arg is not None and m.arg.default is not None
                          else None,
                          bake=list(m.bake), summary=m.summary, cost=m.cost,
                          params=[ParamInfo(name=p.name, default=p.default, low=p.low, high=p.high, doc=p.doc,
                                            kind=p.kind, low_open=p.low_open, high_open=p.high_open)
                                  for p in m.params])
               for m in METHODS if bakes or not m.needs_bake]
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
    """Render methods the API accepts (the registry the request model validates with) and the resources it
    routes (read from the app's OpenAPI document)."""
    # the OpenAPI document lists every routed path (app.routes may hold lazily included routers)
    paths = sorted(p for p in request.app.openapi().get("paths", {}) if p.startswith("/v1/"))
    return capabilities_of(paths)


# ------------------------------------------------------------------------------ images (numpy + OpenImageIO)


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


def to_srgb8(linear: np.ndarray, exposure_stops: float) -> np.ndarray:
    """The 8-bit samples the engine's PNG writer stores for ``linear`` at an exposure
    (``engine.imageio.encode_display``: ``rint(255 srgb_encode(clip(x 2^e, 0, 1)))``, straight alpha)."""
    out: np.ndarray = encode_display(linear, exposure_stops, 255).astype(np.uint8)
    return out


def coverage_mask(ref: np.ndarray) -> np.ndarray:
    """The reference's covered pixels: alpha > 0 for 4 channels, else every pixel."""
    if ref.shape[2] == 4:
        mask: np.ndarray = ref[..., 3] > 0
        return mask
    return np.ones(ref.shape[:2], dtype=bool)


def heatmap(test: np.ndarray, ref: np.ndarray, mask: np.ndarray, scale: float | None = None) -> np.ndarray:
    """``engine.metrics.error_heatmap`` (viridis of ``|Y_test - Y_ref| / scale``, black outside ``mask``)
    as 8-bit display colours."""
    out: np.ndarray = np.rint(error_heatmap_display(test, ref, scale=scale, mask=mask) * 255.0).astype(np.uint8)
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
        img: np.ndarray = decode_image(blob, read_blob(store, key, blob))[0]  # ChecksumMismatch -> 404 corrupt
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


TestKey = Annotated[Sha256, Query(description="Key of the image to judge: a render's artifact key, a relight's "
                                  "artifact key (test_kind=relight) or a walkthrough's key (test_kind=walkthrough)")]
RefKey = Annotated[Sha256, Query(description="Key of the reference: a render's artifact key, or a dataset "
                                 "generation's key (ref_kind=ground_truth)")]
TestKind = Annotated[Literal["render", "relight", "walkthrough"], Query(
    description="render: the artifact's radiance.exr; relight: the relit image.exr; walkthrough: frame `frame`'s EXR")]
Frame = Annotated[int | None, Query(ge=0, le=100_000, description="Walkthrough frame index (test_kind=walkthrough)")]
RefKind = Annotated[Literal["render", "ground_truth"], Query(
    description="render: the artifact's radiance.exr; ground_truth: the sum of a dataset generation's ground-truth "
                "renders (one per light: the reference of a relight under those lights together)")]
RefLights = Annotated[str | None, Query(pattern=r"^[0-9]{1,2}(,[0-9]{1,2}){0,63}$",
                                        description="Ground-truth images to sum, e.g. 0,1 (default: all)")]


def _test_image(store: ObjectStore, owner: str | None, key: str, kind: str, frame: int | None) -> np.ndarray:
    field = "query.test"
    if kind == "render":
        visible_render(store, key, owner, field)
        return RADIANCE.get(store, key)
    if kind == "relight":
        manifest = read_manifest(store, key)
        did = manifest.inputs.get("dataset") if manifest is not None and manifest.kind == RELIGHT_KIND else None
        if did is None or (owner is not None and not dataset_visible(store, did, owner)):
            raise MissingResource(field, key)
        return RADIANCE.get(store, key)  # the relit image.exr is stored as radiance.exr
    req = read_request(store, key)
    if req is None or not scene_visible(store, req.scene_id, owner):
        raise MissingResource(field, key)
    if frame is None or not 0 <= frame < len(req.frames):
        raise ValidationProblem([FieldError(field="query.frame", type="frame_index", message=(
            f"give the frame index, in [0, {len(req.frames) - 1}]" if frame is None
            else f"frame index {frame} is outside [0, {len(req.frames) - 1}]"))])
    for i, (a, b) in enumerate(chunks(req)):
        if a <= frame < b:
            return RADIANCE.get(store, chunk_key(key, i, a, b), f"frame_{frame:05d}.exr")
    raise NotFound(key)  # pragma: no cover - chunks cover every index


def _ref_image(store: ObjectStore, owner: str | None, key: str, kind: str, lights: str | None) -> np.ndarray:
    field = "query.ref"
    if kind == "render":
        visible_render(store, key, owner, field)
        return RADIANCE.get(store, key)
    manifest = read_manifest(store, key)
    if manifest is None or manifest.kind != GENERATE_KIND or (
            owner is not None and not scene_visible(store, manifest.inputs.get("scene", ""), owner)):
        raise MissingResource(field, key)
    have = sorted(b.name for b in manifest.blobs if b.name.startswith("ground_truth_"))
    names = have if lights is None else [f"ground_truth_{int(i)}.exr" for i in lights.split(",")]
    missing = [n for n in names if n not in have]
    if missing or not names:
        raise ValidationProblem([FieldError(field="query.ref_lights", type="no_ground_truth", message=(
            f"generation {key} has no {', '.join(missing)}" if missing else f"generation {key} has no ground truth"))])
    total: np.ndarray | None = None
    for n in dict.fromkeys(names):  # each light once
        img = RADIANCE.get(store, key, n)[..., :3].astype(np.float64)
        total = img if total is None else total + img
    assert total is not None
    return total.astype(np.float32)


def _pair(store: ObjectStore, owner: str | None, test: str, ref: str, test_kind: str = "render",
          frame: int | None = None, ref_kind: str = "render", ref_lights: str | None = None
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = _test_image(store, owner, test, test_kind, frame)
    r = _ref_image(store, owner, ref, ref_kind, ref_lights)
    if t.shape[:2] != r.shape[:2]:
        raise ValidationProblem([FieldError(
            field="query.test", message=f"image is {t.shape[1]} x {t.shape[0]} but the reference is "
            f"{r.shape[1]} x {r.shape[0]}: compare renders of the same size", type="size_mismatch")])
    mask = coverage_mask(r)
    if not mask.any():
        raise ValidationProblem([FieldError(field="query.ref", message="the reference covers no pixel",
                                            type="empty_mask")])
    return t, r, mask


def _compare(store: ObjectStore, owner: str | None, test: str, ref: str, test_kind: str = "render",
             frame: int | None = None, ref_kind: str = "render", ref_lights: str | None = None) -> Comparison:
    t, r, mask = _pair(store, owner, test, ref, test_kind, frame, ref_kind, ref_lights)
    lum_t, lum_r = luminance(t), luminance(r)  # the metrics of a luminance image are those of the image
    y_t, y_r = lum_t[mask], lum_r[mask]
    value = lrms(lum_t, lum_r, mask)
    query = f"test={test}&ref={ref}"
    if test_kind != "render":
        query += f"&test_kind={test_kind}" + (f"&frame={frame}" if frame is not None else "")
    if ref_kind != "render":
        query += f"&ref_kind={ref_kind}" + (f"&ref_lights={ref_lights}" if ref_lights is not None else "")
    return Comparison(
        test=test, ref=ref, lrms=value if math.isfinite(value) else None,
        rms=math.sqrt(float(np.mean(np.square(y_t - y_r)))), mean_ref_luminance=float(np.mean(y_r)),
        fraction_over_5pct=fraction_over(lum_t, lum_r, 0.05, mask),
        n_pixels=int(y_r.size), width=int(r.shape[1]), height=int(r.shape[0]),
        links={"heatmap": f"/v1/preview/compare/heatmap.png?{query}"},
    )


_ERRORS = problem_responses(401, 404, 422, 429, 503)
_PNG: dict[int | str, dict[str, Any]] = {
    200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}}}, "description": "PNG"}}


@router.get("/v1/preview/compare", response_model=Comparison, tags=["preview"], responses=_ERRORS)
async def compare(store: StoreDep, owner: OwnerDep, test: TestKey, ref: RefKey, test_kind: TestKind = "render",
                  frame: Frame = None, ref_kind: RefKind = "render", ref_lights: RefLights = None) -> Comparison:
    """LRMS of image ``test`` (a render, a relit image or a walkthrough frame) against reference ``ref`` (a
    render, or the ground truth of a generated dataset under the relight's lights)."""
    return await run_in_threadpool(_compare, store, owner, test, ref, test_kind, frame, ref_kind, ref_lights)


@router.get("/v1/preview/compare/heatmap.png", response_class=Response, tags=["preview"],
            responses={**_PNG, **_ERRORS})
async def compare_heatmap(
    store: StoreDep, owner: OwnerDep, test: TestKey, ref: RefKey, test_kind: TestKind = "render",
    frame: Frame = None, ref_kind: RefKind = "render", ref_lights: RefLights = None,
    scale: Annotated[float | None, Query(gt=0, le=1e30, description="Error shown at full scale (default: the "
                                         "mean reference luminance, so yellow = 100 % relative error)")] = None,
) -> Response:
    """False-colour map of the luminance error of ``test`` against ``ref`` (viridis, black outside coverage)."""
    def run() -> bytes:
        t, r, mask = _pair(store, owner, test, ref, test_kind, frame, ref_kind, ref_lights)
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


@router.get("/v1/preview/reference.png", response_class=Response, tags=["preview"], responses={**_PNG, **_ERRORS})
async def reference_image(
    store: StoreDep, owner: OwnerDep, ref: RefKey, ref_kind: RefKind = "render", ref_lights: RefLights = None,
    exposure: Annotated[float, Query(ge=-30, le=30, allow_inf_nan=False,
                                     description="Exposure in stops applied to the linear radiance")] = 0.0,
) -> Response:
    """A reference as an sRGB PNG at an exposure: a render's radiance, or the summed ground truth of a
    generated dataset (what ``/v1/preview/compare`` compares with)."""
    def run() -> bytes:
        return png_bytes(to_srgb8(_ref_image(store, owner, ref, ref_kind, ref_lights), exposure))

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
            raise LacksPart(f"artifact {key} has no provenance (method {manifest.params.get('method', '?')})")
        # linear: the 8-bit values are codes, not colours (read back as code / 255)
        codes = decode_image("provenance.png", read_blob(store, key, "provenance.png"), transfer="linear")[0]
        return png_bytes(provenance_rgb(np.rint(codes[..., 0] * 255.0).astype(np.int64)))

    return Response(await run_in_threadpool(run), media_type="image/png",
                    headers={"Cache-Control": "private, max-age=31536000, immutable"})
