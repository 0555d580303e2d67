"""Following a bake from a test: until it ends, or until its plan has named its parts."""

from __future__ import annotations

import time

from redis import Redis

from api_schemas.service import BakeParams, BakePublic
from producer import bakes
from producer.store import ObjectStore
from tests.fixtures.redis import WorkerProcess


def wait_bake(redis: Redis, store: ObjectStore, sid: str, key: str, params: BakeParams, timeout: float,
              w: WorkerProcess, seen: list[BakePublic] | None = None) -> BakePublic:
    """The bake's status once it is finished, failed, canceled or missing (every poll into ``seen``)."""
    deadline = time.monotonic() + timeout
    st = bakes.bake_status(redis, store, sid, key, params)
    while time.monotonic() < deadline:
        st = bakes.bake_status(redis, store, sid, key, params)
        if seen is not None:
            seen.append(st)
        if st.state in ("finished", "failed", "canceled", "missing"):
            return st
        time.sleep(0.1)
    raise AssertionError(f"bake not done after {timeout} s: {st.state} {st.progress}\n{w.log()}")


def wait_parts(redis: Redis, store: ObjectStore, sid: str, key: str, params: BakeParams, timeout: float,
               w: WorkerProcess) -> BakePublic:
    """The bake's status as soon as its plan job has enqueued the parts."""
    deadline = time.monotonic() + timeout
    st = bakes.bake_status(redis, store, sid, key, params)
    while not st.parts:
        assert time.monotonic() < deadline, w.log()
        time.sleep(0.02)
        st = bakes.bake_status(redis, store, sid, key, params)
    return st
