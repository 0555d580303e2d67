"""Scene listings that read an index, not every scene: per-owner index entries in the store.

``GET /v1/scenes`` pages through the scenes an API key stored. Reading every scene document to
answer it would make its time grow with the size of every scene in the store (one 30 MiB scene:
seconds per listing, for every key); the index makes it a listing of one "directory" page and one
small read per scene shown:

- ``scene-index/owners/<owner>/<stamp>-<scene_id>``: an empty entry per scene ``owner`` stored;
- ``scene-index/all/<stamp>-<scene_id>``: an entry per scene, the listing with auth off;

``<stamp>`` is the scene's ``created_at`` (``20261202T153012123456Z``, UTC), so an index lists in
creation order, and the entry name is the listing's cursor. Each entry shows the scene's summary
(``producer.artifacts.read_scene_summary``: the public view, independent of the scene's size).

Order of writes: document, summary, owner marker (``producer.ownership``), index entries; removal
runs the other way (index entry before the marker, summary before the document). A listing that
meets an entry whose scene is gone (deleted, or its document found corrupt and removed) or no
longer visible to the owner removes the entry and goes on; a scene whose summary alone is missing
(stored before summaries existed) gets it written from its document once.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from api_schemas.service import ScenePublic
from producer.artifacts import get_scene, read_scene_summary, scene_key, write_scene_summary
from producer.ownership import ANON_OWNER, SCENE_OWNERS_PREFIX, is_entry, scene_visible, stamp
from producer.store import ChecksumMismatch, LocalStore, NotFound, ObjectStore, StoreError

__all__ = [
    "SCENE_INDEX_PREFIX",
    "BadCursor",
    "index_scene",
    "list_scene_page",
    "page_index",
    "rebuild_scene_index",
    "unindex_scene",
    "unindex_scene_owner",
]

log = logging.getLogger(__name__)

SCENE_INDEX_PREFIX = "scene-index/"
_READ_THREADS = 8


class BadCursor(ValueError):
    """A listing cursor that no listing returned."""


def _prefix(owner: str | None) -> str:
    return f"{SCENE_INDEX_PREFIX}all/" if owner is None else f"{SCENE_INDEX_PREFIX}owners/{owner}/"


def _entry(public: ScenePublic) -> str:
    return f"{stamp(public.created_at)}-{public.id}"


def index_scene(store: ObjectStore, public: ScenePublic, owner: str | None) -> None:
    """List ``public`` (a stored scene) for everybody (auth off) and for ``owner``. Idempotent:
    the entry's name depends only on the scene, so storing it again rewrites the same entries."""
    name = _entry(public)
    store.put_bytes(_prefix(None) + name, b"", "text/plain")
    if owner is not None:
        store.put_bytes(_prefix(owner) + name, b"", "text/plain")


def _find(store: ObjectStore, owner: str | None, scene_id: str) -> list[str]:
    """The index entries of ``scene_id`` in ``owner``'s index: from its summary, or by a listing
    of the index when the summary is gone."""
    summary = read_scene_summary(store, scene_id)
    if summary is not None:
        return [_prefix(owner) + _entry(summary)]
    return [k for k in store.list(_prefix(owner)) if k.endswith(f"-{scene_id}")]


def unindex_scene_owner(store: ObjectStore, scene_id: str, owner: str) -> None:
    """``owner`` no longer lists the scene (call before its marker is removed)."""
    for key in _find(store, owner, scene_id):
        store.delete(key)


def unindex_scene(store: ObjectStore, scene_id: str) -> None:
    """Nobody lists the scene any more (call before its document and summary are removed)."""
    for key in _find(store, None, scene_id):
        store.delete(key)


def _read_summaries(store: ObjectStore, ids: list[str]) -> list[ScenePublic | None]:
    if len(ids) < 2 or isinstance(store, LocalStore):  # local reads take microseconds: no threads
        return [read_scene_summary(store, i) for i in ids]
    with ThreadPoolExecutor(min(_READ_THREADS, len(ids)), thread_name_prefix="ibr-listing") as pool:
        return list(pool.map(lambda i: read_scene_summary(store, i), ids))


def _repair(store: ObjectStore, scene_id: str, owner: str | None) -> ScenePublic | None:
    """An entry without a summary: the scene's public view when the scene is still there and
    visible to ``owner`` (its summary written again), else None (the entry is stale)."""
    if not store.exists(scene_key(scene_id)) or not scene_visible(store, scene_id, owner):
        return None
    try:
        _, _, public = get_scene(store, scene_id)  # reads the document once
    except (NotFound, ChecksumMismatch):
        return None
    except StoreError as exc:  # a document the current schema refuses: listed from its summary
        log.error("scene %s: not listed (%s)", scene_id, exc)
        return None
    write_scene_summary(store, public)
    return public


T = TypeVar("T")


def page_index(store: ObjectStore, prefix: str, limit: int, cursor: str | None,
               load: Callable[[list[str]], list[T | None]]) -> tuple[list[T], str | None]:
    """One page of an index of entries ``<prefix><stamp>-<id>``: ``load(ids)`` gives each entry's
    item, None for a stale entry (its resource is gone), which is removed; reads ``limit`` (+1)
    entries, more only to replace stale ones. ``(items, cursor of the next page or None)``;
    ``BadCursor`` for a cursor that is not an entry name."""
    if cursor is not None and not is_entry(cursor):
        raise BadCursor(f"invalid cursor {cursor[:80]!r}: pass the next_cursor of the previous page")
    limit = max(1, limit)
    after = prefix + cursor if cursor else ""
    out: list[T] = []
    while True:
        want = limit - len(out)
        keys = store.list_page(prefix, start_after=after, limit=want + 1)
        page = keys[:want]
        valid = [k for k in page if is_entry(k[len(prefix):])]
        found = dict(zip(valid, load([k[-64:] for k in valid]), strict=True))
        for key in page:
            after = key
            item = found.get(key)
            if item is None:
                log.info("index entry %s of a resource that is gone removed", key)
                store.delete(key)
                continue
            out.append(item)
        if len(keys) <= want:  # nothing after this page
            return out, None
        if len(out) == limit:
            return out, after[len(prefix):]


def list_scene_page(store: ObjectStore, owner: str | None, limit: int, cursor: str | None = None
                    ) -> tuple[list[ScenePublic], str | None]:
    """One page of the scenes ``owner`` stored (every scene with owner None), oldest first, and the
    cursor of the next page (None after the last). Reads ``limit`` (+1) index entries and the
    summaries of the scenes shown; stale entries are removed on the way. ``BadCursor`` for a cursor
    no listing returned."""

    def load(ids: list[str]) -> list[ScenePublic | None]:
        out: list[ScenePublic | None] = []
        for sid, summary in zip(ids, _read_summaries(store, ids), strict=True):
            if summary is None:
                summary = _repair(store, sid, owner)
            out.append(None if summary is None else summary.model_copy(update={"links": {
                "self": f"/v1/scenes/{sid}", "document": f"/v1/scenes/{sid}/document"}}))
        return out

    return page_index(store, _prefix(owner), limit, cursor, load)


def rebuild_scene_index(store: ObjectStore) -> int:
    """Index every stored scene for its owners (the markers ``scene-owners/<id>/<owner>``) and for
    everybody: what a store written before the index needs once; idempotent. Returns how many
    scenes were indexed. Reads each scene's summary (its document when it has none)."""
    owners: dict[str, list[str]] = {}
    for key in store.list(SCENE_OWNERS_PREFIX):
        sid, _, who = key[len(SCENE_OWNERS_PREFIX):].partition("/")
        owners.setdefault(sid, []).append(who)
    n = 0
    for sid, holders in owners.items():
        summary = read_scene_summary(store, sid) or _repair(store, sid, None)
        if summary is None:
            continue
        for w in holders:
            index_scene(store, summary, None if w == ANON_OWNER else w)
        n += 1
    return n
