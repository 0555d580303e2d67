"""``RenderRequest.time``: a reference render of an animated scene at a moment of its animation. What
the API refuses before anything is queued (422 naming ``time``), and the artifact key: one per time,
and a request without a time keeps the key it always had."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient

from api_schemas.service import RenderRequest
from producer.renders import render_artifact_key, render_params
from tests.service.api.conftest import small_scene

CAM = {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0, 0], "width": 8, "height": 8}
ANIMATION = {"start": 0, "end": 2, "objects": {"ball": [
    {"time": 0, "transform": {"translate": [-1, 0.5, 0]}}, {"time": 2, "transform": {"translate": [1, 0.5, 0]}}]}}


def _animated() -> dict[str, Any]:
    doc = small_scene(name="moving", animation=ANIMATION)
    doc["objects"][0]["name"] = "ball"
    return doc


def _sid(c: TestClient, doc: dict[str, Any]) -> str:
    r = c.post("/v1/scenes", json={"scene": doc})
    assert r.status_code in (200, 201), r.text
    sid: str = r.json()["id"]
    return sid


def _errors(r: Any) -> list[dict[str, Any]]:
    assert r.status_code == 422, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    errors: list[dict[str, Any]] = r.json()["errors"]
    return errors


def test_each_time_is_its_own_render_and_no_time_keeps_the_old_key(client: TestClient) -> None:
    sid = _sid(client, _animated())
    plain = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM})
    at_1 = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM, "time": 1})
    at_2 = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM, "time": 2.0})
    assert plain.status_code == at_1.status_code == at_2.status_code == 202, (plain.text, at_1.text, at_2.text)
    keys = [r.json()["artifact_key"] for r in (plain, at_1, at_2)]
    assert len(set(keys)) == 3
    # the same moment (1 == 1.0) is the same render, shared
    again = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM, "time": 1.0}).json()
    assert again["artifact_key"] == keys[1] and again["job"]["id"] == at_1.json()["job"]["id"]
    # without a time, the request's key params are what they were before the field existed
    req = RenderRequest(scene_id=sid, camera=CAM)  # type: ignore[arg-type]
    assert "time" not in render_params(req) and render_artifact_key(req) == keys[0]
    assert render_params(RenderRequest(scene_id=sid, camera=CAM, time=1))["time"] == 1.0  # type: ignore[arg-type]
    # -0.0 and 0.0 are one moment
    zero = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM, "time": 0.0}).json()
    minus = client.post("/v1/renders", json={"scene_id": sid, "camera": CAM, "time": -0.0}).json()
    assert zero["artifact_key"] == minus["artifact_key"]


def test_a_time_outside_the_animation_names_the_interval(client: TestClient) -> None:
    sid = _sid(client, _animated())
    for t in (2.5, -0.25):
        (err,) = _errors(client.post("/v1/renders", json={"scene_id": sid, "time": t}))
        assert err["field"] == "time" and err["type"] == "time_out_of_range"
        assert err["message"] == f"time {t:g} is outside the animation interval [0, 2]"
    (err,) = _errors(client.post("/v1/renders", json={"scene_id": sid, "time": "soon"}))
    assert err["field"] == "time"
    assert client.get("/v1/jobs").json()["items"] == []  # nothing was queued


def test_a_time_on_a_scene_without_animation_is_refused(client: TestClient) -> None:
    sid = _sid(client, small_scene(name="still"))
    (err,) = _errors(client.post("/v1/renders", json={"scene_id": sid, "time": 0}))
    assert err["field"] == "time" and err["type"] == "no_animation"
    assert "no animation" in err["message"]


def test_a_time_needs_the_reference_method(client: TestClient) -> None:
    sid = _sid(client, _animated())
    (err,) = _errors(client.post("/v1/renders", json={"scene_id": sid, "method": "ldc+llf", "time": 1}))
    assert err["field"] == "time" and err["type"] == "time_with_bake"
    assert "'ldc+llf'" in err["message"] and "bake of the scene as stored" in err["message"]
    (err,) = _errors(client.post("/v1/renders", json={"scene_id": sid, "quality": {"max_ms": 100}, "time": 1}))
    assert err["field"] == "time" and err["type"] == "time_with_quality"
    assert "quality contract" in err["message"]


def test_a_batch_checks_each_time_against_its_scene(client: TestClient) -> None:
    moving, still = _sid(client, _animated()), _sid(client, small_scene(name="still"))
    r = client.post("/v1/batches", json={"renders": [
        {"scene_id": moving, "time": 1}, {"scene_id": moving, "time": 3}, {"scene_id": still, "time": 1}]})
    errors = _errors(r)
    assert {(e["field"], e["type"]) for e in errors} == {("renders.1.time", "time_out_of_range"),
                                                         ("renders.2.time", "no_animation")}
    r = client.post("/v1/batches", json={"renders": [{"scene_id": moving, "time": 1}, {"scene_id": moving}]})
    assert r.status_code == 202, r.text
    assert len({rp["artifact_key"] for rp in r.json()["renders"]}) == 2


def test_the_client_and_ibr_render_send_the_time(api_url: str) -> None:
    from typer.testing import CliRunner

    from ibr_client import ApiError, Client
    from service.cli import app as cli_app

    with Client(api_url) as c:
        sid = c.create_scene(_animated()).id
        at_1 = c.render(sid, camera=CAM, time=1.0)
        assert at_1.artifact_key == render_artifact_key(RenderRequest(scene_id=sid, camera=CAM, time=1.0))  # type: ignore[arg-type]
        with pytest.raises(ApiError, match=r"time: time 9 is outside the animation interval \[0, 2\]") as exc:
            c.render(sid, time=9.0)
        assert exc.value.status == 422

    def ibr(*args: str) -> Any:
        return CliRunner().invoke(cli_app, ["render", sid, "--no-wait", *args],
                                  env={"IBR_API_URL": api_url, "IBR_API_KEY": ""})

    r = ibr("--time", "1", "--spp", "1")
    assert r.exit_code == 0, r.output
    key = render_artifact_key(RenderRequest(scene_id=sid, time=1.0, params={"spp": 1}))  # type: ignore[arg-type]
    assert r.stdout == f"render-{key}\n"
    r = ibr("--time", "3")
    assert r.exit_code == 2 and "time 3 is outside the animation interval [0, 2]" in r.stderr, r.output
    r = ibr("--time", "1", "--method", "ldc")
    assert r.exit_code != 0 and "--time" in r.stderr and r.stdout == "", r.output
