"""Indirect light in scene bakes, on a real forking bake worker: the indirect pass of each LDC axis is
split into ``indirect.chunks`` jobs (``ldc-indirect-<axis>-<i>``) that run after their axis; the bake
loaded from the store is bit for bit the LDC a one-process ``bake_ldc(..., indirect=...)`` computes;
a lost chunk is redone alone; a chunk that cannot run fails the bake naming it; a scene where no
indirect light can arrive bakes no chunk and says why; the plan refuses a bake over the CPU limit
with its estimate."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from redis import Redis

from api_schemas.scene import Scene
from api_schemas.service import BakeParams, BakePublic
from producer import bakes
from producer.artifacts import artifact_prefix, delete_artifact, put_scene, read_manifest
from producer.names import scene_bake_plan_job_id
from producer.queue import fetch_job
from producer.store import ObjectStore
from tests.fixtures.redis import StartWorker
from tests.workers.queue.bake_waits import wait_bake, wait_parts
from tests.workers.queue.jobs_for_tests import tiny_scene

CHEAP = {"noise": 0.05, "min_paths": 4, "max_paths": 8, "round_paths": 2, "bounces": 2, "chunks": 3}
"""A few paths per sample side: the mechanism, not the converged light, is under test."""
PARAMS = BakeParams.model_validate({"ldc_resolution": 16, "max_layers": 8, "area_light_samples": 1, "seed": 5,
                                    "indirect": CHEAP})


def one_process_ldc(scene: Scene, params: BakeParams, *, indirect: bool) -> Any:
    """The obvious reference: the whole LDC baked in this process by the engine, no jobs."""
    from engine.newviews.indirect import IndirectParams
    from engine.newviews.ldc import bake_ldc
    from engine.raycast import make_caster
    from workers.scene_loader import load_scene

    rt = load_scene(scene, lambda p: (b"", "")).runtime
    ip = params.indirect
    return bake_ldc(rt, make_caster(rt, "embree"), params.ldc_resolution, max_layers=params.max_layers,
                    area_light_samples=params.area_light_samples, seed=params.seed,
                    indirect=IndirectParams(noise=ip.noise, min_paths=ip.min_paths, max_paths=ip.max_paths,
                                            bounces=ip.bounces, round_paths=ip.round_paths, seed=params.seed)
                    if indirect else None)


def loaded_ldc(store: ObjectStore, scene: Scene, key: str) -> Any:
    from workers.jobs.bake import load_bake
    from workers.scene_loader import load_scene

    ldc, _llf, _plan = load_bake(store, load_scene(scene, lambda p: (b"", "")).runtime, key)
    return ldc


def created(store: ObjectStore, st: BakePublic) -> dict[str, Any]:
    return {p.name: read_manifest(store, p.key).created_at for p in st.parts}  # type: ignore[union-attr]


@pytest.mark.slow  # four bakes (17-25 s on the shared 2 cores)
def test_indirect_chunks_merge_bit_identical_and_a_lost_or_failed_chunk_is_redone_alone(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    scene = tiny_scene()
    pub = put_scene(worker_store, scene, {}, None)
    key, job = bakes.enqueue_bake(redis_conn, worker_store, pub.id, PARAMS, owner=None)
    assert job is not None
    w = worker_process("bake")
    seen: list[BakePublic] = []
    st = wait_bake(redis_conn, worker_store, pub.id, key, PARAMS, 180, w, seen)
    assert st.state == "finished", (st.error, w.log())
    # three axes, then three chunks of each axis's indirect pass; progress aggregated over all
    chunks = [f"ldc-indirect-{a}-{i}" for a in range(3) for i in range(3)]
    assert [p.name for p in st.parts] == ["ldc-axis-0", "ldc-axis-1", "ldc-axis-2", *chunks]
    assert all(p.state == "finished" for p in st.parts)
    assert {p.kind for p in st.parts[3:]} == {"ldc_indirect"}
    fr = [s.progress.fraction for s in seen]
    assert all(b >= a - 1e-9 for a, b in zip(fr, fr[1:], strict=False)) and st.progress.fraction == 1.0
    # the chunks tile each axis: chunk i of 3 covers [i n // 3, (i + 1) n // 3)
    for a in range(3):
        n = read_manifest(worker_store, st.parts[a].key).result["n_samples"]  # type: ignore[union-attr]
        for i in range(3):
            r = read_manifest(worker_store, st.parts[3 + 3 * a + i].key).result  # type: ignore[union-attr]
            assert (r["first"], r["n_samples"], r["axis_samples"]) == (i * n // 3, (i + 1) * n // 3 - i * n // 3, n)
    # the plan says it was baked, with the achieved noise level
    assert st.plan is not None
    ind = st.plan["indirect"]
    assert ind["state"] == "baked" and ind["mode"] == "auto" and ind["chunks_per_axis"] == 3
    assert len(ind["axes"]) == 3 and ind["summary"]["sides"] > 0 and ind["summary"]["noise_target"] == 0.05
    assert 4 <= ind["summary"]["paths_mean"] <= 8 and ind["summary"]["paths_total"] > 0

    # bit for bit the one-process bake; and indirect light really was added
    ldc = loaded_ldc(worker_store, scene, key)
    ref = one_process_ldc(scene, PARAMS, indirect=True)
    direct = one_process_ldc(scene, PARAMS, indirect=False)
    for a in range(3):
        assert np.array_equal(ldc.axes[a].diffuse, ref.axes[a].diffuse), a
        assert np.array_equal(ldc.axes[a].ldi.depth, ref.axes[a].ldi.depth)
        extra = ldc.axes[a].diffuse.astype(np.float64) - direct.axes[a].diffuse
        assert extra.min() >= -1e-6 and extra.max() > 1e-2, (a, extra.max())  # light from the sphere or floor

    # a lost chunk: the bake is incomplete, and a re-request redoes that chunk alone
    before = created(worker_store, st)
    victim = st.parts[3 + 4]  # ldc-indirect-1-1
    delete_artifact(worker_store, victim.key)
    key2, job2 = bakes.enqueue_bake(redis_conn, worker_store, pub.id, PARAMS, owner=None)
    assert key2 == key and job2 is not None
    st2 = wait_bake(redis_conn, worker_store, pub.id, key, PARAMS, 120, w)
    assert st2.state == "finished", (st2.error, w.log())
    planned: dict[str, Any] = fetch_job(redis_conn, scene_bake_plan_job_id(key)).return_value()  # type: ignore[union-attr,assignment]
    assert planned["enqueued"] == [victim.name]
    after = created(worker_store, st2)
    assert all((after[n] > t) == (n == victim.name) for n, t in before.items())
    assert np.array_equal(loaded_ldc(worker_store, scene, key).axes[1].diffuse, ref.axes[1].diffuse)

    # a chunk that cannot run (its axis corrupt in the store) fails the bake naming the chunk...
    axis0 = st.parts[0]
    blob = artifact_prefix(axis0.key) + "ldc_axis.npz"
    worker_store.put_bytes(blob, worker_store.get_bytes(blob)[:-7] + b"garbage", "application/x-npz")
    victim = st.parts[3 + 1]  # ldc-indirect-0-1
    delete_artifact(worker_store, victim.key)
    bakes.enqueue_bake(redis_conn, worker_store, pub.id, PARAMS, owner=None)
    st3 = wait_bake(redis_conn, worker_store, pub.id, key, PARAMS, 120, w)
    assert st3.state == "failed" and st3.error is not None, st3
    assert victim.name in st3.error and "ldc-axis-0" in st3.error and "request the bake again" in st3.error
    # ... and the next request redoes exactly what is missing: the axis (withdrawn as corrupt) and the chunk
    bakes.enqueue_bake(redis_conn, worker_store, pub.id, PARAMS, owner=None)
    st4 = wait_bake(redis_conn, worker_store, pub.id, key, PARAMS, 120, w)
    assert st4.state == "finished", (st4.error, w.log())
    planned = fetch_job(redis_conn, scene_bake_plan_job_id(key)).return_value()  # type: ignore[union-attr,assignment]
    assert planned["enqueued"] == ["ldc-axis-0", victim.name]
    assert np.array_equal(loaded_ldc(worker_store, scene, key).axes[0].diffuse, ref.axes[0].diffuse)


def lone_box() -> Scene:
    """One convex closed object (a box) lit from outside under a black background: no path that
    leaves it comes back, so no indirect light can arrive (the effect plan says so)."""
    doc = tiny_scene().model_dump(mode="json")
    doc["objects"] = [{"type": "box", "center": [0, 0.5, 0], "size": [1.0, 1.0, 1.0], "material": "floor"}]
    return Scene.model_validate(doc)


def test_a_scene_without_indirect_light_bakes_no_chunk_and_says_why(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    params = BakeParams(ldc_resolution=16, max_layers=8, area_light_samples=1)  # indirect: the defaults (auto)
    assert params.indirect.mode == "auto"
    pub = put_scene(worker_store, lone_box(), {}, None)
    key, _ = bakes.enqueue_bake(redis_conn, worker_store, pub.id, params, owner=None)
    w = worker_process("bake")
    st = wait_bake(redis_conn, worker_store, pub.id, key, params, 120, w)
    assert st.state == "finished", (st.error, w.log())
    assert [p.name for p in st.parts] == ["ldc-axis-0", "ldc-axis-1", "ldc-axis-2"]
    assert st.plan is not None and st.plan["indirect_skip"]
    ind = st.plan["indirect"]
    assert ind["state"] == "skipped" and ind["reason"] == st.plan["indirect_skip"] and "convex" in ind["reason"]
    assert ind["chunks_per_axis"] == 0
    planned: dict[str, Any] = fetch_job(redis_conn, scene_bake_plan_job_id(key)).return_value()  # type: ignore[union-attr,assignment]
    assert "indirect_cpu_s" not in planned["estimates"] and planned["estimates"]["cpu_s"] == 0.0
    # the LDC is the direct-lit one, bit for bit
    ldc = loaded_ldc(worker_store, lone_box(), key)
    direct = one_process_ldc(lone_box(), params, indirect=False)
    assert all(np.array_equal(ldc.axes[a].diffuse, direct.axes[a].diffuse) for a in range(3))
    # and indirect off says so too
    off = BakeParams.model_validate({**params.model_dump(), "indirect": {"mode": "off"}})
    pub2 = put_scene(worker_store, tiny_scene(), {}, None)
    key2, _ = bakes.enqueue_bake(redis_conn, worker_store, pub2.id, off, owner=None)
    st2 = wait_bake(redis_conn, worker_store, pub2.id, key2, off, 120, w)
    assert st2.state == "finished" and len(st2.parts) == 3 and st2.plan is not None
    assert st2.plan["indirect"]["state"] == "off" and not st2.plan["indirect_skip"]


def test_the_plan_refuses_a_bake_over_the_cpu_limit_with_its_estimate(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    """At LDC 512 the default indirect pass of the tiny scene is estimated well over a minute of CPU
    (~10^6 samples x 2 sides x 128 paths): refused before anything is baked, the estimate named."""
    params = BakeParams(ldc_resolution=512, max_layers=8)
    pub = put_scene(worker_store, tiny_scene(), {}, None)
    key, _ = bakes.enqueue_bake(redis_conn, worker_store, pub.id, params, owner=None)
    w = worker_process("bake", env={"IBR_MAX_BAKE_CPU_S": "60"})
    st = wait_bake(redis_conn, worker_store, pub.id, key, params, 60, w)
    assert st.state == "failed" and st.error is not None, (st, w.log())
    assert "planning the bake failed" in st.error and "estimated CPU time" in st.error
    assert "M indirect paths" in st.error and "limit of 60 s" in st.error and "indirect.mode=off" in st.error
    assert st.parts == [] and worker_store.list("artifacts/") == []


def test_a_canceled_axis_cancels_its_waiting_chunks_and_a_new_request_redoes_them(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    """RQ never releases the jobs waiting for a canceled job: the axis's chunks would wait forever,
    and the bake with them. The bake reads as canceled instead, and the next request redoes the
    axis and its chunks (fresh chunk jobs: the waiting ones lost their link to the axis job)."""
    from producer.cancel import cancel

    params = BakeParams.model_validate({**PARAMS.model_dump(), "indirect": {**CHEAP, "chunks": 2}})
    pub = put_scene(worker_store, tiny_scene(), {}, None)
    key, _ = bakes.enqueue_bake(redis_conn, worker_store, pub.id, params, owner=None)
    w = worker_process("bake")
    st = wait_parts(redis_conn, worker_store, pub.id, key, params, 60, w)
    victim = st.parts[2]  # ldc-axis-2: queued behind the other two on the one worker
    assert victim.name == "ldc-axis-2" and victim.job_id is not None
    cancel(redis_conn, victim.job_id)
    st = wait_bake(redis_conn, worker_store, pub.id, key, params, 60, w)
    assert st.state == "canceled" and st.error is not None and victim.name in st.error, st
    assert {p.name: p.state for p in st.parts}["ldc-indirect-2-0"] == "queued"  # still waiting, never released
    key2, job = bakes.enqueue_bake(redis_conn, worker_store, pub.id, params, owner=None)
    assert key2 == key and job is not None
    st = wait_bake(redis_conn, worker_store, pub.id, key, params, 60, w)
    assert st.state == "finished", (st.error, w.log())
    planned: dict[str, Any] = fetch_job(redis_conn, scene_bake_plan_job_id(key)).return_value()  # type: ignore[union-attr,assignment]
    assert planned["enqueued"] == ["ldc-axis-2", "ldc-indirect-2-0", "ldc-indirect-2-1"]
    assert st.plan is not None and st.plan["indirect"]["state"] == "baked"


def test_the_plan_refuses_an_indirect_chunk_over_the_memory_limit(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    """With an 8 MiB limit per job, the LDC axes of this bake fit (<= 3.2 MiB at their worst case)
    but an indirect chunk (its axis + a path batch of ~6 k sample sides x 8 paths x 576 bytes,
    ~13 MiB) does not: refused before anything is baked, naming the estimate and what to lower."""
    params = BakeParams(ldc_resolution=64, max_layers=8)
    pub = put_scene(worker_store, tiny_scene(), {}, None)
    key, _ = bakes.enqueue_bake(redis_conn, worker_store, pub.id, params, owner=None)
    w = worker_process("bake", env={"IBR_MAX_BAKE_PART_BYTES": str(8 << 20)})
    st = wait_bake(redis_conn, worker_store, pub.id, key, params, 60, w)
    assert st.state == "failed" and st.error is not None, (st, w.log())
    assert "an indirect chunk needs up to 13 MiB" in st.error and "limit of 8 MiB" in st.error, st.error
    assert "raise indirect.chunks" in st.error and worker_store.list("artifacts/") == []
