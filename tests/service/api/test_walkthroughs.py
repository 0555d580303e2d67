"""/v1/walkthroughs: bad input (422 naming the field and the allowed range), job split and an end
to end run through real bake and render workers (tiny bases), ending in an MP4."""

from __future__ import annotations

import copy
import time
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient
from redis import Redis

from api_schemas.walkthrough import WalkthroughPublic

ROOM: dict[str, Any] = {
    "name": "walk",
    "camera": {"type": "perspective", "eye": [0, 0, 0], "look_at": [0, 0, 1], "width": 16, "height": 12},
    "materials": [{"name": "white", "kd": [0.7, 0.7, 0.7]}, {"name": "red", "kd": [0.7, 0.1, 0.1]}],
    "objects": [
        {"type": "box", "name": "wall", "material": "white", "center": [0, 0, 10], "size": [40, 40, 0.2]},
        {"type": "box", "name": "occluder", "material": "red", "center": [0, 0, 5], "size": [1, 1, 1]},
    ],
    "lights": [{"type": "point", "name": "key", "position": [0, 3, 1], "intensity": [40, 40, 40]}],
    "ambient": [0.05, 0.05, 0.05],
    "view_space": {"type": "path", "points": [[-1, 0, 0], [1, 0, 0]]},
    "animation": {"start": 0, "end": 2, "objects": {"occluder": [
        {"time": 0, "transform": {}}, {"time": 2, "transform": {"translate": [1, 0, 0]}}]}},
}


def _scene(c: TestClient, doc: dict[str, Any] | None = None) -> str:
    r = c.post("/v1/scenes", json={"scene": doc or ROOM})
    assert r.status_code in (200, 201), r.text
    sid: str = r.json()["id"]
    return sid


def _frames(n: int, w: int = 16, h: int = 12) -> list[dict[str, Any]]:
    return [{"time": 2.0 * i / max(n - 1, 1),
             "camera": {"type": "perspective", "eye": [-1 + 2.0 * i / max(n - 1, 1), 0, 0], "look_at": [0, 0, 5],
                        "width": w, "height": h}} for i in range(n)]


BAKE = {"quality": "low", "face_res": 16, "indirect_samples": 0, "max_views": 2, "max_time_samples": 3}


def _errors(r: Any) -> dict[str, str]:
    assert r.status_code == 422, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    return {e["field"]: e["message"] for e in r.json()["errors"]}


def test_bad_walkthrough_requests_name_field_and_range(client: TestClient) -> None:
    sid = _scene(client)
    frames = _frames(3)
    # a camera path leaving the view space
    bad = copy.deepcopy(frames)
    bad[1]["camera"]["eye"] = [0, 0.5, 0]
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": bad}))
    assert "0.5 outside the scene's path view space" in errs["frames.1.camera.eye"]
    assert "bounds [-1.0, 0.0, 0.0] .. [1.0, 0.0, 0.0]" in errs["frames.1.camera.eye"]
    # times outside the animation
    bad = copy.deepcopy(frames)
    bad[2]["time"] = 2.5
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": bad}))
    assert errs["frames.2.time"] == "time 2.5 is outside the animation interval [0, 2]"
    # frames of different sizes, odd sizes, an unknown fill, bad bake settings
    bad = copy.deepcopy(frames)
    bad[1]["camera"]["width"] = 20
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": bad}))
    assert "every frame must be 16 x 12 like frames.0" in errs["frames.1.camera.width"]
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames, "fill": "magic",
                                                         "bake": {"quality": "ultra", "max_views": 0}}))
    assert {"fill", "bake.quality", "bake.max_views"} <= set(errs)
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames,
                                                         "bake": {"face_res": 15}}))
    assert errs["bake.face_res"] == "face_res must be even (got 15)"
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames,
                                                         "bake": {"indirect_noise": 0.9, "indirect_max_paths": 8}}))
    assert "less than or equal to 0.5" in errs["bake.indirect_noise"]
    assert "greater than or equal to 128" in errs["bake.indirect_max_paths"]
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": frames,
                                                         "bake": {"quality": "high", "face_res": 1024}}))
    assert "exceeds this server's limit" in errs["bake.face_res"]
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": sid, "frames": []}))
    assert "frames" in errs
    # a scene without a view space; a view space with no room; keyframes out of order
    no_vs = {k: v for k, v in ROOM.items() if k != "view_space"}
    errs = _errors(client.post("/v1/walkthroughs", json={"scene_id": _scene(client, no_vs), "frames": frames}))
    assert "no view_space" in errs["scene_id"]
    errs = _errors(client.post("/v1/scenes", json={"scene": {**ROOM, "view_space": {
        "type": "box", "min": [1, 1, 1], "max": [1, 1, 1]}}}))
    assert "no room" in errs["scene.view_space.max"]
    anim = copy.deepcopy(ROOM["animation"])
    anim["objects"]["occluder"][1]["time"] = 0
    errs = _errors(client.post("/v1/scenes", json={"scene": {**ROOM, "animation": anim}}))
    assert "increase strictly" in errs["scene.animation.objects.occluder.1.time"]
    # unknown scene / walkthrough
    r = client.post("/v1/walkthroughs", json={"scene_id": "a" * 64, "frames": frames})
    assert r.status_code == 404
    assert client.get("/v1/walkthroughs/" + "b" * 64).status_code == 404


def test_walkthrough_is_split_into_shared_jobs(client: TestClient, redis_conn: Redis) -> None:
    sid = _scene(client)
    body = {"scene_id": sid, "frames": _frames(5), "chunk_frames": 2, "bake": BAKE}
    r = client.post("/v1/walkthroughs", json=body)
    assert r.status_code == 202, r.text
    pub = WalkthroughPublic.model_validate(r.json())
    assert r.headers["location"] == f"/v1/walkthroughs/{pub.key}"
    assert pub.status == "queued" and pub.frames == 5 and pub.frames_done == 0
    kinds = sorted(j.id.split("-")[0] for j in pub.jobs)
    assert kinds == ["walkthrough", "wtbake", "wtchunk", "wtchunk", "wtchunk"]
    # the same request shares every job; another fill shares the bake only
    again = WalkthroughPublic.model_validate(client.post("/v1/walkthroughs", json=body).json())
    assert again.key == pub.key and {j.id for j in again.jobs} == {j.id for j in pub.jobs}
    other = WalkthroughPublic.model_validate(client.post("/v1/walkthroughs", json={**body, "fill": "none"}).json())
    assert other.key != pub.key and other.bake_key == pub.bake_key
    assert len({j.id for j in other.jobs} & {j.id for j in pub.jobs}) == 1
    got = WalkthroughPublic.model_validate(client.get(f"/v1/walkthroughs/{pub.key}").json())
    assert got.key == pub.key and got.status == "queued"
    # canceling one chunk job fails the walkthrough, naming the frames
    chunk_job = next(j.id for j in pub.jobs if j.id.startswith("wtchunk"))
    assert client.post(f"/v1/jobs/{chunk_job}/cancel").status_code == 200
    got = WalkthroughPublic.model_validate(client.get(f"/v1/walkthroughs/{pub.key}").json())
    assert got.status == "failed" and got.error is not None and got.error.startswith("frames ")
    assert "canceled" in got.error


def test_walkthrough_end_to_end(client: TestClient, worker_process: Any, store_dir: Path) -> None:
    bake_worker = worker_process("bake")
    render_worker = worker_process("render")
    sid = _scene(client)
    body = {"scene_id": sid, "frames": _frames(5), "chunk_frames": 2, "fill": "trace", "bake": BAKE, "fps": 10}
    r = client.post("/v1/walkthroughs", json=body)
    assert r.status_code == 202, r.text
    url = r.headers["location"]
    deadline = time.monotonic() + 240
    while True:
        pub = WalkthroughPublic.model_validate(client.get(url).json())
        if pub.status in ("finished", "failed") or time.monotonic() > deadline:
            break
        time.sleep(0.3)
    assert pub.status == "finished", (pub, bake_worker.log()[-3000:], render_worker.log()[-3000:])
    assert pub.frames_done == 5 and pub.progress == 1.0
    video = client.get(pub.links["video.mp4"])
    assert video.status_code == 200 and video.content[4:8] == b"ftyp" and len(video.content) > 200
    png = client.get(pub.links["frame.png"].format(index=3))
    assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
    assert client.get(pub.links["frame.exr"].format(index=4)).content[:4] == b"v/1\x01"
    assert client.get(pub.links["frame.provenance"].format(index=0)).status_code == 200
    assert client.get(pub.links["frame.png"].format(index=5)).status_code == 422
    chunk = client.get(pub.links["chunk.1"]).json()
    names = {b["name"] for b in chunk["blobs"]}
    assert {"frame_00002.exr", "frame_00003.png", "provenance_00003.png"} <= names
    assert chunk["result"]["frames"] == [2, 4] and sum(chunk["result"]["provenance"].values()) == 2 * 16 * 12
    # finished: the same request answers 200 at once
    r = client.post("/v1/walkthroughs", json=body)
    assert r.status_code == 200 and r.json()["status"] == "finished"


def test_preset_sizes_match_the_engine() -> None:
    from api_schemas.walkthrough import PRESET_SIZES
    from engine.walkthrough.bake import PRESETS

    for q, sizes in PRESET_SIZES.items():
        assert {k: PRESETS[q][k] for k in sizes} == sizes
