"""Fixtures of the browser tests: one live local stack for the whole session (embedded
Redis, real bake and render workers, the API via uvicorn, the sample scenes loaded), Debian's
chromium driven by Playwright, and a page per test module. Screenshots go to test-artifacts/preview/
(git-ignored).

Each module's tests build on each other (open a scene, then orbit it, ...), so a module must run
in one process in file order: ``make test`` runs xdist with ``--dist loadfile`` (``loadgroup``
cannot be used: pytest-xdist 3.8 groups by rewriting ``item._nodeid``, which pytest 9.2 ignores).
``make test``'s scheduler (tests/conftest.py) gives every module here to the same worker, one after
another, so one stack and one browser serve them all."""

from __future__ import annotations

import io
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image
from playwright.sync_api import Browser, Page, sync_playwright

from service.up import Stack
from tests.fixtures.stack import own_stack

CHROMIUM = "/usr/bin/chromium"
LAUNCH_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
               "--disable-sync", "--no-first-run"]
ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts" / "preview"


@pytest.fixture(scope="session")
def stack() -> Iterator[Stack]:
    with own_stack(samples=True) as st:
        yield st


@pytest.fixture(scope="session")
def scene_ids(stack: Stack) -> dict[str, str]:
    """Sample scene name -> id."""
    items = httpx.get(f"{stack.api_url}/v1/scenes?limit=1000", timeout=30).json()["items"]
    return {s["name"]: s["id"] for s in items}


@pytest.fixture(scope="session")
def capabilities(stack: Stack) -> dict[str, Any]:
    caps: dict[str, Any] = httpx.get(f"{stack.api_url}/v1/preview/capabilities", timeout=30).json()
    return caps


@pytest.fixture(scope="session")
def browser() -> Iterator[Browser]:
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=LAUNCH_ARGS)
        try:
            yield b
        finally:
            b.close()


@contextmanager
def new_page(browser: Browser, url: str) -> Iterator[Page]:
    """A page at ``url`` in a browser context of its own, closed on exit."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    ctx = browser.new_context(viewport={"width": 1400, "height": 900})
    try:
        pg = ctx.new_page()
        pg.set_default_timeout(30_000)
        pg.goto(url)
        yield pg
    finally:
        ctx.close()


def shot(page: Page, name: str) -> None:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / f"{name}.png"), full_page=True)


def element_pixels(page: Page, selector: str) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(page.locator(selector).screenshot())).convert("RGB"), dtype=np.int16)


def wait_for_load(page: Page, loads_before: int, timeout: float = 60_000) -> dict[str, Any]:
    page.wait_for_function(
        f"window.__preview.loads > {loads_before} && document.querySelector('#view').naturalWidth > 0",
        timeout=timeout)
    return page.evaluate("window.__preview.last")  # type: ignore[no-any-return]


SETTLED = ("!window.__preview.scheduled && window.__preview.last && "
           "window.__preview.last.seq === window.__preview.requests")
"""No view request waiting to start, and the image shown is the latest one asked for."""

RELIT_SETTLED = ("!window.__relight.scheduled && window.__relight.last && "
                 "window.__relight.last.seq === window.__relight.requests")


def drag(page: Page, selector: str, dx: float, dy: float, steps: int = 4, start: tuple[float, float] = (0.5, 0.5)
         ) -> None:
    box = page.locator(selector).bounding_box()
    assert box is not None
    x, y = box["x"] + box["width"] * start[0], box["y"] + box["height"] * start[1]
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + dx, y + dy, steps=steps)
    page.mouse.up()
