"""The render job: one reference render of a stored scene, written as a content-addressed artifact.

``render_job(payload) -> dict`` runs inside an RQ render worker (``rq.SimpleWorker``, so the
scene cache below stays warm across jobs):

1. validate the payload (:class:`RenderJobPayload`); a bad payload, a key that does not match
   the request, or a scene that is not stored fails the job at once (never retried);
2. if the artifact's manifest already exists (a retry after the commit, or a duplicate), return
   its result: jobs are at-least-once, artifacts are written once;
3. load the scene from the store (``get_scene`` + ``blob_reader`` + ``load_scene``) through the
   per-process :class:`RendererCache`, apply the request's camera; with an animation ``time`` the
   scene at that moment (``load_scene_at``: ``AnimatedScene.scene_at``, cached per scene and time);
4. render with a progress callback that saves ``job.meta["progress"]`` a few times per second
   and raises :class:`JobCanceled` once cancellation was requested (flag key or RQ status);
5. encode (:func:`encode_render_blobs`) ``preview.png`` (8-bit sRGB, exposure 0), ``radiance.exr``
   (float32, linear) and the AOVs ``depth.exr``, ``normal.exr``, ``object_id.exr``,
   ``material_id.exr`` (engine.imageio writes 1/3/4-channel images only, so each AOV is its own
   file; ids are stored as float32, exact below 2**24, -1 where nothing is hit), plus
   ``provenance.png`` for the LDC methods, each with ``ibr:`` metadata (camera, scene id and hash,
   render parameters, engine version) -- only those the request's ``outputs`` names when it names
   any (an interactive client asks for the preview alone; the subset is part of the artifact key);
   then write the blobs concurrently and the manifest LAST via
   ``write_artifact(..., max_workers=STORE_WRITERS)``.

A render that produces NaN/Inf raises ``engine.errors.NonFiniteOutputError`` before anything is
written: the job fails with that message and no manifest exists (docs/hard-cases.md #13). Images are
byte-deterministic (engine.imageio suppresses timestamps, the renderer is deterministic per
seed), so a re-run writes identical blobs under the same key.

Encoding is the main cost after the render itself (``bench/render_latency.py``): the images are
encoded in memory (``engine.imageio.encode_image``: no scratch-file fsync) on a small thread pool
(OpenImageIO and numpy release the GIL), the preview first, with lossless codecs picked per image
by measurement (:data:`EXR_COMPRESSION`, PNG ``fast``); the 8-bit sRGB transform is exact.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from collections.abc import Collection, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError
from rq import get_current_job

from api_schemas.service import RenderRequest, method_needs_bake
from engine import ENGINE_VERSION
from engine.errors import NonFiniteOutputError
from engine.imageio import encode_image
from engine.methods import parse_method
from engine.newviews.effects import analyze
from engine.newviews.renderer import LDCViewRenderer
from engine.reference import ReferenceParams
from producer.artifacts import read_manifest, write_artifact
from producer.bakes import bake_complete, bake_key
from producer.names import scene_bake_job_id
from producer.payloads import InvalidPayload, RenderJobPayload, describe_validation_error
from producer.renders import render_artifact_key, render_params
from producer.settings import get_settings
from producer.store import ObjectStore
from workers.cache import CachedBakeRenderer, RendererCache, runtime_scene_bytes
from workers.jobs.bake import BakeFailed, load_bake
from workers.jobs.common import (
    LOAD_END,
    RENDER_END,
    ProgressReporter,
    codes_png,
    dependency_note,
    fold_served,
    json_safe,
    load_stored_scene,
    worker_store,
)
from workers.scene_loader import camera_params

__all__ = [
    "AOV_BLOBS",
    "EXR_COMPRESSION",
    "NonFiniteOutputError",
    "OUTPUT_BLOBS",
    "encode_render_blobs",
    "render_job",
    "renderer_cache",
    "scene_cache_key",
]

EXR = "image/x-exr"
PNG = "image/png"
AOV_BLOBS = ("depth.exr", "normal.exr", "object_id.exr", "material_id.exr")
PROVENANCE_BLOB = "provenance.png"
"""LDC methods: 8-bit grey PNG whose pixel value IS the provenance code (not a brightness)."""
PROVENANCE_CODES = {0: "background", 1: "warped", 2: "hole-filled", 3: "gathered", 4: "traced"}

EXR_COMPRESSION = {"radiance.exr": "zip", "depth.exr": "zip", "normal.exr": "zip", "object_id.exr": "zip",
                   "material_id.exr": "zip"}
"""Lossless EXR codec per blob (engine.imageio.COMPRESSIONS), chosen by measurement on 512x512 LDC and
reference renders (``bench/render_latency.py``, docs/performance.md)."""
PNG_COMPRESSION = "fast"
"""zlib level 1 + 'sub' row filter for the PNGs: ~4x faster than libpng's default, files ~30 % larger."""
ENCODE_THREADS = 3
STORE_WRITERS = 4

_SCRATCH = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK | os.X_OK) else None

_cache: RendererCache | None = None


def renderer_cache() -> RendererCache:
    """This process's LRU of warm renderers (budget ``Settings.cache_bytes``)."""
    global _cache
    if _cache is None:
        _cache = RendererCache(get_settings().cache_bytes)
    return _cache


def set_renderer_cache(cache: RendererCache | None) -> RendererCache | None:
    """Replace this process's renderer cache (None: a fresh one on next use); returns the previous one
    (the warm-up renders into a scratch store with its own cache, then puts the worker's back)."""
    global _cache
    previous, _cache = _cache, cache
    return previous


OUTPUT_BLOBS = {"preview": "preview.png", "radiance": "radiance.exr", "depth": "depth.exr", "normal": "normal.exr",
                "object_id": "object_id.exr", "material_id": "material_id.exr", "provenance": PROVENANCE_BLOB}
"""``RenderRequest.outputs`` name -> the artifact blob it stands for."""


def encode_render_blobs(images: Mapping[str, Any], meta: dict[str, Any],
                        outputs: Collection[str] | None = None) -> dict[str, tuple[bytes, str]]:
    """The artifact's image blobs ``name -> (bytes, content type)`` of one render.

    ``images``: ``radiance`` (h, w, 3) float32, ``depth`` (h, w), ``normal`` (h, w, 3), ``object_id``
    and ``material_id`` (h, w) int, and for the LDC methods ``provenance`` (h, w) uint8 codes.
    ``meta`` goes into every image's ``ibr:`` metadata (plus ``exposure_stops`` for the preview and
    ``aov`` for the AOVs). ``outputs`` (``RenderRequest.outputs`` names, see :data:`OUTPUT_BLOBS`):
    encode only these; None: all of them (``provenance`` when ``images`` has it). Encoded
    concurrently on :data:`ENCODE_THREADS` threads, the preview first; the EXRs hold the render's
    float32 values bit for bit, the preview is ``rint(tonemap_srgb(radiance) * 255)`` exactly.
    NaN/Inf raise ``NonFiniteOutputError``.
    """
    if outputs is not None:
        unknown = sorted(set(outputs) - set(OUTPUT_BLOBS))
        if unknown or not outputs:
            raise ValueError(f"outputs {unknown or '[]'}: pick a non-empty subset of {sorted(OUTPUT_BLOBS)}")
        if "provenance" in outputs and images.get("provenance") is None:
            raise ValueError("outputs asks for 'provenance', which only the LDC methods produce")
    want = set(OUTPUT_BLOBS) if outputs is None else set(outputs)
    work: list[tuple[str, str, Any, dict[str, Any], str]] = [
        ("preview.png", PNG, images["radiance"], {**meta, "exposure_stops": 0.0}, PNG_COMPRESSION),
        ("radiance.exr", EXR, images["radiance"], meta, EXR_COMPRESSION["radiance.exr"]),
        ("normal.exr", EXR, images["normal"], {**meta, "aov": "normal"}, EXR_COMPRESSION["normal.exr"]),
        ("depth.exr", EXR, images["depth"], {**meta, "aov": "depth"}, EXR_COMPRESSION["depth.exr"]),
        ("object_id.exr", EXR, images["object_id"], {**meta, "aov": "object_id"}, EXR_COMPRESSION["object_id.exr"]),
        ("material_id.exr", EXR, images["material_id"], {**meta, "aov": "material_id"},
         EXR_COMPRESSION["material_id.exr"]),
    ]
    blob_names = {OUTPUT_BLOBS[o] for o in want}
    work = [w for w in work if w[0] in blob_names]
    provenance = images.get("provenance") if PROVENANCE_BLOB in blob_names else None

    def encode(name: str, pixels: Any, metadata: dict[str, Any], compression: str) -> bytes:
        if name.endswith("_id.exr"):
            pixels = np.asarray(pixels).astype(np.float32)  # exact below 2**24
        return encode_image(name, pixels, metadata=metadata, compression=compression)

    if len(work) + (provenance is not None) == 1 and work:  # one image: no pool
        name, ctype, px, md, comp = work[0]
        return {name: (encode(name, px, md, comp), ctype)}
    with ThreadPoolExecutor(ENCODE_THREADS, thread_name_prefix="ibr-encode") as pool:
        futures = {name: (pool.submit(encode, name, px, md, comp), ctype) for name, ctype, px, md, comp in work}
        if provenance is not None:
            futures[PROVENANCE_BLOB] = (pool.submit(_provenance_png, provenance), PNG)
        return {name: (f.result(), ctype) for name, (f, ctype) in futures.items()}


def render_job(payload: dict[str, Any]) -> dict[str, Any]:
    """Render one view of a stored scene and publish it as an artifact.

    Returns ``{"artifact_key", "timings", "counts", "mesh_reports"}``, plus ``adaptive`` for a
    progressive reference render (``max_error`` / ``max_ms``: ``engine.progressive.AdaptiveReport``,
    the estimated error, samples per pixel, passes and why it stopped), which the artifact's
    manifest keeps in its result and the images in their ``ibr:`` metadata.
    """
    t_start = time.perf_counter()
    try:
        p = RenderJobPayload.model_validate(payload)
    except ValidationError as exc:
        raise InvalidPayload(f"invalid render job payload: {describe_validation_error(exc)}") from None
    key = render_artifact_key(p.request)
    if key != p.artifact_key:
        raise InvalidPayload(f"artifact_key {p.artifact_key} does not match the request (expected {key})")

    store = worker_store()
    existing = read_manifest(store, key)
    if existing is not None:  # already published (retry after commit, or a duplicate run)
        keep = [k for k in ("timings", "counts", "mesh_reports", "adaptive") if k in existing.result or k != "adaptive"]
        return {"artifact_key": key, **{k: existing.result.get(k) for k in keep}}

    job = get_current_job()
    progress = ProgressReporter(job)
    progress.report(0.0, "loading scene", force=True)
    contract = p.contract.model_dump(mode="json") if p.contract is not None else None
    if method_needs_bake(p.request.method):
        return _render_from_bake(p.request, key, store, progress, t_start, contract)

    req = p.request
    t0 = time.perf_counter()
    entry, cache_hit = renderer_cache().get_or_load(
        scene_cache_key(req.scene_id, req.time), lambda: load_stored_scene(store, req.scene_id, req.time))
    t_load = time.perf_counter() - t0
    loaded = entry.loaded
    camera = camera_params(req.camera) if req.camera is not None else loaded.camera
    params = ReferenceParams(**req.params.model_dump())
    progress.report(LOAD_END, "render", force=True)

    t0 = time.perf_counter()
    out = entry.renderer.render(camera, params, progress)  # NonFiniteOutputError: nothing is written
    t_render = time.perf_counter() - t0

    progress.report(RENDER_END, "writing", force=True)
    t0 = time.perf_counter()
    meta: dict[str, Any] = {
        "camera": camera.to_dict(),
        "scene_id": req.scene_id,
        "scene_hash": loaded.scene_hash,
        "method": req.method,
        "render_params": params.to_dict(),
        "engine_version": ENGINE_VERSION,
        "artifact_key": key,
    }
    if req.time is not None:  # an animated scene at that moment
        meta["time"] = req.time
    if out.adaptive is not None:  # a progressive render: its estimated error travels with its images
        meta["adaptive"] = out.adaptive
    blobs = encode_render_blobs({"radiance": out.radiance, "depth": out.depth, "normal": out.normal,
                                 "object_id": out.object_id, "material_id": out.material_id}, meta, req.outputs)
    progress.check_canceled()  # last chance before the commit
    timings = {**out.timings, "render_wall": t_render, "load_scene": t_load, "encode": time.perf_counter() - t0}
    counts = {**out.counts, "scene_cache_hit": int(cache_hit), "width": camera.width, "height": camera.height}
    doc: dict[str, Any] = {"timings": timings, "counts": counts, "mesh_reports": loaded.mesh_reports,
                           **_contract_result(contract, t_render, out.adaptive)}
    if out.adaptive is not None:
        doc["adaptive"] = out.adaptive
    result = json_safe(doc)
    t0 = time.perf_counter()
    write_artifact(store, key, "render", {"scene": req.scene_id}, render_params(req), ENGINE_VERSION, blobs, result,
                   max_workers=STORE_WRITERS)
    result["timings"]["store"] = time.perf_counter() - t0
    result["timings"]["job_total"] = time.perf_counter() - t_start
    _record_served(store, req.scene_id, result)
    progress.report(1.0, "done", force=True, check=False)  # committed: too late to cancel
    return {"artifact_key": key, **result}


def scene_cache_key(scene_id: str, time: float | None) -> str:
    """The renderer cache's key of a scene as stored (its id) or at animation time ``time`` (a runtime
    scene, and an Embree BVH, of its own per moment)."""
    return scene_id if time is None else f"{scene_id}@t={time!r}"


# ------------------------------------------------------------------------------------ LDC methods


class BakeUnavailable(RuntimeError):
    """The render's bake is missing or failed: the message says which and what to do."""


def _provenance_png(codes: Any) -> bytes:
    """Exact codes in an 8-bit single-channel PNG (OpenImageIO, no sRGB encoding), encoded in a
    RAM-backed scratch directory when there is one (no fsync: the file is not kept)."""
    with tempfile.TemporaryDirectory(prefix="ibr-render-", dir=_SCRATCH) as tmpdir:
        return codes_png(Path(tmpdir) / PROVENANCE_BLOB, codes,
                         {"DateTime": "", "ibr:provenance_codes": json.dumps(PROVENANCE_CODES),
                          "png:compressionLevel": 1, "png:filter": 16})


def _bake_error(store: ObjectStore, req: RenderRequest, bkey: str) -> str:
    why = dependency_note(scene_bake_job_id(bkey))
    return (f"bake {bkey} of scene {req.scene_id} is not available{why}; request it with POST "
            f"/v1/scenes/{req.scene_id}/bakes and render again")


def _load_bake_renderer(store: ObjectStore, req: RenderRequest, bkey: str) -> CachedBakeRenderer:
    if not bake_complete(store, bkey):
        raise BakeUnavailable(_bake_error(store, req, bkey))
    loaded = load_stored_scene(store, req.scene_id)
    try:
        ldc, llf, plan = load_bake(store, loaded.runtime, bkey)
    except BakeFailed as exc:
        raise BakeUnavailable(str(exc)) from None
    renderer = LDCViewRenderer(loaded.runtime, ldc, llf, analyze(loaded.runtime),
                               area_light_samples=req.bake.area_light_samples, seed=req.bake.seed)
    return CachedBakeRenderer(loaded=loaded, renderer=renderer, bake_key=bkey, plan=plan)


def _record_served(store: ObjectStore, scene_id: str, result: Mapping[str, Any]) -> None:
    """Fold a contract render's achieved time into its calibration's corrections
    (:func:`workers.jobs.common.fold_served`), unless an adaptive render was stopped by its time
    budget (its time then says what it was told, not what the setting costs)."""
    contract = result.get("contract")
    if not contract or (result.get("adaptive") or {}).get("stop_reason") == "time":
        return
    fold_served(store, scene_id, contract, achieved_ms=float(contract["achieved_ms"]))


def _contract_result(contract: dict[str, Any] | None, t_render: float,
                     adaptive: dict[str, Any] | None = None) -> dict[str, Any]:
    """``{"contract": ...}`` with the achieved time for a request planned from a quality contract, and
    for the adaptive reference the estimated achieved error (its estimate times the calibrated scale)."""
    if contract is None:
        return {}
    out = {**contract, "achieved_ms": 1000.0 * t_render}
    scale = contract.get("error_scale")
    if contract.get("estimated_error_source") == "render" and adaptive is not None and scale is not None:
        out["estimated_error"] = float(scale) * float(adaptive["estimated_error"])
    return {"contract": out}


def _render_from_bake(req: RenderRequest, key: str, store: ObjectStore, progress: ProgressReporter,
                      t_start: float, contract: dict[str, Any] | None = None) -> dict[str, Any]:
    """``ldc``, ``ldc+llf``, ``ldc+ibrt:k``: render from the scene's bake (LDC + LLF) with
    ``engine.newviews.renderer.LDCViewRenderer``, cached per bake in this worker."""
    bkey = bake_key(req.scene_id, req.bake)
    t0 = time.perf_counter()
    entry, cache_hit = renderer_cache().get_or_load_bake(bkey, lambda: _load_bake_renderer(store, req, bkey))
    t_load = time.perf_counter() - t0
    loaded = entry.loaded
    camera = camera_params(req.camera) if req.camera is not None else loaded.camera
    if entry.renderer.llf is None and parse_method(req.method).gathers and entry.renderer.plan.needs_llf:
        raise BakeUnavailable(f"method {req.method} needs the light field, but bake {bkey} has none "
                              f"(baked with llf={req.bake.llf!r}); bake with llf 'auto' or 'always'")
    progress.report(LOAD_END, "render", force=True)
    t0 = time.perf_counter()
    out = entry.renderer.render(camera, req.method, progress=progress, supersample=req.view.supersample,
                                antialias=req.view.antialias, glossy_rays=req.view.glossy_rays,
                                glossy_filter=req.view.glossy_filter)
    t_render = time.perf_counter() - t0
    renderer_cache().resize(f"bake:{bkey}", runtime_scene_bytes(loaded.runtime) + int(entry.renderer.nbytes))
    progress.report(RENDER_END, "writing", force=True)
    t0 = time.perf_counter()
    meta: dict[str, Any] = {"camera": camera.to_dict(), "scene_id": req.scene_id, "scene_hash": loaded.scene_hash,
                            "method": req.method, "view": req.view.model_dump(mode="json"), "bake_key": bkey,
                            "engine_version": ENGINE_VERSION, "artifact_key": key}
    blobs = encode_render_blobs({"radiance": out.radiance, "depth": out.depth, "normal": out.normal,
                                 "object_id": out.object_id, "material_id": out.material_id,
                                 "provenance": out.provenance}, meta, req.outputs)
    progress.check_canceled()
    prov = np.bincount(np.asarray(out.provenance, dtype=np.int64).ravel(), minlength=5)
    timings = {**out.timings, "render_wall": t_render, "load_bake": t_load, "encode": time.perf_counter() - t0}
    counts = {**out.counts, "hole_pixels": int(np.count_nonzero(out.hole_mask)),
              "provenance": {PROVENANCE_CODES[i]: int(prov[i]) for i in range(5)},
              "bake_cache_hit": int(cache_hit), "width": camera.width, "height": camera.height}
    result = json_safe({"timings": timings, "counts": counts, "plan": out.plan, "bake_key": bkey,
                         "mesh_reports": loaded.mesh_reports, **_contract_result(contract, t_render)})
    t0 = time.perf_counter()
    write_artifact(store, key, "render", {"scene": req.scene_id}, render_params(req), ENGINE_VERSION, blobs, result,
                   max_workers=STORE_WRITERS)
    result["timings"]["store"] = time.perf_counter() - t0
    result["timings"]["job_total"] = time.perf_counter() - t_start
    _record_served(store, req.scene_id, result)
    progress.report(1.0, "done", force=True, check=False)
    return {"artifact_key": key, **result}
