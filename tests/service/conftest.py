"""``stack``: one ``ibr up`` stack (embedded Redis, real bake and render workers, uvicorn API, local store) per
test module, for the CLI tests that talk to a live service."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from service.up import free_port, start_stack


@pytest.fixture(scope="module")
def stack() -> Iterator[Any]:
    saved = {k: os.environ.pop(k) for k in ("IBR_REDIS_URL", "IBR_STORE_URL") if k in os.environ}
    with tempfile.TemporaryDirectory(prefix="ibr-", dir="/tmp") as tmp:
        st = start_stack(Path(tmp), port=free_port(), log=lambda s: None)
        try:
            yield st
        finally:
            st.stop()
            os.environ.update(saved)
