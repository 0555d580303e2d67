"""The preview page's Walkthroughs panel (on top of the walkthrough API): request a walkthrough of
the animated sample scene along its view-space path at a quality level, watch the progress reach
done, play the frames (mouse and keyboard); compare a paused frame with a reference render of its camera (an
animated scene's at the frame's animation time, a static scene's as stored)."""

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
from tests.e2e.conftest import element_pixels, new_page, shot

# Everyday runs skip this file (make test-fast): browser end-to-end: a live stack driven through chromium.
pytestmark = pytest.mark.slow

SCENE = "cornell_animated"
# a tiny bake so the test stays quick: 16 px cube faces, 2 viewpoints, 3 time samples, no indirect light
URL = "/preview/?walk={scene}&wt_face=16&wt_views=2&wt_times=3&wt_indirect=0"


@pytest.fixture(scope="module")
def page(stack: Stack, browser: Browser, capabilities: dict[str, Any]) -> Iterator[Page]:
    assert capabilities["walkthroughs"], capabilities  # the service routes walkthroughs: never a silent skip
    with new_page(browser, stack.api_url + URL.format(scene=SCENE)) as pg:
        yield pg


def _exr_with_meta(url: str) -> tuple[np.ndarray, dict[str, Any]]:
    r = httpx.get(url, timeout=30)
    assert r.status_code == 200, (url, r.text)
    return decode_image("x.exr", r.content)


def _exr(url: str) -> np.ndarray:
    return _exr_with_meta(url)[0]


def test_walkthrough_renders_with_progress_and_plays(page: Page, capabilities: dict[str, Any]) -> None:
    page.wait_for_selector("body[data-ready=true]")
    expect(page.locator("#walks-panel")).to_be_visible()
    expect(page.locator("#walk-panel")).to_be_visible()
    opts = capabilities["walkthrough_options"]
    assert page.locator("#wt-quality option").all_inner_texts() == opts["quality"] + [
        f"path-traced, noise {n}" for n in opts["path_noise"]]
    expect(page.locator("#walk-path-desc")).to_contain_text("along the view-space path")
    page.select_option("#wt-quality", "low")
    page.select_option("#wt-frames", "8")
    page.select_option("#wt-size", "64")
    page.click("#wt-go")
    expect(page.locator("#wt-progress")).to_be_visible()
    seen: list[float] = []
    for _ in range(900):
        seen.append(float(page.evaluate("window.__walk.progress")))
        if page.evaluate("window.__walk.status") in ("finished", "failed"):
            break
        expect(page.locator("#error")).to_be_hidden()
        page.wait_for_timeout(200)
    assert page.evaluate("window.__walk.status") == "finished", page.locator("#wt-stage").inner_text()
    assert seen == sorted(seen)
    expect(page.locator("#wt-bar")).to_have_js_property("value", 1)
    page.wait_for_function("window.__walk.loaded === 8 && window.__walk.played > 2", timeout=60_000)
    expect(page.locator("#wt-player")).to_be_visible()
    expect(page.locator("#wt-stage")).to_contain_text("done: 8 frames")
    assert page.evaluate("document.querySelector('#wt-frame').naturalWidth") == 64
    shot(page, "30-walkthrough-playing")


def test_walkthrough_frames_step_with_keyboard(page: Page) -> None:
    page.click("#wt-play")  # pause
    expect(page.locator("#wt-play")).to_have_text("Play")
    page.locator("#wt-slider").fill("0")
    page.locator("#wt-slider").dispatch_event("input")
    page.wait_for_function("window.__walk.shown === 0 && document.querySelector('#wt-frame').complete")
    first = element_pixels(page, "#wt-frame")
    page.locator("#wt-viewport").focus()
    page.keyboard.press("ArrowLeft")  # wraps to the last frame
    page.wait_for_function("window.__walk.shown === 7 && document.querySelector('#wt-frame').complete")
    expect(page.locator("#wt-label")).to_have_text("frame 8 / 8")
    last = element_pixels(page, "#wt-frame")
    assert np.abs(last - first).mean() > 1.0  # the camera moved along the path and the animation ran
    page.keyboard.press(" ")
    expect(page.locator("#wt-play")).to_have_text("Pause")
    shot(page, "31-walkthrough-last-frame")


def test_animated_frame_compares_with_a_reference_render_at_its_time(page: Page, stack: Stack) -> None:
    page.click("#wt-play")  # pause (the previous test left it playing)
    expect(page.locator("#wt-play")).to_have_text("Play")
    page.locator("#wt-slider").fill("5")
    page.locator("#wt-slider").dispatch_event("input")
    page.select_option("#wt-compare", "diff")
    page.wait_for_function("window.__walkCompare.runs > 0 && window.__walkCompare.last.frame === 5", timeout=120_000)
    last = page.evaluate("window.__walkCompare.last")
    api = stack.api_url
    frame, frame_meta = _exr_with_meta(f"{api}/v1/walkthroughs/{last['walkthrough']}/frames/5.exr")
    ref, ref_meta = _exr_with_meta(f"{api}/v1/artifacts/{last['ref']}/image.exr")
    manifest = httpx.get(f"{api}/v1/artifacts/{last['ref']}", timeout=30).json()
    frame_time = frame_meta["time"]
    assert frame_time == pytest.approx(4 * 5 / 7) and last["time"] == frame_time  # animation [0, 4], 8 frames
    # the reference is a reference render of frame 5's camera at frame 5's time, at the frame's size
    assert manifest["params"]["method"] == "reference" and manifest["params"]["time"] == frame_time
    assert ref_meta["time"] == frame_time and ref_meta["camera"] == frame_meta["camera"]
    assert frame.shape[:2] == ref.shape[:2] == (64, 64)  # the cornell camera is square
    assert last["lrms"] == pytest.approx(lrms(frame, ref), rel=1e-9)
    assert page.locator("#wt-lrms").inner_text() == f"LRMS {last['lrms']:.4f}"
    expect(page.locator("#wt-compare-caption")).to_contain_text(
        f"difference vs reference (4 spp) of frame 6 at time {round(frame_time, 4):g}")
    # the reference is the scene at the frame's moment, not at the start: the lamp moved and changed colour,
    # the ball and the cube moved (LRMS ~0.1 between the two 4 spp references)
    body = {"scene_id": ref_meta["scene_id"], "camera": manifest["params"]["camera"], "method": "reference",
            "params": {"spp": 4}, "time": 0.0}
    start = httpx.post(f"{api}/v1/renders?wait=60", json=body, timeout=90).json()
    assert start["status"] in ("cached", "finished"), start
    assert start["artifact_key"] != last["ref"]
    assert lrms(ref, _exr(f"{api}/v1/artifacts/{start['artifact_key']}/image.exr")) > 0.05
    expect(page.locator("#error")).to_be_hidden()
    shot(page, "32a-walkthrough-animated-frame-diff")
    page.select_option("#wt-compare", "side")
    page.wait_for_function("window.__walkCompare.runs > 1 && window.__walkCompare.last.mode === 'side'",
                           timeout=120_000)
    assert page.evaluate("window.__walkCompare.last.ref") == last["ref"]  # the same render, side by side
    assert page.evaluate("document.querySelector('#wt-compare-img').naturalWidth") == 64
    page.select_option("#wt-compare", "off")
    expect(page.locator("#wt-compare-view")).to_be_hidden()


STATIC = "static_room"


def test_static_scene_frame_compares_with_a_reference_render(stack: Stack, browser: Browser) -> None:
    with new_page(browser, stack.api_url + URL.format(scene=STATIC) + "&spp=1") as pg:
        pg.wait_for_selector("body[data-ready=true]")
        pg.select_option("#wt-quality", "low")
        pg.select_option("#wt-frames", "8")
        pg.select_option("#wt-size", "64")
        pg.click("#wt-go")
        pg.wait_for_function("window.__walk.loaded === 8", timeout=600_000)
        pg.click("#wt-play")  # pause
        pg.locator("#wt-slider").fill("3")
        pg.locator("#wt-slider").dispatch_event("input")
        pg.select_option("#wt-compare", "diff")
        pg.wait_for_function("window.__walkCompare.runs > 0 && window.__walkCompare.last.frame === 3",
                             timeout=120_000)
        last = pg.evaluate("window.__walkCompare.last")
        api = stack.api_url
        frame = _exr(f"{api}/v1/walkthroughs/{last['walkthrough']}/frames/3.exr")
        ref = _exr(f"{api}/v1/artifacts/{last['ref']}/image.exr")
        manifest = httpx.get(f"{api}/v1/artifacts/{last['ref']}", timeout=30).json()
        request = httpx.get(f"{api}/v1/walkthroughs/{last['walkthrough']}", timeout=30).json()
        assert request["frames"] == 8
        # the reference is a reference render of frame 3's camera, at the frame's size
        assert manifest["params"]["method"] == "reference"
        assert frame.shape[:2] == ref.shape[:2] == (48, 64)
        assert last["lrms"] == pytest.approx(lrms(frame, ref), rel=1e-9)
        assert pg.locator("#wt-lrms").inner_text() == f"LRMS {last['lrms']:.4f}"
        expect(pg.locator("#wt-compare-caption")).to_contain_text("difference vs reference (1 spp) of frame 4")
        shot(pg, "32-walkthrough-frame-diff")
        pg.select_option("#wt-compare", "side")
        pg.wait_for_function("window.__walkCompare.runs > 1 && window.__walkCompare.last.mode === 'side'",
                             timeout=120_000)
        assert pg.evaluate("document.querySelector('#wt-compare-img').naturalWidth") == 64
        expect(pg.locator("#error")).to_be_hidden()
        shot(pg, "33-walkthrough-frame-side")


def test_path_traced_frames_need_no_bake(page: Page, stack: Stack) -> None:
    """The quality choice "path-traced" sends ``path_traced`` (no bake, no fill) and plays its frames."""
    page.click("#wt-play")  # pause (the previous test may have left it playing)
    page.select_option("#wt-quality", "path:0.2")
    expect(page.locator("#wt-fill")).to_be_disabled()
    page.select_option("#wt-frames", "8")
    page.select_option("#wt-size", "64")
    with page.expect_request(lambda q: q.method == "POST" and q.url.endswith("/v1/walkthroughs")) as sent:
        page.click("#wt-go")
    body = sent.value.post_data_json
    assert body["path_traced"] == {"noise": 0.2} and "bake" not in body and "fill" not in body
    page.wait_for_function("window.__walk.status === 'finished' && window.__walk.loaded === 8", timeout=180_000)
    key = page.evaluate("window.__walk.key")
    pub = httpx.get(f"{stack.api_url}/v1/walkthroughs/{key}", timeout=30).json()
    assert pub["bake_key"] is None and not any(j["id"].startswith("wtbake") for j in pub["jobs"])
    expect(page.locator("#wt-stage")).to_contain_text("done: 8 frames")
    expect(page.locator("#error")).to_be_hidden()
    page.select_option("#wt-quality", "low")
    expect(page.locator("#wt-fill")).to_be_enabled()
    shot(page, "32-walkthrough-path-traced")
