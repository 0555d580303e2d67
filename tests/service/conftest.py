"""``stack``: one ``ibr up`` stack (embedded Redis, real bake and render workers, uvicorn API, local store) per
test module, for the CLI tests that talk to a live service."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.fixtures.stack import own_stack


@pytest.fixture(scope="module")
def stack() -> Iterator[Any]:
    with own_stack() as st:
        yield st
