"""Illumination datasets over the API (no workers): multipart and resumable uploads of a real
dataset (a 40x40 crop of DiLiGenT's ball, 16-bit PNGs, distant lights), bad uploads answered with
a 4xx naming the file or field, nothing partially stored becoming visible.

``diligent_ball()`` is shared with tests/service/api/test_datasets_jobs.py."""

from __future__ import annotations

import hashlib
import json
import os
import struct
import tempfile
import zlib
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio
import pytest
from fastapi.testclient import TestClient

DILIGENT = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "diligent-ball"
CROP_ROWS, CROP_COLS, STEP = (184, 344), (228, 388), 4  # 160 x 160 around the ball -> 40 x 40
SIZE = 40
EYE_Z = 100.0


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def write_bytes(pixels: np.ndarray, ext: str, fmt: str) -> bytes:
    """Raw samples to a file through OpenImageIO (no transfer function applied)."""
    if pixels.ndim == 2:  # OpenImageIO needs the channel axis, even for one channel
        pixels = pixels[:, :, None]
    h, w, c = pixels.shape
    fd, path = tempfile.mkstemp(suffix=ext)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(path)
        assert out is not None, oiio.geterror()
        assert out.open(path, oiio.ImageSpec(w, h, c, fmt)), out.geterror()
        assert out.write_image(np.ascontiguousarray(pixels)), out.geterror()
        out.close()
        return Path(path).read_bytes()
    finally:
        os.unlink(path)


def _read(name: str) -> np.ndarray:
    buf = oiio.ImageBuf(str(DILIGENT / name))
    px = np.asarray(buf.get_pixels(oiio.FLOAT), np.float64)
    assert px.size, buf.geterror()
    return px


def _down(px: np.ndarray) -> np.ndarray:
    r0, r1 = CROP_ROWS
    c0, c1 = CROP_COLS
    crop = px[r0:r1, c0:c1]
    return crop.reshape(SIZE, STEP, SIZE, STEP, -1).mean(axis=(1, 3))


@lru_cache(maxsize=1)
def diligent_ball() -> tuple[dict[str, Any], dict[str, bytes], dict[str, np.ndarray]]:
    """(manifest, files, linear images): the 96 DiLiGenT ball photographs cropped around the ball and
    averaged 4x4 (40x40, stored as linear 16-bit PNGs), their lights (directions toward the lights,
    RGB intensities), an orthographic camera with one world unit per pixel, the depth of the sphere
    fitted to the mask (float EXR, 0 = background) and the mask (8-bit PNG)."""
    if not DILIGENT.is_dir():
        pytest.fail(f"shared data set missing: {DILIGENT}")
    names = (DILIGENT / "filenames.txt").read_text().split()
    dirs = np.loadtxt(DILIGENT / "light_directions.txt")
    ints = np.loadtxt(DILIGENT / "light_intensities.txt")
    full_mask = _read("mask.png")[:, :, 0] > 0.5
    rows, cols = np.nonzero(full_mask)
    # sphere fitted to the mask, in the coordinates of the 40x40 image (pixel centres at +0.5)
    cy = (rows.mean() + 0.5 - CROP_ROWS[0]) / STEP
    cx = (cols.mean() + 0.5 - CROP_COLS[0]) / STEP
    radius = np.sqrt(full_mask.sum() / np.pi) / STEP
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    r2 = radius**2 - (xx - cx) ** 2 - (yy - cy) ** 2
    mask = (_down(full_mask[:, :, None].astype(np.float64))[:, :, 0] == 1.0) & (r2 > 0)
    depth = np.where(mask, EYE_Z - np.sqrt(np.maximum(r2, 0.0)), 0.0).astype(np.float32)
    files: dict[str, bytes] = {
        "depth.exr": write_bytes(depth, ".exr", "float"),
        "mask.png": write_bytes((mask * 255).astype(np.uint8), ".png", "uint8"),
    }
    linear: dict[str, np.ndarray] = {}
    images = []
    for name, d, inten in zip(names, dirs, ints, strict=True):
        q = np.round(_down(_read(name)) * 65535.0).astype(np.uint16)
        files[name] = write_bytes(q, ".png", "uint16")
        linear[name] = (q.astype(np.float64) / 65535.0).astype(np.float32)
        images.append({"file": name, "direction": [float(x) for x in d], "intensity": [float(x) for x in inten]})
    manifest = {
        "name": "diligent-ball-40",
        "images": images,
        "transfer": "linear",
        "camera": {"type": "orthographic", "eye": [0, 0, EYE_Z], "look_at": [0, 0, 0], "up": [0, 1, 0],
                   "ortho_height": float(SIZE), "width": SIZE, "height": SIZE},
        "geometry": {"type": "depth", "file": "depth.exr", "depth_kind": "z"},
        "mask": {"file": "mask.png"},
    }
    return manifest, files, linear


def subset(k: int, drop: tuple[int, ...] = ()) -> tuple[dict[str, Any], dict[str, bytes]]:
    """The first ``k`` images (minus ``drop``) with depth and mask."""
    manifest, files, _ = diligent_ball()
    images = [img for i, img in enumerate(manifest["images"][:k]) if i not in drop]
    m = {**manifest, "images": images}
    names = {img["file"] for img in images} | {"depth.exr", "mask.png"}
    return m, {n: files[n] for n in names}


def multipart(manifest: dict[str, Any], files: dict[str, bytes]) -> list[tuple[str, tuple[str | None, bytes, str]]]:
    parts: list[tuple[str, tuple[str | None, bytes, str]]] = [
        ("manifest", (None, json.dumps(manifest).encode(), "application/json"))]
    parts += [(name, (name, data, "application/octet-stream")) for name, data in files.items()]
    return parts


def with_shas(manifest: dict[str, Any], files: dict[str, bytes]) -> dict[str, Any]:
    m = json.loads(json.dumps(manifest))
    for img in m["images"]:
        img["sha256"] = sha(files[img["file"]])
    for part in ("geometry", "mask"):
        if m.get(part) and "file" in m[part]:
            m[part]["sha256"] = sha(files[m[part]["file"]])
    return m


def fields(r: Any) -> dict[str, str]:
    assert r.headers["content-type"].startswith("application/problem+json"), r.text
    return {e["field"]: e["message"] for e in r.json()["errors"]}


# ------------------------------------------------------------------------------ uploads


def test_multipart_upload_get_list_delete(client: TestClient) -> None:
    manifest, files = subset(12)
    r = client.post("/v1/datasets", files=multipart(manifest, files))
    assert r.status_code == 201, r.text
    ds = r.json()
    assert r.headers["location"] == f"/v1/datasets/{ds['id']}"
    assert (ds["n_images"], ds["width"], ds["height"], ds["distant"], ds["geometry"], ds["has_mask"]) == (
        12, SIZE, SIZE, True, "depth", True)
    assert ds["manifest"]["images"][3]["sha256"] == sha(files[manifest["images"][3]["file"]])
    assert ds["total_bytes"] == sum(len(b) for b in files.values())
    # the same content again: same id, 200
    again = client.post("/v1/datasets", files=multipart(manifest, files))
    assert again.status_code == 200 and again.json()["id"] == ds["id"]
    assert client.get(f"/v1/datasets/{ds['id']}").json()["manifest"] == ds["manifest"]
    listing = client.get("/v1/datasets").json()
    assert [d["id"] for d in listing["items"]] == [ds["id"]] and listing["next_cursor"] is None
    # files come back byte for byte
    img_sha = ds["manifest"]["images"][0]["sha256"]
    got = client.get(f"/v1/datasets/{ds['id']}/files/{img_sha}")
    assert got.status_code == 200 and got.headers["content-type"] == "image/png"
    assert got.content == files[manifest["images"][0]["file"]]
    assert client.get(f"/v1/datasets/{ds['id']}/files/{'0' * 64}").status_code == 404
    assert client.delete(f"/v1/datasets/{ds['id']}").status_code == 204
    assert client.get(f"/v1/datasets/{ds['id']}").status_code == 404
    assert client.get("/v1/datasets").json()["items"] == []


def test_resumable_upload_asks_only_for_missing_files(client: TestClient) -> None:
    manifest, files = subset(10)
    m = with_shas(manifest, files)
    r = client.post("/v1/datasets", json=m)
    assert r.status_code == 200, r.text
    status = r.json()
    did = status["dataset_id"]
    assert status["state"] == "pending" and status["received"] == 0 and len(status["missing"]) == 12
    assert {x["field"] for x in status["missing"]} >= {"images.0", "geometry", "mask"}
    first = status["missing"][:4]
    for item in first:
        put = client.put(item["upload_url"], content=files[item["name"]])
        assert put.status_code == 201, put.text
        assert put.json()["sha256"] == item["sha256"] and put.json()["width"] == SIZE
    # the same PUT again: already there
    assert client.put(first[0]["upload_url"], content=files[first[0]["name"]]).status_code == 200
    assert client.get(first[0]["upload_url"]).json()["sha256"] == first[0]["sha256"]
    # the second manifest post asks for none of the files already received
    r2 = client.post("/v1/datasets", json=m).json()
    assert r2["dataset_id"] == did and r2["received"] == 4
    assert {x["sha256"] for x in r2["missing"]} == {x["sha256"] for x in status["missing"][4:]}
    # committing early: 409 naming every missing file; nothing visible
    early = client.post(f"/v1/datasets/{did}/commit")
    assert early.status_code == 409
    assert len(fields(early)) == 8 and all("has not been uploaded" in v for v in fields(early).values())
    assert client.get(f"/v1/datasets/{did}").status_code == 404
    for item in r2["missing"]:
        assert client.put(item["upload_url"], content=files[item["name"]]).status_code == 201
    done = client.post(f"/v1/datasets/{did}/commit")
    assert done.status_code == 201, done.text
    assert done.json()["id"] == did and client.get(f"/v1/datasets/{did}").status_code == 200
    assert client.post(f"/v1/datasets/{did}/commit").status_code == 200
    assert client.post("/v1/datasets", json=m).json()["state"] == "committed"
    # a multipart upload of the same content is the same dataset
    assert client.post("/v1/datasets", files=multipart(manifest, files)).json()["id"] == did


# ------------------------------------------------------------------------------ bad input


def _png_header_only(width: int, height: int) -> bytes:
    """A PNG whose IHDR declares width x height pixels, with no image data to speak of."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\x00" * 16)) + \
        chunk(b"IEND", b"")


def test_bad_files_are_named(client: TestClient) -> None:
    manifest, files = subset(4)
    names = [img["file"] for img in manifest["images"]]
    cases: list[tuple[str, bytes, str, str]] = [
        (names[1], b"this is not an image", f"files.{names[1]}", "unrecognised file signature"),
        (names[2], write_bytes(np.zeros((SIZE, SIZE - 8, 3), np.uint16), ".png", "uint16"), f"files.{names[2]}",
         f"is {SIZE - 8}x{SIZE} but the camera"),
        (names[0], _png_header_only(100_000, 100_000), f"files.{names[0]}", "more than this server's limit|exceeds"),
        (names[3], files[names[3]][: len(files[names[3]]) // 2], f"files.{names[3]}", "cannot read"),
        (names[1], write_bytes(np.full((SIZE, SIZE, 3), np.nan, np.float32), ".exr", "float"), f"files.{names[1]}",
         "NaN/Inf"),
        (names[1], write_bytes(np.full((SIZE, SIZE, 3), -1.0, np.float32), ".exr", "float"), f"files.{names[1]}",
         "negative"),
        ("depth.exr", write_bytes(np.ones((SIZE + 1, SIZE), np.float32), ".exr", "float"), "files.depth.exr",
         f"is {SIZE}x{SIZE + 1} but the camera"),
        ("depth.exr", files["mask.png"], "files.depth.exr", "depth must be a float image"),
    ]
    for name, data, field, words in cases:
        bad = {**files, name: data}
        r = client.post("/v1/datasets", files=multipart(manifest, bad))
        assert r.status_code == 422, (name, r.text)
        errs = fields(r)
        assert field in errs and any(w in errs[field] for w in words.split("|")), (field, words, errs)
    assert client.get("/v1/datasets").json()["items"] == []  # nothing half-stored is visible


def test_bad_manifests_are_named(client: TestClient) -> None:
    manifest, files = subset(4)
    name0 = manifest["images"][0]["file"]

    def post(m: dict[str, Any], f: dict[str, bytes] | None = None) -> dict[str, str]:
        r = client.post("/v1/datasets", files=multipart(m, files if f is None else f))
        assert r.status_code == 422, r.text
        return fields(r)

    dup = json.loads(json.dumps(manifest))
    dup["images"][2]["direction"] = [2 * x for x in dup["images"][0]["direction"]]
    assert "duplicates the light of images.0" in post(dup)["manifest.images.2.direction"]
    nan = json.loads(json.dumps(manifest))
    nan["images"][1]["intensity"] = [1.0, float("nan"), 1.0]
    assert "manifest.images.1.intensity.1" in post(nan)
    mixed = json.loads(json.dumps(manifest))
    mixed["images"][3] = {**{k: v for k, v in mixed["images"][3].items() if k != "direction"},
                          "position": [0, 0, 5]}
    assert "same light kind" in post(mixed)["manifest.images.3.position"]
    assert "transfer must be" in post({**manifest, "transfer": "gamma"})["manifest.transfer"]
    six, _ = subset(6)
    huge = {**six, "camera": {**six["camera"], "width": 8000, "height": 8000}}  # 6 x 8000^2 x 3 > 2^30
    assert "more than the limit" in post(huge)["manifest.images"]
    two = {**manifest, "images": manifest["images"][:2]}
    assert "manifest.images" in post(two, {k: v for k, v in files.items() if k != manifest["images"][2]["file"]
                                           and k != manifest["images"][3]["file"]})
    # a manifest image without its part, and a part nobody asked for
    missing = {k: v for k, v in files.items() if k != name0}
    assert "no file part named" in post(manifest, missing)["manifest.images.0.file"]
    assert "not name" in post(manifest, {**files, "extra.png": files[name0]})["files"]
    # a wrong sha256 in the manifest
    wrong = json.loads(json.dumps(manifest))
    wrong["images"][0]["sha256"] = "0" * 64
    assert "not " + "0" * 64 in post(wrong)[f"files.{name0}"]
    # JSON manifests need the sha256s; a PUT must match its URL
    r = client.post("/v1/datasets", json=manifest)
    assert r.status_code == 422 and "images.0.sha256" in fields(r)
    r = client.put(f"/v1/datasets/uploads/{'0' * 64}", content=files[name0])
    assert r.status_code == 422 and "not " + "0" * 64 in fields(r)[f"files.{'0' * 64}"]
    r = client.post("/v1/datasets", content=b"x", headers={"content-type": "text/plain"})
    assert r.status_code == 415
    assert client.get("/v1/datasets").json()["items"] == []


def test_oversized_file_is_413(make_app: Any) -> None:
    manifest, files = subset(3)
    limit = max(len(b) for b in files.values()) + 16
    with TestClient(make_app(max_upload_bytes=limit, max_body_bytes=1 << 20)) as c:
        name0 = manifest["images"][0]["file"]
        big = {**files, name0: files[name0] + b"\0" * limit}
        r = c.post("/v1/datasets", files=multipart(manifest, big))
        assert r.status_code == 413 and r.json()["errors"][0]["field"] == name0
        r = c.put(f"/v1/datasets/uploads/{sha(big[name0])}", content=big[name0])
        assert r.status_code == 413


def test_relight_needs_a_baked_visible_dataset(client: TestClient) -> None:
    manifest, files = subset(6)
    did = client.post("/v1/datasets", files=multipart(manifest, files)).json()["id"]
    light = {"type": "directional", "direction": [0, 0, -1]}
    r = client.post("/v1/relights", json={"dataset_id": did, "lights": [light]})
    assert r.status_code == 409 and "not baked" in fields(r)["dataset_id"]
    r = client.post("/v1/relights", json={"dataset_id": "1" * 64, "lights": [light]})
    assert r.status_code == 404
    env = {"type": "environment", "image_sha256": "2" * 64}
    r = client.post("/v1/relights", json={"dataset_id": did, "lights": [light, env]})
    assert r.status_code == 422 and "environment map not uploaded" in fields(r)["lights.1.image_sha256"]
    r = client.post("/v1/relights", json={"dataset_id": did, "lights": []})
    assert r.status_code == 422 and "lights" in fields(r)
    r = client.post("/v1/relights", json={"dataset_id": did, "lights": [{"type": "point", "position": [0, 0]}]})
    assert r.status_code == 422 and "lights.0.position.2" in fields(r)
    r = client.post("/v1/datasets/generate", json={"scene_id": "3" * 64})
    assert r.status_code == 404
    many = [{"type": "environment", "image_sha256": "2" * 64, "n_lights": 4096}] * 5
    r = client.post("/v1/relights", json={"dataset_id": did, "lights": many})
    assert r.status_code == 422 and "expand to 20480" in fields(r)["lights"]


def test_datasets_are_per_api_key(make_app: Any) -> None:
    from service.core.security import hash_key

    manifest, files = subset(5)
    with TestClient(make_app(api_keys=[hash_key("alice"), hash_key("bob")])) as c:
        alice = {"Authorization": "Bearer alice"}
        bob = {"Authorization": "Bearer bob"}
        did = c.post("/v1/datasets", files=multipart(manifest, files), headers=alice).json()["id"]
        assert c.get(f"/v1/datasets/{did}", headers=alice).status_code == 200
        assert c.get(f"/v1/datasets/{did}", headers=bob).status_code == 404
        assert c.get("/v1/datasets", headers=bob).json()["items"] == []
        assert c.delete(f"/v1/datasets/{did}", headers=bob).status_code == 404
        assert c.post(f"/v1/datasets/{did}/bake", headers=bob).status_code == 404
        assert c.get("/v1/datasets", headers={}).status_code == 401


def test_bake_is_queued_and_delete_waits_for_it(client: TestClient) -> None:
    """No worker runs here: the bake stays queued; identical requests share the job; deleting the
    dataset is refused while the job is queued, allowed once it is canceled."""
    manifest, files = subset(5)
    did = client.post("/v1/datasets", files=multipart(manifest, files)).json()["id"]
    r = client.post(f"/v1/datasets/{did}/bake", json={"params": {"layout": "tiled"}})
    assert r.status_code == 202, r.text
    body = r.json()
    assert body["status"] == "queued" and r.headers["location"] == f"/v1/jobs/{body['job']['id']}"
    assert body["job"]["id"] == f"relight-bake-{body['artifact_key']}" and body["job"]["kind"] == "bake"
    assert client.post(f"/v1/datasets/{did}/bake", json={"params": {"layout": "tiled"}}).json()["job"]["id"] == \
        body["job"]["id"]
    other = client.post(f"/v1/datasets/{did}/bake", json={"params": {"layout": "pixel_major"}}).json()
    assert other["artifact_key"] != body["artifact_key"]
    r = client.delete(f"/v1/datasets/{did}")
    assert r.status_code == 409 and "queued or running job" in r.json()["detail"]
    relight = {"dataset_id": did, "bake": {"layout": "tiled"},
               "lights": [{"type": "directional", "direction": [0, 0, -1]}]}
    r = client.post("/v1/relights", json=relight)
    assert r.status_code == 409 and f"/v1/jobs/{body['job']['id']} is still queued" in fields(r)["dataset_id"]
    for job in (body["job"]["id"], other["job"]["id"]):
        assert client.post(f"/v1/jobs/{job}/cancel").json()["state"] == "canceled"
    assert client.delete(f"/v1/datasets/{did}").status_code == 204
    assert client.post(f"/v1/datasets/{did}/bake", json={}).status_code == 404  # gone
    bad = client.post(f"/v1/datasets/{did}/bake", json={"params": {"max_face_radius_deg": 120}})
    assert bad.status_code == 422 and "params.max_face_radius_deg" in fields(bad)


def test_file_names_are_metadata_only(client: TestClient, store_dir: Path) -> None:
    """docs/hard-cases.md #17: names like ../../x are only labels; files live under their sha256 in the store,
    and a name with a control character (NUL) is refused."""
    manifest, files = subset(3)
    m = json.loads(json.dumps(manifest))
    renamed: dict[str, bytes] = {}
    for i, img in enumerate(m["images"]):
        new = ["../../evil.png", "C:\\..\\x.png", "/etc/passwd"][i]
        renamed[new] = files[img["file"]]
        img["file"] = new
    renamed.update({k: files[k] for k in ("depth.exr", "mask.png")})
    r = client.post("/v1/datasets", files=multipart(m, renamed))
    assert r.status_code == 201, r.text
    assert not (store_dir.parent / "evil.png").exists() and not (store_dir.parent.parent / "evil.png").exists()
    for img in r.json()["manifest"]["images"]:
        assert (store_dir / "blobs" / img["sha256"]).is_file()
    m["images"][0]["file"] = "a\x00b.png"
    r = client.post("/v1/datasets", json=with_shas({**manifest}, files) | {"images": m["images"]})
    assert r.status_code == 422 and "images.0.file" in fields(r)


def test_uploading_a_file_again_replaces_its_corrupt_stored_copy(client: TestClient, store_dir: Path) -> None:
    """A stored image that went bad before any reader checked it (a flipped byte, a truncation) is
    replaced by the next upload of the same bytes, by PUT or in a multipart dataset."""
    manifest, files = subset(3)
    did = client.post("/v1/datasets", files=multipart(manifest, files)).json()["id"]
    name = manifest["images"][1]["file"]
    data = files[name]
    blob = store_dir / "blobs" / sha(data)
    for bad in (data[:100] + bytes([data[100] ^ 1]) + data[101:], data[:-9]):
        blob.write_bytes(bad)
        put = client.put(f"/v1/datasets/uploads/{sha(data)}", content=data)
        assert put.status_code == 200, put.text  # already received ...
        assert blob.read_bytes() == data  # ... and its stored copy is good again
    blob.write_bytes(b"")
    assert client.post("/v1/datasets", files=multipart(manifest, files)).json()["id"] == did
    assert blob.read_bytes() == data
    assert client.get(f"/v1/datasets/{did}/files/{sha(data)}").content == data
