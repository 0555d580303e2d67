"""Bake jobs on the ``bake`` queue: plan, parts (LDC axes, their indirect chunks, LLF direction chunks) and merge.

See ``producer/bakes.py`` for the keys, the job graph and the store layout. Every job validates its
payload, recomputes the keys it was given (a payload cannot make a worker publish under another
request's key), reads the store URL from the worker's own settings, reports progress in
``job.meta["progress"]`` and honours cancellation between stages.

Parts are stored as ``npz`` blobs (``npz_bytes``: ``np.load`` reads them, no pickle) of the engine's
``to_arrays()``: ``ldc_axis.npz`` for an LDC axis (direct light), ``ldc_indirect.npz`` for a chunk
of an axis's indirect light (``IndirectResult.to_arrays``), ``llf_views.npz`` (views prefixed
``v<index>_``) for an LLF chunk. The same part baked twice stores the same bytes: the blobs hold no
wall-clock time (no zip member dates, no timings), which go to the part's manifest ``result``.

Estimates (the plan job, before anything is baked; refused over ``Settings.max_bake_part_bytes`` /
``Settings.max_bake_cpu_s`` with the estimate in the message):

- memory per job: an LDC axis at its worst case (every pixel full to ``max_layers``); an indirect
  chunk holds that axis plus its path-tracing batch, ``min(MAX_RAYS_PER_BATCH, sides x round_paths)``
  rays of ``INDIRECT_RAY_BYTES`` each (measured: a batch of 2^20 rays raised the peak RSS by
  ~560 MiB), or its caustic photon map's ``CAUSTIC_BYTES_PER_PHOTON`` per photon if more; an LLF
  chunk as ``estimate_llf_bytes``;
- CPU time, dominated by the indirect pass: expected LDC samples (each triangle's area projected on
  the axis / pixel area: the rays of an axis's grid that cross it, capped at ``max_layers`` per
  pixel) x 2 sides x expected paths per side (``engine.newviews.indirect_sampling``: the fixed
  sampler's count; the adaptive sampler's ``min_paths + 20 %`` of the way to ``max_paths``, 118-122
  measured on the Cornell box at noise 0.02; divided by ``stride^2``, the share of sides traced)
  / ``Settings.bake_paths_per_s`` (scaled by ``4 / (bounces + 1)``, the rate being measured at 3
  bounces), plus the light field's indirect paths when it has them, plus a caustic photon map
  per indirect chunk job in a scene with caustics (``CAUSTIC_CPU_S_PER_PHOTON``).
"""

from __future__ import annotations

import importlib
import io
import json
import time
import zipfile
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

import numpy as np
from pydantic import BaseModel, ValidationError
from redis import Redis
from rq import get_current_job

from api_schemas.service import BakeParams
from engine import ENGINE_VERSION
from engine.caustics import has_caustics
from engine.errors import InvalidInputError
from engine.newviews.effects import EffectPlan, analyze
from engine.newviews.indirect import MAX_RAYS_PER_BATCH, IndirectParams, IndirectResult
from engine.newviews.indirect_sampling import fixed_paths
from engine.newviews.ldc import (
    LDC_ATTR_BYTES,
    LDCAxis,
    bake_ldc_axis,
    indirect_chunk,
    ldc_pixel_size,
    merge_ldc,
    with_indirect,
)
from engine.newviews.ldi import LDI_SAMPLE_BYTES, axis_frame, estimate_ldi_bytes
from engine.newviews.llf import LLFView, bake_llf_views, estimate_llf_bytes, llf_params_dict, merge_llf
from engine.raycast import make_caster
from engine.reference import ReferenceParams
from engine.scene import RuntimeScene
from producer.artifacts import manifest_key, read_blob, read_manifest, write_artifact
from producer.bakes import (
    BAKE_MAX_TOTAL_BYTES,
    bake_complete,
    bake_key,
    enqueue_parts,
    llf_direction_count,
    part_key,
    part_weight,
    plan_parts,
)
from producer.costs import duration_text, expected_paths
from producer.names import scene_bake_part_job_id, scene_bake_plan_job_id
from producer.payloads import InvalidPayload, SceneBakeJobPayload, SceneBakePartJobPayload, describe_validation_error
from producer.queue import fetch_job, redis_from_url
from producer.settings import get_settings
from producer.status import job_public
from producer.store import ChecksumMismatch, NotFound, ObjectStore
from workers.jobs.common import ProgressReporter, json_safe, load_stored_scene, worker_store
from workers.scene_loader import LoadedScene

__all__ = [
    "PRELOAD_MODULES",
    "BakeFailed",
    "BakeTooLarge",
    "bake_ldc_axis_job",
    "bake_ldc_indirect_job",
    "bake_llf_views_job",
    "bake_merge_job",
    "bake_plan_job",
    "load_bake",
    "npz_bytes",
    "preload_modules",
    "read_npz",
]

NPZ = "application/x-npz"
M = TypeVar("M", bound=BaseModel)


class BakeFailed(RuntimeError):
    """A bake cannot be completed (planning failed, a part is missing or inconsistent)."""


class BakeTooLarge(InvalidInputError):
    """The memory estimate of a part is over the limit: refused before baking."""


# ------------------------------------------------------------------------------------ helpers

PRELOAD_MODULES = (
    "trimesh", "trimesh.exchange.ply", "trimesh.resolvers", "scipy.sparse.csgraph",
)
"""Modules the engine and the scene loader import lazily (mesh loading, Embree), beyond what this
module imports itself: imported once by the bake worker's parent so every forked horse has them
(~0.7 s per job otherwise)."""


def preload_modules() -> None:
    """Import -- never run -- what the bake jobs need (see ``workers/runner.py``: no numba kernel
    and no Embree device may exist in the parent before it forks)."""
    for name in PRELOAD_MODULES:
        try:
            importlib.import_module(name)
        except ImportError:  # an optional format library; the job reports it if it needs it
            pass



_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


def npz_bytes(arrays: Mapping[str, np.ndarray]) -> bytes:
    """The arrays as an ``.npz`` (what ``np.savez`` writes, read by ``np.load``), byte for byte the
    same for the same arrays: ``np.savez`` stamps each member with the current time, so the same
    part baked twice would differ; here every member carries the zip epoch instead."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, value in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_EPOCH)
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asarray(value), allow_pickle=False)
    return buf.getvalue()


def read_npz(data: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _validate(model: type[M], payload: dict[str, Any]) -> M:
    try:
        return model.model_validate(payload)
    except ValidationError as exc:
        raise InvalidPayload(f"invalid bake job payload: {describe_validation_error(exc)}") from None


def _check_bake(p: SceneBakeJobPayload) -> None:
    expected = bake_key(p.scene_id, p.params)
    if expected != p.bake_key:
        raise InvalidPayload(f"bake_key {p.bake_key} does not match the request (expected {expected})")


def _redis() -> Redis:
    job = get_current_job()
    if job is not None:
        return job.connection
    return redis_from_url(get_settings().effective_redis_url)


def _owner() -> str | None:
    job = get_current_job()
    owner = job.meta.get("owner") if job is not None else None
    return owner if isinstance(owner, str) else None


INDIRECT_RAY_BYTES = 576
"""Working memory per path of an indirect batch (measured ~560 B: 2^20 paths raised the peak RSS of
an indirect chunk of the Cornell box by ~560 MiB)."""
PATHS_RATE_BOUNCES = 3
"""``Settings.bake_paths_per_s`` is measured at this many bounces."""
CAUSTIC_CPU_S_PER_PHOTON = 1.0e-6
"""The caustic photon map that every indirect chunk job of a scene with caustics builds
(``engine/caustics.py``): CPU per photon, tracing and indexing (measured 0.76 CPU s, 0.68 s of wall
time, per million photons on the mirror / glossy Cornell box, warm)."""
CAUSTIC_BYTES_PER_PHOTON = 400
"""The map's working memory per photon while it is built (rays, hits, stored photons, its index;
measured: a 132 MiB peak of numpy memory for a million photons on the mirror / glossy Cornell box,
tracemalloc; the rest is room for scenes that store more of them)."""


def indirect_params(params: BakeParams) -> IndirectParams | None:
    """The engine's settings of the indirect pass, None for ``mode="off"``. The sampler seed is the
    bake's; light sampling and mirror / glossy depth at path vertices are the engine's defaults."""
    ip = params.indirect
    if ip.mode == "off":
        return None
    return IndirectParams(noise=ip.noise, sampling=ip.sampling, min_paths=ip.min_paths, max_paths=ip.max_paths,
                          bounces=ip.bounces, round_paths=ip.round_paths, stride=ip.stride, seed=params.seed,
                          caustics=ip.caustics, caustic_photons=ip.caustic_photons, caustic_radius=ip.caustic_radius)


def bakes_indirect(params: BakeParams, plan: EffectPlan) -> bool:
    """Does this bake path-trace indirect light? ``auto``: when the effect plan says it can arrive."""
    return params.indirect.mode == "auto" and not plan.indirect_skip


def llf_indirect_samples(params: BakeParams, plan_doc: Mapping[str, Any]) -> int:
    """Indirect paths per LLF sample: ``min_paths`` when the bake has indirect light (the LLF is
    rendered by the reference renderer's ``shade_hits`` with a fixed count per sample: the fewest
    paths an LDC sample side traces), else 0."""
    ind = plan_doc.get("indirect") or {}
    return params.indirect.min_paths if ind.get("state") in ("planned", "baked") else 0


def bakes_llf(params: BakeParams, plan: EffectPlan) -> bool:
    """Does this bake include the light field? ``auto``: when the scene has glossy or mirror surfaces."""
    return params.llf == "always" or (params.llf == "auto" and plan.needs_llf)


def bake_plan_doc(scene: RuntimeScene, params: BakeParams, plan: EffectPlan) -> dict[str, Any]:
    """The bake's ``plan.json``: the effect plan plus what this bake stores (light field or not and
    why, its direction count, visibility words per sample). The plan job writes it; the merge job
    publishes it with the manifest."""
    with_llf = bakes_llf(params, plan)
    ip = params.indirect
    if bakes_indirect(params, plan):
        indirect: dict[str, Any] = {"state": "planned", "reason": "the effect plan says indirect light can arrive"}
    elif ip.mode == "off":
        indirect = {"state": "off", "reason": "indirect.mode=off: direct light only"}
    else:
        indirect = {"state": "skipped", "reason": plan.indirect_skip}
    indirect |= {"mode": ip.mode, "chunks_per_axis": ip.chunks if indirect["state"] == "planned" else 0,
                 "sampling": ip.sampling, "noise_target": ip.noise, "min_paths": ip.min_paths,
                 "max_paths": ip.max_paths,
                 "bounces": ip.bounces, "stride": ip.stride, "caustics": ip.caustics,
                 "llf_indirect_samples": ip.min_paths if indirect["state"] == "planned" and with_llf else 0}
    return {**plan.to_dict(), "indirect": indirect, "bake_llf": with_llf, "llf_mode": params.llf,
            "llf_directions": llf_direction_count(params.llf_f) if with_llf else 0,
            "visibility_words": (scene.lights.count + 63) // 64 if plan.any_occludable else 0,
            "reason": ("light field forced by llf=always" if params.llf == "always" and not plan.needs_llf
                       else "glossy or mirror materials need the light field" if with_llf
                       else "llf=never" if params.llf == "never" and plan.needs_llf
                       else "no glossy or mirror materials: no light field")}


def _ldc_axis_bytes(scene: RuntimeScene, params: BakeParams, words: int) -> list[int]:
    h = ldc_pixel_size(scene, params.ldc_resolution)
    lo, hi = scene.bounds
    per = LDI_SAMPLE_BYTES + LDC_ATTR_BYTES + 16 * words
    return [estimate_ldi_bytes(axis_frame(lo, hi, a, h).n_pixels, params.max_layers, per) for a in range(3)]


def expected_ldc_samples(scene: RuntimeScene, params: BakeParams) -> tuple[list[int], list[int]]:
    """Expected samples per LDC axis, all and those on materials that receive indirect light
    (kd > 0): each triangle is crossed by ``|n . axis| area / h^2`` rays of the axis's pixel grid;
    capped at ``max_layers`` per pixel."""
    h = ldc_pixel_size(scene, params.ldc_resolution)
    lo, hi = scene.bounds
    e1 = scene.tri_p[:, 1] - scene.tri_p[:, 0]
    e2 = scene.tri_p[:, 2] - scene.tri_p[:, 0]
    proj = np.abs(np.cross(e1, e2)) * 0.5 / (h * h)  # (nt, 3): projected area / pixel area per axis
    receives = np.any(scene.materials.kd[scene.tri_material] > 0.0, axis=1)
    out_all, out_recv = [], []
    for a in range(3):
        cap = axis_frame(lo, hi, a, h).n_pixels * params.max_layers
        out_all.append(int(min(cap, proj[:, a].sum())))
        out_recv.append(int(min(cap, proj[receives, a].sum())))
    return out_all, out_recv


def bake_estimates(scene: RuntimeScene, params: BakeParams, plan_doc: Mapping[str, Any]) -> dict[str, Any]:
    """The bake's memory per job and CPU time, estimated before anything is baked (see the module
    docstring for how)."""
    settings = get_settings()
    words = int(plan_doc["visibility_words"])
    axis_bytes = _ldc_axis_bytes(scene, params, words)
    samples, receiving = expected_ldc_samples(scene, params)
    rate = settings.bake_paths_per_s * (PATHS_RATE_BOUNCES + 1) / (params.indirect.bounces + 1)
    est: dict[str, Any] = {"ldc_axis_bytes_max": axis_bytes, "part_limit_bytes": settings.max_bake_part_bytes,
                           "ldc_samples_expected": samples, "paths_per_s": rate,
                           "cpu_limit_s": settings.max_bake_cpu_s}
    cpu = 0.0
    if plan_doc["indirect"]["state"] == "planned":
        k = params.indirect.chunks
        sides = [2 * n for n in receiving]
        per_side = expected_paths(params)
        est["indirect_paths_per_side_expected"] = per_side
        est["indirect_paths_expected"] = int(sum(sides) * per_side)
        ip = params.indirect
        most = ip.max_paths if ip.sampling == "adaptive" else fixed_paths(ip.noise, ip.min_paths, ip.max_paths,
                                                                           ip.round_paths)
        est["indirect_paths_max"] = int(sum(sides) * most)
        photons = ip.caustic_photons if ip.caustics == "photons" and has_caustics(scene) else 0
        est["caustic_map_cpu_s"] = 3 * k * photons * CAUSTIC_CPU_S_PER_PHOTON
        est["indirect_cpu_s"] = sum(sides) * per_side / rate + est["caustic_map_cpu_s"]
        cpu += est["indirect_cpu_s"]
        batch = [max(min(MAX_RAYS_PER_BATCH, -(-sd // k) * params.indirect.round_paths) * INDIRECT_RAY_BYTES,
                     photons * CAUSTIC_BYTES_PER_PHOTON) for sd in sides]
        est["indirect_chunk_bytes_max"] = [ab + b for ab, b in zip(axis_bytes, batch, strict=True)]
    if plan_doc["bake_llf"]:
        est["llf_chunk_bytes_max"] = estimate_llf_bytes(
            params.llf_f, params.llf_resolution, params.max_layers,
            n_views=min(params.llf_chunk, llf_direction_count(params.llf_f)))
        k_llf = int(plan_doc["indirect"].get("llf_indirect_samples", 0))
        if k_llf:
            # about one visible surface per LLF pixel (layers behind it are few in most scenes)
            llf_samples = llf_direction_count(params.llf_f) * params.llf_resolution ** 2
            est["llf_indirect_paths_expected"] = llf_samples * k_llf
            est["llf_indirect_cpu_s"] = llf_samples * k_llf / rate
            cpu += est["llf_indirect_cpu_s"]
    est["cpu_s"] = cpu
    return est


def check_estimates(params: BakeParams, est: Mapping[str, Any]) -> None:
    """Refuse a bake whose estimate is over the server's limits (``BakeTooLarge`` naming both)."""
    limit = int(est["part_limit_bytes"])
    axis = max(est["ldc_axis_bytes_max"])
    if axis > limit:
        raise BakeTooLarge(
            f"ldc_resolution {params.ldc_resolution} with max_layers {params.max_layers} needs up to "
            f"{axis / 2**20:.0f} MiB per LDC axis, over this server's limit of "
            f"{limit / 2**20:.0f} MiB; lower ldc_resolution or max_layers")
    chunk = max(est.get("indirect_chunk_bytes_max", [0]))
    if chunk > limit:
        raise BakeTooLarge(
            f"an indirect chunk needs up to {chunk / 2**20:.0f} MiB (its LDC axis at the worst case plus the "
            f"path-tracing batch), over this server's limit of {limit / 2**20:.0f} MiB; lower ldc_resolution or "
            "max_layers, or raise indirect.chunks")
    llf = int(est.get("llf_chunk_bytes_max", 0))
    if llf > limit:
        raise BakeTooLarge(
            f"llf_resolution {params.llf_resolution} x llf_chunk {params.llf_chunk} directions x max_layers "
            f"{params.max_layers} needs up to {llf / 2**20:.0f} MiB per LLF job, over this server's "
            f"limit of {limit / 2**20:.0f} MiB; lower llf_resolution, llf_chunk or max_layers")
    cpu, cpu_limit = float(est["cpu_s"]), float(est["cpu_limit_s"])
    if cpu > cpu_limit:
        ind = est.get("indirect_paths_expected", 0)
        raise BakeTooLarge(
            f"the bake's estimated CPU time is {duration_text(cpu)} ({ind / 1e6:.0f} M indirect paths in the LDC: "
            f"{sum(est['ldc_samples_expected']) / 1e3:.0f} k samples x 2 sides x "
            f"~{est.get('indirect_paths_per_side_expected', 0):.0f} paths, "
            f"{est.get('llf_indirect_paths_expected', 0) / 1e6:.0f} M in the light field, at "
            f"{est['paths_per_s'] / 1e3:.0f} k paths/s per core), over this server's limit of "
            f"{duration_text(cpu_limit)}; lower ldc_resolution, indirect.max_paths or indirect.bounces, raise "
            "indirect.noise, or set indirect.mode=off")


# ------------------------------------------------------------------------------------ plan


def bake_plan_job(payload: dict[str, Any]) -> dict[str, Any]:
    """Analyse the scene, check the memory and time estimates, enqueue the parts not yet in the store.

    Returns ``{"plan", "parts": [spec + key + weight], "reused": [names], "enqueued": [names],
    "estimates": {...}}``; the merge job and the API read it."""
    p = _validate(SceneBakeJobPayload, payload)
    _check_bake(p)
    store = worker_store()
    progress = ProgressReporter(get_current_job())
    if bake_complete(store, p.bake_key):
        manifest = read_manifest(store, p.bake_key)
        assert manifest is not None
        parts = manifest.result.get("parts", [])
        return {"plan": manifest.result.get("plan"), "parts": parts, "reused": [s["name"] for s in parts],
                "enqueued": [], "estimates": manifest.result.get("estimates", {})}
    progress.report(0.1, "loading scene", force=True)
    loaded = load_stored_scene(store, p.scene_id)
    scene = loaded.runtime
    if scene.n_triangles == 0:
        raise InvalidInputError("cannot bake a scene without surfaces")
    progress.report(0.5, "effect analysis", force=True)
    plan = analyze(scene)
    plan_doc = bake_plan_doc(scene, p.params, plan)
    with_llf = bool(plan_doc["bake_llf"])
    estimates = bake_estimates(scene, p.params, plan_doc)
    check_estimates(p.params, estimates)
    specs: list[dict[str, Any]] = []
    for spec in plan_parts(p.params, with_llf, plan_doc["indirect"]["state"] == "planned"):
        specs.append({**spec, "key": part_key(p.scene_id, p.bake_key, spec), "weight": part_weight(p.params, spec)})
    missing = [s for s in specs if not store.exists(manifest_key(s["key"]))]
    progress.report(0.8, f"enqueueing {len(missing)} of {len(specs)} parts", force=True)
    enqueue_parts(_redis(), p.scene_id, p.bake_key, p.params, missing, _owner())
    progress.report(1.0, "planned", force=True, check=False)
    out: dict[str, Any] = json_safe({"plan": plan_doc, "parts": specs,
                                      "reused": [s["name"] for s in specs if s not in missing],
                                      "enqueued": [s["name"] for s in missing], "estimates": estimates})
    return out


# ------------------------------------------------------------------------------------ parts


def _part_prologue(payload: dict[str, Any]) -> tuple[SceneBakePartJobPayload, ObjectStore, dict[str, Any] | None]:
    p = _validate(SceneBakePartJobPayload, payload)
    _check_bake(p)
    spec = p.part.model_dump(mode="json")
    expected = part_key(p.scene_id, p.bake_key, spec)
    if expected != p.part_key:
        raise InvalidPayload(f"part_key {p.part_key} does not match the part (expected {expected})")
    store = worker_store()
    existing = read_manifest(store, p.part_key)
    if existing is not None:  # published already (a retry after the commit, or a duplicate)
        return p, store, {"artifact_key": p.part_key, "part": p.part.name, "reused": True, **existing.result}
    return p, store, None


def _publish_part(store: ObjectStore, p: SceneBakePartJobPayload, blob_name: str, arrays: Mapping[str, np.ndarray],
                  result: dict[str, Any], progress: ProgressReporter) -> dict[str, Any]:
    data = npz_bytes(arrays)
    progress.check_canceled()  # last chance before the commit
    res = json_safe({**result, "bytes": len(data)})
    write_artifact(store, p.part_key, "bake-part", {"scene": p.scene_id, "bake": p.bake_key},
                   p.part.model_dump(mode="json"), ENGINE_VERSION, {blob_name: (data, NPZ)}, res)
    progress.report(1.0, "done", force=True, check=False)
    return {"artifact_key": p.part_key, "part": p.part.name, "reused": False, **res}


def _scene_and_caster(store: ObjectStore, scene_id: str) -> tuple[LoadedScene, Any, EffectPlan]:
    loaded = load_stored_scene(store, scene_id)
    return loaded, make_caster(loaded.runtime, "embree"), analyze(loaded.runtime)


def bake_ldc_axis_job(payload: dict[str, Any]) -> dict[str, Any]:
    """Bake one LDC axis and publish it as the part's artifact (``ldc_axis.npz``)."""
    t_start = time.perf_counter()
    p, store, done = _part_prologue(payload)
    if done is not None:
        return done
    part = p.part
    assert part.kind == "ldc_axis"
    progress = ProgressReporter(get_current_job())
    progress.report(0.02, "loading scene", force=True)
    t0 = time.perf_counter()
    loaded, caster, plan = _scene_and_caster(store, p.scene_id)
    t_load = time.perf_counter() - t0
    progress.report(0.1, f"casting LDC axis {part.axis}", force=True)

    def on_progress(frac: float, stage: str) -> None:
        what = "casting" if stage == "cast" else "shading"
        progress.report(0.1 + 0.8 * frac, f"{what} LDC axis {part.axis}")

    ax = bake_ldc_axis(loaded.runtime, caster, part.axis, p.params.ldc_resolution, plan=plan,
                       area_light_samples=p.params.area_light_samples, seed=p.params.seed,
                       max_layers=p.params.max_layers, max_bytes=get_settings().max_bake_part_bytes,
                       progress=on_progress)
    progress.report(0.9, "writing", force=True)
    timings = {k: v for k, v in ax.timings.items() if isinstance(v, float)}
    counts = {k: v for k, v in ax.timings.items() if not isinstance(v, float)}
    result = {"n_samples": ax.n_samples, "nbytes": ax.nbytes,
              "timings": {**timings, "load_scene": t_load, "job_total": time.perf_counter() - t_start},
              "counts": {**counts, "pixels": ax.ldi.frame.n_pixels}}
    return _publish_part(store, p, "ldc_axis.npz", ax.to_arrays(), result, progress)


def bake_ldc_indirect_job(payload: dict[str, Any]) -> dict[str, Any]:
    """Path-trace the indirect light of one chunk of an LDC axis's samples and publish it
    (``ldc_indirect.npz``). Runs after the axis's part (an RQ dependency) and reads it from the
    store; chunk i of k covers samples ``[i n // k, (i + 1) n // k)`` of the axis's n samples."""
    t_start = time.perf_counter()
    p, store, done = _part_prologue(payload)
    if done is not None:
        return done
    part = p.part
    assert part.kind == "ldc_indirect"
    ip = indirect_params(p.params)
    if ip is None or part.chunks != p.params.indirect.chunks:
        raise InvalidPayload(f"part {part.name} does not belong to a bake with indirect.chunks={part.chunks}")
    progress = ProgressReporter(get_current_job())
    progress.report(0.02, "loading scene and LDC axis", force=True)
    t0 = time.perf_counter()
    axis_spec = {"name": f"ldc-axis-{part.axis}", "kind": "ldc_axis", "axis": part.axis}
    axis_key = part_key(p.scene_id, p.bake_key, axis_spec)
    try:
        axis = LDCAxis.from_arrays(_read_part(store, axis_key, "ldc_axis.npz"))
    except (NotFound, ChecksumMismatch) as exc:
        raise BakeFailed(f"part {part.name} needs ldc-axis-{part.axis}, which is not in the store or is corrupt "
                         f"({exc}); request the bake again to redo the missing parts") from None
    loaded, caster, plan = _scene_and_caster(store, p.scene_id)
    if plan.indirect_skip:
        raise InvalidPayload(f"part {part.name}: the scene gets no indirect light ({plan.indirect_skip})")
    t_load = time.perf_counter() - t0
    n = axis.n_samples
    start, stop = part.chunk * n // part.chunks, (part.chunk + 1) * n // part.chunks
    what = f"indirect light of LDC axis {part.axis}, samples {start}..{stop - 1}"
    progress.report(0.05, what, force=True)
    res = indirect_chunk(loaded.runtime, caster, axis, start, stop, ip,
                         progress=lambda f: progress.report(0.05 + 0.9 * f, what))
    progress.report(0.95, "writing", force=True)
    arrays = res.to_arrays()
    result = {"n_samples": stop - start, "first": start, "axis_samples": n,
              "nbytes": int(sum(np.asarray(a).nbytes for a in arrays.values())), "indirect": res.stats,
              "timings": {"indirect": float(res.stats.get("time", 0.0)), "load": t_load,
                          "job_total": time.perf_counter() - t_start}}
    return _publish_part(store, p, "ldc_indirect.npz", arrays, result, progress)


def _reference_params(params: BakeParams, plan_doc: Mapping[str, Any] | None = None) -> Any:
    """The reference renderer's settings for the LLF views: ``llf_params``, plus indirect paths
    (``llf_indirect_samples`` per sample, ``indirect.bounces`` bounces) when the bake has indirect
    light, so gathered and traced reflections show the room as lit by it."""
    lp = params.llf_params
    k = llf_indirect_samples(params, plan_doc) if plan_doc is not None else 0
    return ReferenceParams(spp=lp.spp, max_depth=lp.max_depth, glossy_samples=lp.glossy_samples,
                           area_light_samples=lp.area_light_samples, seed=lp.seed, indirect_samples=k,
                           indirect_bounces=params.indirect.bounces if k else ReferenceParams().indirect_bounces)


def bake_llf_views_job(payload: dict[str, Any]) -> dict[str, Any]:
    """Bake one chunk of LLF directions and publish it (``llf_views.npz``, views prefixed ``v<i>_``)."""
    t_start = time.perf_counter()
    p, store, done = _part_prologue(payload)
    if done is not None:
        return done
    part = p.part
    assert part.kind == "llf_views"
    n_dirs = llf_direction_count(p.params.llf_f)
    if part.stop > n_dirs:
        raise InvalidPayload(f"part {part.name}: directions {part.start}..{part.stop - 1} outside 0..{n_dirs - 1}")
    progress = ProgressReporter(get_current_job())
    progress.report(0.02, "loading scene", force=True)
    t0 = time.perf_counter()
    loaded, caster, plan = _scene_and_caster(store, p.scene_id)
    rparams = _reference_params(p.params, bake_plan_doc(loaded.runtime, p.params, plan))
    t_load = time.perf_counter() - t0

    def on_progress(frac: float) -> None:
        progress.report(0.1 + 0.8 * frac, f"light field directions {part.start}..{part.stop - 1}")

    progress.report(0.1, f"light field directions {part.start}..{part.stop - 1}", force=True)
    t0 = time.perf_counter()
    views = bake_llf_views(loaded.runtime, caster, p.params.llf_f, p.params.llf_resolution,
                           list(range(part.start, part.stop)), params=rparams, progress=on_progress,
                           max_layers=p.params.max_layers, max_bytes=get_settings().max_bake_part_bytes)
    t_bake = time.perf_counter() - t0
    progress.report(0.9, "writing", force=True)
    arrays: dict[str, np.ndarray] = {"indices": np.array([v.index for v in views], np.int64)}
    for v in views:
        arrays.update({f"v{v.index}_{k}": a for k, a in v.to_arrays().items()})
    result = {"n_views": len(views), "n_samples": int(sum(v.ldi.n_samples for v in views)),
              "indirect_samples": rparams.indirect_samples,
              "nbytes": int(sum(a.nbytes for a in arrays.values())),
              "timings": {"bake": t_bake, "load_scene": t_load, "job_total": time.perf_counter() - t_start}}
    return _publish_part(store, p, "llf_views.npz", arrays, result, progress)


# ------------------------------------------------------------------------------------ load + merge


def _read_part(store: ObjectStore, pkey: str, name: str) -> dict[str, np.ndarray]:
    return read_npz(read_blob(store, pkey, name))


def load_bake_parts(store: ObjectStore, scene: RuntimeScene, params: BakeParams, parts: list[dict[str, Any]],
                    plan: dict[str, Any], progress: Callable[[float], None] | None = None) -> tuple[Any, Any]:
    """``(LDC, LLF or None)`` from a bake's part artifacts, checked: checksums (``read_blob``),
    array shapes (``from_arrays``) and that the parts fit together (``merge_ldc`` / ``merge_llf``)."""
    axes = []
    chunks: dict[int, list[IndirectResult]] = {}
    views: list[Any] = []
    for i, spec in enumerate(parts):
        if spec["kind"] == "ldc_axis":
            axes.append(LDCAxis.from_arrays(_read_part(store, spec["key"], "ldc_axis.npz")))
        elif spec["kind"] == "ldc_indirect":
            chunks.setdefault(int(spec["axis"]), []).append(
                IndirectResult.from_arrays(_read_part(store, spec["key"], "ldc_indirect.npz")))
        else:
            d = _read_part(store, spec["key"], "llf_views.npz")
            for idx in d["indices"].tolist():
                pre = f"v{idx}_"
                views.append(LLFView.from_arrays({k[len(pre):]: a for k, a in d.items() if k.startswith(pre)}))
        if progress is not None:
            progress((i + 1) / max(1, len(parts)))
    planned = (plan.get("indirect") or {}).get("state") in ("planned", "baked")
    if planned or chunks:
        ip = indirect_params(params)
        if ip is None or not planned or sorted(chunks) != [0, 1, 2]:
            raise BakeFailed(f"the bake's indirect parts do not match its plan (chunks of axes {sorted(chunks)}, "
                             f"plan says {(plan.get('indirect') or {}).get('state')})")
        axes = [with_indirect(ax, chunks[ax.axis], ip) for ax in axes]  # checks the chunks tile each axis
    ldc = merge_ldc(scene, axes, params.ldc_resolution, analyze(scene))
    llf = None
    if plan.get("bake_llf"):
        llf = merge_llf(params.llf_f, params.llf_resolution, views,
                        llf_params_dict(_reference_params(params, plan), params.max_layers))
    return ldc, llf


def indirect_outcome(ldc: Any, plan: Mapping[str, Any], params: BakeParams) -> dict[str, Any]:
    """The plan's ``indirect`` entry once the bake is merged: ``baked`` with the achieved noise level
    (per axis and for the whole LDC, ``with_indirect``'s summaries), ``skipped`` with the effect
    plan's reason, or ``off``; with the request's settings."""
    got = dict(ldc.plan.get("indirect") or {})
    out = {**dict(plan.get("indirect") or {}), **got}
    if got.get("state") == "baked":
        ip = indirect_params(params)
        assert ip is not None
        out["reason"] = "the effect plan says indirect light can arrive"
        out["summary"] = _ldc_summary(list(got.get("axes", [])), ip.noise)
    return out


def _ldc_summary(axes: list[dict[str, Any]], noise: float) -> dict[str, Any]:
    """One achieved-noise summary over the three axes' (``with_indirect``'s, sides-weighted)."""
    live = [a for a in axes if a.get("sides", 0)]
    sides = int(sum(a["sides"] for a in live))
    paths = int(sum(a.get("paths_total", 0) for a in live))

    def weighted(name: str) -> float:
        return float(sum(a["sides"] * a.get(name, 0.0) for a in live) / sides) if sides else 0.0

    return {"sides": sides, "noise_target": noise, "met_target": weighted("met_target") if sides else 1.0,
            "rel_stderr_median_of_chunks": weighted("rel_stderr_median_of_chunks"),
            "rel_stderr_p95_of_chunks": weighted("rel_stderr_p95_of_chunks"),
            "rel_stderr_max": float(max((a.get("rel_stderr_max", 0.0) for a in live), default=0.0)),
            "paths_total": paths, "paths_mean": paths / sides if sides else 0.0,
            "paths_max": int(max((a.get("paths_max", 0) for a in live), default=0)),
            **({"time": float(sum(a["time"] for a in axes if "time" in a))} if any("time" in a for a in axes) else {})}


def bake_merge_job(payload: dict[str, Any]) -> dict[str, Any]:
    """Runs after the plan job and every part job ended: verifies the parts and publishes the bake
    manifest (``plan.json`` + the result: plan, parts with sizes and timings, totals)."""
    t_start = time.perf_counter()
    p = _validate(SceneBakeJobPayload, payload)
    _check_bake(p)
    store = worker_store()
    if bake_complete(store, p.bake_key):
        manifest = read_manifest(store, p.bake_key)
        assert manifest is not None
        return {"artifact_key": p.bake_key, **manifest.result}
    redis = _redis()
    progress = ProgressReporter(get_current_job())
    progress.report(0.0, "checking parts", force=True)
    plan_job = fetch_job(redis, scene_bake_plan_job_id(p.bake_key))
    if plan_job is None:
        raise BakeFailed(f"the plan of bake {p.bake_key} is no longer in Redis; request the bake again")
    plan_pub = job_public(plan_job)
    if plan_pub.state != "finished":
        raise BakeFailed(f"planning the bake failed: {plan_pub.error or plan_pub.state}")
    planned = plan_job.return_value()
    if not isinstance(planned, dict):
        raise BakeFailed("the bake's plan job returned no plan")
    specs: list[dict[str, Any]] = list(planned["parts"])
    manifests = {s["name"]: read_manifest(store, s["key"]) for s in specs}
    missing = [s for s in specs if manifests[s["name"]] is None]
    if missing:
        why = []
        for s in missing[:4]:
            pj = fetch_job(redis, scene_bake_part_job_id(s["key"]))
            if pj is None:
                why.append(f"{s['name']} (no job)")
            else:
                pp = job_public(pj)
                why.append(f"{s['name']} ({pp.state}: {pp.error})" if pp.error else f"{s['name']} ({pp.state})")
        more = f" and {len(missing) - 4} more" if len(missing) > 4 else ""
        raise BakeFailed(f"{len(missing)} of {len(specs)} bake parts are missing: {', '.join(why)}{more}; request "
                         "the bake again to redo only the missing parts")
    total = sum(int(m.result.get("nbytes") or 0) for m in manifests.values() if m is not None)
    if total > BAKE_MAX_TOTAL_BYTES:
        raise BakeTooLarge(f"the bake's parts hold {total / 2**20:.0f} MiB, over this server's limit of "
                           f"{BAKE_MAX_TOTAL_BYTES / 2**20:.0f} MiB for one bake in memory; lower ldc_resolution, "
                           "max_layers, llf_f or llf_resolution")
    progress.report(0.05, "verifying parts", force=True)
    loaded = load_stored_scene(store, p.scene_id)
    t0 = time.perf_counter()
    ldc, llf = load_bake_parts(store, loaded.runtime, p.params, specs, planned["plan"],
                               lambda f: progress.report(0.05 + 0.85 * f, "verifying parts"))
    t_verify = time.perf_counter() - t0
    plan_out = {**planned["plan"], "indirect": indirect_outcome(ldc, planned["plan"], p.params)}
    parts_out = []
    cpu = 0.0
    for s in specs:
        r = manifests[s["name"]].result  # type: ignore[union-attr]
        t = r.get("timings", {}).get("job_total", 0.0)
        cpu += float(t)
        parts_out.append({**s, "bytes": r.get("bytes"), "n_samples": r.get("n_samples"), "timings": r.get("timings")})
    sizes = {"ldc_bytes": int(ldc.nbytes), "llf_bytes": int(llf.nbytes) if llf is not None else 0,
             "stored_bytes": int(sum(int(x.get("bytes") or 0) for x in parts_out)),
             "ldc_samples": int(ldc.n_samples)}
    wall = None
    if plan_job.enqueued_at is not None:
        wall = time.time() - plan_job.enqueued_at.timestamp()
    result = json_safe({
        "plan": plan_out, "parts": parts_out, "sizes": sizes, "estimates": planned.get("estimates", {}),
        "timings": {"parts_total": cpu, "verify": t_verify, "merge_total": time.perf_counter() - t_start,
                    "wall_since_request": wall},
    })
    progress.check_canceled()
    write_artifact(store, p.bake_key, "bake", {"scene": p.scene_id}, p.params.model_dump(mode="json"), ENGINE_VERSION,
                   {"plan.json": (json.dumps(result["plan"], sort_keys=True).encode(), "application/json")}, result)
    progress.report(1.0, "done", force=True, check=False)
    return {"artifact_key": p.bake_key, **result}


def load_bake(store: ObjectStore, scene: RuntimeScene, key: str) -> tuple[Any, Any, dict[str, Any]]:
    """``(LDC, LLF or None, plan)`` of a complete bake (for the render worker). Raises BakeFailed when
    the bake or one of its parts is missing or corrupt (the bake must be requested again)."""
    manifest = read_manifest(store, key)
    if manifest is None:
        raise BakeFailed(f"bake {key} is not in the store; request it with POST /v1/scenes/<id>/bakes")
    params = BakeParams.model_validate(manifest.params)
    try:
        ldc, llf = load_bake_parts(store, scene, params, list(manifest.result["parts"]), manifest.result["plan"])
    except (NotFound, ChecksumMismatch) as exc:
        bake_complete(store, key)  # withdraws the manifest when a part has gone
        raise BakeFailed(f"bake {key} is incomplete ({exc}); request the bake again to redo the missing parts") \
            from None
    return ldc, llf, dict(manifest.result["plan"])

