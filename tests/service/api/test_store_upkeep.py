"""A writer killed mid-write leaves its temp file in the local store; the API's store upkeep
(producer/upkeep.py) removes it at start-up once it is older than the grace period, and leaves
every object and every younger temp file alone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient

from tests.fixtures.redis import wait_for

WRITER = """
import sys
from producer.store import LocalStore
store = LocalStore(sys.argv[1])
data = bytes(48 << 20)
i = 0
while True:  # write until killed: one of the writes is cut short
    store.put_bytes(f"artifacts/{'c' * 64}/part-{i % 4}.npz", data)
    i += 1
"""


def _temp_files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.is_file() and "~" in p.name]


def test_api_start_up_sweeps_the_temp_file_of_a_killed_writer(make_app: Any, store_dir: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(store_dir)], env=os.environ.copy())
    try:
        wait_for(lambda: _temp_files(store_dir), 60, "the writer's temp file", interval=0.001)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    left = _temp_files(store_dir)
    assert left and all(p.name.endswith(".tmp") and p.name.startswith(".part-") for p in left)
    objects = {p: p.stat().st_size for p in store_dir.rglob("*") if p.is_file() and "~" not in p.name}

    with TestClient(make_app(store_temp_grace_s=3600.0, store_upkeep_interval_s=0)) as c:
        upkeep = c.app.state.store_upkeep  # type: ignore[attr-defined]
        wait_for(lambda: upkeep.rounds >= 1, 30, "the start-up upkeep")
        assert _temp_files(store_dir) == left  # younger than the grace period: maybe a live write

    time.sleep(0.2)
    with TestClient(make_app(store_temp_grace_s=0.1, store_upkeep_interval_s=0)) as c:
        upkeep = c.app.state.store_upkeep  # type: ignore[attr-defined]
        wait_for(lambda: upkeep.rounds >= 1, 30, "the start-up upkeep")
        assert _temp_files(store_dir) == []
        assert {p: p.stat().st_size for p in store_dir.rglob("*")
                if p.is_file() and "~" not in p.name and "scene-index" not in p.parts} == objects
        assert c.get("/readyz").status_code == 200


def test_the_upkeep_runs_again_every_interval(tmp_path: Path) -> None:
    from producer.store import LocalStore
    from producer.upkeep import StoreUpkeep

    store = LocalStore(tmp_path / "store")
    store.put_bytes("artifacts/" + "d" * 64 + "/image.exr", b"kept")
    upkeep = StoreUpkeep(store, temp_grace_s=1.5, interval_s=0.1).start()
    try:
        wait_for(lambda: upkeep.rounds >= 1, 10, "the first round")
        stray = store.root / "artifacts" / ("d" * 64) / ".image.exr~0011223344556677.tmp"
        stray.write_bytes(b"half")  # a writer killed after the first round
        seen = upkeep.rounds
        wait_for(lambda: upkeep.rounds >= seen + 2, 10, "two more rounds")
        assert stray.exists()  # still younger than the grace period: maybe a write in progress
        wait_for(lambda: not stray.exists(), 15, "a later round to remove it")
        assert upkeep.rounds >= 2 and store.get_bytes("artifacts/" + "d" * 64 + "/image.exr") == b"kept"
    finally:
        upkeep.stop()
    assert not upkeep._thread.is_alive()
