"""Image upload bombs: a few KiB to MiB of compressed PNG or EXR declaring gigabytes of pixels are
refused from their header (422 naming the file, its dimensions, the decoded size and the limit)
before any pixel is decoded; an image within the budget is scanned a band of rows at a time; the
API process's peak memory stays bounded (measured in a separate API process through VmHWM)."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio
import pytest
from fastapi.testclient import TestClient

from tests.service.api.test_datasets import multipart, sha, subset

MIB = 1 << 20
DEFAULT_BUDGET = 256 * MIB


def png_bomb(width: int, height: int, channels: int = 3) -> bytes:
    """A valid 8-bit PNG of zeros, compressed row by row (8000x8000 RGB: ~190 KiB)."""
    def chunk(tag: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + tag + body + struct.pack(">I", zlib.crc32(tag + body) & 0xFFFFFFFF)

    co = zlib.compressobj(9)
    row = b"\0" * (1 + width * channels)
    idat = b"".join(co.compress(row) for _ in range(height)) + co.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 8, {1: 0, 3: 2, 4: 6}[channels], 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def exr_file(path: Path, width: int, height: int, channels: int, fmt: str = "half", tile: int = 0) -> bytes:
    """A valid zip-compressed EXR of zeros, written a band at a time (the writer never holds it whole)."""
    spec = oiio.ImageSpec(width, height, channels, fmt)
    spec.attribute("compression", "zip")
    if tile:
        spec.tile_width = spec.tile_height = tile
    out = oiio.ImageOutput.create(str(path))
    assert out is not None and out.open(str(path), spec), oiio.geterror()
    band = tile or 256
    dtype = np.float16 if fmt == "half" else np.float32
    for y in range(0, height, band):
        y1 = min(y + band, height)
        z = np.zeros((y1 - y, width, channels), dtype)
        ok = out.write_tiles(0, width, y, y1, 0, 1, z) if tile else out.write_scanlines(y, y1, 0, z)
        assert ok, out.geterror()
    out.close()
    return path.read_bytes()


@pytest.fixture(scope="module")
def bombs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    d = tmp_path_factory.mktemp("bombs")
    return {
        "png-8000x8000x3": png_bomb(8000, 8000, 3),  # 768 MB decoded
        "exr-4000x4000x16": exr_file(d / "a.exr", 4000, 4000, 16),  # 1 GiB decoded, ~0.5 MiB
        "exr-tiled-4000x4000x16": exr_file(d / "b.exr", 4000, 4000, 16, tile=64),
    }


def _problem(r: Any) -> dict[str, str]:
    assert r.status_code == 422, r.text
    errors = r.json()["errors"]
    assert len(errors) == 1
    assert errors[0]["type"] == "image_too_large"
    return {"field": errors[0]["field"], "message": errors[0]["message"]}


def test_bombs_are_refused_from_the_header_naming_the_file_and_the_limit(client: TestClient, store_dir: Path,
                                                                         bombs: dict[str, bytes]) -> None:
    for label, data in bombs.items():
        w, h, c = (int(x) for x in label.rsplit("-", 1)[1].split("x"))
        h256 = sha(data)
        p = _problem(client.put(f"/v1/datasets/uploads/{h256}", content=data))
        msg = p["message"]
        assert p["field"] == f"files.{h256}" and h256 in msg, p
        assert f"{w}x{h} pixels x {c} channels" in msg and str(w * h * c * 4) in msg, msg
        assert str(DEFAULT_BUDGET) in msg and "per file" in msg, msg
        assert client.get(f"/v1/datasets/uploads/{h256}").status_code == 404
        assert not (store_dir / "blobs" / h256).exists() and not (store_dir / "blob-info" / f"{h256}.json").exists()
    # in a multipart dataset upload the bomb is named by its file name; nothing is stored
    manifest, files = subset(3)
    name = manifest["images"][1]["file"]
    files[name] = bombs["png-8000x8000x3"]
    r = client.post("/v1/datasets", files=multipart(manifest, files))
    p = _problem(r)
    assert p["field"] == f"files.{name}" and p["message"].startswith(f"{name}: ") and "8000x8000" in p["message"]
    assert client.get("/v1/datasets").json()["items"] == []


def test_the_budget_is_a_setting(make_app: Any) -> None:
    """A 64x64 RGBA float image is 64 KiB decoded: over a 32 KiB budget, within the default one."""
    data = exr_file(Path(os.environ.get("TMPDIR", "/tmp")) / f"budget-{os.getpid()}.exr", 64, 64, 4, "float")
    with TestClient(make_app(max_decoded_image_bytes=32 * 1024)) as c:
        msg = _problem(c.put(f"/v1/datasets/uploads/{sha(data)}", content=data))["message"]
        assert "65536 bytes" in msg and "limit of 32768 bytes" in msg, msg
    with TestClient(make_app()) as c:
        r = c.put(f"/v1/datasets/uploads/{sha(data)}", content=data)
        assert r.status_code == 201 and r.json()["width"] == 64 and r.json()["channels"] == 4, r.text


def test_decodes_wait_for_a_free_slot(make_app: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """With every decode slot taken the upload waits, then answers 503 (Retry-After); a freed slot serves it."""
    from producer.datasets import decode_slots
    from service.api.routes import datasets as routes

    monkeypatch.setattr(routes, "_DECODE_WAIT_S", 0.2)
    manifest, files = subset(1)
    data = files[manifest["images"][0]["file"]]
    slots = decode_slots(1)
    with TestClient(make_app(max_concurrent_decodes=1)) as c:
        assert slots.acquire(timeout=5)
        try:
            r = c.put(f"/v1/datasets/uploads/{sha(data)}", content=data)
            assert r.status_code == 503 and r.headers["retry-after"] == "5", r.text
        finally:
            slots.release()
        assert c.put(f"/v1/datasets/uploads/{sha(data)}", content=data).status_code == 201


_PEAK_SCRIPT = textwrap.dedent("""
    import json, sys
    from pathlib import Path
    from fastapi.testclient import TestClient
    from producer.settings import Settings
    from service.main import create_app

    cfg = json.loads(sys.argv[1])

    def hwm_kib():
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
        raise RuntimeError("no VmHWM")

    app = create_app(Settings(redis_url=cfg["redis"], store_url="file://" + cfg["store"], data_dir=cfg["data"],
                              log_json=True, log_level="WARNING"))
    out = []
    with TestClient(app) as c:
        warm = Path(cfg["warm"]).read_bytes()  # imports OpenImageIO and warms the request path
        assert c.put("/v1/datasets/uploads/" + cfg["warm_sha"], content=warm).status_code == 201
        for name, sha in cfg["files"]:
            data = Path(name).read_bytes()
            Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current RSS
            before = hwm_kib()
            r = c.put("/v1/datasets/uploads/" + sha, content=data)
            out.append({"file": Path(name).name, "status": r.status_code, "grew_kib": hwm_kib() - before,
                        "body": r.text[:2000]})
    print(json.dumps(out))
""")


def test_the_api_process_peak_memory_stays_bounded(embedded_redis: str, redis_conn: Any, store_dir: Path,
                                                   tmp_path: Path, bombs: dict[str, bytes]) -> None:
    """In a separate API process: every bomb is refused and raises the peak RSS by less than 32 MiB
    (decoding them whole took 1.8 to 2.5 GiB); an accepted image of 48 MiB decoded (2048x2048 RGB
    float, scanned in bands: ~25 MiB, 120 MiB when decoded whole) raises it by less than its
    decoded size."""
    files: list[tuple[str, str]] = []
    for label, data in bombs.items():
        (tmp_path / label).write_bytes(data)
        files.append((str(tmp_path / label), sha(data)))
    ok = exr_file(tmp_path / "ok-2048x2048x3.exr", 2048, 2048, 3, "float")
    files.append((str(tmp_path / "ok-2048x2048x3.exr"), sha(ok)))
    warm = exr_file(tmp_path / "warm.exr", 16, 16, 3, "float")
    cfg = {"redis": embedded_redis, "store": str(store_dir), "data": str(tmp_path / "data"),
           "warm": str(tmp_path / "warm.exr"), "warm_sha": sha(warm), "files": files}
    proc = subprocess.run([sys.executable, "-c", _PEAK_SCRIPT, json.dumps(cfg)], capture_output=True, text=True,
                          timeout=300, env=os.environ.copy())
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads(proc.stdout.strip().splitlines()[-1])
    by_name = {r["file"]: r for r in results}
    for label in bombs:
        r = by_name[label]
        assert r["status"] == 422 and "image_too_large" in r["body"], r
        assert r["grew_kib"] < 32 * 1024, r
    r = by_name["ok-2048x2048x3.exr"]
    assert r["status"] == 201, r
    assert r["grew_kib"] < 2048 * 2048 * 3 * 4 // 1024, r


def test_bombs_against_an_api_process_under_a_1_gib_memory_ceiling(embedded_redis: str, redis_conn: Any,
                                                                    store_dir: Path, tmp_path: Path,
                                                                    bombs: dict[str, bytes]) -> None:
    """The API as uvicorn runs it, in a memory cgroup limited to 1 GiB (the kernel's OOM killer ends
    it beyond): every image bomb and a PLY declaring 2e9 faces are refused with a 422 naming the
    problem, nothing is OOM-killed, the API stays ready and never maps numba
    (bench/upload_bombs.py runs the full set and writes docs/reliability.md)."""
    import hashlib
    import socket
    import time

    import httpx

    from bench.upload_bombs import MemoryCgroup, absurd_ply, maps_numba

    try:
        cg = MemoryCgroup(1 << 30)
    except (OSError, SystemExit) as exc:
        pytest.skip(f"no writable memory cgroup here: {exc}")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "IBR_REDIS_URL": embedded_redis, "IBR_STORE_URL": f"file://{store_dir}",
           "IBR_DATA_DIR": str(tmp_path / "data"), "IBR_LOG_JSON": "false", "TMPDIR": str(tmp_path)}
    env.pop("IBR_API_KEYS", None)
    log = tmp_path / "api.log"
    with open(log, "wb") as out:
        api = subprocess.Popen([sys.executable, "-m", "uvicorn", "service.main:create_app", "--factory", "--host",
                                "127.0.0.1", "--port", str(port), "--no-access-log"], env=env, stdout=out,
                               stderr=subprocess.STDOUT, preexec_fn=cg.enter)  # noqa: PLW1509
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=120) as c:
            deadline = time.monotonic() + 60
            while True:
                try:
                    if c.get("/readyz").status_code == 200:
                        break
                except httpx.HTTPError:
                    pass
                assert time.monotonic() < deadline and api.poll() is None, log.read_text()[-3000:]
                time.sleep(0.2)
            for label, data in bombs.items():
                r = c.put(f"/v1/datasets/uploads/{hashlib.sha256(data).hexdigest()}", content=data)
                assert r.status_code == 422 and r.json()["errors"][0]["type"] == "image_too_large", (label, r.text)
            scene = {"name": "b", "camera": {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0, 0],
                                             "width": 16, "height": 16},
                     "materials": [{"name": "m", "kd": [0.5, 0.5, 0.5]}],
                     "objects": [{"type": "mesh_file", "path": "b.ply", "material": "m"}],
                     "lights": [{"type": "point", "position": [2, 3, 2], "intensity": [1, 1, 1]}]}
            r = c.post("/v1/scenes", files={"scene": (None, json.dumps(scene)),
                                            "b.ply": ("b.ply", absurd_ply(), "application/octet-stream")})
            assert r.status_code == 422, r.text
            err = r.json()["errors"][0]
            assert err["type"] == "scene_too_large" and "2,000,000,000 triangles" in err["message"], err
            assert c.get("/readyz").status_code == 200
        assert api.poll() is None and cg.oom_kills() == 0
        assert cg.peak() < 1 << 30
        assert not maps_numba(api.pid)
    finally:
        api.kill()
        api.wait(timeout=10)
        cg.remove()
