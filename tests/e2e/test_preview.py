"""The browser preview page in a real browser (Debian's chromium driven by Playwright)
against a live local stack: embedded Redis, real bake and render workers, uvicorn API."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from playwright.sync_api import Browser, Page, expect

from service.up import Stack
from tests.e2e.conftest import SETTLED, element_pixels, new_page, shot, wait_for_load
from tests.fixtures.stack import own_stack

# Everyday runs skip this file (make test-fast): browser end-to-end: a live stack driven through chromium.
pytestmark = pytest.mark.slow

SIZE = 128
SCENE = "mirror_box"


@pytest.fixture(scope="module")
def page(stack: Stack, browser: Browser) -> Iterator[Page]:
    with new_page(browser, f"{stack.api_url}/?size={SIZE}&spp=1") as pg:
        yield pg


def image_pixels(page: Page) -> np.ndarray:
    return element_pixels(page, "#view")


def test_page_loads_and_lists_sample_scenes(page: Page, capabilities: dict[str, Any]) -> None:
    assert page.url.endswith(f"/preview/?size={SIZE}&spp=1")  # / redirects to the page
    page.wait_for_selector("body[data-ready=true]")
    # each button's label (its first text): the scene's name; the short id follows as secondary text
    names = page.locator("#scene-list button").evaluate_all("bs => bs.map((b) => b.firstChild.textContent)")
    assert {"teapot_glossy", "mirror_box", "cornell_box"} <= set(names)
    # only the methods that exist, as the API says (never a list of its own)
    assert page.locator("#method option").all_inner_texts() == [m["name"] for m in capabilities["methods"]]
    assert "reference" in page.locator("#method option").all_inner_texts()
    expect(page.locator("#datasets-panel")).to_be_visible(visible=capabilities["datasets"] and capabilities["relights"])
    expect(page.locator("#error")).to_be_hidden()
    shot(page, "01-scene-list")


def test_open_scene_shows_image_and_timings(page: Page) -> None:
    loads = page.evaluate("window.__preview.loads")
    page.get_by_role("button", name=SCENE, exact=True).click()
    last = wait_for_load(page, loads)
    assert page.evaluate("document.querySelector('#view').naturalWidth") == SIZE
    assert last["latency"] > 0
    expect(page.locator("#timings")).to_contain_text("total")
    expect(page.locator("#timings")).to_contain_text("round trip")
    shot(page, "02-scene-open")


def test_drag_orbits_and_changes_the_image(page: Page) -> None:
    before = image_pixels(page)
    key_before = page.locator("#view").get_attribute("data-key")
    src_before = page.locator("#view").get_attribute("src")
    loads = page.evaluate("window.__preview.loads")
    box = page.locator("#viewport").bounding_box()
    assert box is not None
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 60, y + 10, steps=4)
    page.mouse.up()
    wait_for_load(page, loads)
    page.wait_for_function("window.__preview.requests > 0")
    # latest request wins: wait until the shown image is the last one asked for
    page.wait_for_function(SETTLED)
    assert page.locator("#view").get_attribute("src") != src_before
    assert page.locator("#view").get_attribute("data-key") != key_before
    after = image_pixels(page)
    assert after.shape == before.shape
    assert np.abs(after - before).mean() > 1.0
    shot(page, "03-orbited")


def test_keyboard_zoom_requests_a_new_view(page: Page) -> None:
    key_before = page.locator("#view").get_attribute("data-key")
    loads = page.evaluate("window.__preview.loads")
    page.locator("#viewport").focus()
    page.keyboard.press("+")
    wait_for_load(page, loads)
    assert page.locator("#view").get_attribute("data-key") != key_before
    shot(page, "04-zoomed")


def test_fast_drag_and_arrow_keys_latest_view_wins(page: Page) -> None:
    box = page.locator("#viewport").bounding_box()
    assert box is not None
    x, y = box["x"] + 20, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    for i in range(12):  # faster than the renders: stale requests are aborted and their jobs canceled
        page.mouse.move(x + 6 * (i + 1), y - 2 * i)
        page.wait_for_timeout(30)
    page.mouse.up()
    page.locator("#viewport").focus()
    page.keyboard.press("ArrowLeft")
    page.keyboard.press("ArrowUp")
    page.wait_for_function(SETTLED, timeout=60_000)
    expect(page.locator("#error")).to_be_hidden()
    assert page.evaluate("document.querySelector('#view').naturalWidth") == SIZE
    shot(page, "04b-fast-drag")


def test_jobs_panel_shows_finished_jobs(page: Page) -> None:
    rows = page.locator("#jobs tbody tr[data-state=finished]")
    expect(rows.first).to_be_visible(timeout=10_000)
    # the scene's first view, the orbited one and the zoomed one (stale drag views may be canceled)
    page.wait_for_function("document.querySelectorAll('#jobs tbody tr[data-state=finished]').length >= 3",
                           timeout=10_000)
    expect(rows.first.locator("progress")).to_have_attribute("value", "1")
    shot(page, "05-jobs")


def test_api_error_is_shown_as_readable_message(page: Page) -> None:
    page.fill("#spp", "99999")
    page.locator("#spp").dispatch_event("change")
    err = page.locator("#error")
    expect(err).to_be_visible()
    expect(err).to_contain_text("params.spp")
    expect(err).to_contain_text("4096")
    text = err.inner_text()
    assert "{" not in text and '"' not in text  # words, not a JSON dump
    shot(page, "06-error")
    page.fill("#spp", "1")
    page.locator("#spp").dispatch_event("change")
    expect(err).to_be_hidden()


def test_api_key_is_kept_in_session_storage_and_sent(page: Page) -> None:
    seen: list[str | None] = []
    page.on("request", lambda r: seen.append(r.headers.get("authorization")) if "/v1/scenes" in r.url else None)
    page.fill("#api-key", "k-test")
    page.click("#key-form button[type=submit]")
    page.wait_for_function("document.querySelector('#key-state').textContent.includes('key set')")
    assert page.evaluate("sessionStorage.getItem('ibr.apiKey')") == "k-test"
    page.wait_for_timeout(300)
    assert "Bearer k-test" in seen
    page.fill("#api-key", "")
    page.click("#key-form button[type=submit]")
    page.wait_for_function("sessionStorage.getItem('ibr.apiKey') === null")


AUTH_KEY = "preview-test-key"


@pytest.fixture(scope="module")
def auth_stack() -> Iterator[Stack]:
    """A second stack with API keys on: the page must say what is wrong, then work with the key."""
    with own_stack({"IBR_API_KEYS": hashlib.sha256(AUTH_KEY.encode()).hexdigest()}, samples=True,
                   api_key=AUTH_KEY) as st:
        yield st


def test_missing_or_wrong_api_key_is_a_readable_message(auth_stack: Stack, browser: Browser) -> None:
    ctx = browser.new_context(viewport={"width": 1280, "height": 800})
    pg = ctx.new_page()
    pg.set_default_timeout(30_000)
    try:
        pg.goto(f"{auth_stack.api_url}/preview/?size={SIZE}")
        err = pg.locator("#error")
        expect(err).to_be_visible()
        expect(err).to_contain_text("401")
        expect(err).to_contain_text("API key")
        assert "{" not in err.inner_text()
        shot(pg, "07-missing-key")
        pg.fill("#api-key", "wrong-key")
        pg.click("#key-form button[type=submit]")
        expect(err).to_contain_text("401")
        pg.fill("#api-key", AUTH_KEY)
        pg.click("#key-form button[type=submit]")
        expect(err).to_be_hidden()
        expect(pg.get_by_role("button", name="teapot_glossy", exact=True)).to_be_visible()
        shot(pg, "08-with-key")
        pg.reload()  # kept for the session
        pg.wait_for_selector("body[data-ready=true]")
        assert pg.input_value("#api-key") == AUTH_KEY
        expect(pg.get_by_role("button", name="teapot_glossy", exact=True)).to_be_visible()
        expect(err).to_be_hidden()
    finally:
        ctx.close()
