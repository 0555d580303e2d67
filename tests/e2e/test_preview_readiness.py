"""The preview's method readiness line (service/static/index.html, ``GET /v1/methods``): while the
render worker's warm-up compiles, "compiling, ready in ~N s" per method; "All methods ready." once
every kind is ready; hidden while no render worker reports a warm-up.

The stack's render worker runs without a warm-up (tests/conftest.py turns it off: with a cold
numba cache it would compile for minutes), so the test publishes the readiness documents a warm-up
of that worker would publish (``workers.warmup_readiness.ReadinessTracker`` through
``producer.readiness``) into the stack's Redis, for the live worker's registered name."""

from __future__ import annotations

import re
from collections.abc import Iterator

import pytest
from playwright.sync_api import Browser, Page, expect
from redis import Redis

from producer.queue import get_queue, redis_from_url
from producer.readiness import clear_readiness, publish_readiness
from service.up import Stack
from tests.e2e.conftest import new_page, shot
from workers import warmup
from workers.warmup_readiness import METHOD_STEPS, ReadinessTracker

# Everyday runs skip this file (make test-fast): browser end-to-end: a live stack driven through chromium.
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def redis(stack: Stack) -> Iterator[Redis]:
    r = redis_from_url(stack.env["IBR_REDIS_URL"])
    yield r
    r.close()


@pytest.fixture(scope="module")
def worker_name(redis: Redis) -> str:
    from rq import Worker

    names = [w.name for w in Worker.all(connection=redis, queue=get_queue(redis, "render"))]
    assert names, "the stack's render worker is not registered"
    return names[0]


@pytest.fixture(scope="module")
def page(browser: Browser, stack: Stack, redis: Redis, worker_name: str) -> Iterator[Page]:
    clear_readiness(redis, worker_name)
    with new_page(browser, f"{stack.api_url}/preview") as pg:
        yield pg
    clear_readiness(redis, worker_name)


def test_no_warm_up_reported_hides_the_line(page: Page) -> None:
    page.wait_for_function("window.__readiness !== undefined")
    assert page.evaluate("window.__readiness.workers") == 0
    expect(page.locator("#readiness")).to_be_hidden()


def test_compiling_methods_show_their_estimate_then_ready(page: Page, redis: Redis, worker_name: str) -> None:
    tracker = ReadinessTracker(list(warmup.STEPS), worker_name)
    for s in METHOD_STEPS["reference"]:
        tracker.started(s)
        tracker.finished(s, 0.5, True)
    tracker.started("ldc-bake")
    publish_readiness(redis, worker_name, tracker.document())
    line = page.locator("#readiness")
    expect(line).to_be_visible(timeout=15_000)
    expect(line).to_contain_text("reference ready")
    expect(line).to_contain_text(re.compile(r"ldc compiling, ready in ~\d+ s"))
    expect(line).to_contain_text(re.compile(r"walkthrough compiling, ready in ~\d+ s"))
    shot(page, "readiness-compiling")
    for s in warmup.STEPS:
        tracker.started(s)
        tracker.finished(s, 0.1, True)
    tracker.end()
    publish_readiness(redis, worker_name, tracker.document())
    expect(line).to_have_text("All methods ready.", timeout=15_000)
