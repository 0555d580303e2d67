"""Batches: many renders enqueued as one, remembered in the Redis hash ``ibr:batch:<id>``."""

from __future__ import annotations

import json
import uuid
from collections.abc import Sequence
from datetime import UTC, datetime
from typing import Literal, cast

from redis import Redis

from api_schemas.service import BatchPublic, JobProgress, JobState, RenderPublic, RenderRequest, method_needs_bake
from producer.artifacts import read_manifest
from producer.bakes import bake_complete, bake_key
from producer.errors import BakeMissing
from producer.queue import BATCH_TTL_S, KEY_PREFIX, fetch_jobs
from producer.renders import enqueue_render
from producer.status import job_public
from producer.store import ObjectStore

__all__ = ["batch_owner", "batch_status", "enqueue_batch"]


def batch_key(batch_id: str) -> str:
    return f"{KEY_PREFIX}batch:{batch_id}"


def enqueue_batch(
    redis: Redis,
    requests: Sequence[RenderRequest],
    owner: str | None,
    *,
    store: ObjectStore | None = None,
    batch_id: str | None = None,
    scene_ids: Sequence[str] = (),
) -> BatchPublic:
    """Enqueue many renders as one batch and remember its members (Redis hash ``ibr:batch:<id>``).

    ``scene_ids``: scenes the caller stored for this batch (listed in the answer). Each render
    goes through :func:`enqueue_render` (cache hits and de-duplication included).
    """
    bid = batch_id or uuid.uuid4().hex
    if store is not None:  # an LDC render without its bake fails the whole batch before anything is queued
        for req in requests:
            if method_needs_bake(req.method) and req.missing_bake == "fail":
                bkey = bake_key(req.scene_id, req.bake)
                if not bake_complete(store, bkey):
                    raise BakeMissing(req.scene_id, bkey, None)
    members: list[dict[str, str | None]] = []
    for req in requests:
        key, job = enqueue_render(redis, req, owner, batch_id=bid, store=store)
        members.append({"artifact_key": key, "job_id": job.id if job is not None else None})
    record = {
        "owner": owner or "",
        "created_at": datetime.now(UTC).isoformat(),
        "scene_ids": json.dumps(list(scene_ids)),
        "renders": json.dumps(members),
    }
    with redis.pipeline() as p:
        p.hset(batch_key(bid), mapping=record)  # type: ignore[arg-type]  # redis-py Mapping key invariance
        p.expire(batch_key(bid), BATCH_TTL_S)
        p.execute()
    status = batch_status(redis, bid, store=store)
    assert status is not None
    return status


def batch_owner(redis: Redis, batch_id: str) -> str | None:
    raw = redis.hget(batch_key(batch_id), "owner")
    if raw is None:
        return None
    text = raw.decode() if isinstance(raw, bytes) else str(raw)
    return text or None


_RENDER_STATUS: dict[JobState, Literal["queued", "running", "finished", "failed"]] = {
    "queued": "queued", "started": "running", "finished": "finished", "failed": "failed", "canceled": "failed",
}


def batch_status(redis: Redis, batch_id: str, *, store: ObjectStore | None = None) -> BatchPublic | None:
    """A batch's renders with their states, counts per state (plus ``cached`` and ``lost``) and the
    mean progress (a finished, failed, canceled or cached render counts as done). None if unknown.

    A member whose job has expired from Redis counts as finished when ``store`` holds its
    artifact, else as ``lost`` (e.g. Redis restarted without persistence, docs/hard-cases.md #22).
    """
    raw = cast(dict[bytes, bytes], redis.hgetall(batch_key(batch_id)))
    if not raw:
        return None
    members = json.loads(raw.get(b"renders", b"[]"))
    scene_ids = json.loads(raw.get(b"scene_ids", b"[]"))
    job_ids = [m["job_id"] for m in members if m.get("job_id")]
    fetched = fetch_jobs(redis, job_ids)
    by_id = dict(zip(job_ids, fetched, strict=True))
    renders: list[RenderPublic] = []
    counts: dict[str, int] = {}
    total = 0.0
    for m in members:
        key = m["artifact_key"]
        links = {"artifact": f"/v1/artifacts/{key}"}
        jid = m.get("job_id")
        if not jid:
            renders.append(RenderPublic(artifact_key=key, status="cached", links=links))
            counts["cached"] = counts.get("cached", 0) + 1
            total += 1.0
            continue
        job = by_id.get(jid)
        if job is None:
            done = False
            if store is not None:
                done = read_manifest(store, key) is not None
            label = "finished" if done else "lost"
            counts[label] = counts.get(label, 0) + 1
            renders.append(RenderPublic(artifact_key=key, status="finished" if done else "failed", links=links))
            total += 1.0
            continue
        pub = job_public(job)
        counts[pub.state] = counts.get(pub.state, 0) + 1
        total += 1.0 if pub.state in ("finished", "failed", "canceled") else pub.progress.fraction
        renders.append(RenderPublic(artifact_key=key, status=_RENDER_STATUS[pub.state], job=pub,
                                    links={**links, "job": f"/v1/jobs/{jid}"}))
    n = len(members)
    frac = total / n if n else 1.0
    n_open = sum(counts.get(s, 0) for s in ("queued", "started"))
    stage = "done" if n_open == 0 else f"{n - n_open} of {n} renders done"
    return BatchPublic(id=batch_id, scene_ids=scene_ids, renders=renders,
                       progress=JobProgress(fraction=min(1.0, frac), stage=stage), counts=counts)
