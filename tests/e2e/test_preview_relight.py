"""The preview page's Datasets panel (on top of the relighting API): a small dataset generated
from a sphere-on-floor scene, baked from the page, relit live by dragging the light over the sphere
widget, a second light added, the coverage mask shown."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
from playwright.sync_api import Browser, Page, expect

from engine.imageio import decode_image
from engine.metrics import lrms
from service.up import Stack
from tests.e2e.conftest import RELIT_SETTLED, drag, element_pixels, new_page, shot

# Everyday runs skip this file (make test-fast): browser end-to-end: a live stack driven through chromium.
pytestmark = pytest.mark.slow

BALL: dict[str, Any] = {
    "name": "e2e_ball",
    "camera": {"type": "perspective", "eye": [0, 1.2, 3.2], "look_at": [0, 0.45, 0], "fov_y_deg": 40,
               "width": 64, "height": 48},
    "materials": [{"name": "white", "kd": [0.8, 0.8, 0.8]}, {"name": "red", "kd": [0.8, 0.15, 0.1]}],
    "objects": [
        {"type": "sphere", "material": "red", "radius": 0.5, "transform": {"translate": [0, 0.5, 0]}},
        {"type": "plane", "material": "white", "size": [3, 3]},
    ],
    "lights": [{"type": "point", "position": [2, 3, 2], "intensity": [10, 10, 10]}],
}


@pytest.fixture(scope="module")
def dataset(stack: Stack, capabilities: dict[str, Any]) -> dict[str, Any]:
    # the service routes datasets and relights: capabilities saying otherwise is a bug, not a skip
    assert capabilities["datasets"] and capabilities["relights"], capabilities
    api = stack.api_url
    scene = httpx.post(f"{api}/v1/scenes", json={"scene": BALL}, timeout=30).json()
    req = {"scene_id": scene["id"], "placement": {"region": "upper_front_quarter", "spacing_deg": 30},
           "params": {"spp": 1, "area_light_samples": 1, "glossy_samples": 1}}
    r = httpx.post(f"{api}/v1/datasets/generate?wait=60", json=req, timeout=90)
    assert r.status_code in (200, 202), r.text
    body = r.json()
    for _ in range(300):
        if body.get("dataset_id"):
            break
        assert body["status"] not in ("failed",), body
        import time
        time.sleep(0.3)
        body = httpx.post(f"{api}/v1/datasets/generate?wait=5", json=req, timeout=30).json()
    d: dict[str, Any] = httpx.get(f"{api}/v1/datasets/{body['dataset_id']}", timeout=30).json()
    return d


@pytest.fixture(scope="module")
def page(stack: Stack, browser: Browser, dataset: dict[str, Any]) -> Iterator[Page]:
    with new_page(browser, f"{stack.api_url}/preview/") as pg:
        yield pg


def test_open_dataset_bakes_and_relights(page: Page, dataset: dict[str, Any]) -> None:
    page.wait_for_selector("body[data-ready=true]")
    expect(page.locator("#datasets-panel")).to_be_visible()
    page.click("#reload-datasets")
    button = page.locator(f"#dataset-list button[data-id='{dataset['id']}']")
    expect(button).to_be_visible()
    # named by the scene it was generated from (its own name is "generated-<scene hash>"); the hash is secondary
    assert dataset["name"].startswith("generated-")
    expect(button).to_have_accessible_name(f"{BALL['name']} (generated)")
    expect(button.locator(".hash")).to_have_text(dataset["id"][:8])
    button.click()
    expect(page.locator("#dataset-name")).to_have_text(f"— {BALL['name']} (generated)")
    expect(page.locator("#relight-panel")).to_be_visible()
    expect(page.locator("#view-panel")).to_be_hidden()
    page.wait_for_function("window.__relight.loads >= 1", timeout=120_000)
    expect(page.locator("#dbake-stage")).to_contain_text("done")
    assert page.evaluate("document.querySelector('#relit').naturalWidth") == dataset["width"]
    expect(page.locator("#error")).to_be_hidden()
    expect(page.locator("#relight-stats")).to_contain_text("round trip")
    shot(page, "20-relight-open")


def test_drag_light_relights(page: Page, dataset: dict[str, Any]) -> None:
    page.wait_for_function(RELIT_SETTLED)
    before = element_pixels(page, "#relit")
    first = page.evaluate("window.__relight.last")
    # from the left of the sphere widget to its upper right: the light swings across the object
    drag(page, "#light-sphere", 110, -40, steps=6, start=(0.2, 0.5))
    page.wait_for_function(f"window.__relight.loads > {page.evaluate('window.__relight.loads') - 1} && "
                           + RELIT_SETTLED, timeout=60_000)
    page.wait_for_function(RELIT_SETTLED + f" && window.__relight.last.seq > {first['seq']}", timeout=60_000)
    last = page.evaluate("window.__relight.last")
    assert last["lights"] != first["lights"]
    p0, p1 = np.array(first["lights"][0]["position"]), np.array(last["lights"][0]["position"])
    centre = np.array(dataset["manifest"]["sphere_center"] or [0, 0, 0])
    # the distance is kept, the direction moved
    assert np.linalg.norm(p0 - centre) == pytest.approx(np.linalg.norm(p1 - centre), rel=1e-5)
    assert np.linalg.norm(p0 - p1) > 0.2 * np.linalg.norm(p0 - centre)
    assert np.abs(element_pixels(page, "#relit") - before).mean() > 1.0
    expect(page.locator("#error")).to_be_hidden()
    shot(page, "21-light-dragged")


def test_keyboard_distance_intensity_and_second_light(page: Page) -> None:
    seq = page.evaluate("window.__relight.last.seq")
    page.locator("#light-sphere").focus()
    page.keyboard.press("ArrowUp")
    page.wait_for_function(RELIT_SETTLED + f" && window.__relight.last.seq > {seq}", timeout=60_000)
    seq = page.evaluate("window.__relight.last.seq")
    page.locator("#light-int").fill("1")
    page.locator("#light-int").dispatch_event("input")
    page.wait_for_function(RELIT_SETTLED + f" && window.__relight.last.seq > {seq}", timeout=60_000)
    seq = page.evaluate("window.__relight.last.seq")
    page.click("#add-light")
    page.wait_for_function(RELIT_SETTLED + f" && window.__relight.last.seq > {seq}", timeout=60_000)
    last = page.evaluate("window.__relight.last")
    assert len(last["lights"]) == 2
    expect(page.locator("#light-list li")).to_have_count(2)
    expect(page.locator("#error")).to_be_hidden()
    shot(page, "22-two-lights")


def test_coverage_mask_and_warning(page: Page, dataset: dict[str, Any]) -> None:
    page.check("#coverage")
    mask = page.locator("#coverage-mask")
    expect(mask).to_be_visible()
    same_key = "document.querySelector('#coverage-mask').dataset.key === document.querySelector('#relit').dataset.key"
    page.wait_for_function(same_key)
    assert mask.get_attribute("data-outside") == "0"
    assert page.evaluate("window.__relight.last.counts.n_outside") == 0  # both lights inside the coverage
    warning = page.locator("#coverage-warning")
    expect(warning).to_be_hidden()
    # a light below the dataset's lights (they cover the upper front quarter): outside the coverage
    seq = page.evaluate("window.__relight.last.seq")
    page.fill("#light-el", "-60")
    page.locator("#light-el").dispatch_event("change")
    page.wait_for_function(RELIT_SETTLED + f" && window.__relight.last.seq > {seq}", timeout=60_000)
    n_outside = page.evaluate("window.__relight.last.counts.n_outside")
    assert n_outside > 0
    # said in words next to the image, not only as a count in the table
    expect(warning).to_be_visible()
    expect(warning).to_contain_text("Outside the dataset's coverage")
    expect(warning).to_contain_text(f"{n_outside} pixels")
    pct = 100 * n_outside / (dataset["width"] * dataset["height"])
    expect(warning).to_contain_text(f"({pct:.{2 if pct < 0.1 else 1}f} % of the image)")
    expect(warning).to_contain_text("at least one of the lights")
    expect(page.locator("#coverage-show")).to_be_hidden()  # the mask is already on
    page.wait_for_function(same_key)
    # the mask marks exactly the pixels the relight counted as outside
    assert int(mask.get_attribute("data-outside") or -1) == page.evaluate("window.__relight.last.counts.n_outside")
    with_mask = element_pixels(page, "#relight-viewport")
    shot(page, "23-coverage")
    page.uncheck("#coverage")
    expect(mask).to_be_hidden()
    assert np.abs(element_pixels(page, "#relight-viewport") - with_mask).mean() > 1.0  # the mask was drawn
    # the warning's button shows where
    page.get_by_role("button", name="Show where").click()
    expect(mask).to_be_visible()
    assert page.is_checked("#coverage")
    # back inside the coverage: no warning
    seq = page.evaluate("window.__relight.last.seq")
    page.fill("#light-el", "30")
    page.locator("#light-el").dispatch_event("change")
    page.wait_for_function(RELIT_SETTLED + f" && window.__relight.last.seq > {seq}", timeout=60_000)
    assert page.evaluate("window.__relight.last.counts.n_outside") == 0
    expect(warning).to_be_hidden()


def _exr(url: str) -> np.ndarray:
    r = httpx.get(url, timeout=30)
    assert r.status_code == 200, (url, r.text)
    return decode_image("x.exr", r.content)[0]


def test_relit_image_compares_with_its_ground_truth(page: Page, stack: Stack, dataset: dict[str, Any]) -> None:
    """The dataset was generated from a scene: the ground truth of the relit image is that scene under the
    same lights, which the page asks from the generation API; the LRMS is engine.metrics' of the two."""
    api = stack.api_url
    page.wait_for_function(RELIT_SETTLED)
    runs = page.evaluate("window.__relightCompare.runs")
    page.select_option("#relight-compare", "diff")
    try:
        page.wait_for_function(f"window.__relightCompare.runs > {runs}", timeout=120_000)
    except Exception:
        shot(page, "24-relight-ground-truth-failed")
        raise AssertionError((page.locator("#relight-compare-caption").inner_text(),
                              page.locator("#error").inner_text())) from None
    last = page.evaluate("window.__relightCompare.last")
    lights = page.evaluate("window.__relight.last.lights")
    assert last["relight"] == page.evaluate("window.__relight.last.key") and len(lights) == 2
    gen = httpx.get(f"{api}/v1/datasets/generations/{last['generation']}", timeout=30).json()
    assert gen["params"]["ground_truth"] == lights  # the relight's lights, one ground-truth render each
    # the stored dataset was reused: only the ground truth was rendered
    assert gen["result"]["dataset_id"] == dataset["id"]
    assert gen["result"]["dataset_from"] == dataset["source"]["generation_key"]
    relit = _exr(f"{api}/v1/relights/{last['relight']}/image.exr")
    truth = sum(_exr(f"{api}/v1/datasets/generations/{last['generation']}/ground_truth_{i}.exr")[..., :3]
                .astype(np.float64) for i in range(len(lights)))
    assert last["lrms"] == pytest.approx(lrms(relit, np.asarray(truth, np.float32)), rel=1e-9)
    text = page.locator("#relight-lrms").inner_text()
    assert text == f"LRMS {last['lrms']:.4f}"
    expect(page.locator("#relight-compare-caption")).to_contain_text("difference vs ground truth")
    expect(page.locator("#relight-compare-img")).to_be_visible()
    shot(page, "24-relight-ground-truth-diff")
    page.select_option("#relight-compare", "side")
    page.wait_for_function(f"window.__relightCompare.runs > {runs + 1}", timeout=120_000)
    assert page.evaluate("document.querySelector('#relight-compare-img').naturalWidth") == dataset["width"]
    side = element_pixels(page, "#relight-compare-img")
    assert side.mean() > 5  # the lit ground truth, not a black image
    shot(page, "25-relight-ground-truth-side")
    page.select_option("#relight-compare", "off")
    expect(page.locator("#relight-compare-view")).to_be_hidden()
    expect(page.locator("#error")).to_be_hidden()
