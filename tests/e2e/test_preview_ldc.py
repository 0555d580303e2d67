"""The preview page with the LDC methods (on top of the scene bakes): bake a sample scene from the
page, watch its progress reach done, render it with ``ldc`` and orbit, show the provenance, and
compare with the reference renderer (LRMS computed by the API, checked here against engine.metrics)."""

from __future__ import annotations

import io
import re
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import OpenImageIO as oiio
import pytest
from playwright.sync_api import Browser, Page, expect

from engine.metrics import lrms
from service.up import Stack
from tests.e2e.conftest import SETTLED, drag, element_pixels, new_page, shot, wait_for_load

# Everyday runs skip this file (make test-fast): browser end-to-end: a live stack driven through chromium.
pytestmark = pytest.mark.slow

SIZE = 128
SCENE = "cornell_box"  # diffuse: the bake needs no light field, so it is quick at LDC 64


@pytest.fixture(scope="module")
def page(stack: Stack, browser: Browser, capabilities: dict[str, Any]) -> Iterator[Page]:
    assert capabilities["bakes"], capabilities  # the service routes bakes: never a silent skip
    with new_page(browser, f"{stack.api_url}/preview/?size={SIZE}&spp=1&ldc=64&scene={SCENE}") as pg:
        yield pg


def _exr(api: str, key: str) -> np.ndarray:
    data = httpx.get(f"{api}/v1/artifacts/{key}/image.exr", timeout=30).content
    buf = io.BytesIO(data)
    path = f"/tmp/h7-{key[:12]}.exr"
    with open(path, "wb") as f:
        f.write(buf.getvalue())
    inp = oiio.ImageInput.open(path)
    assert inp is not None
    spec = inp.spec()
    arr = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, "float")).reshape(spec.height, spec.width, -1)
    inp.close()
    return arr


def test_ldc_methods_offered_with_k(page: Page) -> None:
    page.wait_for_selector("body[data-ready=true]")
    opts = page.locator("#method option").all_inner_texts()
    assert {"reference", "ldc", "ldc+llf", "ldc+ibrt"} <= set(opts)
    wait_for_load(page, 0)  # the scene's reference view
    expect(page.locator("#bake-box")).to_be_visible()
    expect(page.locator("#k-label")).to_be_hidden()
    page.select_option("#method", "ldc+ibrt")
    expect(page.locator("#k-label")).to_be_visible()
    assert "8" in page.locator("#ibrt-k option").all_inner_texts()


def test_ldc_without_bake_says_what_to_do(page: Page) -> None:
    page.select_option("#method", "ldc")
    err = page.locator("#error")
    expect(err).to_be_visible()
    expect(err).to_contain_text("409")
    expect(err).to_contain_text("Bake")
    assert "{" not in err.inner_text()
    shot(page, "10-ldc-needs-bake")


def test_bake_progress_reaches_done_then_ldc_view(page: Page) -> None:
    loads = page.evaluate("window.__preview.loads")
    # direct light only: this test is about the preview's bake flow, not indirect light (which would
    # add 12 chunk jobs and ~10 s of path tracing at LDC 64)
    page.select_option("#bake-indirect", "off")
    page.click("#bake")
    expect(page.locator("#bake-progress")).to_be_visible()
    fractions: list[float] = []
    for _ in range(600):
        fractions.append(float(page.evaluate("window.__bake.fraction")))
        if page.evaluate("window.__bake.state") in ("finished", "failed", "canceled", "missing"):
            break
        page.wait_for_timeout(200)
    assert page.evaluate("window.__bake.state") == "finished", page.locator("#bake-stage").inner_text()
    expect(page.locator("#bake-bar")).to_have_js_property("value", 1)
    expect(page.locator("#bake-stage")).to_contain_text("done")
    assert fractions == sorted(fractions)  # progress only moves forward
    expect(page.locator("#bake-parts li[data-state=finished]")).to_have_count(3)  # the three LDC axes
    expect(page.locator("#bake-stage")).to_contain_text("indirect light: off")
    shot(page, "11-bake-done")
    # the page renders the LDC view it was waiting for
    last = wait_for_load(page, loads, timeout=120_000)
    page.wait_for_function(SETTLED, timeout=60_000)
    last = page.evaluate("window.__preview.last")
    assert last["method"] == "ldc"
    expect(page.locator("#error")).to_be_hidden()
    expect(page.locator("#timings")).to_contain_text("warp")
    expect(page.locator("#counts")).to_contain_text("holes")
    assert isinstance(last["counts"]["hole_pixels"], int)
    expect(page.locator("#bake-list button[aria-pressed=true]")).to_contain_text("finished")
    expect(page.locator("#scene-list button[aria-current=true] .badge")).to_have_text("1 baked")
    expect(page.get_by_role("button", name=SCENE, exact=True)).to_be_visible()  # the badge is not in the name
    shot(page, "12-ldc-view")


def test_orbit_ldc_view_changes_image(page: Page) -> None:
    before = element_pixels(page, "#view")
    key_before = page.locator("#view").get_attribute("data-key")
    loads = page.evaluate("window.__preview.loads")
    drag(page, "#viewport", 40, 8)
    wait_for_load(page, loads)
    page.wait_for_function(SETTLED, timeout=60_000)
    assert page.locator("#view").get_attribute("data-key") != key_before
    assert np.abs(element_pixels(page, "#view") - before).mean() > 1.0
    assert page.evaluate("window.__preview.last.method") == "ldc"
    shot(page, "13-ldc-orbited")


def test_the_page_asks_only_for_the_images_it_shows(page: Page, stack: Stack) -> None:
    """``outputs``: preview, radiance (exposure, compare) and provenance; no AOV EXRs."""
    key = page.locator("#view").get_attribute("data-key")
    manifest = httpx.get(f"{stack.api_url}/v1/artifacts/{key}", timeout=30).json()
    assert {b["name"] for b in manifest["blobs"]} == {"preview.png", "radiance.exr", "provenance.png"}
    assert manifest["params"]["outputs"] == ["preview", "radiance", "provenance"]


def test_antialiasing_an_ldc_view(page: Page, stack: Stack) -> None:
    """The Antialias control (LDC methods only) sends the request's ``view``: 4 x 4 at the edges is a
    render of its own, whose sub-pixels the worker traced; off returns to the one-sample artifact."""
    expect(page.locator("#aa-label")).to_be_visible()
    expect(page.locator("#spp-label")).to_be_hidden()  # the LDC methods take no spp
    key_plain = page.locator("#view").get_attribute("data-key")
    loads = page.evaluate("window.__preview.loads")
    page.select_option("#aa", "4-edges")
    wait_for_load(page, loads)
    page.wait_for_function(SETTLED, timeout=60_000)
    key_aa = page.locator("#view").get_attribute("data-key")
    assert key_aa != key_plain
    manifest = httpx.get(f"{stack.api_url}/v1/artifacts/{key_aa}", timeout=30).json()
    assert manifest["params"]["view"] == {"supersample": 4, "antialias": "edges"}
    assert manifest["result"]["counts"]["supersample"] == 4 and manifest["result"]["counts"]["edge_pixels"] > 0
    shot(page, "13b-ldc-antialiased")
    page.select_option("#aa", "1")
    page.wait_for_function(f"({SETTLED}) && document.querySelector('#view').dataset.key === {key_plain!r}",
                           timeout=60_000)
    page.select_option("#method", "reference")
    expect(page.locator("#aa-label")).to_be_hidden()
    expect(page.locator("#spp-label")).to_be_visible()
    loads = page.evaluate("window.__preview.loads")
    page.select_option("#method", "ldc")
    wait_for_load(page, loads)
    page.wait_for_function(SETTLED, timeout=60_000)


def test_glossy_lobes_of_an_ldc_ibrt_view(page: Page, stack: Stack) -> None:
    """The Glossy control (ldc+ibrt only) sends the request's ``view.glossy_rays``; "auto", the
    server's default, is left out, so that view keeps the plain artifact."""
    expect(page.locator("#glossy-label")).to_be_hidden()  # ldc: no traced rays
    loads = page.evaluate("window.__preview.loads")
    page.select_option("#method", "ldc+ibrt")
    wait_for_load(page, loads)
    page.wait_for_function(SETTLED, timeout=60_000)
    expect(page.locator("#glossy-label")).to_be_visible()
    key_auto = page.locator("#view").get_attribute("data-key")
    assert "view" not in httpx.get(f"{stack.api_url}/v1/artifacts/{key_auto}", timeout=30).json()["params"]
    loads = page.evaluate("window.__preview.loads")
    page.select_option("#glossy", "16")
    wait_for_load(page, loads)
    page.wait_for_function(SETTLED, timeout=60_000)
    key_16 = page.locator("#view").get_attribute("data-key")
    assert key_16 != key_auto
    manifest = httpx.get(f"{stack.api_url}/v1/artifacts/{key_16}", timeout=30).json()
    assert manifest["params"]["view"]["glossy_rays"] == 16
    assert manifest["result"]["plan"]["passes"]["ibrt"]["glossy_why"] == "requested"
    shot(page, "13c-ldc-ibrt-glossy-rays")
    page.select_option("#glossy", "auto")
    page.wait_for_function(f"({SETTLED}) && document.querySelector('#view').dataset.key === {key_auto!r}",
                           timeout=60_000)
    loads = page.evaluate("window.__preview.loads")
    page.select_option("#method", "ldc")
    wait_for_load(page, loads)
    page.wait_for_function(SETTLED, timeout=60_000)
    expect(page.locator("#glossy-label")).to_be_hidden()


def test_provenance_view(page: Page, capabilities: dict[str, Any]) -> None:
    page.check("#provenance")
    img = page.locator("#provenance-img")
    expect(img).to_be_visible()
    page.wait_for_function("document.querySelector('#provenance-img').naturalWidth > 0 && "
                           "document.querySelector('#provenance-img').dataset.key === "
                           "document.querySelector('#view').dataset.key")
    expect(page.locator("#provenance-legend")).to_contain_text("warped")
    colours = {tuple(int(c[i:i + 2], 16) for i in (1, 3, 5)) for _, c in capabilities["provenance"].values()}
    px = element_pixels(page, "#provenance-img").reshape(-1, 3)
    uniq, counts = np.unique(px, axis=0, return_counts=True)
    top = {tuple(int(v) for v in u) for u, n in zip(uniq, counts, strict=True) if n > px.shape[0] * 0.02}
    assert top and top <= colours, (top, colours)  # every large region is one of the legend's colours
    shot(page, "14-provenance")
    page.uncheck("#provenance")
    expect(img).to_be_hidden()


def test_difference_view_shows_lrms(page: Page, stack: Stack) -> None:
    runs = page.evaluate("window.__compare.runs")
    page.select_option("#compare", "diff")
    page.wait_for_function(f"window.__compare.runs > {runs}", timeout=120_000)
    text = page.locator("#lrms").inner_text()
    m = re.fullmatch(r"LRMS (\d+\.\d+)", text)
    assert m, text
    last = page.evaluate("window.__compare.last")
    assert last["mode"] == "diff"
    expect(page.locator("#compare-img")).to_be_visible()
    shot(page, "15-difference-lrms")
    # the number is engine.metrics.lrms of the two linear images
    test, ref = _exr(stack.api_url, last["test"]), _exr(stack.api_url, last["ref"])
    assert last["ref"] != last["test"]
    assert last["lrms"] == pytest.approx(lrms(test, ref), rel=1e-9)
    assert float(m.group(1)) == pytest.approx(last["lrms"], abs=5e-5)
    page.select_option("#compare", "side")
    page.wait_for_function(f"window.__compare.runs > {runs + 1}", timeout=120_000)
    assert page.evaluate("window.__compare.last.mode") == "side"
    shot(page, "16-side-by-side")
    page.select_option("#compare", "off")
    expect(page.locator("#compare-view")).to_be_hidden()


def test_exposure_reencodes_without_a_new_render(page: Page) -> None:
    requests = page.evaluate("window.__preview.requests")
    before = element_pixels(page, "#view")
    key = page.locator("#view").get_attribute("data-key")
    src = page.locator("#view").get_attribute("src")
    page.locator("#exposure").fill("2")
    page.locator("#exposure").dispatch_event("change")
    page.wait_for_function(f"document.querySelector('#view').src !== {src!r}")
    page.wait_for_timeout(100)
    after = element_pixels(page, "#view")
    assert page.locator("#view").get_attribute("data-key") == key
    assert page.evaluate("window.__preview.requests") == requests
    assert after.mean() > before.mean() + 5
    expect(page.locator("#exposure-out")).to_have_text("+2.0 EV")
    shot(page, "17-exposure")
