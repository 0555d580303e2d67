"""docs/hard-cases.md #14: bodies over the limit get 413, with or without Content-Length, before the
rest is read, and nothing is written to the store."""

from __future__ import annotations

import asyncio
import json
import socket
import threading
import time
from collections.abc import AsyncIterator, Iterator, MutableMapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.up import free_port
from tests.service.api.conftest import TEAPOT_PLY, small_scene, teapot_scene


def run_async(coro: Any) -> Any:
    """``asyncio.run`` in a fresh thread: a session-scoped Playwright browser (tests/e2e) keeps an
    event loop running in the main thread of the pytest worker that ran it."""
    with ThreadPoolExecutor(max_workers=1) as pool:
        return pool.submit(asyncio.run, coro).result()


LIMIT = 64 * 1024


def _store_files(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


@pytest.fixture
def small_app(make_app: Any) -> FastAPI:
    app: FastAPI = make_app(max_body_bytes=LIMIT, max_upload_bytes=16 * 1024)
    return app


def test_declared_content_length_over_limit(small_app: FastAPI, store_dir: Path) -> None:
    body = json.dumps({"scene": small_scene(name="x" * 100)}).encode() + b" " * (LIMIT + 1)
    with TestClient(small_app) as c:
        r = c.post("/v1/scenes", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 413
    assert r.headers["content-type"].startswith("application/problem+json")
    assert str(LIMIT) in r.json()["detail"]
    assert _store_files(store_dir) == set()


def test_json_documents_have_their_own_smaller_limit(make_app: Any, store_dir: Path) -> None:
    """A JSON scene over ``max_json_bytes`` (but under the body limit) is refused with 413 naming the
    limit and the way out (mesh files), as a body with or without Content-Length and as the
    multipart ``scene`` part; a mesh file part of the same size is not a JSON document."""
    json_limit = 24 * 1024
    app = make_app(max_body_bytes=4 * LIMIT, max_upload_bytes=2 * LIMIT, max_json_bytes=json_limit)
    doc = json.dumps({"scene": small_scene(name="x" * 100)}).encode()
    big_doc = doc[:-1] + b" " * (json_limit + 1) + b"}"
    assert len(big_doc) < 4 * LIMIT
    with TestClient(app) as c:
        assert c.post("/v1/scenes", content=doc, headers={"content-type": "application/json"}).status_code == 201
        r = c.post("/v1/scenes", content=big_doc, headers={"content-type": "application/json"})
        assert r.status_code == 413, r.text
        assert f"JSON body of {len(big_doc)} bytes exceeds the {json_limit}-byte limit" in r.json()["detail"]
        assert "PLY or OBJ file parts" in r.json()["detail"]
        r = c.post("/v1/scenes", content=iter([big_doc]), headers={"content-type": "application/json"})
        assert r.status_code == 413, r.text
        assert "PLY or OBJ file parts" in r.json()["detail"]
        big_scene = json.dumps(teapot_scene()).encode() + b" " * (json_limit + 1)
        ply = TEAPOT_PLY.read_bytes()
        r = c.post("/v1/scenes", files=[("scene", (None, big_scene, "application/json")),
                                        ("meshes/teapot.ply", ("teapot.ply", ply, "application/octet-stream"))])
        assert r.status_code == 413, r.text
        assert r.json()["errors"][0]["field"] == "scene"
        assert "limit for JSON documents" in r.json()["detail"]
    assert len(ply) > json_limit  # the mesh part is larger than a JSON document may be, and accepted below
    with TestClient(app) as c:
        r = c.post("/v1/scenes", files=[("scene", (None, json.dumps(teapot_scene()).encode(), "application/json")),
                                        ("meshes/teapot.ply", ("teapot.ply", ply, "application/octet-stream"))])
        assert r.status_code in (200, 201), r.text


def test_chunked_body_over_limit_is_cut_while_streaming(small_app: FastAPI, store_dir: Path) -> None:
    pulled = 0

    async def chunks() -> AsyncIterator[bytes]:  # no Content-Length: Transfer-Encoding chunked
        nonlocal pulled
        yield b'{"scene": '
        for _ in range(10_000):  # 160 MB if it were all read
            pulled += 1
            yield b" " * 16384

    async def go() -> httpx.Response:
        # httpx's ASGI transport pulls the body lazily, like a server (TestClient reads it all first)
        transport = httpx.ASGITransport(app=small_app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as c:
            return await c.post("/v1/scenes", content=chunks(), headers={"content-type": "application/json"})

    r = run_async(go())
    assert r.status_code == 413, r.text
    assert "content-length" not in {k.lower() for k in r.request.headers}
    assert pulled <= LIMIT // 16384 + 2  # stopped right after the limit, not at the end
    assert _store_files(store_dir) == set()


def test_multipart_over_limit_and_per_file_limit(small_app: FastAPI, store_dir: Path) -> None:
    with TestClient(small_app) as c:
        # one file over max_upload_bytes (16 KiB) but the body under max_body_bytes
        big = TEAPOT_PLY.read_bytes()[: 20 * 1024]
        parts = [("scene", (None, json.dumps(teapot_scene()).encode(), "application/json")),
                 ("meshes/teapot.ply", ("teapot.ply", big, "application/octet-stream"))]
        r = c.post("/v1/scenes", files=parts)
        assert r.status_code == 413, r.text
        assert r.json()["errors"][0]["field"] == "meshes/teapot.ply"

        # the whole body over max_body_bytes, streamed without Content-Length
        boundary = "b0undary"
        head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"scene\"\r\n\r\n"
                f"{json.dumps(teapot_scene())}\r\n--{boundary}\r\n"
                "Content-Disposition: form-data; name=\"meshes/teapot.ply\"; filename=\"t.ply\"\r\n\r\n").encode()

        def stream() -> Iterator[bytes]:
            yield head
            for _ in range(1000):
                yield b"x" * 8192

        r = c.post("/v1/scenes", content=stream(),
                   headers={"content-type": f"multipart/form-data; boundary={boundary}"})
        assert r.status_code == 413
    assert _store_files(store_dir) == set()


def test_real_server_answers_413_before_the_chunked_body_ends(small_app: FastAPI, store_dir: Path) -> None:
    """Through uvicorn and a raw socket: the 413 arrives while the client is still sending."""
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(small_app, host="127.0.0.1", port=port, log_level="warning",
                                           lifespan="off"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 10
        while not server.started and time.monotonic() < deadline:
            time.sleep(0.02)
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
            sock.sendall(b"POST /v1/scenes HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                         b"Transfer-Encoding: chunked\r\n\r\n")
            chunk = b" " * 8192
            frame = f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n"
            sent = 0
            answer = b""
            sock.settimeout(0.05)
            for _ in range(4000):  # up to 32 MB; the server must answer long before
                try:
                    sock.sendall(frame)
                    sent += len(chunk)
                except (BrokenPipeError, ConnectionResetError):
                    break
                try:
                    answer += sock.recv(65536)
                except TimeoutError:
                    continue
                if b"\r\n\r\n" in answer:
                    break
            sock.settimeout(5)
            while b"\r\n\r\n" not in answer:
                data = sock.recv(65536)
                if not data:
                    break
                answer += data
        assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
        assert sent < 4 * 1024 * 1024, sent  # it did not wait for the end of the stream
    finally:
        server.should_exit = True
        thread.join(timeout=10)
    assert _store_files(store_dir) == set()


def test_lying_content_length_is_still_counted(small_app: FastAPI, store_dir: Path) -> None:
    """A Content-Length under the limit with a larger body: the bytes are counted, not the header."""
    from service.api.limits import BodyLimitMiddleware

    received: list[int] = []

    async def app(scope: Any, receive: Any, send: Any) -> None:
        total = 0
        while True:
            msg = await receive()
            total += len(msg.get("body", b""))
            if not msg.get("more_body"):
                break
        received.append(total)
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})

    mw = BodyLimitMiddleware(app, max_body_bytes=1000)
    messages = [{"type": "http.request", "body": b"x" * 600, "more_body": True}] * 5
    sent: list[MutableMapping[str, Any]] = []

    async def receive() -> dict[str, Any]:
        return messages.pop(0)

    async def send(msg: MutableMapping[str, Any]) -> None:
        sent.append(msg)

    scope = {"type": "http", "method": "POST", "path": "/", "headers": [(b"content-length", b"10")]}
    run_async(mw(scope, receive, send))
    assert sent[0]["status"] == 413 and not received
    assert len(messages) == 3  # read 2 x 600 bytes, then stopped
