"""Bakes of a scene (layered depth cube + layered light field), split into jobs for the ``bake`` queue.

The job functions are in ``workers/jobs/bake.py``; this module names, enqueues and follows them.

A bake request ``(scene_id, BakeParams)`` has a content-addressed key
``artifact_key("bake", {"scene": scene_id}, params, ENGINE_VERSION)``. Its work is split into PARTS,
each its own RQ job on the ``bake`` queue and its own artifact in the store:

- ``ldc-axis-0`` .. ``ldc-axis-2``: one LDI of the LDC each, direct light only
  (``engine.newviews.ldc.bake_ldc_axis``);
- ``ldc-indirect-<axis>-<i>`` (i < ``indirect.chunks``): the indirect light of chunk i of that axis's
  n samples, ``[i n // chunks, (i + 1) n // chunks)`` (``engine.newviews.ldc.indirect_chunk``), only
  when ``indirect.mode`` is ``auto`` and the effect plan says indirect light can arrive. Each waits
  for its axis's job (an RQ dependency: it needs the direct-lit axis, and n is known only then);
  the axis and its chunks are combined by ``with_indirect`` wherever the bake is loaded (merge job,
  render worker), bit for bit what a one-process ``bake_ldc(..., indirect=...)`` computes;
- ``llf-views-<first>-<last>``: a chunk of ``llf_chunk`` light-field directions
  (``engine.newviews.llf.bake_llf_views``), only when the effect analysis says the scene needs a light field
  (``llf: "auto"``) or the request forces it (``llf: "always"``).

Part key = ``artifact_key("bake-part", {"scene": scene_id, "bake": bake_key}, spec, ENGINE_VERSION)``
where ``spec`` names the part (``{"name", "kind", "axis"}``, ``{"name", "kind", "axis", "chunk", "chunks"}``
or ``{"name", "kind", "start", "stop"}``).

Jobs (ids are deterministic, so identical requests share them):

- ``bake-plan-<key>`` loads the scene, runs the effect analysis, estimates the bake's memory and
  CPU time and refuses it over the configured limits (``IBR_MAX_BAKE_PART_BYTES``,
  ``IBR_MAX_BAKE_CPU_S``), and enqueues one job per part whose artifact is NOT in the store yet (a re-run
  after a crash or a deleted part redoes only the missing parts);
- ``bake-part-<part key>`` computes one part and publishes it;
- ``bake-<key>`` (the bake's own job, the one a client follows) depends on the plan job and on
  every part job (RQ dependencies with ``allow_failure``, so a failed part fails the bake with that
  part's error instead of leaving it waiting forever); it verifies every part (checksums, shapes,
  that they fit together) and publishes the bake manifest, whose result holds the plan and the part
  keys. The merge job exists from the request on, so a render can depend on it (``missing_bake:
  "bake"``).

Store: ``bakes/<scene_id>/<bake key>.json`` records each requested bake of a scene (its params; the
listing of a scene's bakes); the parts and the bake are ordinary artifacts.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from redis import Redis
from rq import Retry
from rq.job import Dependency, Job, JobStatus
from rq.serializers import JSONSerializer

from api_schemas.service import BakeParams, BakePart, BakePartState, BakePublic, BakeState, JobProgress
from engine import ENGINE_VERSION
from producer.artifacts import artifact_key, delete_artifact, manifest_key, read_manifest
from producer.costs import expected_paths
from producer.enqueue import enqueue_unique
from producer.errors import BakeInUse, UnknownScene
from producer.names import (
    SCENE_BAKE_INDIRECT_JOB,
    SCENE_BAKE_LDC_JOB,
    SCENE_BAKE_LLF_JOB,
    SCENE_BAKE_MERGE_JOB,
    SCENE_BAKE_PLAN_JOB,
    scene_bake_job_id,
    scene_bake_part_job_id,
    scene_bake_plan_job_id,
)
from producer.ownership import add_job_owner
from producer.queue import ACTIVE_STATUSES, BAKE_TIMEOUT_S, fetch_job, fetch_jobs, job_retry
from producer.status import job_public
from producer.store import NotFound, ObjectStore

__all__ = [
    "BAKE_MAX_PART_BYTES",
    "BAKE_MAX_TOTAL_BYTES",
    "PartSpec",
    "bake_key",
    "bake_complete",
    "bake_record_key",
    "bake_status",
    "delete_bake",
    "enqueue_bake",
    "enqueue_parts",
    "indirect_part_specs",
    "ldc_part_specs",
    "list_bakes",
    "merge_stuck",
    "llf_direction_count",
    "llf_part_specs",
    "part_key",
    "plan_parts",
    "read_bake_record",
]

BAKE_MAX_PART_BYTES = 2 << 30
"""Worst-case bytes one part may allocate (LDC axis: every pixel full to ``max_layers``); a request
over it is refused before anything is baked (422 from the API, a failed plan from the worker)."""

BAKE_MAX_TOTAL_BYTES = 8 << 30
"""Bytes of a whole bake in memory (its parts' actual sizes, known once they are baked): the merge
job and a render worker load all of it, so a bigger bake is failed by the merge job before loading,
with its size and what to lower."""

def chunk_retry() -> Retry:
    """Retries of an indirect chunk: one, for transient failures only (store or Redis trouble, a
    worker that died; see workers/runner.py), so a chunk that fails twice fails the bake, which
    names it; a re-request then redoes only the missing chunks."""
    return Retry(max=1, interval=[5])


LDC_SAMPLE_BYTES_UPPER = 20 + 57 + 16
"""Per LDC sample: LDI (20) + attributes (57) + one visibility word per side (16), for the API's
engine-free upper bound (the engine's own estimate is exact and checked again by the plan job)."""


# ------------------------------------------------------------------------------------ keys and parts


def bake_params_dict(params: BakeParams) -> dict[str, Any]:
    return params.model_dump(mode="json")


def bake_key(scene_id: str, params: BakeParams) -> str:
    return artifact_key("bake", {"scene": scene_id}, bake_params_dict(params), ENGINE_VERSION)


def bake_record_key(scene_id: str, key: str) -> str:
    return f"bakes/{scene_id}/{key}.json"


def llf_direction_count(f: int) -> int:
    """Directions of a subdivided octahedron: 4 f^2 + 2 (66, 258, 1026 for f = 4, 8, 16)."""
    return 4 * f * f + 2


PartSpec = dict[str, Any]


def ldc_part_specs() -> list[PartSpec]:
    return [{"name": f"ldc-axis-{a}", "kind": "ldc_axis", "axis": a} for a in range(3)]


def llf_part_specs(params: BakeParams) -> list[PartSpec]:
    n = llf_direction_count(params.llf_f)
    out: list[PartSpec] = []
    for start in range(0, n, params.llf_chunk):
        stop = min(n, start + params.llf_chunk)
        out.append({"name": f"llf-views-{start:04d}-{stop - 1:04d}", "kind": "llf_views", "start": start,
                    "stop": stop})
    return out


def indirect_part_specs(params: BakeParams) -> list[PartSpec]:
    """``indirect.chunks`` chunks of each axis's indirect pass (their sample ranges are fixed at run
    time from the axis's sample count)."""
    k = params.indirect.chunks
    return [{"name": f"ldc-indirect-{a}-{i}", "kind": "ldc_indirect", "axis": a, "chunk": i, "chunks": k}
            for a in range(3) for i in range(k)]


def plan_parts(params: BakeParams, bake_llf: bool, bake_indirect: bool = False) -> list[PartSpec]:
    """The parts of a bake: three LDC axes, the chunks of their indirect pass when it runs, and the
    LLF chunks when the light field is baked."""
    return (ldc_part_specs() + (indirect_part_specs(params) if bake_indirect else [])
            + (llf_part_specs(params) if bake_llf else []))


def part_key(scene_id: str, key: str, spec: PartSpec) -> str:
    return artifact_key("bake-part", {"scene": scene_id, "bake": key}, spec, ENGINE_VERSION)


def part_weight(params: BakeParams, spec: PartSpec) -> float:
    """Rough relative cost of a part (rays cast), for the aggregated progress."""
    if spec["kind"] == "ldc_axis":
        return float(params.ldc_resolution ** 2) * 2.0
    if spec["kind"] == "ldc_indirect":
        # ~2 samples per pixel, 2 sides, ~ (min_paths + a share of the rest) paths of ~(bounces + 1)
        # segments and as many shadow rays each, split over the axis's chunks
        ip = params.indirect
        return float(params.ldc_resolution ** 2) * 4.0 * expected_paths(params) * 2.0 * (ip.bounces + 1) / ip.chunks
    n = int(spec["stop"]) - int(spec["start"])
    lp = params.llf_params
    per_sample = lp.spp * (1.0 + min(lp.max_depth, 1) * lp.glossy_samples * 0.25)
    return float(n * params.llf_resolution ** 2) * per_sample


def ldc_upper_bound_bytes(params: BakeParams, n_lights: int) -> int:
    """Engine-free upper bound on one LDC axis' size (every pixel full to ``max_layers``)."""
    words = (max(n_lights, 0) + 63) // 64
    per = 20 + 57 + 16 * words
    pixels = (params.ldc_resolution + 3) ** 2
    return pixels * (9 + params.max_layers * per) + 8


# ------------------------------------------------------------------------------------ state


def bake_complete(store: ObjectStore, key: str) -> bool:
    """True when the bake's manifest AND every part it lists are in the store.

    A manifest whose part has gone (deleted, found corrupt) is withdrawn, so the next request
    re-plans and redoes only the missing parts."""
    manifest = read_manifest(store, key)
    if manifest is None:
        return False
    parts = manifest.result.get("parts", [])
    if all(isinstance(p, dict) and store.exists(manifest_key(str(p.get("key")))) for p in parts):
        return True
    delete_artifact(store, key)
    return False


def read_bake_record(store: ObjectStore, scene_id: str, key: str) -> dict[str, Any] | None:
    try:
        doc = json.loads(store.get_bytes(bake_record_key(scene_id, key)))
    except NotFound:
        return None
    except ValueError:
        return None
    return doc if isinstance(doc, dict) else None


def _write_record(store: ObjectStore, scene_id: str, key: str, params: BakeParams, owner: str | None) -> None:
    rkey = bake_record_key(scene_id, key)
    if store.exists(rkey):
        return
    doc = {"key": key, "scene_id": scene_id, "params": bake_params_dict(params),
           "created_at": datetime.now(UTC).isoformat(), "owner": owner}
    store.put_bytes(rkey, json.dumps(doc, sort_keys=True).encode(), "application/json")


def list_bakes(store: ObjectStore, scene_id: str) -> list[tuple[str, BakeParams]]:
    """``(bake key, params)`` of every bake requested for the scene (and not deleted), oldest first."""
    out: list[tuple[str, str, BakeParams]] = []
    for k in store.list(f"bakes/{scene_id}/"):
        key = k.rsplit("/", 1)[-1].removesuffix(".json")
        doc = read_bake_record(store, scene_id, key)
        if doc is None:
            continue
        try:
            params = BakeParams.model_validate(doc["params"])
        except (KeyError, ValueError):
            continue
        out.append((str(doc.get("created_at", "")), key, params))
    out.sort()
    return [(key, params) for _, key, params in out]


# ------------------------------------------------------------------------------------ enqueue


def _payload(scene_id: str, key: str, params: BakeParams) -> dict[str, Any]:
    return {"v": 1, "scene_id": scene_id, "bake_key": key, "params": bake_params_dict(params)}


def _meta(kind: str, key: str, owner: str | None, **extra: Any) -> dict[str, Any]:
    return {"kind": "bake", "bake_role": kind, "bake_key": key, "artifact_key": extra.pop("artifact_key", key),
            "owner": owner, "progress": {"fraction": 0.0, "stage": "queued", "eta_s": None}, **extra}


def enqueue_bake(
    redis: Redis, store: ObjectStore, scene_id: str, params: BakeParams, owner: str | None
) -> tuple[str, Job | None]:
    """Request a bake: ``(key, None)`` when it is complete in the store, else ``(key, merge job)``
    -- the running one, or a new plan job + merge job (the plan job enqueues the missing parts)."""
    key = bake_key(scene_id, params)
    if bake_complete(store, key):
        _write_record(store, scene_id, key, params, owner)
        return key, None
    if not store.exists(f"scenes/{scene_id}.json"):
        raise UnknownScene(f"scene {scene_id} does not exist")
    _write_record(store, scene_id, key, params, owner)
    merge_id = scene_bake_job_id(key)
    plan_id = scene_bake_plan_job_id(key)
    with redis.lock(f"ibr:lock:bake:{key}", timeout=30, blocking_timeout=30):
        merge = fetch_job(redis, merge_id)
        if merge is not None and merge.get_status(refresh=False) in ACTIVE_STATUSES and not merge_stuck(redis, merge):
            add_job_owner(redis, merge_id, owner, BAKE_TIMEOUT_S)
            return key, merge
        if merge is not None:
            merge.delete(remove_from_queue=True)
        payload = _payload(scene_id, key, params)
        plan_job = enqueue_unique(
            redis, "bake", SCENE_BAKE_PLAN_JOB, payload, plan_id, timeout=BAKE_TIMEOUT_S,
            meta=_meta("plan", key, owner), retry=job_retry(), description=f"plan bake of scene {scene_id[:12]}",
            owner=owner,
        )
        assert plan_job is not None
        merge = enqueue_unique(
            redis, "bake", SCENE_BAKE_MERGE_JOB, payload, merge_id, timeout=BAKE_TIMEOUT_S,
            meta=_meta("merge", key, owner), retry=job_retry(), description=f"bake scene {scene_id[:12]}",
            owner=owner, depends_on=Dependency(jobs=[plan_id], allow_failure=True),
        )
        assert merge is not None
        return key, merge


def enqueue_parts(redis: Redis, scene_id: str, key: str, params: BakeParams, specs: list[PartSpec],
                  owner: str | None) -> list[str]:
    """Enqueue a job per part (``specs`` carry their ``key``) and make the merge job wait for them.
    An identical part job already queued or running is shared. An indirect chunk whose axis is
    among ``specs`` waits for that axis's job; one whose axis is in the store already runs at once.
    Returns the part job ids.

    ``specs`` lists every axis before its chunks (``plan_parts``' order). When an axis job is
    created anew here (its previous job was canceled, failed or is gone), a chunk job still
    deferred behind that previous job is replaced: RQ dropped its link when the old axis job was
    deleted, so it would wait forever."""
    ids: list[str] = []
    axis_jobs = {int(s["axis"]): scene_bake_part_job_id(str(s["key"])) for s in specs if s["kind"] == "ldc_axis"}
    renewed: set[int] = set()
    for spec in specs:
        pkey = str(spec["key"])
        pid = scene_bake_part_job_id(pkey)
        previous = fetch_job(redis, pid)
        prev_status = previous.get_status(refresh=False) if previous is not None else None
        if spec["kind"] == "ldc_axis" and prev_status not in ACTIVE_STATUSES:
            renewed.add(int(spec["axis"]))
        if (spec["kind"] == "ldc_indirect" and int(spec["axis"]) in renewed and previous is not None
                and prev_status == JobStatus.DEFERRED):
            previous.delete(remove_from_queue=True)
        func = {"ldc_axis": SCENE_BAKE_LDC_JOB, "ldc_indirect": SCENE_BAKE_INDIRECT_JOB}.get(
            spec["kind"], SCENE_BAKE_LLF_JOB)
        part = {k: v for k, v in spec.items() if k not in ("key", "weight")}
        payload = {**_payload(scene_id, key, params), "part": part, "part_key": pkey}
        depends = None
        if spec["kind"] == "ldc_indirect" and int(spec["axis"]) in axis_jobs:
            # the chunk needs its direct-lit axis; allow_failure: a failed axis makes the chunk fail
            # at once naming it (instead of waiting forever), and the merge job reports both
            depends = Dependency(jobs=[axis_jobs[int(spec["axis"])]], allow_failure=True)
        job = enqueue_unique(
            redis, "bake", func, payload, pid, timeout=BAKE_TIMEOUT_S,
            meta=_meta("part", key, owner, artifact_key=pkey, part=spec["name"]),
            retry=chunk_retry() if spec["kind"] == "ldc_indirect" else job_retry(),
            description=f"bake {spec['name']} of scene {scene_id[:12]}", owner=owner, depends_on=depends,
        )
        assert job is not None
        ids.append(job.id)
    add_part_dependency(redis, scene_bake_job_id(key), ids)
    return ids


_DEAD = frozenset({JobStatus.CANCELED, JobStatus.STOPPED})


def merge_stuck(redis: Redis, merge: Job, _depth: int = 0) -> bool:
    """A deferred merge job that can never run: one of the jobs it waits for was canceled or
    stopped (RQ does not release dependents of those) or has vanished, or is itself a deferred job
    that can never run (an indirect chunk behind a canceled axis), and none is still active.
    The bake then counts as canceled, and a new request re-plans it (redoing the missing parts)."""
    if merge.get_status(refresh=False) != JobStatus.DEFERRED:
        return False
    ids = merge.dependency_ids
    if not ids:
        return False
    deps = fetch_jobs(redis, ids)
    statuses: list[JobStatus | None] = []
    for d in deps:
        st = d.get_status(refresh=False) if d is not None else None
        if d is not None and st == JobStatus.DEFERRED and _depth < 2 and merge_stuck(redis, d, _depth + 1):
            st = JobStatus.CANCELED  # an indirect chunk waiting for a canceled axis: as dead as that
        statuses.append(st)
    if any(st in ACTIVE_STATUSES for st in statuses):
        return False
    return any(st is None or st in _DEAD for st in statuses)


def add_part_dependency(redis: Redis, merge_id: str, part_job_ids: list[str]) -> None:
    """Make the (deferred) merge job wait for these part jobs too.

    RQ records a dependency as two sets: ``rq:job:<merge>:dependencies`` (what it waits for) and
    ``rq:job:<part>:dependents`` (whom a finishing part wakes up); exactly what
    ``Job.register_dependency`` writes. The plan job calls this before it finishes, and RQ
    re-checks ALL of the merge job's dependencies whenever one of them ends (including the plan
    job itself), so a part that finished before it was registered is still counted."""
    if not part_job_ids:
        return
    merge_deps = Job(id=merge_id, connection=redis, serializer=JSONSerializer).dependencies_key
    with redis.pipeline() as p:
        for pid in part_job_ids:
            p.sadd(Job.dependents_key_for(pid), merge_id)
            p.sadd(merge_deps, pid)
        p.execute()


# ------------------------------------------------------------------------------------ status


@dataclass
class _Plan:
    plan: dict[str, Any] | None
    parts: list[dict[str, Any]]


def _plan_from(manifest_result: dict[str, Any] | None, plan_job: Job | None) -> _Plan | None:
    if manifest_result is not None:
        return _Plan(manifest_result.get("plan"), list(manifest_result.get("parts", [])))
    if plan_job is not None and plan_job.get_status(refresh=False) == JobStatus.FINISHED:
        rv = plan_job.return_value()
        if isinstance(rv, dict):
            return _Plan(rv.get("plan"), list(rv.get("parts", [])))
    return None


_PART_STATE: dict[str, BakePartState] = {"queued": "queued", "started": "started", "finished": "finished",
                                          "failed": "failed", "canceled": "canceled"}


def bake_status(redis: Redis, store: ObjectStore, scene_id: str, key: str, params: BakeParams,
                *, cached: bool = False) -> BakePublic:
    """The bake's state, plan, parts (each with state and progress) and aggregated progress."""
    links = {"self": f"/v1/scenes/{scene_id}/bakes/{key}", "job": f"/v1/jobs/{scene_bake_job_id(key)}"}
    # The jobs before the manifest: the merge job publishes the manifest, then RQ records it as
    # finished. Read the other way round, a merge that ends between the two reads shows a finished
    # job and no manifest, which means "the artifact has gone" (state "missing", seen on CI).
    merge = fetch_job(redis, scene_bake_job_id(key))
    plan_job = fetch_job(redis, scene_bake_plan_job_id(key))
    manifest = read_manifest(store, key)
    merge_pub = job_public(merge) if merge is not None else None
    plan_pub = job_public(plan_job) if plan_job is not None else None
    plan = _plan_from(manifest.result if manifest is not None else None, plan_job)

    parts: list[BakePart] = []
    total_w = done_w = 0.0
    if plan is not None:
        specs = plan.parts
        pjobs = fetch_jobs(redis, [scene_bake_part_job_id(str(s["key"])) for s in specs])
        for spec, pj in zip(specs, pjobs, strict=True):
            pkey = str(spec["key"])
            w = float(spec.get("weight", 1.0))
            state: BakePartState
            frac = 0.0
            err: str | None = None
            if store.exists(manifest_key(pkey)):
                state, frac = "finished", 1.0
            elif pj is not None:
                pp = job_public(pj)
                state = _PART_STATE[pp.state] if pp.state != "finished" else "missing"
                frac = pp.progress.fraction if state == "started" else 0.0
                err = pp.error
            else:
                state = "missing"
            total_w += w
            done_w += w * frac
            parts.append(BakePart(name=str(spec["name"]), kind=spec["kind"], key=pkey, state=state,
                                  progress=min(1.0, max(0.0, frac)), weight=w,
                                  job_id=scene_bake_part_job_id(pkey), error=err))

    state_: BakeState
    error: str | None = None
    if manifest is not None and all(p.state == "finished" for p in parts):
        state_ = "finished"
        progress = JobProgress(fraction=1.0, stage="done", eta_s=0.0)
        links["artifact"] = f"/v1/artifacts/{key}"
    else:
        if merge_pub is None:
            state_ = "missing"
        elif merge_pub.state == "failed":
            state_, error = "failed", merge_pub.error
        elif merge_pub.state == "canceled":
            state_, error = "canceled", merge_pub.error
        elif merge is not None and merge_stuck(redis, merge):
            dead = [p.name for p in parts if p.state in ("canceled", "missing")]
            state_ = "canceled"
            error = (f"part(s) {', '.join(dead[:4]) or '(plan)'} were canceled or lost, so the bake cannot finish; "
                     "request it again to redo only the missing parts")
        elif merge_pub.state == "finished":
            state_ = "missing"  # finished, but the artifact has gone since: request it again
        elif merge_pub.state == "started" or (plan_pub is not None and plan_pub.state != "queued"):
            state_ = "running"
        else:
            state_ = "queued"
        if plan_pub is not None and plan_pub.state == "failed" and state_ != "failed":
            error = f"planning failed: {plan_pub.error}"
        frac = 0.95 * (done_w / total_w) if total_w > 0 else 0.0
        if merge_pub is not None and merge_pub.state == "started":
            frac = 0.95 + 0.05 * merge_pub.progress.fraction
        n_done = sum(p.state == "finished" for p in parts)
        stage: str
        if plan is None:
            stage = "planning" if state_ in ("queued", "running") else state_
        elif merge_pub is not None and merge_pub.state == "started":
            stage = "merging"
        else:
            stage = f"{n_done} of {len(parts)} parts done"
        progress = JobProgress(fraction=min(1.0, max(0.0, frac)), stage=stage)
    return BakePublic(key=key, scene_id=scene_id, params=params, state=state_, cached=cached, progress=progress,
                      plan=plan.plan if plan is not None else None, parts=parts, job=merge_pub, error=error,
                      artifact=manifest if state_ == "finished" else None, links=links)


def bake_jobs_active(redis: Redis, key: str, part_keys: list[str]) -> list[str]:
    ids = [scene_bake_job_id(key), scene_bake_plan_job_id(key)] + [scene_bake_part_job_id(k) for k in part_keys]
    out = []
    for jid, job in zip(ids, fetch_jobs(redis, ids), strict=True):
        if job is not None and job.get_status(refresh=False) in ACTIVE_STATUSES:
            out.append(jid)
    return out


def delete_bake(redis: Redis, store: ObjectStore, scene_id: str, key: str, params: BakeParams) -> None:
    """Remove a bake: its manifest, every part artifact and its record. Raises :class:`BakeInUse`
    while one of its jobs is queued or running (cancel ``bake-<key>`` first)."""
    part_keys = [part_key(scene_id, key, s) for s in plan_parts(params, bake_llf=True,
                                                                bake_indirect=params.indirect.mode != "off")]
    active = bake_jobs_active(redis, key, part_keys)
    if active:
        raise BakeInUse(f"bake {key} has {len(active)} queued or running job(s) ({active[0]}, ...); "
                        f"cancel {scene_bake_job_id(key)} and its parts or wait")
    delete_artifact(store, key)
    for pk in part_keys:
        delete_artifact(store, pk)
    store.delete(bake_record_key(scene_id, key))
    ids = [scene_bake_job_id(key), scene_bake_plan_job_id(key)] + [scene_bake_part_job_id(k) for k in part_keys]
    for job in fetch_jobs(redis, ids):
        if job is not None:
            job.delete(remove_from_queue=True)
