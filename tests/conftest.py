"""Every module in tests/fixtures/ is a pytest plugin: real Redis, real S3 server, etc."""

import os
import pkgutil
from collections import Counter

import pytest

import tests.fixtures

# Worker subprocesses started by tests (tests/fixtures/redis.py, service.up stacks) inherit this:
# no start-up warm-up (workers/warmup.py), which with a cold numba cache (CI's first run) compiles
# every render kernel (minutes) before the first job, longer than those tests wait for it.
# tests/test_worker_warmup.py starts its render worker with IBR_WORKER_WARMUP=true.
os.environ.setdefault("IBR_WORKER_WARMUP", "false")

pytest_plugins = [f"tests.fixtures.{m.name}" for m in pkgutil.iter_modules(tests.fixtures.__path__)]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Files with a ``slow`` test first, then the others; within each group, files with more tests
    first (pytest-xdist's own order for ``--dist loadfile``, which ``make test`` turns off with
    ``--no-loadscope-reorder`` so this one holds). ``make test``'s two workers take whole files in
    this order: with xdist's order alone, by test count, the long single-test files (live stacks,
    the README tour, schemathesis, the deployment tests) came last, and one worker idled while the
    other finished them. Items of a file stay together and in their order (the sort is stable)."""
    counts = Counter(item.path for item in items)
    slow = {item.path for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: (item.path not in slow, -counts[item.path]))
