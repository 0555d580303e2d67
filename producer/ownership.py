"""Who may see what: the owners of scenes, datasets, uploaded files, bakes and jobs.

An owner is the id of an API key (``service.core.security``); with authentication off every
caller is ``None`` and sees everything. Content is stored once however many keys send it (scenes,
datasets and uploaded files are content-addressed, bakes are keyed by their inputs, identical
requests share one job), but what a key may see is recorded per key: each gets its own empty
marker object, or its member of a Redis set. A key that knows a hash but never sent the content
gets 404, exactly as for content that does not exist; an upload proves possession by sending the
bytes.

- ``scene-owners/<scene_id>/<owner>``, ``dataset-owners/<dataset_id>/<owner>``: markers in the
  object store (``_`` for an object stored with auth off); a dataset marker holds the name of the
  owner's entry ``dataset-index/owners/<owner>/<stamp>-<dataset_id>`` in its dataset index
  (``GET /v1/datasets`` pages through it; scenes have theirs in ``producer.listings``);
- ``blob-owners/<sha256>/<owner>``: a key that uploaded the file ``blobs/<sha256>`` itself;
- ``bake-owners/<bake_key>/<owner>``: a key that requested the scene bake. A bake recorded before
  these markers existed (none present) is held by the owner its record names. Deleting a bake
  removes the caller's marker; the bake itself goes with the last one;
- ``ibr:job-owners:<job_id>``: the Redis set of everybody who asked for the job;
  ``ibr:job-detached:<job_id>``: those of them who canceled it. Canceling detaches the caller; the
  job is canceled when no owner remains attached (``producer.cancel.cancel_for``).
- ``ibr:job-index:<owner>``: the sorted set of the jobs an owner asked for (score: when it asked,
  in microseconds), and ``ibr:job-index`` of every job: what ``GET /v1/jobs`` pages through
  (``producer.status.list_jobs_page``), so a listing never reads the jobs of other keys. Entries
  are not removed when RQ expires a job (its result or failure TTL): the listing drops the entries
  of jobs Redis no longer holds, and every addition trims entries older than
  ``JOB_INDEX_HORIZON_S``.
"""

from __future__ import annotations

import re
import time
from datetime import UTC, datetime
from typing import Any, cast

from redis import Redis

from producer.queue import FAILURE_TTL_S, KEY_PREFIX
from producer.store import NotFound, ObjectStore

__all__ = [
    "ANON_OWNER",
    "SCENE_OWNERS_PREFIX",
    "add_bake_owner",
    "add_blob_owner",
    "attached_job_owners",
    "bake_owners",
    "blob_visible",
    "detach_job_owner",
    "remove_bake_owner",
    "add_dataset_owner",
    "add_job_owner",
    "add_scene_owner",
    "dataset_index_prefix",
    "dataset_owners",
    "is_entry",
    "stamp",
    "dataset_visible",
    "job_owners",
    "job_owners_key",
    "JOB_INDEX_HORIZON_S",
    "index_job",
    "job_index_key",
    "remove_dataset_owner",
    "remove_scene_owner",
    "scene_owners",
    "scene_visible",
    "visible_dataset_ids",
    "visible_scene_ids",
]

ANON_OWNER = "_"
"""Marker name for scenes and datasets stored while authentication is off."""
SCENE_OWNERS_PREFIX = "scene-owners/"
DATASET_OWNERS_PREFIX = "dataset-owners/"
BLOB_OWNERS_PREFIX = "blob-owners/"
BAKE_OWNERS_PREFIX = "bake-owners/"
DATASET_INDEX_PREFIX = "dataset-index/"
_SHA256 = re.compile(r"[0-9a-f]{64}")
_ENTRY = re.compile(r"\d{8}T\d{12}Z-[0-9a-f]{64}")


def stamp(when: datetime) -> str:
    """The sortable time in an index entry's name ``<stamp>-<id>``: ``20261202T153012123456Z`` (UTC)."""
    return when.astimezone(UTC).strftime("%Y%m%dT%H%M%S%fZ")


def is_entry(name: str) -> bool:
    """Is ``name`` an index entry's name ``<stamp>-<sha256 id>`` (what listings take as a cursor)?"""
    return _ENTRY.fullmatch(name) is not None


def _checked_marker(prefix: str, what: str, ident: str, owner: str | None) -> str:
    """``<prefix><ident>/<owner>``; an ident that is not a sha256 is a 404 naming ``what``."""
    if not isinstance(ident, str) or _SHA256.fullmatch(ident) is None:
        raise NotFound(f"{what} {ident!r}")
    return f"{prefix}{ident}/{owner or ANON_OWNER}"


def _ids_visible_to(store: ObjectStore, prefix: str, owner: str | None) -> set[str] | None:
    """The ids under ``prefix`` with a marker of ``owner`` (one listing); None means all (auth off)."""
    if owner is None:
        return None
    out: set[str] = set()
    for key in store.list(prefix):
        ident, _, who = key[len(prefix):].partition("/")
        if who == owner:
            out.add(ident)
    return out


# ------------------------------------------------------------------------------------ scenes


def _scene_marker(scene_id: str, owner: str | None) -> str:
    return f"{SCENE_OWNERS_PREFIX}{scene_id}/{owner or ANON_OWNER}"


def add_scene_owner(store: ObjectStore, scene_id: str, owner: str | None) -> None:
    store.put_bytes(_scene_marker(scene_id, owner), b"", "text/plain")


def remove_scene_owner(store: ObjectStore, scene_id: str, owner: str | None) -> None:
    store.delete(_scene_marker(scene_id, owner))


def scene_owners(store: ObjectStore, scene_id: str) -> list[str]:
    prefix = f"{SCENE_OWNERS_PREFIX}{scene_id}/"
    return [k[len(prefix):] for k in store.list(prefix)]


def scene_visible(store: ObjectStore, scene_id: str, owner: str | None) -> bool:
    """Can ``owner`` see scene ``scene_id``? With auth off (owner None) every scene is visible."""
    if owner is None:
        return True
    return store.exists(_scene_marker(scene_id, owner))


def visible_scene_ids(store: ObjectStore, owner: str | None) -> set[str] | None:
    """Scene ids ``owner`` may see (one listing); None means all (auth off)."""
    return _ids_visible_to(store, SCENE_OWNERS_PREFIX, owner)


# ------------------------------------------------------------------------------------ datasets


def _dataset_marker(dataset_id: str, owner: str | None) -> str:
    return _checked_marker(DATASET_OWNERS_PREFIX, "dataset", dataset_id, owner)


def dataset_index_prefix(owner: str | None) -> str:
    """The index ``GET /v1/datasets`` pages through for ``owner`` (None: every dataset, auth off)."""
    if owner is None or owner == ANON_OWNER:
        return f"{DATASET_INDEX_PREFIX}all/"
    return f"{DATASET_INDEX_PREFIX}owners/{owner}/"


def add_dataset_owner(store: ObjectStore, dataset_id: str, owner: str | None, since: datetime | None = None) -> None:
    """``owner`` holds the dataset: its marker, then its entry in ``owner``'s dataset index (so a
    listed dataset is always visible). The marker holds the entry's name; the entry's time is when
    ``owner`` first held the dataset (``since``, else now), kept when it is added again."""
    marker = _dataset_marker(dataset_id, owner)
    if owner is None or owner == ANON_OWNER:  # auth off: listed from the index of every dataset
        store.put_bytes(marker, b"", "text/plain")
        return
    try:
        entry = store.get_bytes(marker).decode("ascii", "replace")
    except NotFound:
        entry = ""
    if not is_entry(entry) or not entry.endswith(dataset_id):
        entry = f"{stamp(since or datetime.now(UTC))}-{dataset_id}"
        store.put_bytes(marker, entry.encode("ascii"), "text/plain")
    store.put_bytes(dataset_index_prefix(owner) + entry, b"", "text/plain")


def remove_dataset_owner(store: ObjectStore, dataset_id: str, owner: str | None) -> None:
    """``owner`` lets go of the dataset: its index entry first, then its marker."""
    marker = _dataset_marker(dataset_id, owner)
    if owner is not None and owner != ANON_OWNER:
        prefix = dataset_index_prefix(owner)
        try:
            entry = store.get_bytes(marker).decode("ascii", "replace")
        except NotFound:
            entry = ""
        for key in [prefix + entry] if is_entry(entry) else [k for k in store.list(prefix)
                                                              if k.endswith(f"-{dataset_id}")]:
            store.delete(key)
    store.delete(marker)


def dataset_owners(store: ObjectStore, dataset_id: str) -> list[str]:
    prefix = _dataset_marker(dataset_id, None)[: -len(ANON_OWNER)]
    return [k[len(prefix):] for k in store.list(prefix)]


def dataset_visible(store: ObjectStore, dataset_id: str, owner: str | None) -> bool:
    """With auth off (owner None) every dataset is visible."""
    if _SHA256.fullmatch(dataset_id or "") is None:
        return False
    return owner is None or store.exists(_dataset_marker(dataset_id, owner))


def visible_dataset_ids(store: ObjectStore, owner: str | None) -> set[str] | None:
    """Dataset ids ``owner`` may see (one listing); None means all (auth off)."""
    return _ids_visible_to(store, DATASET_OWNERS_PREFIX, owner)


# ------------------------------------------------------------------------------------ uploaded files


def _blob_marker(sha: str, owner: str | None) -> str:
    return _checked_marker(BLOB_OWNERS_PREFIX, "file", sha, owner)


def add_blob_owner(store: ObjectStore, sha: str, owner: str | None) -> None:
    """Record that ``owner`` sent the bytes of file ``sha`` (nothing to record with auth off)."""
    if owner is not None:
        store.put_bytes(_blob_marker(sha, owner), b"", "text/plain")


def blob_visible(store: ObjectStore, sha: str, owner: str | None) -> bool:
    """Did ``owner`` upload file ``sha`` itself? With auth off (owner None) every file counts."""
    if _SHA256.fullmatch(sha or "") is None:
        return False
    return owner is None or store.exists(_blob_marker(sha, owner))


# ------------------------------------------------------------------------------------ scene bakes


def _bake_marker(bake_key: str, owner: str | None) -> str:
    return _checked_marker(BAKE_OWNERS_PREFIX, "bake", bake_key, owner)


def bake_owners(store: ObjectStore, bake_key: str, recorded_owner: str | None = None) -> set[str]:
    """Who holds a bake: its markers, or the owner its record names when it has none."""
    prefix = _bake_marker(bake_key, None)[: -len(ANON_OWNER)]
    markers = {k[len(prefix):] for k in store.list(prefix)}
    if not markers and recorded_owner:
        return {recorded_owner}
    return markers


def add_bake_owner(store: ObjectStore, bake_key: str, owner: str | None, recorded_owner: str | None = None
                   ) -> None:
    """``owner`` holds the bake now. The first marker of a bake recorded without markers also
    records the owner its record names, who held it implicitly until now."""
    if recorded_owner and recorded_owner != owner and not bake_owners(store, bake_key) - {recorded_owner}:
        store.put_bytes(_bake_marker(bake_key, recorded_owner), b"", "text/plain")
    store.put_bytes(_bake_marker(bake_key, owner), b"", "text/plain")


def remove_bake_owner(store: ObjectStore, bake_key: str, owner: str | None) -> None:
    """Let go of a bake (everybody lets go with owner None: auth off, or the bake is deleted)."""
    prefix = _bake_marker(bake_key, None)[: -len(ANON_OWNER)]
    for key in store.list(prefix) if owner is None else [_bake_marker(bake_key, owner)]:
        store.delete(key)


# ------------------------------------------------------------------------------------ jobs


def job_owners_key(job_id: str) -> str:
    return f"{KEY_PREFIX}job-owners:{job_id}"


def job_detached_key(job_id: str) -> str:
    return f"{KEY_PREFIX}job-detached:{job_id}"


JOB_INDEX_HORIZON_S = 2 * FAILURE_TTL_S
"""How long a job stays in the job indexes: longer than any job lives in Redis once it ended (RQ
keeps a failed job ``FAILURE_TTL_S``); a job still queued after this long drops out of the
listing (it stays readable by its id)."""


def job_index_key(owner: str | None) -> str:
    """The sorted set ``GET /v1/jobs`` reads for ``owner`` (None: every job, for auth off)."""
    return f"{KEY_PREFIX}job-index:{owner}" if owner else f"{KEY_PREFIX}job-index"


def _index_add(p: Any, owner: str | None, job_id: str, now_us: int, *, only_new: bool) -> None:
    key = job_index_key(owner)
    p.zadd(key, {job_id: now_us}, nx=only_new)
    p.zremrangebyscore(key, "-inf", f"({now_us - JOB_INDEX_HORIZON_S * 1_000_000}")
    p.expire(key, JOB_INDEX_HORIZON_S)


def index_job(redis: Redis, job_id: str, owner: str | None) -> None:
    """A job was created (anew, or again under the same id): it goes to the top of the index of
    every job and of ``owner``'s (an earlier entry of the same id moves)."""
    now_us = time.time_ns() // 1000
    with redis.pipeline(transaction=False) as p:
        _index_add(p, None, job_id, now_us, only_new=False)
        if owner:
            _index_add(p, owner, job_id, now_us, only_new=False)
        p.execute()


def add_job_owner(redis: Redis, job_id: str, owner: str | None, timeout: int) -> None:
    """Record ``owner`` as one of the keys that asked for ``job_id`` (so they may see it); the set
    lives as long as the job can (its timeout plus the failure TTL). Asking again after canceling
    attaches the owner again. The job enters ``owner``'s job index unless it is there already (a
    key joining a shared job lists it from the time it first asked)."""
    if owner:
        key = job_owners_key(job_id)
        with redis.pipeline() as p:
            p.sadd(key, owner)
            p.expire(key, timeout + FAILURE_TTL_S)
            p.srem(job_detached_key(job_id), owner)
            _index_add(p, owner, job_id, time.time_ns() // 1000, only_new=True)
            p.execute()


def _members(raw: Any) -> set[str]:
    return {m.decode() if isinstance(m, bytes) else str(m) for m in cast(set[Any], raw)}


def attached_job_owners(redis: Redis, job_id: str, first_owner: str | None) -> set[str]:
    """The owners still waiting for a job: everybody who asked for it (``first_owner``, the one
    its meta names, included) but has not canceled it."""
    asked = job_owners(redis, job_id) | ({first_owner} if first_owner else set())
    return asked - _members(redis.smembers(job_detached_key(job_id)))


def detach_job_owner(redis: Redis, job_id: str, owner: str, first_owner: str | None) -> set[str]:
    """``owner`` cancels its interest in a job; returns the owners still attached (empty: cancel
    the job itself). Atomic against a concurrent ``add_job_owner`` of the same job id."""
    detached = job_detached_key(job_id)
    with redis.pipeline() as p:
        p.sadd(detached, owner)
        p.expire(detached, FAILURE_TTL_S * 2)
        p.smembers(job_owners_key(job_id))
        p.smembers(detached)
        _, _, asked, gone = p.execute()
    return (_members(asked) | ({first_owner} if first_owner else set())) - _members(gone)


def job_owners(redis: Redis, job_id: str) -> set[str]:
    """Everybody who asked for this job (identical requests share one job)."""
    return _members(redis.smembers(job_owners_key(job_id)))
