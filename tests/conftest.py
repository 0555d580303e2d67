"""Every module in tests/fixtures/ is a pytest plugin: real Redis, real S3 server, etc."""

import os
import pkgutil
from collections import Counter
from typing import Any

import pytest

import tests.fixtures

# Worker subprocesses started by tests (tests/fixtures/redis.py, service.up stacks) inherit this:
# no start-up warm-up (workers/warmup.py), which with a cold numba cache (CI's first run) compiles
# every render kernel (minutes) before the first job, longer than those tests wait for it.
# tests/test_worker_warmup.py starts its render worker with IBR_WORKER_WARMUP=true.
os.environ.setdefault("IBR_WORKER_WARMUP", "false")

pytest_plugins = [f"tests.fixtures.{m.name}" for m in pkgutil.iter_modules(tests.fixtures.__path__)]

SHARED_STACK_FILES = {
    "tests/e2e": "tests/e2e/",
    "tests/service/cli-live": ("tests/service/test_bake_cli_live.py", "tests/service/test_client_cli_live.py",
                               "tests/service/test_dataset_cli_live.py", "tests/service/test_walkthrough_cli_live.py"),
}
"""Files that use one live stack per test process (the ``stack`` fixtures of tests/e2e/conftest.py and
tests/service/conftest.py), by group: ``make test``'s workers take each group whole, as if it were
one file, so one process starts that stack (and, for the browser tests, Chromium) once, not once per
worker that happens to get one of the files."""


def group_of(path: str) -> str:
    """The work unit of a test file (its path relative to the repository): its group, else itself."""
    for group, members in SHARED_STACK_FILES.items():
        if path.startswith(members) if isinstance(members, str) else path in members:
            return group
    return path


def _rel(item: pytest.Item) -> str:
    return item.nodeid.split("::", 1)[0]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Work units (files, or the groups of ``SHARED_STACK_FILES``) with a ``slow`` test first, then the
    others; within each, units with more tests first (pytest-xdist's own order for ``--dist loadfile``,
    which ``make test`` turns off with ``--no-loadscope-reorder`` so this one holds). ``make test``'s
    two workers take whole units in this order: with xdist's order alone, by test count, the long
    single-test files (live stacks, the README tour, schemathesis, the deployment tests) came last,
    and one worker idled while the other finished them. Items of a file stay together and in their
    order, and the files of a group in theirs (the sort is stable)."""
    unit = {item.nodeid: group_of(_rel(item)) for item in items}
    counts = Counter(unit.values())
    slow = {unit[item.nodeid] for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: (unit[item.nodeid] not in slow, -counts[unit[item.nodeid]], unit[item.nodeid]))


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``--dist loadfile`` with the groups of ``SHARED_STACK_FILES`` as single work units."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class GroupedFileScheduling(LoadFileScheduling):  # type: ignore[misc]  # xdist is untyped here
        def _split_scope(self, nodeid: str) -> str:
            return group_of(nodeid.split("::", 1)[0])

    return GroupedFileScheduling(config, log)
