"""Who may see what: the owners of scenes, datasets and jobs.

An owner is the id of an API key (``service.core.security``); with authentication off every
caller is ``None`` and sees everything. Scenes and datasets are content-addressed, so two keys
that upload the same scene share it: each gets its own empty marker object. Jobs are shared by
identical requests: their owners are a Redis set.

- ``scene-owners/<scene_id>/<owner>`` and ``dataset-owners/<dataset_id>/<owner>``: markers in the
  object store (``_`` for an object stored with auth off);
- ``ibr:job-owners:<job_id>``: the Redis set of everybody who asked for the job.
"""

from __future__ import annotations

import re
from typing import Any, cast

from redis import Redis

from producer.queue import FAILURE_TTL_S, KEY_PREFIX
from producer.store import NotFound, ObjectStore

__all__ = [
    "ANON_OWNER",
    "SCENE_OWNERS_PREFIX",
    "add_dataset_owner",
    "add_job_owner",
    "add_scene_owner",
    "dataset_owners",
    "dataset_visible",
    "job_owners",
    "job_owners_key",
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
_SHA256 = re.compile(r"[0-9a-f]{64}")

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
    if owner is None:
        return None
    out: set[str] = set()
    for key in store.list(SCENE_OWNERS_PREFIX):
        scene_id, _, who = key[len(SCENE_OWNERS_PREFIX):].partition("/")
        if who == owner:
            out.add(scene_id)
    return out


# ------------------------------------------------------------------------------------ datasets


def _dataset_marker(dataset_id: str, owner: str | None) -> str:
    if not isinstance(dataset_id, str) or _SHA256.fullmatch(dataset_id) is None:
        raise NotFound(f"dataset {dataset_id!r}")
    return f"{DATASET_OWNERS_PREFIX}{dataset_id}/{owner or ANON_OWNER}"


def add_dataset_owner(store: ObjectStore, dataset_id: str, owner: str | None) -> None:
    store.put_bytes(_dataset_marker(dataset_id, owner), b"", "text/plain")


def remove_dataset_owner(store: ObjectStore, dataset_id: str, owner: str | None) -> None:
    store.delete(_dataset_marker(dataset_id, owner))


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
    if owner is None:
        return None
    out: set[str] = set()
    for key in store.list(DATASET_OWNERS_PREFIX):
        did, _, who = key[len(DATASET_OWNERS_PREFIX):].partition("/")
        if who == owner:
            out.add(did)
    return out


# ------------------------------------------------------------------------------------ jobs


def job_owners_key(job_id: str) -> str:
    return f"{KEY_PREFIX}job-owners:{job_id}"


def add_job_owner(redis: Redis, job_id: str, owner: str | None, timeout: int) -> None:
    """Record ``owner`` as one of the keys that asked for ``job_id`` (so they may see it); the set
    lives as long as the job can (its timeout plus the failure TTL)."""
    if owner:
        key = job_owners_key(job_id)
        with redis.pipeline() as p:
            p.sadd(key, owner)
            p.expire(key, timeout + FAILURE_TTL_S)
            p.execute()


def job_owners(redis: Redis, job_id: str) -> set[str]:
    """Everybody who asked for this job (identical requests share one job)."""
    return {m.decode() if isinstance(m, bytes) else str(m)
            for m in cast(set[Any], redis.smembers(job_owners_key(job_id)))}
