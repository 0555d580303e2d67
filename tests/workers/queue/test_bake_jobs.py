"""Bakes split into parts on a real forking bake worker (``python -m workers.runner --queue bake``):
plan -> one job per LDC axis (and per LLF chunk when the scene needs a light field) -> merge; the
aggregated progress reaches 1; a deleted part is redone alone; a diffuse scene bakes no LLF."""

from __future__ import annotations

import time
from typing import Any

import pytest
from redis import Redis

from api_schemas.scene import Scene
from api_schemas.service import BakeParams, BakePublic
from producer import bakes
from producer.artifacts import put_scene, read_manifest
from producer.cancel import cancel
from producer.errors import BakeInUse
from producer.names import scene_bake_job_id, scene_bake_plan_job_id
from producer.queue import fetch_job
from producer.renders import enqueue_render
from producer.status import job_public
from producer.store import ObjectStore
from tests.fixtures.redis import StartWorker
from tests.workers.queue.bake_waits import wait_bake, wait_parts
from tests.workers.queue.jobs_for_tests import tiny_scene

SMALL = BakeParams.model_validate({"ldc_resolution": 24, "max_layers": 8, "area_light_samples": 1,
                                    "indirect": {"mode": "off"}})
"""Direct light only: these tests are about the part / job mechanism (test_indirect_parts.py bakes
indirect light); the default indirect pass would add 12 chunk jobs (~10 s) to each."""


def diffuse_scene() -> Scene:
    doc = tiny_scene().model_dump(mode="json")
    for m in doc["materials"]:
        m["ks"] = [0.0, 0.0, 0.0]
        m["shininess"] = 0.0
    return Scene.model_validate(doc)


def test_bake_splits_into_parts_merges_and_redoes_a_deleted_part_alone(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    pub = put_scene(worker_store, diffuse_scene(), {}, None)
    key, job = bakes.enqueue_bake(redis_conn, worker_store, pub.id, SMALL, owner=None)
    assert job is not None and job.id == scene_bake_job_id(key)
    first = bakes.bake_status(redis_conn, worker_store, pub.id, key, SMALL)
    assert first.state == "queued" and first.progress.fraction == 0.0 and first.parts == []
    w = worker_process("bake")
    seen: list[BakePublic] = []
    st = wait_bake(redis_conn, worker_store, pub.id, key, SMALL, 120, w, seen)
    assert st.state == "finished", (st, w.log())
    assert st.progress.fraction == 1.0 and st.artifact is not None
    # progress never went backwards and passed through intermediate values
    fr = [s.progress.fraction for s in seen]
    assert all(b >= a - 1e-9 for a, b in zip(fr, fr[1:], strict=False)), fr
    # diffuse scene: three LDC axes, no light field, and the plan says why
    assert [p.name for p in st.parts] == ["ldc-axis-0", "ldc-axis-1", "ldc-axis-2"]
    assert all(p.kind == "ldc_axis" and p.state == "finished" for p in st.parts)
    assert st.plan is not None and st.plan["bake_llf"] is False and st.plan["needs_llf"] is False
    assert st.plan["llf_directions"] == 0 and "no glossy or mirror" in st.plan["reason"]
    manifest = read_manifest(worker_store, key)
    assert manifest is not None and manifest.kind == "bake"
    assert manifest.result["plan"] == st.plan and len(manifest.result["parts"]) == 3
    assert manifest.result["sizes"]["ldc_samples"] > 0
    # each part is its own artifact with the LDC axis as npz arrays of its samples
    from producer.artifacts import read_blob
    from workers.jobs.bake import read_npz

    for part in st.parts:
        pm = read_manifest(worker_store, part.key)
        assert pm is not None and pm.kind == "bake-part" and pm.inputs == {"scene": pub.id, "bake": key}
        arrays = read_npz(read_blob(worker_store, part.key, "ldc_axis.npz"))
        assert int(arrays["axis"]) == int(part.name[-1]) and arrays["ldi_depth"].shape[0] == pm.result["n_samples"]
    # a second request is answered from the store: no job
    again, job2 = bakes.enqueue_bake(redis_conn, worker_store, pub.id, SMALL, owner=None)
    assert again == key and job2 is None
    assert bakes.list_bakes(worker_store, pub.id) == [(key, SMALL)]

    # a part lost (crash, removed as corrupt): the bake is no longer complete, and the next request
    # redoes that part alone (the others are not recomputed) and merges again
    from producer.artifacts import delete_artifact

    created = {p.name: read_manifest(worker_store, p.key).created_at for p in st.parts}  # type: ignore[union-attr]
    victim = st.parts[1]
    delete_artifact(worker_store, victim.key)
    assert bakes.bake_status(redis_conn, worker_store, pub.id, key, SMALL).state != "finished"
    key2, job3 = bakes.enqueue_bake(redis_conn, worker_store, pub.id, SMALL, owner=None)
    assert key2 == key and job3 is not None  # the incomplete bake is not served as cached
    st2 = wait_bake(redis_conn, worker_store, pub.id, key, SMALL, 120, w)
    assert st2.state == "finished", w.log()
    plan_job = fetch_job(redis_conn, scene_bake_plan_job_id(key))
    assert plan_job is not None
    planned: dict[str, Any] = plan_job.return_value()  # type: ignore[assignment]
    assert planned["enqueued"] == [victim.name]
    assert sorted(planned["reused"]) == sorted(n for n in created if n != victim.name)
    after = {p.name: read_manifest(worker_store, p.key).created_at for p in st2.parts}  # type: ignore[union-attr]
    for name, t in created.items():
        if name == victim.name:
            assert after[name] > t
        else:
            assert after[name] == t  # not recomputed


def mirror_scene() -> Scene:
    doc = tiny_scene().model_dump(mode="json")
    doc["materials"][0] = {"name": "m", "kd": [0.3, 0.3, 0.3], "kr": [0.5, 0.5, 0.5]}
    return Scene.model_validate(doc)


@pytest.mark.slow
def test_mirror_scene_bakes_light_field_chunks(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    """The effect analysis asks for a light field: LDC axes + LLF chunks of ``llf_chunk`` directions,
    merged into one LLF whose every direction is present once."""
    params = BakeParams.model_validate({
        **SMALL.model_dump(), "llf_f": 1, "llf_resolution": 8, "llf_chunk": 4,
        "llf_params": {"spp": 1, "max_depth": 1, "glossy_samples": 1, "area_light_samples": 1}})
    pub = put_scene(worker_store, mirror_scene(), {}, None)
    key, _ = bakes.enqueue_bake(redis_conn, worker_store, pub.id, params, owner=None)
    w = worker_process("bake")
    rw = worker_process("render")  # starts (imports the engine) while the bake runs
    st = wait_bake(redis_conn, worker_store, pub.id, key, params, 120, w)
    assert st.state == "finished", (st.error, w.log())
    assert st.plan is not None and st.plan["needs_llf"] and st.plan["bake_llf"] and st.plan["llf_directions"] == 6
    assert [p.name for p in st.parts] == ["ldc-axis-0", "ldc-axis-1", "ldc-axis-2",
                                          "llf-views-0000-0003", "llf-views-0004-0005"]
    from workers.jobs.bake import load_bake
    from workers.scene_loader import load_scene

    loaded = load_scene(mirror_scene(), lambda p: (b"", ""))
    ldc, llf, plan = load_bake(worker_store, loaded.runtime, key)
    assert llf is not None and llf.n_directions == 6 and [v.index for v in llf.views] == list(range(6))
    assert ldc.resolution == params.ldc_resolution and plan["bake_llf"] is True

    # the view-dependent methods render from it on a render worker: the mirror sphere's pixels are
    # gathered from the light field (ldc+llf) or traced through the LDC (ldc+ibrt:2)
    from api_schemas.service import RenderRequest

    results = {}
    keys = {}
    for method, view in (("ldc+llf", None), ("ldc+ibrt:2", None), ("ldc+llf", {"supersample": 2}),
                         ("ldc+ibrt:2", {"glossy_rays": 4, "glossy_filter": 1})):
        req = RenderRequest.model_validate({"scene_id": pub.id, "method": method, "bake": params.model_dump(),
                                            **({"view": view} if view else {})})
        name = method + ((" edges x2" if "supersample" in view else " glossy rays") if view else "")
        rkey, rjob = enqueue_render(redis_conn, req, owner=None, store=worker_store)
        assert rjob is not None
        deadline = time.monotonic() + 90
        while (state := job_public(fetch_job(redis_conn, rjob.id)).state) not in (  # type: ignore[arg-type]
                "finished", "failed"):
            assert time.monotonic() < deadline, rw.log()
            time.sleep(0.1)
        assert state == "finished", rw.log()
        m = read_manifest(worker_store, rkey)
        assert m is not None and "provenance.png" in {b.name for b in m.blobs}
        results[name], keys[name] = m.result, rkey
    # the request's view reaches the renderer: 2 x 2 sub-pixels in the edge pixels, an artifact of its own
    aa = results["ldc+llf edges x2"]
    assert aa["counts"]["supersample"] == 2 and aa["counts"]["edge_pixels"] > 0 and "edges" in aa["timings"]
    assert "supersample" not in results["ldc+llf"]["counts"] and keys["ldc+llf edges x2"] != keys["ldc+llf"]
    assert results["ldc+llf"]["counts"]["provenance"]["gathered"] > 0
    assert results["ldc+ibrt:2"]["counts"]["provenance"]["traced"] > 0
    assert "gather" in results["ldc+llf"]["timings"] and "ibrt" in results["ldc+ibrt:2"]["timings"]
    assert results["ldc+llf"]["bake_key"] == key
    # the view's glossy lobe settings reach the renderer (this scene's default, "auto", traces none: no rect light)
    assert results["ldc+ibrt:2"]["plan"]["passes"]["ibrt"]["glossy_why"] == "auto: no glossy surface"
    traced = results["ldc+ibrt:2 glossy rays"]["plan"]["passes"]["ibrt"]
    assert traced["glossy_why"] == "requested" and keys["ldc+ibrt:2 glossy rays"] != keys["ldc+ibrt:2"]


def test_canceling_the_bake_job_cancels_its_parts_then_it_can_be_deleted(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    params = BakeParams.model_validate({**SMALL.model_dump(), "llf_f": 1, "llf_resolution": 8, "llf_chunk": 1})
    pub = put_scene(worker_store, mirror_scene(), {}, None)
    key, job = bakes.enqueue_bake(redis_conn, worker_store, pub.id, params, owner=None)
    assert job is not None
    w = worker_process("bake")
    deadline = time.monotonic() + 60
    st = bakes.bake_status(redis_conn, worker_store, pub.id, key, params)
    while not any(p.state == "started" for p in st.parts):
        assert time.monotonic() < deadline, w.log()
        time.sleep(0.05)
        st = bakes.bake_status(redis_conn, worker_store, pub.id, key, params)
    assert len(st.parts) == 9
    with pytest.raises(BakeInUse):
        bakes.delete_bake(redis_conn, worker_store, pub.id, key, params)
    from api_schemas.service import RenderRequest

    req = RenderRequest(scene_id=pub.id, method="ldc", bake=params, missing_bake="bake")
    _, render = enqueue_render(redis_conn, req, owner=None, store=worker_store)
    assert render is not None and job_public(render).progress.stage == "waiting for the bake"
    cancel(redis_conn, job.id)
    waiting = fetch_job(redis_conn, render.id)
    assert waiting is not None and job_public(waiting).state == "canceled"  # could never run now
    deadline = time.monotonic() + 30
    while True:
        st = bakes.bake_status(redis_conn, worker_store, pub.id, key, params)
        if not any(p.state in ("queued", "started") for p in st.parts):
            break
        assert time.monotonic() < deadline, (st.parts, w.log())
        time.sleep(0.1)
    assert st.state == "canceled"
    assert sum(p.state == "canceled" for p in st.parts) >= 7  # at most the running one finished first
    # a part that was running when the cancel came can already read as not running while its job
    # is still active (seen on CI): its worker stops the horse a moment later, and until then the
    # delete rightly refuses
    deadline = time.monotonic() + 30
    while True:
        try:
            bakes.delete_bake(redis_conn, worker_store, pub.id, key, params)
            break
        except BakeInUse:
            assert time.monotonic() < deadline, w.log()
            time.sleep(0.1)
    assert worker_store.list("artifacts/") == [] and bakes.list_bakes(worker_store, pub.id) == []
    assert w.alive()


def test_a_failed_plan_fails_the_bake_with_its_reason(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    """Past the API (whose bound is checked first), the plan job refuses a bake over the part limit
    with the engine's estimate; the merge job then fails the bake with that reason instead of
    waiting forever, and nothing is baked."""
    params = BakeParams.model_validate({"ldc_resolution": 4096, "max_layers": 256, "indirect": {"mode": "off"}})
    pub = put_scene(worker_store, diffuse_scene(), {}, None)
    key, job = bakes.enqueue_bake(redis_conn, worker_store, pub.id, params, owner=None)
    assert job is not None
    w = worker_process("bake")
    st = wait_bake(redis_conn, worker_store, pub.id, key, params, 60, w)
    assert st.state == "failed", (st, w.log())
    assert st.error is not None and "planning the bake failed" in st.error and "ldc_resolution 4096" in st.error
    assert "MiB" in st.error and st.parts == []
    assert worker_store.list("artifacts/") == []


def test_a_canceled_part_cancels_the_bake_and_a_new_request_redoes_it(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker
) -> None:
    """RQ never releases the dependents of a canceled job, so a bake with a canceled part would wait
    forever: it reads as canceled instead, and the next request re-plans and redoes just that part."""
    pub = put_scene(worker_store, diffuse_scene(), {}, None)
    key, _ = bakes.enqueue_bake(redis_conn, worker_store, pub.id, SMALL, owner=None)
    w = worker_process("bake")
    st = wait_parts(redis_conn, worker_store, pub.id, key, SMALL, 60, w)
    victim = st.parts[2]
    assert victim.job_id is not None
    cancel(redis_conn, victim.job_id)
    st = wait_bake(redis_conn, worker_store, pub.id, key, SMALL, 60, w)
    assert st.state == "canceled" and st.error is not None and victim.name in st.error, st
    key2, job = bakes.enqueue_bake(redis_conn, worker_store, pub.id, SMALL, owner=None)
    assert key2 == key and job is not None
    st = wait_bake(redis_conn, worker_store, pub.id, key, SMALL, 60, w)
    assert st.state == "finished", w.log()
    planned: dict[str, Any] = fetch_job(redis_conn, scene_bake_plan_job_id(key)).return_value()  # type: ignore[union-attr,assignment]
    assert planned["enqueued"] == [victim.name]


def test_a_bake_whose_merge_ends_while_its_status_is_read_is_finished_not_missing(
    redis_conn: Redis, worker_store: ObjectStore, worker_process: StartWorker, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The merge job writes the manifest, then RQ marks the job finished. Here the merge "ends"
    # at the moment the status reads its job: the manifest appears and the job turns finished
    # right then, and the status must see a finished bake (it said "missing" when it read the
    # manifest before the job).
    pub = put_scene(worker_store, diffuse_scene(), {}, None)
    key, _ = bakes.enqueue_bake(redis_conn, worker_store, pub.id, SMALL, owner=None)
    w = worker_process("bake")
    assert wait_bake(redis_conn, worker_store, pub.id, key, SMALL, 120, w).state == "finished", w.log()
    from producer.artifacts import manifest_key

    mkey = manifest_key(key)
    saved = worker_store.get_bytes(mkey)
    worker_store.delete(mkey)
    merge = fetch_job(redis_conn, scene_bake_job_id(key))
    assert merge is not None
    merge.set_status("started")
    real_fetch = bakes.fetch_job

    def fetch_as_the_merge_ends(redis: Redis, job_id: str) -> Any:
        if job_id == scene_bake_job_id(key) and not worker_store.exists(mkey):
            worker_store.put_bytes(mkey, saved, "application/json")
            real_fetch(redis, job_id).set_status("finished")
        return real_fetch(redis, job_id)

    monkeypatch.setattr(bakes, "fetch_job", fetch_as_the_merge_ends)
    st = bakes.bake_status(redis_conn, worker_store, pub.id, key, SMALL)
    assert st.state == "finished", st
