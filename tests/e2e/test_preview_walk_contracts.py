"""The preview's Walkthroughs panel asks by error or by time instead of by preset and fill, in a real
browser against a live stack: an uncalibrated scene says how to calibrate it and offers the button
that does; the button calibrates (its progress shown), then the walkthrough is asked again as a
quality contract and the panel shows the plan with its predicted against achieved numbers; an
unreachable target shows what the scene can do; by time the page sends a best-effort budget.

The page knows the view spaces of the sample scenes only (``/preview/sample-cameras.json``), whose
bakes take minutes at the presets' sizes (a calibration cannot shrink them as ``?wt_face=`` does):
the tests upload a tiny room instead (the API tests' walkthrough scene, about 10 s to calibrate
both presets) and add its view space to that list on its way to the page."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from playwright.sync_api import Browser, Page, Request, Route, expect

from api_schemas.walkthrough import DEFAULT_PATH_NOISES
from service.up import Stack
from tests.e2e.conftest import ARTIFACTS, shot
from tests.service.api.test_walkthroughs import ROOM

# Everyday runs skip this file (make test-fast): browser end-to-end: a live stack driven through chromium.
pytestmark = pytest.mark.slow

NAME = "e2e_walk_contract_room"
SCENE = {**ROOM, "name": NAME}  # two boxes, a point light, an animated occluder, a path view space
URL = "/preview/?walk={name}&wt_ask=error&wt_target=25"
FRAMES, WIDTH = 8, 64  # 64 x 48 frames (the room's camera is 4:3)
CALIBRATE_PARAMS = {"presets": ["low", "medium"], "fills": ["both"], "path_noises": list(DEFAULT_PATH_NOISES)}


@pytest.fixture(scope="module")
def scene_id(stack: Stack) -> str:
    r = httpx.post(f"{stack.api_url}/v1/scenes", json={"scene": SCENE}, timeout=30)
    assert r.status_code in (200, 201), r.text
    sid: str = r.json()["id"]
    return sid


def _with_room(route: Route) -> None:
    """The sample scenes' cameras plus the room's: the Walkthroughs panel lists it."""
    cams = route.fetch().json()
    anim = SCENE["animation"]
    cams[NAME] = {"camera": SCENE["camera"], "pivot": SCENE["camera"]["look_at"], "view_space": SCENE["view_space"],
                  "animation": {"start": anim["start"], "end": anim["end"]}}
    route.fulfill(status=200, content_type="application/json", body=json.dumps(cams))


@pytest.fixture(scope="module")
def posted() -> list[Request]:
    """Every POST the page sends to the API, in order."""
    return []


@pytest.fixture(scope="module")
def page(stack: Stack, browser: Browser, capabilities: dict[str, Any], scene_id: str,
         posted: list[Request]) -> Iterator[Page]:
    assert capabilities["walkthroughs"], capabilities  # the service routes walkthroughs: never a silent skip
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    ctx = browser.new_context(viewport={"width": 1400, "height": 900})
    try:
        ctx.route("**/preview/sample-cameras.json", _with_room)
        pg = ctx.new_page()
        pg.set_default_timeout(30_000)
        pg.on("request", lambda q: posted.append(q) if q.method == "POST" and "/v1/" in q.url else None)
        pg.goto(stack.api_url + URL.format(name=NAME))
        yield pg
    finally:
        ctx.close()


def _body(q: Request) -> dict[str, Any]:
    body = q.post_data_json
    assert isinstance(body, dict), q.post_data
    return body


def _last_post(posted: list[Request], path: str) -> dict[str, Any]:
    sent = [q for q in posted if path in q.url]
    assert sent, [q.url for q in posted]
    return _body(sent[-1])


def _render(page: Page) -> dict[str, Any]:
    """Press Render walkthrough; the body the page sent."""
    with page.expect_request(lambda q: q.method == "POST" and "/v1/walkthroughs" in q.url) as sent:
        page.click("#wt-go")
    return _body(sent.value)


def test_asking_by_error_without_a_calibration_says_how_to_make_one(page: Page, stack: Stack, scene_id: str) -> None:
    page.wait_for_selector("body[data-ready=true]")
    expect(page.locator("#walk-panel")).to_be_visible()
    expect(page.locator("#walk-name")).to_contain_text(NAME)
    # asked by error (from the URL): the target instead of the quality and fill controls
    expect(page.locator("#wt-ask")).to_have_value("error")
    expect(page.locator("#wt-target")).to_have_value("25")
    expect(page.locator("#wt-target-unit")).to_have_text("max error % per frame")
    expect(page.locator("#wt-quality-label")).to_be_hidden()
    expect(page.locator("#wt-fill-label")).to_be_hidden()
    page.select_option("#wt-frames", str(FRAMES))
    page.select_option("#wt-size", str(WIDTH))
    body = _render(page)
    # a contract, no preset and no fill (the planner picks them; naming them too is a 422); error: strict
    assert body["quality"] == {"max_error": 0.25} and "bake" not in body and "fill" not in body
    assert body["scene_id"] == scene_id and len(body["frames"]) == FRAMES
    note = page.locator("#wt-note")
    expect(note).to_be_visible()
    expect(note).to_contain_text("has no walkthrough calibration yet")
    expect(note).to_contain_text(f"POST /v1/scenes/{scene_id}/walkthrough-calibrations")
    expect(note).to_contain_text(f"ibr calibrate-walkthroughs {scene_id}")
    button = page.get_by_role("button", name="Calibrate walkthroughs")
    expect(button).to_be_visible()
    # the title says what the button asks for
    title = button.get_attribute("title") or ""
    assert f"POST /v1/scenes/{scene_id}/walkthrough-calibrations" in title
    assert json.dumps(CALIBRATE_PARAMS) in title
    expect(page.locator("#wt-contract")).to_be_hidden()
    expect(page.locator("#wt-player")).to_be_hidden()
    expect(page.locator("#error")).to_be_hidden()  # said in the panel, next to the button, not in the banner
    assert httpx.get(f"{stack.api_url}/v1/scenes/{scene_id}/walkthrough-calibrations", timeout=30).status_code == 404
    shot(page, "60-walkthrough-contract-uncalibrated")


def test_a_refused_calibration_says_why_and_the_button_tries_again(page: Page) -> None:
    # the API refusing it as it refuses a preset whose bake exceeds this server's limits (the answer is
    # stood in for: the stack's limits take every preset of the tiny room)
    problem = {"type": "about:blank", "title": "Invalid input", "status": 422, "detail": "1 invalid field(s)",
               "errors": [{"field": "params.presets.1", "type": "bake_too_large",
                           "message": "the medium bake needs more memory than this server allows"}]}
    refuse = "**/walkthrough-calibrations"
    page.route(refuse, lambda route: route.fulfill(status=422, content_type="application/problem+json",
                                                   body=json.dumps(problem)))
    try:
        page.get_by_role("button", name="Calibrate walkthroughs").click()
        note = page.locator("#wt-note")
        expect(note).to_contain_text("Invalid input (HTTP 422): 1 invalid field(s)")
        expect(note).to_contain_text("params.presets.1: the medium bake needs more memory")
        expect(page.get_by_role("button", name="Calibrate walkthroughs")).to_be_enabled()
        expect(page.locator("#wt-cal-progress")).to_be_hidden()
    finally:
        page.unroute(refuse)


def test_calibrating_asks_again_and_shows_the_plan_with_achieved_times(page: Page, stack: Stack, scene_id: str,
                                                                      posted: list[Request]) -> None:
    with page.expect_request(lambda q: q.method == "POST" and "/walkthrough-calibrations" in q.url) as sent:
        page.get_by_role("button", name="Calibrate walkthroughs").click()
    assert _body(sent.value) == {"params": CALIBRATE_PARAMS}
    expect(page.locator("#wt-cal-progress")).to_be_visible()
    expect(page.locator("#wt-calibrate")).to_be_hidden()
    expect(page.locator("#wt-note")).to_contain_text("Calibrating the walkthroughs")
    # the page follows the job: its state, stage and fraction as the API reports them
    seen: list[dict[str, Any]] = []
    for _ in range(600):
        cal = page.evaluate("window.__walkCalibration")
        seen.append(cal)
        if cal["state"] in ("finished", "failed", "missing"):
            break
        if cal["state"] == "running" and cal["stage"]:
            expect(page.locator("#wt-cal-stage")).to_contain_text("walkthrough calibration running")
        page.wait_for_timeout(200)
    assert cal["state"] == "finished", (cal, page.locator("#wt-cal-stage").inner_text(),
                                        page.locator("#wt-note").inner_text())
    assert all(0 <= c["fraction"] <= 1 for c in seen) and cal["fraction"] == 1
    assert any(c["state"] == "running" and c["stage"] for c in seen), seen
    expect(page.locator("#wt-cal-stage")).to_contain_text("walkthrough calibration finished")
    stored = httpx.get(f"{stack.api_url}/v1/scenes/{scene_id}/walkthrough-calibrations", timeout=30).json()
    assert stored["state"] == "finished" and stored["key"] == cal["key"]
    assert set(stored["model"]["fits"]) == {"low/both", "medium/both",
                                              *(f"path/{n:g}" for n in DEFAULT_PATH_NOISES)}
    # then the page asks the same walkthrough again, now planned, and follows it to its frames
    page.wait_for_function("window.__walk.contract && window.__walk.status === 'finished' && "
                           f"window.__walk.loaded === {FRAMES}", timeout=120_000)
    body = _last_post(posted, "/v1/walkthroughs")
    assert body["quality"] == {"max_error": 0.25} and "bake" not in body and "fill" not in body
    expect(page.locator("#wt-note")).to_be_hidden()
    shown = page.evaluate("window.__walk.contract")
    api = httpx.get(f"{stack.api_url}/v1/walkthroughs/{page.evaluate('window.__walk.key')}", timeout=30).json()
    con = api["contract"]
    assert shown == con  # the page shows the API's plan, not its own
    assert con["met"] and con["rule"] == "cheapest_meeting_error" and con["predicted_error"] <= 0.25
    # the calibration made and stored both presets' bakes; path-traced frames need none (on this room, with
    # little indirect light and tiny frames, either can be the cheapest)
    assert con["bake"] == ("none" if con["path_noise"] is not None else "ready")
    achieved = con["achieved_frame_ms"]
    assert achieved and 0 < achieved["median"] <= achieved["max"]
    table = page.locator("#wt-contract")
    expect(table).to_be_visible()
    expect(table).to_contain_text("error ≤ 25.00 % per frame")
    plan = (f"path-traced frames (noise {con['path_noise']:g}, no bake)" if con["path_noise"] is not None
            else f"bake preset {con['preset']}, fill {con['fill']}")
    expect(table).to_contain_text(plan)
    expect(table).to_contain_text("cheapest_meeting_error")
    expect(table).to_contain_text(f"{con['predicted_error'] * 100:.2f} %")
    if con["path_noise"] is not None:  # path-traced frames state their own estimates of their error
        est = con["achieved_estimated_error"]
        assert est and 0 < est["median"] <= est["max"]
        expect(table).to_contain_text(f"estimated by the frames: median {est['median'] * 100:.2f} %")
    else:
        assert con["achieved_estimated_error"] is None
        expect(table).to_contain_text("not measured")
    expect(table).to_contain_text(f"{con['predicted_frame_ms']:.1f} ms per frame")
    expect(table).to_contain_text(f"median {achieved['median']:.1f} ms, max {achieved['max']:.1f} ms per frame")
    expect(table).to_contain_text("none needed" if con["path_noise"] is not None else "ready (in the store)")
    expect(page.locator("#wt-player")).to_be_visible()
    expect(page.locator("#error")).to_be_hidden()
    shot(page, "61-walkthrough-contract-by-error")


def test_an_unreachable_target_shows_what_the_scene_can_do(page: Page) -> None:
    page.fill("#wt-target", "0.05")
    body = _render(page)
    assert body["quality"] == {"max_error": 0.0005}
    note = page.locator("#wt-note")
    expect(note).to_contain_text("Quality contract cannot be met (HTTP 422)")
    expect(note).to_contain_text("no walkthrough setting reaches LRMS 0.0005")
    expect(note).to_contain_text("Raise the target")
    expect(page.locator("#wt-calibrate")).to_be_hidden()
    expect(page.locator("#wt-contract")).to_be_hidden()
    expect(page.locator("#error")).to_be_hidden()
    shot(page, "62-walkthrough-contract-unmet")


def test_asking_by_time_sends_a_best_effort_budget_and_settings_come_back(page: Page) -> None:
    page.select_option("#wt-ask", "time")
    expect(page.locator("#wt-target-unit")).to_have_text("max ms per frame")
    expect(page.locator("#wt-target")).to_have_value("50")  # each kind of target keeps its own value
    page.select_option("#wt-ask", "error")
    expect(page.locator("#wt-target")).to_have_value("0.05")
    page.select_option("#wt-ask", "time")
    body = _render(page)
    assert body["quality"] == {"max_ms": 50, "on_miss": "best_effort"} and "bake" not in body
    expect(page.locator("#wt-note")).to_be_hidden()  # a new request: the last one's problem is gone
    page.wait_for_function("window.__walk.contract && window.__walk.status === 'finished'", timeout=120_000)
    con = page.evaluate("window.__walk.contract")
    assert con["rule"] in ("most_accurate_within_time", "best_effort_fastest") and con["max_ms"] == 50
    table = page.locator("#wt-contract")
    expect(table).to_contain_text("time ≤ 50.0 ms per frame (best effort)")
    if not con["met"]:
        expect(table).to_contain_text(con["reason"])
    shot(page, "63-walkthrough-contract-by-time")
    # back to settings: the quality and fill controls, no plan; the request names them again
    page.select_option("#wt-ask", "settings")
    expect(page.locator("#wt-quality-label")).to_be_visible()
    expect(page.locator("#wt-fill-label")).to_be_visible()
    expect(page.locator("#wt-target-label")).to_be_hidden()
    expect(table).to_be_hidden()
    page.select_option("#wt-quality", "low")
    page.select_option("#wt-fill", "both")
    body = _render(page)
    assert "quality" not in body and body["bake"] == {"quality": "low"} and body["fill"] == "both"
    page.wait_for_function("window.__walk.status === 'finished'", timeout=120_000)
    expect(table).to_be_hidden()  # asked by settings: no contract to show
