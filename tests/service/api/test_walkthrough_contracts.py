"""Walkthrough quality contracts through the API: bad input, 409 without a calibration, and an end to
end run (calibration job, a planned walkthrough rendered by real workers, the contract it states)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient

from api_schemas.walkthrough import WalkthroughCalibrationPublic, WalkthroughPublic
from producer.store import LocalStore
from producer.walkthrough_calibrations import read_served_walkthroughs
from tests.service.api.test_walkthroughs import BAKE, _errors, _frames, _scene


def _wait(client: TestClient, url: str, done: tuple[str, ...], seconds: float = 240) -> dict[str, Any]:
    deadline = time.monotonic() + seconds
    while True:
        doc: dict[str, Any] = client.get(url).json()
        if doc.get("state", doc.get("status")) in done or time.monotonic() > deadline:
            return doc
        time.sleep(0.3)


def test_contract_requests_that_cannot_be_planned(client: TestClient) -> None:
    sid = _scene(client)
    frames = _frames(3)
    # quality excludes bake and fill (the planner picks them); verify is for renders
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames, "bake": BAKE,
                                                         "fill": "none", "quality": {"max_error": 0.2}}))
    assert "bake and quality exclude each other" in errs["bake"] and "fill" in errs
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames,
                                                         "quality": {"max_error": 0.2, "verify": True}}))
    assert "not offered for walkthroughs" in errs["quality.verify"]
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames,
                                                         "quality": {"max_error": 1.5}}))
    assert "quality" in errs
    # the frames are checked against the scene before the calibration is looked for
    bad = [dict(f, time=9.0) for f in frames]
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": bad,
                                                         "quality": {"max_error": 0.2}}))
    assert "frames.0.time" in errs
    # no walkthrough calibration yet: 409 naming the request that makes one
    r = client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames, "quality": {"max_error": 0.2}})
    assert r.status_code == 409, r.text
    assert r.json()["type"] == "urn:ibr:problem:calibration-missing"
    assert f"POST /v1/scenes/{sid}/walkthrough-calibrations" in r.json()["detail"]
    assert client.get(f"/v1/scenes/{sid}/walkthrough-calibrations").status_code == 404
    # calibration requests: duplicates, a scene without a view space
    errs = _errors(client.post(f"/v1/scenes/{sid}/walkthrough-calibrations",
                               json={"params": {"presets": ["low", "low"]}}))
    assert "presets lists a value twice" in errs["params.presets"]
    from tests.service.api.test_walkthroughs import ROOM

    no_vs = _scene(client, {k: v for k, v in ROOM.items() if k != "view_space"})
    errs = _errors(client.post(f"/v1/scenes/{no_vs}/walkthrough-calibrations", json={}))
    assert "no view_space" in errs["scene_id"]
    assert client.post("/v1/scenes/" + "a" * 64 + "/walkthrough-calibrations", json={}).status_code == 404


def test_walkthrough_contract_end_to_end(client: TestClient, worker_process: Any, store_dir: Path) -> None:
    bake_worker = worker_process("bake")
    render_worker = worker_process("render")
    sid = _scene(client)
    body = {"params": {"presets": ["low"], "fills": ["both"], "probes": 2, "size": 32, "truth_noise": 0.03,
                       "path_noises": []}}  # bake presets only (path-traced frames: the test below)
    r = client.post(f"/v1/scenes/{sid}/walkthrough-calibrations", json=body)
    assert r.status_code == 202, r.text
    queued = WalkthroughCalibrationPublic.model_validate(r.json())
    doc = _wait(client, r.headers["location"], ("finished", "failed"))
    assert doc["state"] == "finished", (doc, bake_worker.log()[-3000:])
    cal = WalkthroughCalibrationPublic.model_validate(doc)
    assert cal.key == queued.key and cal.model is not None
    fit = cal.model["fits"]["low/both"]
    assert 0 < fit["error"] < 0.5 and cal.model["bake_cost_s"]["low"] > 0
    # the same calibration again: cached, nothing queued
    again = client.post(f"/v1/scenes/{sid}/walkthrough-calibrations", json=body)
    assert again.status_code == 200 and again.json()["cached"] is True
    # a target the low preset meets: planned onto its bake, which the calibration made and stored
    frames = _frames(4)
    target = min(0.99, fit["error"] / fit["margin"] * 1.05)
    r = client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames, "chunk_frames": 2,
                                              "quality": {"max_error": target}})
    assert r.status_code == 202, r.text
    pub = WalkthroughPublic.model_validate(r.json())
    c = pub.contract
    assert c is not None and c.met and c.rule == "cheapest_meeting_error"
    assert (c.preset, c.fill, c.bake, c.frames) == ("low", "both", "ready", 4)
    assert c.predicted_error == fit["error"] and c.predicted_bake_ms == 0
    assert c.calibration["key"] == cal.key and c.achieved_frame_ms is None
    assert pub.bake_key == cal.model["bake_keys"]["low"]
    assert not any(j.id.startswith("wtbake") for j in pub.jobs)  # the bake is there already
    doc = _wait(client, f"/v1/walkthroughs/{pub.key}", ("finished", "failed"))
    assert doc["status"] == "finished", (doc, render_worker.log()[-3000:])
    done = WalkthroughPublic.model_validate(doc)
    assert done.contract is not None and done.contract.achieved_frame_ms is not None
    assert 0 < done.contract.achieved_frame_ms["median"] <= done.contract.achieved_frame_ms["max"]
    assert done.contract.achieved_estimated_error is None  # reconstructed frames estimate nothing
    # its frame times are folded into the calibration's time corrections (2 chunks of 2 frames)
    served = read_served_walkthroughs(LocalStore(store_dir), sid, cal.key)
    assert served["time"]["low/both"]["n"] == 1
    # the same walkthrough asked explicitly shares the frames (same key), and states no contract
    explicit = client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames, "chunk_frames": 2,
                                                     "bake": {"quality": "low"}, "fill": "both"})
    assert explicit.status_code == 200 and explicit.json()["key"] == pub.key
    assert explicit.json()["contract"] is None
    assert client.get(f"/v1/walkthroughs/{pub.key}").json()["contract"]["preset"] == "low"
    # a target below what the scene can do: 422 naming the target and the best setting; best effort marks it
    r = client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames,
                                              "quality": {"max_error": fit["error"] / 4}})
    errs = _errors(r)
    assert "no walkthrough setting reaches" in errs["quality.max_error"] and "low/both" in errs["quality.max_error"]
    r = client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames,
                                              "quality": {"max_error": fit["error"] / 4, "on_miss": "best_effort"}})
    assert r.status_code in (200, 202), r.text
    c = WalkthroughPublic.model_validate(r.json()).contract
    assert c is not None and not c.met and c.unmet == ["max_error"] and c.rule == "best_effort_most_accurate"
    # a time budget below the fixed overhead
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames,
                                                         "quality": {"max_ms": 0.001}}))
    assert "fixed overhead" in errs["quality.max_ms"]


def test_path_traced_walkthrough_end_to_end(client: TestClient, worker_process: Any) -> None:
    """Frames path-traced without a bake: asked explicitly, and chosen by a contract whose target is
    below what the low preset's bake reaches."""
    bake_worker = worker_process("bake")
    render_worker = worker_process("render")
    sid = _scene(client)
    frames = _frames(3)
    # path_traced excludes the bake and the fill; its noise has a range
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames, "bake": BAKE,
                                                         "path_traced": {"noise": 0.1}}))
    assert "bake and path_traced exclude each other" in errs["bake"]
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames,
                                                         "path_traced": {"noise": 0.0001}}))
    assert "path_traced.noise" in errs
    # explicit: no bake job, every frame traced, what the frames reached in the chunks' results
    r = client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames, "chunk_frames": 2,
                                              "path_traced": {"noise": 0.1}})
    assert r.status_code == 202, r.text
    pub = WalkthroughPublic.model_validate(r.json())
    assert pub.bake_key is None and not any(j.id.startswith("wtbake") for j in pub.jobs)
    doc = _wait(client, f"/v1/walkthroughs/{pub.key}", ("finished", "failed"))
    assert doc["status"] == "finished", (doc, render_worker.log()[-3000:])
    chunk = client.get(doc["links"]["chunk.0"]).json()
    assert chunk["result"]["provenance"]["traced"] > 0 and len(chunk["result"]["rel_stderr_median"]) == 2
    assert len(chunk["result"]["estimated_error"]) == 2 and min(chunk["result"]["paths_per_pixel"]) >= 4
    png = client.get(f"/v1/walkthroughs/{pub.key}/frames/2.png")
    assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
    # calibrated with the low preset and path-traced frames at 0.05
    body = {"params": {"presets": ["low"], "fills": ["both"], "probes": 2, "size": 32, "truth_noise": 0.03,
                       "path_noises": [0.05]}}
    r = client.post(f"/v1/scenes/{sid}/walkthrough-calibrations", json=body)
    assert r.status_code == 202, r.text
    cal = WalkthroughCalibrationPublic.model_validate(
        _wait(client, r.headers["location"], ("finished", "failed")))
    assert cal.state == "finished" and cal.model is not None, bake_worker.log()[-3000:]
    low, path = cal.model["fits"]["low/both"], cal.model["fits"]["path/0.05"]
    assert path["error"] < low["error"] and path["b_ms"] == 0 and path["c_ms"] > 0
    assert cal.model["probe"]["cost_breakdown_s"]["path_traced"] > 0
    # a target only the path-traced frames keep: planned onto them, no bake
    target = min(0.99, max(path["error"] / path["margin"] * 1.05, low["error"] * 0.5))
    assert target < low["error"] * low["margin"]
    r = client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames, "chunk_frames": 2,
                                              "quality": {"max_error": target}})
    assert r.status_code == 202, r.text
    pub = WalkthroughPublic.model_validate(r.json())
    c = pub.contract
    assert c is not None and c.met and (c.preset, c.fill, c.path_noise, c.bake) == (None, None, 0.05, "none")
    assert c.predicted_bake_ms == 0 and pub.bake_key is None
    assert abs(c.predicted_frame_ms - path["c_ms"] * 16 * 12) < 1e-6
    doc = _wait(client, f"/v1/walkthroughs/{pub.key}", ("finished", "failed"))
    assert doc["status"] == "finished", (doc, render_worker.log()[-3000:])
    # once finished, the contract states the frames' own estimates of their error (each sized for 0.05)
    est = WalkthroughPublic.model_validate(doc).contract.achieved_estimated_error  # type: ignore[union-attr]
    assert est is not None and 0 < est["median"] <= est["max"] <= 0.06, est
    # the same frames asked explicitly share the key
    explicit = client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames, "chunk_frames": 2,
                                                     "path_traced": {"noise": 0.05}})
    assert explicit.status_code == 200 and explicit.json()["key"] == pub.key
