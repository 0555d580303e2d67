"""Bake artifacts are byte-identical for identical inputs: the same bake done twice on a real
forking bake worker (every part kind: LDC axes, their indirect chunks, LLF view chunks; and the
bake's plan.json) stores the same bytes, although the wall-clock times of the two runs differ
(they live in each artifact's manifest ``result``, outside the content-addressed bytes)."""

from __future__ import annotations

import io
import re
import time

import numpy as np
import pytest
from redis import Redis

from api_schemas.service import BakeParams
from producer import bakes
from producer.artifacts import delete_artifact, put_scene, read_blob, read_manifest
from producer.store import ObjectStore
from tests.fixtures.redis import StartWorker, WorkerProcess
from tests.workers.queue.bake_waits import wait_bake
from tests.workers.queue.test_bake_jobs import SMALL, mirror_scene
from workers.jobs.bake import npz_bytes, read_npz

PARAMS = BakeParams.model_validate({
    **SMALL.model_dump(), "ldc_resolution": 16, "seed": 3, "llf_f": 1, "llf_resolution": 8, "llf_chunk": 6,
    "llf_params": {"spp": 1, "max_depth": 1, "glossy_samples": 1, "area_light_samples": 1},
    "indirect": {"noise": 0.05, "min_paths": 4, "max_paths": 8, "round_paths": 2, "bounces": 2, "chunks": 2}})


def test_npz_bytes_depend_only_on_the_arrays() -> None:
    arrays = {"a": np.arange(7, dtype=np.float32).reshape(7, 1), "axis": np.int64(2), "timings": np.array('{"n": 1}'),
              "empty": np.zeros((0, 2, 3), np.uint64)}
    first = npz_bytes(arrays)
    time.sleep(2.1)  # the zip format stamps members with a 2 s resolution: np.savez's would differ now
    assert npz_bytes(arrays) == first
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=False, **arrays)
    back = read_npz(first)
    for name, value in read_npz(buf.getvalue()).items():  # what np.savez stored, np.load reads the same
        assert back[name].dtype == value.dtype and np.array_equal(back[name], value)
    assert list(back) == list(arrays)


def _bake_bytes(redis: Redis, store: ObjectStore, sid: str, w: WorkerProcess) -> tuple[dict[str, bytes], dict]:
    key, _ = bakes.enqueue_bake(redis, store, sid, PARAMS, owner=None)
    st = wait_bake(redis, store, sid, key, PARAMS, 300, w)
    assert st.state == "finished", (st.error, w.log())
    out: dict[str, bytes] = {"plan.json": read_blob(store, key, "plan.json")}
    timings: dict = {}
    for part in st.parts:
        m = read_manifest(store, part.key)
        assert m is not None
        for blob in m.blobs:
            out[f"{part.name}/{blob.name}"] = read_blob(store, part.key, blob.name)
        timings[part.name] = m.result["timings"]
    return out, timings


@pytest.mark.slow
def test_the_same_bake_twice_stores_the_same_bytes(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    sid = put_scene(worker_store, mirror_scene(), {}, None).id
    w = worker_process("bake")
    first, t1 = _bake_bytes(redis_conn, worker_store, sid, w)
    kinds = {re.sub(r"(-\d+)+$", "", name.split("/")[0]) for name in first}
    assert {"ldc-axis", "ldc-indirect", "llf-views", "plan.json"} <= kinds, sorted(first)
    key = bakes.bake_key(sid, PARAMS)
    manifest = read_manifest(worker_store, key)
    assert manifest is not None
    for part in manifest.result["parts"]:  # forget the whole bake: every part is computed again
        delete_artifact(worker_store, part["key"])
    delete_artifact(worker_store, key)
    assert worker_store.list("artifacts/") == []
    time.sleep(2.1)  # past the 2 s resolution of zip member dates
    second, t2 = _bake_bytes(redis_conn, worker_store, sid, w)
    assert t1 != t2  # the runs took different times ...
    assert sorted(second) == sorted(first)
    for name, data in first.items():
        assert second[name] == data, f"{name} differs between two bakes of the same scene"  # ... stored alike
