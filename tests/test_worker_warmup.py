"""The render worker's start-up warm-up (workers/warmup.py, workers/runner.py).

- After ``warm_up()``, the render queue's jobs on a DIFFERENT scene and dataset -- the sample
  ``mirror_box`` through ``render_job`` with every method, a dataset generated from it baked into
  every store kind through ``relight_job`` and ``composite_job`` -- add no numba signature to any
  engine dispatcher: the warm-up compiled (or loaded) exactly what the jobs need.
- The report lists every step with its time and counts; a failing step is reported, the steps that
  need it are skipped, the others run.
- A real ``python -m workers.runner --queue render`` subprocess starts its warm-up in the
  background and serves a job meanwhile; the warm-up publishes readiness until every kind is
  ready; ``--no-warmup`` / ``IBR_WORKER_WARMUP=false`` turn it off.

With a warm numba cache this file takes a few seconds plus two worker start-ups; with a cold one
the first test compiles what the render jobs compile anyway (the subprocess test then loads it).
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from producer.queue import fetch_job
from producer.renders import enqueue_render
from producer.status import job_public
from tests.fixtures.redis import StartWorker
from workers import warmup

# Everyday runs skip this file (make test-fast): worker processes that compile and run the warm-up.
pytestmark = pytest.mark.slow



@pytest.fixture(scope="module")
def report() -> warmup.WarmupReport:
    return warmup.warm_up()


def test_report_lists_every_step_with_its_numbers(report: warmup.WarmupReport) -> None:
    assert report.ok, report.table()
    assert [s.name for s in report.steps] == list(warmup.STEPS)
    for name in ("reference", "reference-pipelined", "ldc-bake", "ldc", "ldc+llf", "ldc+ibrt:1", "ldc-without-llf",
                 "relight-float16-pixel_major", "relight-float16-tiled", "relight-float32-pixel_major",
                 "relight-float32-tiled", "relight-lowrank", "composite", "walkthrough"):
        assert name in warmup.STEPS
    assert all(s.seconds >= 0 and s.new_signatures >= s.compiled >= 0 for s in report.steps)
    assert report.seconds >= sum(s.seconds for s in report.steps) * 0.99
    assert report.new_signatures == sum(s.new_signatures for s in report.steps)
    d = report.to_dict()
    assert d["ok"] is True and [s["name"] for s in d["steps"]] == list(warmup.STEPS)
    assert "numba signatures" in report.summary() and "reference" in report.table()


def _grown(before: dict[str, int]) -> dict[str, tuple[int, int]]:
    after = warmup.signature_counts()
    return {n: (before.get(n, 0), c) for n, c in after.items() if c != before.get(n, 0)}


def test_other_scene_and_dataset_compile_nothing_after_the_warm_up(report: warmup.WarmupReport,
                                                                    tmp_path: Path) -> None:
    from api_schemas import load_scene_file
    from api_schemas.datasets import DatasetBakeParams
    from api_schemas.service import BakeParams
    from engine import ENGINE_VERSION
    from engine.reference import ReferenceParams
    from engine.relighting.bake import bake_dataset
    from engine.relighting.generate import LightPlacement, generate_dataset
    from producer.artifacts import put_scene, write_artifact
    from producer.datasets import bake_artifact_key
    from producer.names import DATASET_BAKE_KIND
    from producer.store.local import LocalStore
    from samples import sample_path
    from workers.jobs.common import load_stored_scene
    from workers.jobs.datasets import NPZ, baked_to_bytes
    from workers.scene_loader import camera_params

    assert report.ok, report.table()
    store = LocalStore(tmp_path / "store")
    run = warmup._Run(store)
    scene = load_scene_file(sample_path("mirror_box"))  # primitives only: no mesh files
    with warmup._scratch_jobs(store):
        run.scene_id = put_scene(store, scene, {}, owner=None).id
        # the bake (bake-queue work, outside the measurement): a small LDC + LLF of mirror_box
        bake = BakeParams(ldc_resolution=24, max_layers=8, llf_f=1, llf_resolution=8, llf_chunk=3)
        run._publish_bake(bake, with_llf=True)
        no_llf = BakeParams(ldc_resolution=24, max_layers=8, llf="never")
        run._publish_bake(no_llf, with_llf=False)
        # a dataset generated from the sample (not the warm-up's synthetic one), baked into every store kind
        loaded = load_stored_scene(store, run.scene_id)
        cam = camera_params(scene.camera.model_copy(update={"width": 20, "height": 18}))
        ds = generate_dataset(loaded.runtime, cam, LightPlacement(region="hemisphere", spacing_deg=30.0),
                              ReferenceParams(spp=1, max_depth=0, area_light_samples=1))
        # float16 needs every value representable: lift the shadows (images only; the geometry is the sample's)
        ds = type(ds)(ds.images + np.float32(0.05), ds.light_positions, ds.intensities, ds.points, mask=ds.mask,
                      sphere_center=ds.sphere_center)
        chosen = {}
        for name, kwargs in {"f16-pm": {"half": True}, "f16-tiled": {"layout": "tiled", "half": True},
                             "f32-pm": {"half": False}, "f32-tiled": {"layout": "tiled", "half": False},
                             "lowrank": {"half": False, "compress": 0.2}}.items():
            bp = DatasetBakeParams.model_validate(kwargs)
            extra = {"compress": bp.compress} if bp.compress is not None else {}
            baked = bake_dataset(ds, layout=bp.layout, half=bp.half, **extra)
            chosen[name] = "lowrank" if baked.lowrank is not None else f"{baked.store.dtype}-{baked.layout}"
            did = hashlib.sha256(f"test-{name}".encode()).hexdigest()
            write_artifact(store, bake_artifact_key(did, bp), DATASET_BAKE_KIND, {"dataset": did},
                           bp.model_dump(mode="json"),
                           ENGINE_VERSION, {"baked.npz": (baked_to_bytes(baked), NPZ)}, {"report": {}})
            run.datasets[name] = (did, bp)
        assert chosen == {"f16-pm": "float16-pixel_major", "f16-tiled": "float16-tiled",
                          "f32-pm": "float32-pixel_major", "f32-tiled": "float32-tiled", "lowrank": "lowrank"}
        run.light_positions = np.asarray(ds.light_positions)
        env = np.linspace(0.1, 1.0, 32 * 16 * 3, dtype=np.float32).reshape(16, 32, 3)
        run.env_sha = run.image_file("sky.exr", env)

        before = warmup.signature_counts()
        hits0, misses0 = warmup.compile_stats()
        t0 = time.perf_counter()
        cam_doc = {**scene.camera.model_dump(mode="json"), "width": 36, "height": 30}
        run.render(params={"spp": 2, "max_depth": 3}, camera={**cam_doc, "width": 20, "height": 16})  # 1 chunk
        run.render(params={"spp": 1, "indirect_samples": 2}, camera=cam_doc)  # pipelined
        for method in ("ldc", "ldc+llf", "ldc+ibrt:1", "ldc+ibrt:3"):
            run.render(method=method, bake=bake.model_dump(mode="json"), camera=cam_doc)
        run.render(method="ldc", bake=no_llf.model_dump(mode="json"), camera=cam_doc, outputs=["preview"])
        for name in run.datasets:
            run.relight_store(name)
        # the composite: object and background datasets with the same bake params
        obj_id, bp = run.datasets["f16-pm"]
        from api_schemas.datasets import CompositeRequest
        from producer.datasets import composite_artifact_key
        from producer.payloads import CompositeJobPayload
        from workers.jobs.datasets import composite_job

        h, w = ds.shape
        bg_id = hashlib.sha256(b"test-background").hexdigest()  # the same bake under the background's id
        write_artifact(store, bake_artifact_key(bg_id, bp), DATASET_BAKE_KIND, {"dataset": bg_id},
                       bp.model_dump(mode="json"),
                       ENGINE_VERSION, {"baked.npz": (baked_to_bytes(bake_dataset(ds, layout=bp.layout)), NPZ)},
                       {"report": {}})
        req = CompositeRequest.model_validate({
            "object_dataset_id": obj_id, "background_dataset_id": bg_id,
            "plate_sha256": run.image_file("plate.exr", np.full((h, w, 3), 0.3, np.float32)),
            "object_mask_sha256": run.image_file("mask.exr", np.ones((h, w, 1), np.float32)),
            "lights": run.lights()[:3], "bake": bp.model_dump()})
        out = composite_job(CompositeJobPayload(request=req, artifact_key=composite_artifact_key(req))
                            .model_dump(mode="json"))
        assert out["artifact_key"]
        elapsed = time.perf_counter() - t0
    grown = _grown(before)
    hits, misses = warmup.compile_stats()
    assert grown == {}, f"kernels the warm-up did not cover (before, after signatures): {grown}"
    assert (hits, misses) == (hits0, misses0)
    assert elapsed < 120, elapsed  # nothing compiled: the jobs themselves are small


def test_a_failing_step_is_reported_and_the_rest_still_runs(report: warmup.WarmupReport,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(self: Any) -> None:
        raise RuntimeError("no scene today")

    monkeypatch.setattr(warmup._Run, "scene", broken)
    bad = warmup.warm_up()
    assert not bad.ok
    assert bad.step("scene").error == "RuntimeError: no scene today"
    for name in ("reference", "reference-pipelined", "ldc-bake"):
        assert bad.step(name).error == "skipped: needs step scene, which failed"
    for name in ("ldc", "ldc+ibrt:1", "ldc-without-llf"):
        assert bad.step(name).error == "skipped: needs step ldc-bake, which failed"
    assert bad.step("relight-float16-tiled").ok and bad.step("composite").ok  # independent of the scene
    assert "FAILED steps: scene" in bad.summary()


def test_render_worker_serves_while_warming_up_in_the_background(report: warmup.WarmupReport, redis_conn: Any,
                                                                  worker_store: Any,
                                                                  worker_process: StartWorker) -> None:
    """The worker takes a job while its warm-up process runs, the warm-up publishes readiness
    until every kind is ready, and a stopped worker withdraws it."""
    import signal

    from api_schemas.service import RenderRequest
    from producer.artifacts import put_scene, read_manifest
    from producer.readiness import read_readiness, readiness_key
    from tests.workers.queue.jobs_for_tests import tiny_scene

    sid = put_scene(worker_store, tiny_scene(), {}, owner=None).id
    req = RenderRequest(scene_id=sid, params={"spp": 1})
    key, job = enqueue_render(redis_conn, req, None, store=worker_store)
    assert job is not None
    w = worker_process("render", "--name", "render-warm", env={"IBR_WORKER_WARMUP": "true"})  # conftest: off
    deadline = time.monotonic() + 600
    seen_compiling = False
    while time.monotonic() < deadline:
        states = {m.method: m.state for m in read_readiness(redis_conn).methods}
        seen_compiling |= "compiling" in states.values()
        if set(states.values()) == {"ready"}:
            break
        assert w.alive(), w.log()
        time.sleep(0.2)
    log = w.log()
    assert set(states.values()) == {"ready"}, (states, log)
    pub = job_public(fetch_job(redis_conn, job.id))  # type: ignore[arg-type]
    assert pub.state == "finished", (pub.error, log)
    assert read_manifest(worker_store, key) is not None
    assert "warm-up: started in the background" in log and "Listening on" in log, log
    assert log.index("warm-up: started in the background") < log.index("Listening on"), log
    for name in warmup.STEPS:
        assert f"warm-up step {name} " in log, name
    assert "FAILED" not in log, log
    # the warm-up wrote nothing to the worker's store
    assert worker_store.list("artifacts/") == sorted(worker_store.list(f"artifacts/{key}/"))
    w.kill(signal.SIGTERM)
    assert w.wait(60) == 0, w.log()
    assert redis_conn.get(readiness_key("render-warm")) is None


def test_no_warmup_flag_and_setting(redis_conn: Any, worker_process: StartWorker,
                                    monkeypatch: pytest.MonkeyPatch) -> None:
    from producer.settings import Settings
    from workers import runner

    assert runner._parser().parse_args(["--queue", "render", "--no-warmup"]).no_warmup is True
    assert runner._parser().parse_args(["--queue", "render"]).no_warmup is False
    monkeypatch.delenv("IBR_WORKER_WARMUP", raising=False)
    assert Settings().worker_warmup is True  # on unless turned off
    monkeypatch.setenv("IBR_WORKER_WARMUP", "0")
    assert Settings().worker_warmup is False
    w1 = worker_process("render", "--no-warmup", burst=True, env={"IBR_WORKER_WARMUP": "true"})
    w2 = worker_process("render", burst=True, env={"IBR_WORKER_WARMUP": "false"})
    assert w1.wait(120) == 0 and w2.wait(120) == 0
    assert "warm-up: off (--no-warmup)" in w1.log() and "warm-up step" not in w1.log()
    assert "warm-up: off (IBR_WORKER_WARMUP=false)" in w2.log() and "warm-up step" not in w2.log()
    b = worker_process("bake", burst=True, env={"IBR_WORKER_WARMUP": "true"})  # never in a bake worker (forks)
    assert b.wait(120) == 0 and "warm-up" not in b.log()
