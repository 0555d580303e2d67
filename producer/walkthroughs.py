"""Walkthroughs of a stored scene, split into RQ jobs (docs/walkthrough.md, "Service").

The job functions are in ``workers/jobs/walkthrough.py``; this module names, enqueues and follows
them.

A request (:class:`api_schemas.walkthrough.WalkthroughRequest`) becomes three kinds of jobs, each
publishing a content-addressed artifact:

- ``wtbake-<bake key>`` (``bake`` queue): decomposition + base range images of the scene for the
  bake settings; artifact ``bake.npz``. Shared by every walkthrough of that scene and settings.
- ``wtchunk-<chunk key>`` (``render`` queue, depends on the bake job): frames ``start..stop-1``
  as ``frame_NNNNN.exr`` (linear radiance), ``frame_NNNNN.png`` (sRGB preview) and
  ``provenance_NNNNN.png`` (8-bit provenance codes); several workers share a walkthrough.
- ``walkthrough-<key>`` (``render`` queue, depends on every chunk job): checks the chunks, encodes
  ``video.mp4`` (H.264 through the ffmpeg shipped by ``imageio-ffmpeg``) and publishes the
  walkthrough manifest (its result lists the chunk keys and frame counts).

A request with ``path_traced`` has no bake job: its chunk jobs path-trace their frames.

Keys: ``artifact_key("walkthrough-bake", {"scene"}, settings)``, ``artifact_key("walkthrough",
{"scene", "bake"}, {fill, frames, chunk_frames, fps})`` (path-traced: ``{"scene"}``, ``{path_traced,
frames, chunk_frames, fps}``), ``artifact_key("walkthrough-chunk",
{"walkthrough"}, {"index", "start", "stop"})``. The request is kept at
``walkthroughs/<key>.json`` (status and the job payloads read it).
"""

from __future__ import annotations

import math
from typing import Any, Literal

from redis import Redis
from rq.job import Dependency, JobStatus

from api_schemas.errors import FieldError
from api_schemas.scene import Scene
from api_schemas.service import JobPublic
from api_schemas.walkthrough import WalkthroughPublic, WalkthroughRequest, WalkthroughSettings
from engine import ENGINE_VERSION
from producer.artifacts import artifact_key, delete_artifact, read_manifest
from producer.cancel import cancel
from producer.enqueue import enqueue_unique
from producer.errors import JobNotCancelable, JobNotFound, UnknownScene, WalkthroughInUse
from producer.names import (
    WALKTHROUGH_BAKE_JOB,
    WALKTHROUGH_CHUNK_JOB,
    WALKTHROUGH_VIDEO_JOB,
    walkthrough_bake_job_id,
    walkthrough_chunk_job_id,
    walkthrough_video_job_id,
)
from producer.queue import BAKE_TIMEOUT_S, RENDER_TIMEOUT_S, fetch_job, fetch_jobs, job_retry
from producer.status import job_public
from producer.store import NotFound, ObjectStore

__all__ = [
    "WALKTHROUGH_MAX_BAKE_BYTES",
    "bake_bound_errors",
    "chunk_key",
    "contract_key",
    "chunks",
    "check_against_scene",
    "delete_walkthrough",
    "enqueue_walkthrough",
    "frames_bake_key",
    "read_request",
    "walkthrough_bake_key",
    "walkthrough_index_key",
    "walkthrough_inputs",
    "walkthrough_key",
    "walkthrough_status",
]

_EYE_TOL = 1e-6  # relative to the view space's size
WALKTHROUGH_MAX_BAKE_BYTES = 4 << 30
"""Upper bound of one walkthrough bake's base images (a bake worker holds them in memory)."""


def _key(kind: str, inputs: dict[str, str], params: dict[str, Any]) -> str:
    return artifact_key(kind, inputs, params, ENGINE_VERSION)


def walkthrough_bake_key(scene_id: str, settings: WalkthroughSettings) -> str:
    return _key("walkthrough-bake", {"scene": scene_id}, settings.model_dump(mode="json"))


def frames_bake_key(req: WalkthroughRequest) -> str | None:
    """The key of the bake ``req``'s frames are reconstructed from; None for path-traced frames."""
    return None if req.path_traced is not None else walkthrough_bake_key(req.scene_id, req.bake)


def walkthrough_inputs(req: WalkthroughRequest) -> tuple[dict[str, str], dict[str, Any]]:
    """The artifact inputs and parameters of walkthrough ``req`` (its key's and its manifest's)."""
    bkey = frames_bake_key(req)
    if bkey is None:
        return {"scene": req.scene_id}, req.model_dump(mode="json", include={"path_traced", "frames", "chunk_frames",
                                                                            "fps"})
    return ({"scene": req.scene_id, "bake": bkey},
            req.model_dump(mode="json", include={"fill", "frames", "chunk_frames", "fps"}))


def walkthrough_key(req: WalkthroughRequest) -> str:
    inputs, params = walkthrough_inputs(req)
    return _key("walkthrough", inputs, params)


def chunks(req: WalkthroughRequest) -> list[tuple[int, int]]:
    """(start, stop) frame ranges of the chunk jobs."""
    n, c = len(req.frames), req.chunk_frames
    return [(a, min(n, a + c)) for a in range(0, n, c)]


def chunk_key(wkey: str, index: int, start: int, stop: int) -> str:
    return _key("walkthrough-chunk", {"walkthrough": wkey}, {"index": index, "start": start, "stop": stop})


def walkthrough_index_key(scene_id: str, wkey: str) -> str:
    """Marker object listing walkthrough ``wkey`` under its scene (written when it is requested)."""
    return f"walkthroughs-by-scene/{scene_id}/{wkey}"


def record_key(wkey: str) -> str:
    return f"walkthroughs/{wkey}.json"


def contract_key(wkey: str) -> str:
    """Where the quality contract of walkthrough ``wkey`` is kept, when it was asked with one
    (``producer.walkthrough_calibrations``)."""
    return f"walkthroughs/{wkey}.contract.json"


def read_request(store: ObjectStore, wkey: str) -> WalkthroughRequest | None:
    """The request stored for ``wkey`` (None when unknown)."""
    try:
        data = store.get_bytes(record_key(wkey))
    except NotFound:
        return None
    return WalkthroughRequest.model_validate_json(data)


def bake_bound_errors(settings: WalkthroughSettings, field: str = "bake.face_res") -> list[FieldError]:
    """A bake whose base images can exceed :data:`WALKTHROUGH_MAX_BAKE_BYTES`, named at ``field``
    (a walkthrough's ``bake.face_res``, a calibration's preset); empty when it fits."""
    need = settings.upper_bound_bytes()
    if need <= WALKTHROUGH_MAX_BAKE_BYTES:
        return []
    return [FieldError(
        field=field, type="bake_too_large",
        message=f"up to {need / 2**30:.1f} GiB of base images (max_views x max_time_samples x 6 x face_res^2 x "
                f"32 bytes) exceeds this server's limit of {WALKTHROUGH_MAX_BAKE_BYTES / 2**30:.0f} GiB; lower "
                f"face_res, max_views or max_time_samples")]


def check_against_scene(scene: Scene, req: WalkthroughRequest) -> list[FieldError]:
    """Problems of the request that need the scene: no view space, an eye outside it, a time
    outside the animation. Each names the field and the allowed range."""
    errors = bake_bound_errors(req.bake) if req.path_traced is None else []
    vs = scene.view_space
    if vs is None:
        return errors + [FieldError(field="scene_id", type="no_view_space",
                                    message="the scene has no view_space; add one (docs/scene-format.md) to walk "
                                            "through it")]
    lo, hi = vs.bounds()
    size = max(math.dist(lo, hi), max(abs(c) for c in lo + hi), 1e-300)
    anim = scene.animation
    for i, f in enumerate(req.frames):
        d = vs.distance(f.camera.eye)
        if not math.isfinite(d) or d > _EYE_TOL * size:
            errors.append(FieldError(
                field=f"frames.{i}.camera.eye", type="outside_view_space",
                message=f"eye {list(f.camera.eye)} is {d:.6g} outside the scene's {vs.type} view space "
                        f"(bounds {list(lo)} .. {list(hi)})"))
        if anim is not None and not anim.start <= f.time <= anim.end:
            errors.append(FieldError(
                field=f"frames.{i}.time", type="time_out_of_range",
                message=f"time {f.time:g} is outside the animation interval [{anim.start:g}, {anim.end:g}]"))
        if len(errors) >= 20:
            break
    return errors


def delete_walkthrough(redis: Redis, store: ObjectStore, wkey: str) -> None:
    """Remove walkthrough ``wkey``: its manifest and video, every chunk artifact (frames), its
    request record and its job records. The bake stays (shared by every walkthrough of the scene
    with the same bake settings). Raises :class:`WalkthroughInUse` while one of its chunk or video
    jobs runs, or waits in a queue while the walkthrough can still finish (cancel them or wait); the
    jobs left waiting by a failed walkthrough (e.g. the video job behind a canceled chunk) are
    canceled. Idempotent for an unknown key."""
    req = read_request(store, wkey)
    if req is None:
        return
    ckeys = [chunk_key(wkey, i, a, b) for i, (a, b) in enumerate(chunks(req))]
    ids = [walkthrough_chunk_job_id(k) for k in ckeys] + [walkthrough_video_job_id(wkey)]
    ended = {JobStatus.FINISHED, JobStatus.FAILED, JobStatus.STOPPED, JobStatus.CANCELED}
    jobs = [j for j in fetch_jobs(redis, ids) if j is not None]
    status = {j.id: j.get_status(refresh=True) for j in jobs}
    running = [jid for jid, st in status.items() if st == JobStatus.STARTED]
    waiting = [jid for jid, st in status.items() if st not in ended and st != JobStatus.STARTED]
    pub = walkthrough_status(redis, store, wkey)
    failed = pub is not None and pub.status == "failed"
    busy = running + ([] if failed else waiting)
    if busy:
        raise WalkthroughInUse(f"walkthrough {wkey} has {len(busy)} queued or running job(s) ({busy[0]}"
                               f"{', ...' if len(busy) > 1 else ''}); cancel them (POST /v1/jobs/<id>/cancel) "
                               "or wait")
    for jid in waiting:  # a failed walkthrough: these could never run usefully
        try:
            cancel(redis, jid)
        except (JobNotFound, JobNotCancelable):
            pass  # ended meanwhile
    delete_artifact(store, wkey)  # the manifest first: from here on the walkthrough is not finished
    for k in ckeys:
        delete_artifact(store, k)
    store.delete(record_key(wkey))
    store.delete(contract_key(wkey))
    for job in jobs:
        job.delete(remove_from_queue=True)


def enqueue_walkthrough(redis: Redis, store: ObjectStore, req: WalkthroughRequest,
                        owner: str | None) -> tuple[str, bool]:
    """Queue the jobs of ``req`` (skipping artifacts already published). Returns ``(key,
    finished)``. Raises :class:`UnknownScene` when the scene is not stored."""
    if not store.exists(f"scenes/{req.scene_id}.json"):
        raise UnknownScene(f"scene {req.scene_id} does not exist")
    wkey = walkthrough_key(req)
    if read_manifest(store, wkey) is not None:
        return wkey, True
    store.put_bytes(record_key(wkey), req.model_dump_json().encode(), "application/json")
    # listed under its scene, so deleting the scene finds it (producer.scene_outputs)
    store.put_bytes(walkthrough_index_key(req.scene_id, wkey), b"", "application/octet-stream")
    bkey = frames_bake_key(req)
    deps: list[str] = []
    if bkey is not None and read_manifest(store, bkey) is None:
        bjob = enqueue_unique(
            redis, "bake", WALKTHROUGH_BAKE_JOB,
            {"scene_id": req.scene_id, "bake_key": bkey, "settings": req.bake.model_dump(mode="json")},
            walkthrough_bake_job_id(bkey), timeout=BAKE_TIMEOUT_S,
            meta={"kind": "walkthrough-bake", "artifact_key": bkey, "owner": owner},
            retry=job_retry(), description=f"walkthrough bake of scene {req.scene_id[:12]}", owner=owner,
            is_cached=lambda: read_manifest(store, bkey) is not None)
        if bjob is not None:
            deps.append(bjob.id)
    chunk_ids: list[str] = []
    for i, (a, b) in enumerate(chunks(req)):
        ckey = chunk_key(wkey, i, a, b)
        if read_manifest(store, ckey) is not None:
            continue
        job = enqueue_unique(
            redis, "render", WALKTHROUGH_CHUNK_JOB,
            {"walkthrough_key": wkey, "index": i, "start": a, "stop": b, "chunk_key": ckey, "bake_key": bkey},
            walkthrough_chunk_job_id(ckey), timeout=RENDER_TIMEOUT_S,
            meta={"kind": "walkthrough-chunk", "artifact_key": ckey, "owner": owner},
            retry=job_retry(), description=f"walkthrough frames {a}..{b - 1}", owner=owner,
            is_cached=lambda k=ckey: read_manifest(store, k) is not None,  # type: ignore[misc]
            depends_on=Dependency(jobs=deps, allow_failure=True) if deps else None)
        if job is not None:
            chunk_ids.append(job.id)
    enqueue_unique(
        redis, "render", WALKTHROUGH_VIDEO_JOB, {"walkthrough_key": wkey, "bake_key": bkey},
        walkthrough_video_job_id(wkey), timeout=RENDER_TIMEOUT_S,
        meta={"kind": "walkthrough", "artifact_key": wkey, "owner": owner},
        retry=job_retry(), description=f"walkthrough video of scene {req.scene_id[:12]}", owner=owner,
        is_cached=lambda: read_manifest(store, wkey) is not None,
        depends_on=Dependency(jobs=chunk_ids, allow_failure=True) if chunk_ids else None)
    return wkey, False


def walkthrough_status(redis: Redis, store: ObjectStore, wkey: str) -> WalkthroughPublic | None:
    """Public state of walkthrough ``wkey`` (None when this store never saw the request)."""
    req = read_request(store, wkey)
    if req is None:
        return None
    bkey = frames_bake_key(req)
    n = len(req.frames)
    links: dict[str, str] = {}
    manifest = read_manifest(store, wkey)
    if manifest is not None:
        links = {"artifact": f"/v1/artifacts/{wkey}", "video.mp4": f"/v1/walkthroughs/{wkey}/video.mp4",
                 "frame.png": f"/v1/walkthroughs/{wkey}/frames/{{index}}.png",
                 "frame.exr": f"/v1/walkthroughs/{wkey}/frames/{{index}}.exr",
                 "frame.provenance": f"/v1/walkthroughs/{wkey}/frames/{{index}}.provenance"}
        for i, ck in enumerate(manifest.result.get("chunks", [])):
            links[f"chunk.{i}"] = f"/v1/artifacts/{ck}"
        return WalkthroughPublic(key=wkey, status="finished", progress=1.0, frames=n, frames_done=n, bake_key=bkey,
                                 links=links)
    jobs: list[JobPublic] = []
    error: str | None = None
    bake_done = bkey is None or read_manifest(store, bkey) is not None
    bake_frac = 1.0 if bake_done else 0.0
    bjob = None if bkey is None else fetch_job(redis, walkthrough_bake_job_id(bkey))
    if bjob is not None:
        pub = job_public(bjob)
        jobs.append(pub)
        if not bake_done:
            bake_frac = pub.progress.fraction
        if pub.state in ("failed", "canceled"):
            error = f"bake: {pub.error or pub.state}"
    done = 0
    chunk_frac = 0.0
    for i, (a, b) in enumerate(chunks(req)):
        ckey = chunk_key(wkey, i, a, b)
        if read_manifest(store, ckey) is not None:
            done += b - a
            chunk_frac += b - a
            continue
        job = fetch_job(redis, walkthrough_chunk_job_id(ckey))
        if job is not None:
            pub = job_public(job)
            jobs.append(pub)
            chunk_frac += (b - a) * pub.progress.fraction
            if pub.state in ("failed", "canceled") and error is None:
                error = f"frames {a}..{b - 1}: {pub.error or pub.state}"
    vjob = fetch_job(redis, walkthrough_video_job_id(wkey))
    if vjob is not None:
        pub = job_public(vjob)
        jobs.append(pub)
        if pub.state in ("failed", "canceled") and error is None:
            error = f"video: {pub.error or pub.state}"
    # the bake counts as a third of a walkthrough's work; path-traced frames are all of it
    progress = min(0.99, (chunk_frac / max(n, 1) if bkey is None else bake_frac / 3 + 2 / 3 * chunk_frac / max(n, 1)))
    running = any(j.state == "started" for j in jobs)
    status: Literal["queued", "running", "failed"] = (
        "failed" if error is not None else ("running" if running or done else "queued"))
    return WalkthroughPublic(key=wkey, status=status, progress=progress, frames=n, frames_done=done, bake_key=bkey,
                             jobs=jobs, error=error, links=links)


