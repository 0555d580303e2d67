"""The preview page's Walkthroughs panel (on top of the walkthrough API): request a walkthrough of
the animated sample scene along its view-space path at a quality level, watch the progress reach
done, play the frames (mouse and keyboard)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from playwright.sync_api import Browser, Page, expect

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


def test_walkthrough_renders_with_progress_and_plays(page: Page, capabilities: dict[str, Any]) -> None:
    page.wait_for_selector("body[data-ready=true]")
    expect(page.locator("#walks-panel")).to_be_visible()
    expect(page.locator("#walk-panel")).to_be_visible()
    assert page.locator("#wt-quality option").all_inner_texts() == capabilities["walkthrough_options"]["quality"]
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
