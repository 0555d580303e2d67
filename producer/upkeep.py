"""Store upkeep the API runs at start-up and then periodically, in a background thread.

- stray temp files: a local store's writes go through temp files (``producer.store.local``); a
  writer killed mid-write (a job process SIGKILLed, the host lost) leaves
  ``artifacts/<key>/.<name>~<hex>.tmp`` behind, which :meth:`LocalStore.sweep_temp_files`
  removes once older than ``store_temp_grace_s``. (S3 PUTs are atomic: nothing to sweep.)
- the scene and dataset indexes (``producer.listings``, ``producer.datasets``): a store written
  before listings read an index gets its indexes built once (``scene-index/built`` and
  ``dataset-index/built``, empty markers, record that they were; a store without scenes or
  datasets is left as it is); a Redis holding jobs enqueued before the job indexes gets them
  indexed once (``producer.status.rebuild_job_index``).

Every step is idempotent, so several API replicas may run it at once; a failure is logged and
retried at the next round, never raised into the API.
"""

from __future__ import annotations

import logging
import threading

from redis import Redis

from producer.datasets import rebuild_dataset_index
from producer.listings import SCENE_INDEX_PREFIX, rebuild_scene_index
from producer.ownership import DATASET_INDEX_PREFIX
from producer.status import rebuild_job_index
from producer.store import LocalStore, ObjectStore

__all__ = ["DATASET_INDEX_BUILT_KEY", "INDEX_BUILT_KEY", "StoreUpkeep", "run_upkeep"]

log = logging.getLogger(__name__)

INDEX_BUILT_KEY = f"{SCENE_INDEX_PREFIX}built"
DATASET_INDEX_BUILT_KEY = f"{DATASET_INDEX_PREFIX}built"


def run_upkeep(store: ObjectStore, temp_grace_s: float, redis: Redis | None = None) -> dict[str, int]:
    """One round: sweep stray temp files, build the scene, dataset (and, given ``redis``, job)
    indexes if they never were. Returns counts."""
    out = {"temp_files_removed": 0, "scenes_indexed": 0, "datasets_indexed": 0, "jobs_indexed": 0}
    if redis is not None:
        out["jobs_indexed"] = rebuild_job_index(redis)
        if out["jobs_indexed"]:
            log.info("job indexes built for %d jobs", out["jobs_indexed"])
    if isinstance(store, LocalStore):
        removed = store.sweep_temp_files(temp_grace_s)
        out["temp_files_removed"] = len(removed)
        if removed:
            log.warning("removed %d stray temp files of writes that never finished: %s", len(removed),
                        ", ".join(removed[:10]) + (" ..." if len(removed) > 10 else ""))
    if not store.exists(INDEX_BUILT_KEY):
        out["scenes_indexed"] = rebuild_scene_index(store)
        if out["scenes_indexed"]:  # an empty store has nothing to build (and gets no write)
            store.put_bytes(INDEX_BUILT_KEY, b"", "text/plain")
            log.info("scene index built for %d stored scenes", out["scenes_indexed"])
    if not store.exists(DATASET_INDEX_BUILT_KEY):
        out["datasets_indexed"] = rebuild_dataset_index(store)
        if out["datasets_indexed"]:
            store.put_bytes(DATASET_INDEX_BUILT_KEY, b"", "text/plain")
            log.info("dataset index built for %d stored datasets", out["datasets_indexed"])
    return out


class StoreUpkeep:
    """``run_upkeep`` now and then every ``interval_s`` seconds (0: once) on a daemon thread."""

    def __init__(self, store: ObjectStore, temp_grace_s: float, interval_s: float, redis: Redis | None = None
                 ) -> None:
        self.store, self.temp_grace_s, self.interval_s, self.redis = store, temp_grace_s, interval_s, redis
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ibr-store-upkeep", daemon=True)
        self.rounds = 0

    def start(self) -> StoreUpkeep:
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                run_upkeep(self.store, self.temp_grace_s, self.redis)
            except Exception:  # a store outage: the next round tries again
                log.exception("store upkeep failed; retrying at the next round")
            self.rounds += 1
            if self.interval_s <= 0 or self._stop.wait(self.interval_s):
                return
