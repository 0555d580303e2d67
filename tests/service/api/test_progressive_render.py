"""A progressive reference render through the API: ``params.max_error`` / ``params.max_ms``
validated with their ranges, kept out of the artifact key when unset, and the render's adaptive
report (estimated error, samples per pixel, passes, why it stopped) in the artifact's result."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api_schemas.service import RenderRequest
from engine import ENGINE_VERSION
from engine.imageio import read_image
from producer.artifacts import artifact_key
from producer.renders import render_artifact_key
from tests.service.api.conftest import small_scene
from tests.service.api.test_cli_api import ibr

CAM = {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0], "width": 24, "height": 16}
PARAMS = {"spp": 64, "max_depth": 1, "glossy_samples": 1, "area_light_samples": 1, "indirect_samples": 64,
          "seed": 3}


def _scene(c: TestClient) -> str:
    r = c.post("/v1/scenes", json={"scene": small_scene()})
    assert r.status_code in (200, 201), r.text
    sid: str = r.json()["id"]
    return sid


@pytest.mark.parametrize(("field", "value", "text"), [
    ("max_error", 0, "max_error must be a number in (0, 1)"), ("max_error", 1, "(0, 1)"),
    ("max_error", -0.5, "(0, 1)"), ("max_error", "0.1", "valid number"), ("max_error", True, "valid number"),
    ("max_ms", 0, "max_ms must be a number in (0, 600000]"), ("max_ms", 600_001, "(0, 600000]"),
])
def test_out_of_range_targets_are_422_with_the_range(client: TestClient, field: str, value: Any, text: str) -> None:
    sid = _scene(client)
    r = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM, "params": {field: value}})
    assert r.status_code == 422, r.text
    err = r.json()["errors"][0]
    assert err["field"] == f"params.{field}" and text in err["message"], err


def test_unset_targets_leave_the_artifact_key_as_it_was(client: TestClient) -> None:
    sid = _scene(client)
    req = RenderRequest.model_validate({"scene_id": sid, "camera": CAM, "params": PARAMS})
    legacy = req.model_dump(mode="json", exclude={"scene_id", "missing_bake", "outputs", "bake", "quality", "view"})
    # an unset target is not dumped: the params (and the key) are what they were before the targets existed
    assert set(legacy["params"]) == {"spp", "max_depth", "glossy_samples", "area_light_samples", "indirect_samples",
                                     "indirect_bounces", "seed"}
    assert render_artifact_key(req) == artifact_key("render", {"scene": sid}, legacy, ENGINE_VERSION)
    adaptive = RenderRequest.model_validate({"scene_id": sid, "camera": CAM, "params": {**PARAMS, "max_error": 0.05}})
    assert render_artifact_key(adaptive) != render_artifact_key(req)
    ok = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM,
                                          "params": {**PARAMS, "max_error": 0.05, "max_ms": 600_000}})
    assert ok.status_code == 202, ok.text


@pytest.mark.slow
def test_a_progressive_render_through_a_worker(client: TestClient, worker_process: Any, tmp_path: Path) -> None:
    worker = worker_process("render")
    sid = _scene(client)
    body = {"scene_id": sid, "camera": CAM, "params": {**PARAMS, "max_error": 0.05}}
    r = client.post("/v1/renders?wait=60", json=body)
    assert r.status_code == 200 and r.json()["status"] == "finished", (r.text, worker.log())
    result = r.json()["artifact"]["result"]
    a = result["adaptive"]
    assert a["stop_reason"] in ("error", "spp_cap") and a["max_error"] == 0.05 and a["spp_cap"] == 64
    assert a["target_met"] == (a["estimated_error"] <= 0.05)
    assert 2 <= a["spp_min"] <= a["spp_mean"] <= a["spp_max"] <= 64 and a["passes"] >= 1
    assert a["samples"] == result["counts"]["camera"]
    assert r.json()["artifact"]["params"]["params"]["max_error"] == 0.05
    # the images carry the report too
    exr = client.get(f"/v1/artifacts/{r.json()['artifact_key']}/image.exr")
    assert exr.status_code == 200
    path = tmp_path / "radiance.exr"
    path.write_bytes(exr.content)
    _, meta = read_image(path)
    assert meta["adaptive"] == a and meta["render_params"]["max_error"] == 0.05

    # a plain render of the same view has no report
    plain = client.post("/v1/renders?wait=60", json={"scene_id": sid, "camera": CAM, "params": PARAMS})
    assert plain.status_code == 200 and "adaptive" not in plain.json()["artifact"]["result"], plain.text


def _scene_file(tmp_path: Path) -> str:
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(small_scene()))
    return str(path)


def test_cli_sends_the_targets_and_checks_them_through_the_api(api_url: str, tmp_path: Path) -> None:
    scene = _scene_file(tmp_path)
    r = ibr(api_url, "render", scene, "--max-error", "0", "--no-wait")
    assert r.exit_code == 2 and "max_error must be a number in (0, 1)" in r.stderr, r.output
    r = ibr(api_url, "render", scene, "--max-error", "0.05", "--method", "ldc", "--no-wait")
    assert r.exit_code != 0 and "--max-error" in r.stderr, r.output
    sid = ibr(api_url, "scenes", "add", scene).stdout.strip()
    r = ibr(api_url, "render", sid, "--spp", "64", "--max-error", "0.05", "--max-ms", "2500", "--no-wait")
    assert r.exit_code == 0, r.output
    req = RenderRequest.model_validate({"scene_id": sid, "params": {"spp": 64, "max_error": 0.05, "max_ms": 2500}})
    assert r.stdout.strip() == f"render-{render_artifact_key(req)}"


@pytest.mark.slow
def test_cli_reports_how_a_progressive_render_ended(api_url: str, worker_process: Any, tmp_path: Path) -> None:
    worker = worker_process("render")
    out = tmp_path / "img.exr"
    r = ibr(api_url, "render", _scene_file(tmp_path), "--spp", "32", "--indirect", "32", "--max-error", "0.05",
            "-o", str(out))
    assert r.exit_code == 0, (r.output, worker.log())
    assert "estimated error" in r.stderr and "stopped by" in r.stderr and "spp mean" in r.stderr, r.stderr
    assert out.exists()


def test_light_paths_reach_the_api_and_the_default_keeps_the_key(api_url: str, tmp_path: Path) -> None:
    """``--light-paths`` (the reference's light-traced caustics, engine/light_tracing.py) is a render
    parameter checked by the API; asking for the default is the request without it (the same key)."""
    scene = _scene_file(tmp_path)
    r = ibr(api_url, "render", scene, "--light-paths", "65", "--no-wait")
    assert r.exit_code == 2 and "light_paths must be a number in [0, 64]" in r.stderr, r.output
    sid = ibr(api_url, "scenes", "add", scene).stdout.strip()
    r = ibr(api_url, "render", sid, "--light-paths", "4", "--no-wait")
    assert r.exit_code == 0, r.output
    req = RenderRequest.model_validate({"scene_id": sid, "params": {"light_paths": 4}})
    assert r.stdout.strip() == f"render-{render_artifact_key(req)}"
    default = RenderRequest.model_validate({"scene_id": sid, "params": {"light_paths": 1}})
    assert render_artifact_key(default) == render_artifact_key(RenderRequest.model_validate({"scene_id": sid}))
    assert render_artifact_key(default) != render_artifact_key(req)
