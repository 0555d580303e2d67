"""The preview page's view panel in a real browser against a live stack: switching to a scene that
has no bake under an LDC method, the error banner with real API errors, orbit speed scaled to the
scene, and names (not hashes) for scenes and jobs."""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
from playwright.sync_api import Browser, Page, expect

from service.up import Stack
from tests.e2e.conftest import SETTLED, drag, new_page, shot, wait_for_load

# Everyday runs skip this file (make test-fast): browser end-to-end: a live stack driven through chromium.
pytestmark = pytest.mark.slow

SIZE = 64
FIRST, SECOND = "mirror_box", "teapot_glossy"  # two sample scenes nobody bakes in this module


def _sphere_scene(name: str, radius: float, distance: float) -> dict[str, Any]:
    """One sphere at the origin seen from ``distance`` on +z: its bounding sphere is the sphere."""
    return {
        "name": name,
        "camera": {"type": "perspective", "eye": [0, 0, distance], "look_at": [0, 0, 0], "fov_y_deg": 40,
                   "width": SIZE, "height": SIZE},
        "materials": [{"name": "m", "kd": [0.7, 0.5, 0.3]}],
        "objects": [{"type": "sphere", "material": "m", "radius": radius}],
        "lights": [{"type": "point", "position": [distance, distance, distance],
                    "intensity": [3 * distance**2] * 3}],
    }


SMALL = _sphere_scene("e2e_small_sphere", 0.5, 3.0)
LARGE = _sphere_scene("e2e_large_sphere", 40.0, 100.0)


@pytest.fixture(scope="module")
def own_scenes(stack: Stack) -> dict[str, str]:
    ids = {}
    for sc in (SMALL, LARGE):
        r = httpx.post(f"{stack.api_url}/v1/scenes", json={"scene": sc}, timeout=30)
        assert r.status_code in (200, 201), r.text
        ids[sc["name"]] = r.json()["id"]
    return ids


@pytest.fixture(scope="module")
def page(stack: Stack, browser: Browser, own_scenes: dict[str, str]) -> Iterator[Page]:
    with new_page(browser, f"{stack.api_url}/preview/?size={SIZE}&spp=1&ldc=16&scene={FIRST}") as pg:
        yield pg


def _no_image(page: Page) -> bool:
    return bool(page.evaluate("!document.querySelector('#view').hasAttribute('src')"))


def test_scene_without_bake_under_ldc_shows_no_other_scenes_image(page: Page, stack: Stack,
                                                                  scene_ids: dict[str, str]) -> None:
    page.wait_for_selector("body[data-ready=true]")
    wait_for_load(page, 0)  # the first scene's reference view
    assert not _no_image(page)
    page.select_option("#method", "ldc")  # the first scene has no bake: 409
    expect(page.locator("#error")).to_contain_text("409")
    page.get_by_role("button", name=SECOND, exact=True).click()
    expect(page.locator("#scene-name")).to_contain_text(SECOND)
    expect(page.locator("#error")).to_contain_text("409")
    # the view of the second scene is empty and says why: never the first scene's image under its title
    assert _no_image(page)
    overlay = page.locator("#no-bake")
    expect(overlay).to_be_visible()
    expect(overlay).to_contain_text(SECOND)
    expect(overlay).to_contain_text("no bake for ldc")
    assert page.evaluate("window.__preview.last.scene") == scene_ids[FIRST]  # the last image shown was the first's
    shot(page, "40-scene-switch-no-bake")
    # ... and offers to request the bake of this scene
    page.select_option("#bake-indirect", "off")
    with page.expect_response(lambda r: r.request.method == "POST" and
                              r.url.endswith(f"/v1/scenes/{scene_ids[SECOND]}/bakes")) as resp:
        page.get_by_role("button", name="Bake this scene").click()
    assert resp.value.status in (200, 202), resp.value.text()
    bake = resp.value.json()
    assert bake["params"]["ldc_resolution"] == 16
    expect(page.locator("#bake-progress")).to_be_visible()
    expect(overlay).to_contain_text("Baking")
    # the bake itself is not this test's subject: let the workers go
    for job_id in [bake["job"]["id"] if bake.get("job") else None] + [p["job_id"] for p in bake["parts"]]:
        if job_id:
            httpx.post(f"{stack.api_url}/v1/jobs/{job_id}/cancel", timeout=30)
    page.select_option("#method", "reference")
    page.wait_for_function(SETTLED + f" && window.__preview.last.scene === '{scene_ids[SECOND]}'", timeout=60_000)
    expect(overlay).to_be_hidden()


def _banner_is_readable(page: Page) -> str:
    err = page.locator("#error")
    expect(err).to_be_visible()
    box = err.bounding_box()
    assert box is not None and box["x"] >= 0
    assert box["x"] + box["width"] <= page.viewport_size["width"]  # type: ignore[index]
    # nothing cut off: the text fits the box, long ids wrap
    fits = page.evaluate("""() => { const e = document.querySelector('#error');
        const b = document.querySelector('#error-body');
        return [e.scrollWidth <= e.clientWidth, b.scrollWidth <= b.clientWidth,
                [...b.querySelectorAll('*')].every((n) => n.getBoundingClientRect().right
                                                   <= e.getBoundingClientRect().right + 0.5)]; }""")
    assert fits == [True, True, True], fits
    # read as text (assistive technology, copy and paste) the words are the ones shown, none run together
    shown = " ".join(page.locator("#error-body").inner_text().split())
    text = " ".join(str(page.evaluate("document.querySelector('#error-body').textContent")).split())
    assert text == shown, (text, shown)
    return shown


def test_error_banner_wraps_long_messages_and_can_be_dismissed(stack: Stack, browser: Browser,
                                                               scene_ids: dict[str, str]) -> None:
    ctx = browser.new_context(viewport={"width": 520, "height": 800})
    pg = ctx.new_page()
    pg.set_default_timeout(30_000)
    try:
        # a real 409 from the API: long hashes and a route in its detail
        pg.goto(f"{stack.api_url}/preview/?size={SIZE}&spp=1&method=ldc&scene={SECOND}")
        expect(pg.locator("#error")).to_contain_text("409")
        shown = _banner_is_readable(pg)
        assert scene_ids[SECOND] in shown.replace(" ", "")  # the whole id, wrapped not cut
        assert re.search(r"\(HTTP 409\): ", shown)
        assert "bake. Press Bake" in shown or "bake Press Bake" in shown
        shot(pg, "41-error-banner-narrow")
        pg.get_by_role("button", name="Dismiss the error").click()
        expect(pg.locator("#error")).to_be_hidden()
        # a 422 with a per-field error: the list items read as separate words too
        pg.select_option("#method", "reference")
        # the method change's own (valid) render first, so the 422 below is the only request in flight
        pg.wait_for_function(SETTLED, timeout=120_000)
        pg.fill("#spp", "99999")
        # leaving the field commits it (the browser's own change event); clicking the dismiss button
        # while the field still had focus would commit it again and bring a second 422
        pg.locator("#spp").blur()
        expect(pg.locator("#error")).to_contain_text("params.spp")
        shown = _banner_is_readable(pg)
        assert re.search(r"field\(s\) params\.spp: ", shown), shown
        pg.get_by_role("button", name="Dismiss the error").click()
        expect(pg.locator("#error")).to_be_hidden()
    finally:
        ctx.close()


def _yaw(eye: list[float]) -> float:
    return math.atan2(eye[0], eye[2])  # both scenes orbit around the origin about +y


@pytest.mark.parametrize("scene", [SMALL, LARGE], ids=["small", "large"])
def test_drag_turns_by_the_scene_scaled_angle(page: Page, scene: dict[str, Any], own_scenes: dict[str, str]) -> None:
    """A drag of N pixels turns the camera by N x (view height at the pivot / pixels / scene radius):
    the sphere's surface follows the pointer, whatever the scene's size."""
    page.click("#reload-scenes")
    loads = page.evaluate("window.__preview.loads")
    page.get_by_role("button", name=scene["name"], exact=True).click()
    wait_for_load(page, loads)
    page.wait_for_function(SETTLED + f" && window.__preview.last.scene === '{own_scenes[scene['name']]}'",
                           timeout=60_000)
    before = page.evaluate("window.__preview.last.camera")
    assert before["eye"] == scene["camera"]["eye"]  # the scene's own camera, not a default one
    seq = page.evaluate("window.__preview.last.seq")
    dx = 40
    drag(page, "#viewport", dx, 0, steps=4)
    page.wait_for_function(SETTLED + f" && window.__preview.last.seq > {seq}", timeout=60_000)
    after = page.evaluate("window.__preview.last.camera")
    distance = scene["camera"]["eye"][2]
    radius = scene["objects"][0]["radius"]
    view_height = 2 * distance * math.tan(math.radians(scene["camera"]["fov_y_deg"]) / 2)
    expected = dx * view_height / SIZE / radius
    turned = abs(_yaw(after["eye"]) - _yaw(before["eye"]))
    assert turned == pytest.approx(expected, rel=2e-3), (turned, expected)
    assert np.linalg.norm(after["eye"]) == pytest.approx(distance, rel=1e-5)  # an orbit: same distance
    shot(page, f"42-orbit-{scene['name']}")


def test_scenes_and_jobs_are_named(page: Page, stack: Stack, own_scenes: dict[str, str]) -> None:
    sid = own_scenes[LARGE["name"]]
    button = page.locator(f"#scene-list button[data-id='{sid}']")
    expect(button).to_have_accessible_name(LARGE["name"])  # the short hash is secondary, not in the name
    expect(button.locator(".hash")).to_have_text(sid[:8])
    expect(page.locator("#scene-name")).to_have_text(f"— {LARGE['name']}")
    # the jobs panel names the render jobs by scene and method, the hash is secondary
    key = page.evaluate("window.__preview.last.key")
    row = page.locator(f"#jobs tbody tr[data-job-id='render-{key}']")
    expect(row.locator(".job-name")).to_have_text(f"{LARGE['name']} · reference view", timeout=10_000)
    expect(row.locator(".hash")).to_have_text(f"render {key[:8]}")
    # a render job this page did not start is named from its artifact
    body = {"scene_id": own_scenes[SMALL["name"]], "params": {"spp": 1},
            "camera": {**SMALL["camera"], "width": 8, "height": 8}}
    r = httpx.post(f"{stack.api_url}/v1/renders?wait=30", json=body, timeout=60)
    assert r.status_code == 200 and r.json()["status"] in ("finished", "cached"), r.text
    other = page.locator(f"#jobs tbody tr[data-job-id='render-{r.json()['artifact_key']}']")
    expect(other.locator(".job-name")).to_have_text(f"{SMALL['name']} · reference view", timeout=10_000)
    shot(page, "43-named-jobs")
