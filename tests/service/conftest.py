"""``stack``: one ``ibr up`` stack (embedded Redis, real bake and render workers, uvicorn API, local store) for
the CLI tests that talk to a live service (the ``*_cli_live.py`` modules), shared by them: each module
makes its own scenes, datasets and walkthroughs, and ``make test`` runs the modules one after another
in one process (``SHARED_STACK_FILES`` in tests/conftest.py), so the stack starts once. It is stopped
when the tests leave this package. test_readme_live.py starts its own, fresh, as ``make run`` would."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.fixtures.stack import own_stack


@pytest.fixture(scope="package")
def stack() -> Iterator[Any]:
    with own_stack() as st:
        yield st
