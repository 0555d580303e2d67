"""Quality contracts through the HTTP API (embedded Redis, the real app): every Bad-input rule of a
``quality`` request, the rules around a missing bake and an uncalibrated scene, and, with real bake
and render workers, the whole round trip: calibrate, ask for an error target, get the plan, the
image and the achieved time.

The fast tests plan from a model written into the store (an input to the planner: its numbers are
chosen so that each rule has one right answer, worked out in the comments); the slow test plans
from a calibration the worker measured."""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api_schemas.service import BakeParams, RenderRequest
from engine.quality import AdaptiveFit, CandidateFit, SceneModel, correction_key
from producer.bakes import bake_key
from producer.calibrations import (
    calibration_key,
    read_calibration,
    read_served,
    read_verification,
    record_served,
    write_calibration,
    write_verification,
)
from producer.names import verify_job_id
from producer.queue import fetch_job
from producer.renders import render_artifact_key
from producer.store import open_store
from tests.service.api.conftest import small_scene

BAKE = {"ldc_resolution": 16, "max_layers": 8, "area_light_samples": 1, "indirect": {"mode": "off"}}
CAMERA = {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0], "fov_y_deg": 40, "width": 32,
          "height": 32}
PX = 32 * 32


def _scene(c: TestClient) -> str:
    r = c.post("/v1/scenes", json={"scene": small_scene(camera=CAMERA)})
    assert r.status_code == 201, r.text
    sid: str = r.json()["id"]
    return sid


def _model(sid: str, **changes: Any) -> SceneModel:
    # reference: 20 % at 1 spp, 2 ms + 0.01 ms per sample (1024 px: 12 ms at 1 spp, 166 ms at 16 spp);
    # ldc: 0.3 % in 5 ms + 0.001 ms per pixel (6 ms); its bake costs 30 s
    doc: dict[str, Any] = dict(
        scene_id=sid, bake_key=bake_key(sid, BakeParams.model_validate(BAKE)),
        reference=CandidateFit("reference", 0.2, 2.0, 0.01), methods={"ldc": CandidateFit("ldc", 0.003, 5.0, 0.001)},
        excluded={}, reference_params={"max_depth": 4, "glossy_samples": 16, "area_light_samples": 16,
                                       "indirect_bounces": 2, "indirect_per_spp": 0},
        bake_cost_s=30.0, cost_s=3.0, probe={"views": 2}, engine_version=__import__("engine").ENGINE_VERSION,
        created_at="2026-01-01T00:00:00+00:00")
    doc.update(changes)
    return SceneModel(**doc)


def _store_model(store_dir: Any, model: SceneModel, bake: dict[str, Any] = BAKE) -> None:
    from api_schemas.service import CalibrationRequest

    req = CalibrationRequest(bake=BakeParams.model_validate(bake))
    write_calibration(open_store(f"file://{store_dir}"), model.scene_id, model.bake_key,
                      calibration_key(model.scene_id, model.bake_key, req), req.params.model_dump(mode="json"), model)


def _render(c: TestClient, sid: str, quality: dict[str, Any], **extra: Any) -> Any:
    return c.post("/v1/renders", json={"scene_id": sid, "bake": BAKE, "quality": quality, **extra})


def test_out_of_range_targets_are_422_with_the_allowed_range(client: TestClient) -> None:
    sid = _scene(client)
    for quality, needle in [({"max_error": 0}, "(0, 1)"), ({"max_error": 1.2}, "(0, 1)"),
                            ({"max_ms": 0}, "(0, 600000]"), ({"max_ms": 700_000}, "(0, 600000]"), ({}, "or both")]:
        r = _render(client, sid, quality)
        assert r.status_code == 422, r.text
        assert [e["field"] for e in r.json()["errors"]] == ["quality"] and needle in r.text, r.text
    r = _render(client, sid, {"max_error": 0.05}, method="ldc")
    assert r.status_code == 422 and "leave out method" in r.text
    r = client.post("/v1/batches", json={"renders": [{"scene_id": sid, "quality": {"max_error": 0.05}}]})
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "renders.0.quality", r.text


def test_an_uncalibrated_scene_is_409_saying_how_to_calibrate(client: TestClient) -> None:
    sid = _scene(client)
    r = _render(client, sid, {"max_error": 0.05})
    assert r.status_code == 409, r.text
    assert r.json()["type"] == "urn:ibr:problem:calibration-missing"
    assert f"POST /v1/scenes/{sid}/calibrations" in r.json()["detail"]
    # calibrating a scene without its bake follows the missing_bake rule
    r = client.post(f"/v1/scenes/{sid}/calibrations", json={"bake": BAKE})
    assert r.status_code == 409 and r.json()["type"] == "urn:ibr:problem:bake-missing", r.text
    assert client.post(f"/v1/scenes/{'0' * 64}/calibrations", json={"bake": BAKE}).status_code == 404
    bkey = bake_key(sid, BakeParams.model_validate(BAKE))
    assert client.get(f"/v1/scenes/{sid}/calibrations/{bkey}").status_code == 404


def test_plans_with_the_bake_missing(client: TestClient, store_dir: Any) -> None:
    sid = _scene(client)
    _store_model(store_dir, _model(sid))
    # 6 % with the bake missing and missing_bake fail: reference at 16 spp (5 %, 166 ms) renders now
    r = _render(client, sid, {"max_error": 0.06})
    assert r.status_code == 202, r.text
    con = r.json()["contract"]
    assert con["method"] == "reference" and con["params"]["spp"] == 16 and con["bake"] == "best_available_now"
    assert con["rule"] == "cheapest_meeting_error" and con["met"] and con["predicted_error"] == pytest.approx(0.05)
    assert con["predicted_ms"] == pytest.approx(2.0 + 0.01 * 16 * PX) and con["width"] == 32
    assert con["calibration"]["cost_s"] == 3.0 and con["achieved_ms"] is None
    assert con["planned_for"] == {"max_error": pytest.approx(0.051)}
    # the plan's artifact is the explicit request's: one cache entry for both
    explicit = RenderRequest(scene_id=sid, method="reference", params=con["params"], bake=BAKE)
    assert r.json()["artifact_key"] == render_artifact_key(explicit)
    # 0.4 % within 35 s: 2048 spp (0.44 %) is not enough, 4096 spp takes 42 s; the bake's ldc (0.3 %) gets
    # there in 30 s of bake + 6 ms: the missing_bake rule (409) says so
    r = _render(client, sid, {"max_error": 0.004, "max_ms": 35_000})
    assert r.status_code == 409 and r.json()["type"] == "urn:ibr:problem:bake-missing", r.text
    assert "ldc" in r.json()["detail"] and "missing_bake" in r.json()["detail"]
    # missing_bake bake: 4 %, planned for 4 % x 0.85 (the default error margin) = 3.4 %: reference at 48 spp
    # (2.9 %; 32 spp is 3.5 %) takes 0.5 s, ldc 30 s of bake: the reference
    r = _render(client, sid, {"max_error": 0.04}, missing_bake="bake")
    assert r.status_code == 202 and r.json()["contract"]["method"] == "reference"
    assert r.json()["contract"]["bake"] == "not_needed" and r.json()["contract"]["params"]["spp"] == 48
    assert r.json()["contract"]["planned_for"] == {"max_error": pytest.approx(0.034)}
    assert r.json()["contract"]["margins"] == {"error": 0.85, "time": 0.7}
    # 2 % (1.7 %): reference at 192 spp (1.44 %, 2 s; 128 spp is 1.77 %) still beats the bake
    r = _render(client, sid, {"max_error": 0.02}, missing_bake="bake")
    assert r.json()["contract"]["params"]["spp"] == 192
    assert r.json()["contract"]["estimated_error"] == pytest.approx(0.2 / 192 ** 0.5)
    assert r.json()["contract"]["estimated_error_source"] == "calibration"


def test_an_antialiased_ldc_setting_is_planned_with_its_view(client: TestClient, store_dir: Any) -> None:
    sid = _scene(client)
    # ldc 12 %, its 4 x 4 edge supersampling 3 %; a slow reference (20 % at 1 spp, 40 ms per sample: 41 s)
    aa = CandidateFit("ldc", 0.03, 9.0, 0.004, supersample=4)
    _store_model(store_dir, _model(sid, reference=CandidateFit("reference", 0.2, 2.0, 40.0),
                                   methods={"ldc": CandidateFit("ldc", 0.12, 5.0, 0.001), aa.key: aa}))
    r = _render(client, sid, {"max_error": 0.05}, missing_bake="bake")
    assert r.status_code == 202, r.text
    con = r.json()["contract"]
    assert con["method"] == "ldc" and con["view"] == {"supersample": 4, "antialias": "edges"}
    assert con["predicted_error"] == pytest.approx(0.03) and con["bake"] == "waited"
    explicit = RenderRequest.model_validate({"scene_id": sid, "method": "ldc", "bake": BAKE,
                                             "view": {"supersample": 4}})
    assert r.json()["artifact_key"] == render_artifact_key(explicit)
    # 20 %: plain ldc, no view
    r = _render(client, sid, {"max_error": 0.2}, missing_bake="bake")
    assert r.json()["contract"]["method"] == "ldc" and r.json()["contract"]["view"] is None
    # a served render of the antialiased setting corrects that setting alone
    store = open_store(f"file://{store_dir}")
    for _ in range(2):
        record_served(store, sid, con, achieved_ms=3 * con["predicted_ms"])
    served = read_served(store, sid, con["calibration"]["bake_key"], con["calibration"]["key"])
    assert set(served["time"]) == {"ldc@4x4"}


def test_the_adaptive_reference_is_planned_at_the_spp_its_target_needs(client: TestClient, store_dir: Any) -> None:
    sid = _scene(client)
    _store_model(store_dir, _model(sid, adaptive=AdaptiveFit(error_scale=1.5, time_ratio=0.8)))
    # 4 %, planned for 3.4 %: the spp model needs (0.2 / 0.034)^2 = 34.6 spp, 0.8 x (2 + 0.01 x 34.6 x 1024) =
    # 285 ms, against the ladder's 64 spp (657 ms) and ldc's 30 s bake: the adaptive reference, told 3.4 % / 1.5
    # (its estimate covers the whole image), capped at 4 x 34.6 spp rounded up to a power of two
    r = _render(client, sid, {"max_error": 0.04}, missing_bake="bake")
    assert r.status_code == 202, r.text
    con = r.json()["contract"]
    spp = (0.2 / 0.034) ** 2
    assert con["method"] == "reference" and con["params"]["spp"] == 256
    assert con["params"]["max_error"] == pytest.approx(0.034 / 1.5) and "max_ms" not in con["params"]
    assert con["predicted_ms"] == pytest.approx(0.8 * (2.0 + 0.01 * spp * PX))
    assert con["predicted_error"] == pytest.approx(0.034) and con["met"]
    # its error is estimated by the render once it has run; the scale travels with the contract
    assert con["estimated_error_source"] == "render" and con["error_scale"] == 1.5 and con["estimated_error"] is None
    explicit = RenderRequest(scene_id=sid, method="reference", params=con["params"], bake=BAKE)
    assert r.json()["artifact_key"] == render_artifact_key(explicit)
    # with a time budget too, the render is told to stop at it (the request's budget, not the margined one)
    r = _render(client, sid, {"max_error": 0.04, "max_ms": 2000}, missing_bake="bake")
    assert r.json()["contract"]["params"]["max_ms"] == 2000 and r.json()["contract"]["params"]["max_error"]


def test_served_render_times_correct_the_plan(client: TestClient, store_dir: Any) -> None:
    sid = _scene(client)
    model = _model(sid)
    _store_model(store_dir, model)
    store = open_store(f"file://{store_dir}")
    key = read_calibration(store, sid, model.bake_key)["key"]  # type: ignore[index]
    # 200 ms (planned for 140 ms) with the bake missing: the reference at 12 spp (125 ms) as calibrated
    con = _render(client, sid, {"max_ms": 200}).json()["contract"]
    assert con["params"]["spp"] == 12 and con["calibration"]["corrections"] == {"time": 1.0, "error": 1.0}
    # two served renders took 4x their prediction: the reference's times are predicted 4x, so 3 spp (131 ms)
    for _ in range(2):
        record_served(store, sid, con, achieved_ms=4.0 * con["predicted_ms"])
    con = _render(client, sid, {"max_ms": 200}).json()["contract"]
    assert con["params"]["spp"] == 3 and con["predicted_ms"] == pytest.approx(4 * (2.0 + 0.01 * 3 * PX))
    assert con["calibration"]["corrections"] == {"time": pytest.approx(4.0), "error": 1.0}
    # a new calibration of the bake starts afresh
    write_calibration(store, sid, model.bake_key, "n" * 64, {}, model)
    assert _render(client, sid, {"max_ms": 200}).json()["contract"]["params"]["spp"] == 12
    assert key != "n" * 64


def test_a_cheap_bake_is_waited_for(client: TestClient, store_dir: Any) -> None:
    sid = _scene(client)
    _store_model(store_dir, _model(sid, bake_cost_s=0.5))
    # 1 %: reference at 512 spp takes 5.2 s, the bake 0.5 s and ldc 6 ms
    r = _render(client, sid, {"max_error": 0.01}, missing_bake="bake")
    assert r.status_code == 202, r.text
    body = r.json()
    assert body["contract"]["method"] == "ldc" and body["contract"]["bake"] == "waited"
    assert body["contract"]["predicted_bake_ms"] == 500.0 and body["bake"] is not None  # the bake is queued


def test_targets_no_setting_meets_are_never_silent(client: TestClient, store_dir: Any) -> None:
    sid = _scene(client)
    _store_model(store_dir, _model(sid, excluded={"ldc": "the scene has mirror materials, which ldc does not render"},
                                   methods={}))
    # 0.1 %: even 4096 spp is 0.3 % (and the server's memory limit stops the reference earlier)
    r = _render(client, sid, {"max_error": 0.001})
    assert r.status_code == 422 and r.json()["type"] == "urn:ibr:problem:contract-unmet", r.text
    assert [e["field"] for e in r.json()["errors"]] == ["quality.max_error"]
    detail = r.json()["detail"]
    assert "the most accurate is reference@" in detail and "best_effort" in detail and "mirror" in detail
    # best effort: rendered, marked as not meeting the contract
    r = _render(client, sid, {"max_error": 0.001, "on_miss": "best_effort"})
    assert r.status_code == 202, r.text
    con = r.json()["contract"]
    assert not con["met"] and con["unmet"] == ["max_error"] and con["rule"] == "best_effort_most_accurate"
    assert f"reference@{con['params']['spp']}spp" in detail and con["params"]["spp"] >= 256
    assert con["excluded"] == {"ldc": "the scene has mirror materials, which ldc does not render"}
    # a time budget below the fixed overhead (2 ms) says so
    r = _render(client, sid, {"max_ms": 1})
    assert r.status_code == 422 and "fixed overhead" in r.json()["detail"], r.text
    assert [e["field"] for e in r.json()["errors"]] == ["quality.max_ms"]
    # both targets: 5 % is not reachable within 50 ms: the most accurate within it (4 spp, 10 %, 43 ms), marked
    r = _render(client, sid, {"max_error": 0.05, "max_ms": 50, "on_miss": "best_effort"})
    con = r.json()["contract"]
    assert con["rule"] == "most_accurate_within_time_error_unmet" and con["params"]["spp"] == 4
    assert con["predicted_ms"] <= 50 and con["unmet"] == ["max_error"]


def test_cli_asks_by_error_and_states_the_plan(client: TestClient, store_dir: Any, api_url: str) -> None:
    from tests.service.api.test_cli_api import ibr

    sid = _scene(client)
    bake = {"ldc_resolution": 16}
    _store_model(store_dir, _model(sid, bake_key=bake_key(sid, BakeParams.model_validate(bake))), bake)
    r = ibr(api_url, "render", sid, "--quality-error", "0.06", "--ldc-resolution", "16", "--no-wait")
    assert r.exit_code == 0, r.output
    assert "plan: reference at 16 spp (cheapest_meeting_error, the best available now" in r.stderr, r.stderr
    assert "meets the contract" in r.stderr and r.stdout.startswith("render-")
    r = ibr(api_url, "render", sid, "--quality-ms", "1", "--ldc-resolution", "16", "--no-wait")
    assert r.exit_code == 2 and "fixed overhead" in r.stderr, r.output
    r = ibr(api_url, "render", sid, "--quality-error", "0.0001", "--ldc-resolution", "16", "--best-effort",
            "--no-wait")
    assert r.exit_code == 0 and "DOES NOT meet max_error" in r.stderr, r.output
    r = ibr(api_url, "render", sid, "--quality-error", "0.05", "--method", "ldc")
    assert r.exit_code == 2 and "leave out --method" in r.stderr, r.output
    r = ibr(api_url, "render", sid, "--verify", "--ldc-resolution", "16")
    assert r.exit_code == 2 and "--quality-error" in r.stderr, r.output
    r = ibr(api_url, "render", sid, "--quality-error", "1.5")
    assert r.exit_code == 2 and "(0, 1)" in r.stderr, r.output
    r = ibr(api_url, "calibrate", sid, "--ldc-resolution", "16", "--no-wait")  # the stored one: no work
    assert r.exit_code == 0 and "(cached)" in r.stderr and "ldc: LRMS 0.0030" in r.stderr, r.output
    r = ibr(api_url, "calibrate", sid, "--ldc-resolution", "16", "--probes", "3")  # no bake: the missing_bake rule
    assert r.exit_code == 2 and "missing_bake" in r.stderr, r.output


def _poll(c: TestClient, url: str, done: tuple[str, ...], timeout: float) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    body: dict[str, Any] = {}
    while time.monotonic() < deadline:
        body = c.get(url).json()
        if body.get("state") in done:
            return body
        time.sleep(0.2)
    raise AssertionError(f"{url} not done after {timeout} s: {body}")


@pytest.mark.slow
def test_calibrate_then_render_by_error_target(client: TestClient, worker_process: Any, store_dir: Any) -> None:
    sid = _scene(client)
    bake_worker = worker_process("bake")
    render_worker = worker_process("render")
    cal = {"bake": BAKE, "params": {"probes": 1, "size": 24, "truth_spp": 32, "time_scale": 2},
           "missing_bake": "bake"}
    r = client.post(f"/v1/scenes/{sid}/calibrations", json=cal)
    assert r.status_code == 202, r.text
    done = _poll(client, r.headers["location"], ("finished", "failed"), 600)
    assert done["state"] == "finished", (done, bake_worker.log())
    model = done["model"]
    assert model["cost_s"] > 0 and "ldc" in model["methods"] and model["probe"]["views"] == 1
    again = client.post(f"/v1/scenes/{sid}/calibrations", json=cal)
    assert again.status_code == 200 and again.json()["cached"]

    # an error target between ldc's error and 1-spp reference's: the cheapest meeting it
    ldc_err = model["methods"]["ldc"]["error"]
    target = min(0.99, max(ldc_err, model["reference"]["error"] / 4) * 1.05)
    r = client.post("/v1/renders?wait=60", json={"scene_id": sid, "bake": BAKE, "quality": {"max_error": target},
                                                 "outputs": ["preview", "radiance"]})
    assert r.status_code == 200, (r.text, render_worker.log())
    body = r.json()
    con = body["contract"]
    assert con["met"] and con["predicted_error"] <= target and con["achieved_ms"] > 0
    assert con["bake"] in ("ready", "not_needed")
    assert body["artifact"]["result"]["contract"]["method"] == con["method"]
    assert body["artifact"]["result"]["contract"]["achieved_ms"] == pytest.approx(con["achieved_ms"])
    # the worker folded the render's time into the calibration's corrections (achieved over predicted)
    served = read_served(open_store(f"file://{store_dir}"), sid, con["calibration"]["bake_key"],
                         con["calibration"]["key"])
    # keyed by the setting: an antialiased LDC view (``ldc@2x2``) when the plan chose one
    entry = served["time"][correction_key(con["method"], con["params"], con["view"])]
    assert entry["n"] == 1 and entry["log"] == pytest.approx(math.log(con["achieved_ms"] / con["predicted_ms"]))
    # the same contract again: the cached artifact, the same plan
    r2 = client.post("/v1/renders", json={"scene_id": sid, "bake": BAKE, "quality": {"max_error": target},
                                          "outputs": ["preview", "radiance"]})
    assert r2.status_code == 200 and r2.json()["status"] == "cached"
    assert r2.json()["contract"]["method"] == con["method"]

    # the adaptive reference through the worker: the measured model with its LDC methods left out and the adaptive
    # render's time ratio made small (an input to the planner, so that it is the cheapest setting)
    store = open_store(f"file://{store_dir}")
    bkey = bake_key(sid, BakeParams.model_validate(BAKE))
    doc = read_calibration(store, sid, bkey)
    assert doc is not None
    m = SceneModel.from_json(doc["model"])
    assert m.adaptive is not None and m.adaptive.error_scale > 0 and len(m.adaptive.points) == 2  # two levels
    m = replace(m, methods={}, adaptive=replace(m.adaptive, time_ratio=1e-3,
                                                levels=[{**lv, "time_ratio": 1e-3} for lv in m.adaptive.levels]))
    write_calibration(store, sid, bkey, doc["key"], doc["params"], m)
    r = client.post("/v1/renders?wait=60", json={"scene_id": sid, "bake": BAKE, "outputs": ["preview"],
                                                 "quality": {"max_error": m.reference.error_at(8)}})
    assert r.status_code == 200, (r.text, render_worker.log())
    body = r.json()
    con = body["contract"]
    assert con["estimated_error_source"] == "render" and con["params"]["max_error"] > 0
    adaptive = body["artifact"]["result"]["adaptive"]
    assert con["estimated_error"] == pytest.approx(con["error_scale"] * adaptive["estimated_error"])
    assert body["artifact"]["result"]["contract"]["estimated_error"] == pytest.approx(con["estimated_error"])

    # verify: a follow-up job measures the image against a converged reference of the view, at the caller's cost;
    # the radiance is made for it even when the request names only the preview
    write_calibration(store, sid, bkey, doc["key"], doc["params"], SceneModel.from_json(doc["model"]))  # as measured
    q = {"max_error": 0.5 * (ldc_err + model["reference"]["error"]), "verify": True}
    r = client.post("/v1/renders?wait=60", json={"scene_id": sid, "bake": BAKE, "quality": q, "outputs": ["preview"]})
    assert r.status_code == 200, (r.text, render_worker.log())
    con = r.json()["contract"]
    assert con["verify"] and con["verification"]["job_id"] == f"verify-{r.json()['artifact_key']}"
    assert "image.exr" in r.json()["links"], r.json()["links"]
    job = _poll(client, con["verification"]["url"], ("finished", "failed"), 300)
    assert job["state"] == "finished", (job, render_worker.log())
    res = job["result"]
    # the measured error agrees with the calibrated prediction within the calibration's stated factor (2), and the
    # converged reference's own noise is small against it
    assert con["predicted_error"] / 2 <= res["measured_error"] <= con["predicted_error"] * 2, (res, con)
    assert res["measured_error"] <= res["measured_error_raw"] and res["reference_error"] < 0.5 * res["measured_error"]
    assert res["verify_ms"] > 0 and res["met"] == (res["measured_error"] <= q["max_error"])
    again = client.post("/v1/renders", json={"scene_id": sid, "bake": BAKE, "quality": q, "outputs": ["preview"]})
    assert again.json()["contract"]["verification"]["measured_error"] == pytest.approx(res["measured_error"])
    stored = read_verification(store, sid, r.json()["artifact_key"])
    assert stored is not None and stored["measured_error"] == pytest.approx(res["measured_error"])


def test_a_measurement_outlives_its_job_and_is_not_made_twice(client: TestClient, store_dir: Any,
                                                             redis_conn: Any) -> None:
    sid = _scene(client)
    _store_model(store_dir, _model(sid))
    q = {"max_error": 0.01, "verify": True}
    r = _render(client, sid, q, outputs=["preview"])
    assert r.status_code == 202, r.text  # no worker: the render and its verification wait
    key = r.json()["artifact_key"]
    con = r.json()["contract"]
    assert con["verification"]["job_id"] == verify_job_id(key) and con["verification"]["state"] != "finished"
    # the job measured and stored its result, then its record expired
    write_verification(open_store(f"file://{store_dir}"), sid, key,
                       {"artifact_key": key, "measured_error": 0.004, "met": True, "verify_ms": 1234.0})
    job = fetch_job(redis_conn, verify_job_id(key))
    assert job is not None
    job.delete(remove_from_queue=True)
    ver = _render(client, sid, q, outputs=["preview"]).json()["contract"]["verification"]
    assert ver["state"] == "finished" and ver["measured_error"] == 0.004 and ver["met"] is True
    assert ver["url"] is None and "engine_version" not in ver and "artifact_key" not in ver
    assert fetch_job(redis_conn, verify_job_id(key)) is None  # measured already: no second job
    assert open_store(f"file://{store_dir}").list(f"calibrations/{sid}/verified/")  # goes with the scene (below)


def test_a_scenes_calibrations_go_with_it(client: TestClient, store_dir: Any) -> None:
    sid = _scene(client)
    model = _model(sid)
    _store_model(store_dir, model)
    write_verification(open_store(f"file://{store_dir}"), sid, "k" * 64, {"measured_error": 0.01})
    url = f"/v1/scenes/{sid}/calibrations/{model.bake_key}"
    got = client.get(url)
    assert got.status_code == 200 and got.json()["state"] == "finished" and got.json()["model"]["cost_s"] == 3.0
    assert client.delete(f"/v1/scenes/{sid}").status_code == 204
    assert not open_store(f"file://{store_dir}").list(f"calibrations/{sid}/")
    assert client.get(url).status_code == 404
