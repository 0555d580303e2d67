"""The render worker's in-process cache of loaded scenes and warm renderers.

A render worker (``rq.SimpleWorker``) runs every job in one long-lived process, so a scene
loaded for one job -- tessellated, validated, flattened, its Embree BVH built -- serves the
next job on the same scene for free. The cache is an LRU keyed by scene id and bounded by an
estimate of the bytes each entry holds (``Settings.cache_bytes``).

Scene ids are content hashes, so an entry can never go stale: equal id, equal content.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Generic, TypeVar

import numpy as np

from engine.reference import ReferenceRenderer

if TYPE_CHECKING:
    from engine.newviews.renderer import LDCViewRenderer
    from engine.scene import RuntimeScene
    from workers.scene_loader import LoadedScene

__all__ = [
    "EMBREE_BYTES_PER_TRIANGLE",
    "CachedBakeRenderer",
    "CachedRenderer",
    "LRUBytesCache",
    "RendererCache",
    "runtime_scene_bytes",
]

V = TypeVar("V")

EMBREE_BYTES_PER_TRIANGLE = 160
"""Rough size of Embree's BVH plus its copy of the vertices, per triangle (a static scene's
BVH4 with triangle4 leaves measures ~100-200 bytes per triangle)."""


def runtime_scene_bytes(scene: RuntimeScene) -> int:
    """Bytes held by a runtime scene's arrays plus the estimated Embree BVH built from them."""
    total = 0
    for value in vars(scene).values():
        if isinstance(value, np.ndarray):
            total += value.nbytes
        else:  # material / light tables: dataclasses of arrays
            for inner in getattr(value, "__dict__", {}).values():
                if isinstance(inner, np.ndarray):
                    total += inner.nbytes
    return total + EMBREE_BYTES_PER_TRIANGLE * scene.n_triangles


class LRUBytesCache(Generic[V]):
    """Thread-safe LRU of values with a byte size each, bounded by ``max_bytes`` in total.

    Inserting evicts least-recently-used entries until the total fits. An entry larger than the
    whole budget is still kept (alone) so the job that needed it does not load it twice; the
    next insertion evicts it.
    """

    def __init__(self, max_bytes: int):
        if max_bytes <= 0:
            raise ValueError(f"max_bytes must be > 0, got {max_bytes}")
        self.max_bytes = max_bytes
        self._items: OrderedDict[str, tuple[V, int]] = OrderedDict()
        self._total = 0
        self._lock = threading.RLock()
        self._key_locks: dict[str, threading.Lock] = {}
        self.hits = 0
        self.misses = 0
        self.evictions = 0

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: object) -> bool:
        return key in self._items

    @property
    def total_bytes(self) -> int:
        return self._total

    def keys(self) -> list[str]:
        """Keys from least to most recently used."""
        with self._lock:
            return list(self._items)

    def get(self, key: str) -> V | None:
        with self._lock:
            item = self._items.get(key)
            if item is None:
                return None
            self._items.move_to_end(key)
            return item[0]

    def put(self, key: str, value: V, nbytes: int) -> None:
        if nbytes < 0:
            raise ValueError("nbytes must be >= 0")
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self._total -= old[1]
            self._items[key] = (value, nbytes)
            self._total += nbytes
            while self._total > self.max_bytes and len(self._items) > 1:
                _, (_, size) = self._items.popitem(last=False)
                self._total -= size
                self.evictions += 1

    def resize(self, key: str, nbytes: int) -> None:
        """Record a new size for an entry that grew or shrank in place (e.g. an acceleration
        structure built lazily on first use); evicts others if the total no longer fits."""
        with self._lock:
            item = self._items.get(key)
            if item is not None and item[1] != nbytes:
                self.put(key, item[0], nbytes)

    def pop(self, key: str) -> V | None:
        with self._lock:
            item = self._items.pop(key, None)
            if item is None:
                return None
            self._total -= item[1]
            return item[0]

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._total = 0

    def get_or_create(self, key: str, factory: Callable[[], tuple[V, int]]) -> tuple[V, bool]:
        """``(value, hit)``: the cached value, or ``factory()``'s (value, nbytes) stored and returned.

        Concurrent callers for the same key wait for one factory call instead of loading twice.
        """
        value = self.get(key)
        if value is not None:
            self.hits += 1
            return value, True
        with self._lock:
            key_lock = self._key_locks.setdefault(key, threading.Lock())
        try:
            with key_lock:
                value = self.get(key)
                if value is not None:
                    self.hits += 1
                    return value, True
                self.misses += 1
                value, nbytes = factory()  # may raise: nothing is cached then
                self.put(key, value, nbytes)
                return value, False
        finally:
            with self._lock:
                if self._key_locks.get(key) is key_lock and not key_lock.locked():
                    del self._key_locks[key]


@dataclass
class CachedRenderer:
    """A loaded scene and a renderer bound to it (its Embree scene stays built)."""

    loaded: LoadedScene
    renderer: ReferenceRenderer


@dataclass
class CachedBakeRenderer:
    """A loaded scene and an LDC view renderer holding one bake (LDC + LLF) of it."""

    loaded: LoadedScene
    renderer: LDCViewRenderer
    bake_key: str
    plan: dict[str, object]


class RendererCache(LRUBytesCache["CachedRenderer | CachedBakeRenderer"]):
    """LRU of warm renderers, bounded by bytes: reference renderers keyed by scene id, LDC view
    renderers keyed ``bake:<bake key>`` (a bake's LDC and LLF are the large part of a render
    worker's memory, so they share the one budget)."""

    def get_or_load(self, scene_id: str, load: Callable[[], LoadedScene]) -> tuple[CachedRenderer, bool]:
        """The warm renderer for ``scene_id``, loading the scene with ``load()`` on a miss."""

        def factory() -> tuple[CachedRenderer | CachedBakeRenderer, int]:
            loaded = load()
            entry = CachedRenderer(loaded, ReferenceRenderer(loaded.runtime))
            return entry, runtime_scene_bytes(loaded.runtime)

        value, hit = self.get_or_create(scene_id, factory)
        assert isinstance(value, CachedRenderer)
        return value, hit

    def get_or_load_bake(self, bake_key: str,
                         load: Callable[[], CachedBakeRenderer]) -> tuple[CachedBakeRenderer, bool]:
        """The LDC view renderer of bake ``bake_key``, built by ``load()`` on a miss. Its size is the
        scene's arrays plus the LDC and LLF (``LDCViewRenderer.nbytes``); the render job calls
        :meth:`resize` after a render, when the lazily built IBRT structure has joined them."""

        def factory() -> tuple[CachedRenderer | CachedBakeRenderer, int]:
            entry = load()
            return entry, runtime_scene_bytes(entry.loaded.runtime) + int(entry.renderer.nbytes)

        value, hit = self.get_or_create(f"bake:{bake_key}", factory)
        assert isinstance(value, CachedBakeRenderer)
        return value, hit
