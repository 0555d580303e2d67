"""Fixtures for the HTTP API tests: the app on the real embedded Redis and a LocalStore.

The store directory is ``worker_store_dir`` (tests/fixtures/redis.py), the same one the
``worker_process`` fixture's workers write to, so end-to-end tests see their artifacts.
"""

from __future__ import annotations

import copy
import json
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import uvicorn
from fastapi import FastAPI
from fastapi.testclient import TestClient
from redis import Redis

from producer.settings import Settings
from service.main import create_app

REPO_ROOT = Path(__file__).resolve().parents[3]
TEAPOT_PLY = REPO_ROOT / "samples" / "meshes" / "teapot.ply"
TEAPOT_SCENE = REPO_ROOT / "samples" / "scenes" / "teapot_glossy.json"

SMALL_SCENE: dict[str, Any] = {
    "name": "small",
    "camera": {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0], "fov_y_deg": 40,
               "width": 24, "height": 16},
    "materials": [{"name": "white", "kd": [0.8, 0.8, 0.8]}, {"name": "red", "kd": [0.8, 0.1, 0.1]}],
    "objects": [
        {"type": "sphere", "material": "red", "radius": 0.5, "transform": {"translate": [0, 0.5, 0]}},
        {"type": "plane", "material": "white", "size": [4, 4]},
    ],
    "lights": [{"type": "point", "position": [2, 3, 2], "intensity": [10, 10, 10]}],
}


def small_scene(**changes: Any) -> dict[str, Any]:
    s = copy.deepcopy(SMALL_SCENE)
    s.update(changes)
    return s


def teapot_scene(width: int = 32, height: int = 24) -> dict[str, Any]:
    doc: dict[str, Any] = json.loads(TEAPOT_SCENE.read_text())
    doc["camera"]["width"] = width
    doc["camera"]["height"] = height
    return doc


@pytest.fixture
def store_dir(worker_store_dir: Path) -> Path:
    return worker_store_dir


@pytest.fixture
def make_app(embedded_redis: str, redis_conn: Redis, store_dir: Path) -> Callable[..., FastAPI]:
    """``make_app(**settings)``: an app on the test Redis (flushed) and the test store."""

    def make(**overrides: Any) -> FastAPI:
        values: dict[str, Any] = {
            "redis_url": embedded_redis,
            "store_url": f"file://{store_dir}",
            "data_dir": store_dir.parent / "api-data",
            "log_json": True,
        }
        values.update(overrides)
        return create_app(Settings(**values))

    return make


@pytest.fixture
def app(make_app: Callable[..., FastAPI]) -> FastAPI:
    return make_app()


@pytest.fixture
def client(app: FastAPI) -> Iterator[TestClient]:
    with TestClient(app) as c:
        yield c


@pytest.fixture
def api_url(make_app: Callable[..., FastAPI]) -> Iterator[str]:
    """The app served by uvicorn in a thread on a free local port (no lifespan, no workers): for the
    CLI and the HTTP client, which talk to a real socket."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(make_app(), host="127.0.0.1", port=port, log_level="warning",
                                           lifespan="off"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.02)
    assert server.started
    yield f"http://127.0.0.1:{port}"
    server.should_exit = True
    thread.join(timeout=10)
