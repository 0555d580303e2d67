"""The preview page asks by error or by time instead of by method, in a real browser against a live
stack: an uncalibrated scene says how to calibrate it; once calibrated, the page sends a quality
contract (no method), shows the plan the API chose and its predicted against achieved numbers, and
going back to asking by method hides them."""

from __future__ import annotations

import time
from typing import Any

import httpx
import pytest
from playwright.sync_api import Browser, Page, expect

from service.up import Stack
from tests.e2e.conftest import SETTLED, new_page, shot

# Everyday runs skip this file (make test-fast): browser end-to-end: a live stack driven through chromium.
pytestmark = pytest.mark.slow

SIZE = 64
NAME = "e2e_contract_sphere"
SCENE = {
    "name": NAME,
    "camera": {"type": "perspective", "eye": [0, 0, 3], "look_at": [0, 0, 0], "fov_y_deg": 40,
               "width": SIZE, "height": SIZE},
    "materials": [{"name": "m", "kd": [0.7, 0.5, 0.3]}],
    "objects": [{"type": "sphere", "material": "m", "radius": 0.5}],
    "lights": [{"type": "point", "position": [3, 3, 3], "intensity": [27, 27, 27]},
               {"type": "rect", "corner": [-1, 2, -1], "edge_u": [2, 0, 0], "edge_v": [0, 0, 2],
                "radiance": [2, 2, 2]}],
}


def _page_bake(page: Page) -> dict[str, Any]:
    """The bake the page names in its requests (no finished bake is picked: the bake panel's settings)."""
    got: dict[str, Any] = page.evaluate("""() => ({ ldc_resolution: Number(document.querySelector('#bake-res').value),
        llf: document.querySelector('#bake-llf').value,
        indirect: { mode: document.querySelector('#bake-indirect').value } })""")
    return got


def _calibrate(api: str, sid: str, bake: dict[str, Any]) -> dict[str, Any]:
    r = httpx.post(f"{api}/v1/scenes/{sid}/calibrations", timeout=30,
                   json={"bake": bake, "missing_bake": "bake",
                         "params": {"probes": 1, "size": 24, "truth_spp": 32, "time_scale": 2}})
    assert r.status_code in (200, 202), r.text
    url = f"{api}{r.headers['location']}" if r.status_code == 202 else f"{api}/v1/scenes/{sid}/calibrations/" \
        f"{r.json()['bake_key']}"
    deadline = time.monotonic() + 600
    body: dict[str, Any] = r.json()
    while body.get("state") not in ("finished", "failed") and time.monotonic() < deadline:
        time.sleep(0.5)
        body = httpx.get(url, timeout=30).json()
    assert body.get("state") == "finished", body
    return body


def _post_json(request: Any) -> dict[str, Any]:
    got: dict[str, Any] = request.post_data_json
    return got


def test_ask_by_error_and_by_time_shows_the_plan_and_predicted_against_achieved(stack: Stack,
                                                                                browser: Browser) -> None:
    r = httpx.post(f"{stack.api_url}/v1/scenes", json={"scene": SCENE}, timeout=30)
    assert r.status_code in (200, 201), r.text
    sid = r.json()["id"]
    url = f"{stack.api_url}/preview/?size={SIZE}&ldc=16&ask=error&target=10&scene={NAME}"
    with new_page(browser, url) as page:
        page.wait_for_selector("body[data-ready=true]")
        expect(page.locator("#method-label")).to_be_hidden()  # asking by error: no method, no spp
        expect(page.locator("#target-label")).to_be_visible()
        # the scene was never calibrated: the page says so and how, and shows no image
        expect(page.locator("#error")).to_contain_text("calibrat")
        expect(page.locator("#error")).to_contain_text(f"/v1/scenes/{sid}/calibrations")
        assert page.evaluate("!document.querySelector('#view').hasAttribute('src')")
        expect(page.locator("#contract")).to_be_hidden()
        shot(page, "50-contract-uncalibrated")

        bake = _page_bake(page)
        _calibrate(stack.api_url, sid, bake)
        page.get_by_role("button", name="Dismiss the error").click()
        # a new target: the page asks by error (a contract, no method) and shows the plan
        with page.expect_request(lambda q: q.method == "POST" and "/v1/renders" in q.url) as sent:
            page.fill("#target", "8")
            page.locator("#target").blur()
        body = _post_json(sent.value)
        assert body["quality"] == {"max_error": 0.08} and "method" not in body and "params" not in body
        assert body["bake"] == bake
        page.wait_for_function(SETTLED + " && window.__preview.last.contract", timeout=120_000)
        shown = page.evaluate("window.__preview.last.contract")
        # the same request through the API plans the same (the page shows the API's plan, not its own)
        api = httpx.post(f"{stack.api_url}/v1/renders?wait=60", json=body, timeout=90).json()["contract"]
        assert shown["method"] == api["method"] and shown["rule"] == api["rule"] == "cheapest_meeting_error"
        assert shown["predicted_error"] == pytest.approx(api["predicted_error"]) and shown["met"]
        assert shown["predicted_error"] <= 0.08 and shown["achieved_ms"] > 0
        assert shown["estimated_error"] is not None and shown["estimated_error_source"] in ("render", "calibration")
        table = page.locator("#contract")
        expect(table).to_be_visible()
        expect(table).to_contain_text("error ≤ 8.00 %")
        expect(table).to_contain_text(f"{shown['predicted_error'] * 100:.2f} %")
        expect(table).to_contain_text(f"{shown['achieved_ms']:.1f} ms")
        expect(table).to_contain_text(shown["plan"])
        shot(page, "51-contract-by-error")

        # by time: a budget, the most accurate setting within it
        with page.expect_request(lambda q: q.method == "POST" and "/v1/renders" in q.url) as sent:
            page.select_option("#ask", "time")
        body = _post_json(sent.value)
        assert body["quality"]["max_ms"] == 200 and "max_error" not in body["quality"]
        page.wait_for_function(SETTLED + " && window.__preview.last.contract && "
                               "window.__preview.last.contract.rule !== 'cheapest_meeting_error'", timeout=120_000)
        shown = page.evaluate("window.__preview.last.contract")
        assert shown["rule"] in ("most_accurate_within_time", "best_effort_fastest")
        expect(table).to_contain_text("time ≤ 200.0 ms")
        shot(page, "52-contract-by-time")

        # back to asking by method: the method controls again, no contract shown
        page.select_option("#ask", "method")
        expect(page.locator("#method-label")).to_be_visible()
        expect(table).to_be_hidden()
        page.wait_for_function(SETTLED + " && !window.__preview.last.contract", timeout=120_000)
