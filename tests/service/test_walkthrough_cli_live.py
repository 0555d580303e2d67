"""``ibr walkthrough`` / ``ibr walkthroughs ...`` and the Python client's walkthrough calls against a live
local stack (embedded Redis, real bake and render workers, uvicorn API): a tiny animated room, four
16x12 frames from tiny bases, the MP4 and the frames fetched, then deleted."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from engine.imageio import read_image
from service.cli import app
from service.client import ApiError, Client
from tests.service.api.test_walkthroughs import ROOM, _frames

# Everyday runs skip this file (make test-fast): the whole service started as processes, driven through the CLI.
pytestmark = pytest.mark.slow

TINY = ["--quality", "low", "--face-res", "16", "--indirect", "0", "--max-views", "2", "--max-time-samples", "3"]


def test_walkthrough_from_the_command_line(stack: Any, tmp_path: Path) -> None:
    runner = CliRunner()
    api = ["--api", stack.api_url]
    scene_file = tmp_path / "room.json"
    scene_file.write_text(json.dumps(ROOM))
    path = tmp_path / "path.json"
    frames = _frames(4)
    for f in frames:  # cameras without a type are perspective
        del f["camera"]["type"]
    path.write_text(json.dumps(frames))

    # bad input first: exit 2 naming the field and the allowed range, nothing queued
    bad = json.loads(json.dumps(frames))
    bad[2]["camera"]["eye"] = [0, 0.5, 0]
    bad[3]["time"] = 2.5
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    res = runner.invoke(app, ["walkthrough", str(scene_file), "--path", str(tmp_path / "bad.json"), *TINY, *api])
    assert res.exit_code == 2, res.output
    assert "frames.2.camera.eye" in res.output and "outside the scene's path view space" in res.output
    assert "frames.3.time" in res.output and "[0, 2]" in res.output
    res = runner.invoke(app, ["walkthrough", str(scene_file), "--path", str(path), "--quality", "ultra", *api])
    assert res.exit_code == 2 and "bake.quality" in res.output
    res = runner.invoke(app, ["walkthrough", str(scene_file), "--path", str(path), "-o", str(tmp_path / "x.gif"),
                              *api])
    assert res.exit_code == 2 and ".mp4" in res.output

    out, frames_dir = tmp_path / "walk.mp4", tmp_path / "frames"
    res = runner.invoke(app, ["walkthrough", str(scene_file), "--path", str(path), *TINY, "--chunk-frames", "2",
                              "--fps", "8", "--fill", "both", "-o", str(out), "--frames-dir", str(frames_dir), *api])
    assert res.exit_code == 0, res.output
    key = res.stdout.strip().splitlines()[-1]
    assert len(key) == 64 and "4 frames" in res.stderr and "finished: 4 frames" in res.stderr
    data = out.read_bytes()
    assert data[4:8] == b"ftyp" and len(data) > 200
    pngs = sorted(frames_dir.glob("frame_*.png"))
    assert [p.name for p in pngs] == [f"frame_{i:05d}.png" for i in range(4)]
    img, _ = read_image(pngs[1])
    assert img.shape[:2] == (12, 16) and img.max() > 0

    res = runner.invoke(app, ["walkthroughs", "show", key, *api])
    assert res.exit_code == 0 and json.loads(res.stdout)["status"] == "finished"
    exr_dir = tmp_path / "exr"
    res = runner.invoke(app, ["walkthroughs", "fetch", key, "--frames-dir", str(exr_dir), "--frame-format", "exr",
                              *api])
    assert res.exit_code == 0, res.output
    assert len(list(exr_dir.glob("frame_*.exr"))) == 4

    with Client(stack.api_url) as c:
        # the client: the same request is finished at once; frames and video by key
        sid = c.create_scene(ROOM).id
        w = c.walkthrough({"scene_id": sid, "frames": _frames(4), "chunk_frames": 2, "fps": 8, "fill": "both",
                           "bake": {"quality": "low", "face_res": 16, "indirect_samples": 0, "max_views": 2,
                                    "max_time_samples": 3}})
        assert w.key == key and w.status == "finished"
        assert c.wait_walkthrough(w).frames_done == 4
        assert c.download_walkthrough_video(key) == data
        assert c.download_walkthrough_frame(key, 0, "provenance")[:4] == b"\x89PNG"

    # a walkthrough whose job is canceled: following it exits 4 naming the frames; then it can be deleted.
    # The bake worker is paused meanwhile, so the new bake waits and its chunks wait behind it (with a
    # warm numba cache a small bake ends before the chunk can be canceled).
    bake_worker = stack.procs["bake-worker"]
    bake_worker.send_signal(signal.SIGSTOP)
    try:
        res = runner.invoke(app, ["walkthrough", str(scene_file), "--path", str(path), *TINY, "--chunk-frames", "2",
                                  "--fill", "none", "--face-res", "64", *api])  # a new bake: chunks wait behind it
        assert res.exit_code == 0, res.output
        key2 = res.stdout.strip().splitlines()[-1]
        jobs = json.loads(runner.invoke(app, ["walkthroughs", "show", key2, *api]).stdout)["jobs"]
        chunk = next(j["id"] for j in jobs if j["id"].startswith("wtchunk-"))
        res = runner.invoke(app, ["walkthroughs", "delete", key2, *api])  # its jobs are waiting: 409 -> exit 2
        assert res.exit_code == 2 and "queued or running" in res.output
        res = runner.invoke(app, ["jobs", "cancel", chunk, *api])
        assert res.exit_code == 0 and "canceled" in res.stdout, res.output
    finally:
        bake_worker.send_signal(signal.SIGCONT)
    res = runner.invoke(app, ["walkthroughs", "fetch", key2, "-o", str(tmp_path / "no.mp4"), *api])
    assert res.exit_code == 4 and "walkthrough failed" in res.output and "frames 0..1" in res.output
    assert not (tmp_path / "no.mp4").exists()
    # a chunk the worker had already started ends a moment after the cancel (the worker stops its
    # work horse): until then the delete rightly answers 409; it succeeds once nothing runs
    deadline = time.monotonic() + 60.0
    while True:
        res = runner.invoke(app, ["walkthroughs", "delete", key2, *api])
        if res.exit_code == 0 or "queued or running" not in res.output or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert res.exit_code == 0, res.output

    res = runner.invoke(app, ["walkthroughs", "delete", key, *api])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["walkthroughs", "show", key, *api])
    assert res.exit_code == 2
    with Client(stack.api_url) as c, pytest.raises(ApiError) as e:
        c.download_walkthrough_video(key)
    assert e.value.status == 404


def test_walkthrough_quality_contract_from_the_command_line(stack: Any, tmp_path: Path) -> None:
    """``ibr calibrate-walkthroughs`` then ``ibr walkthrough --quality-error``: the planner picks the bake
    preset and the fill, the plan is on stderr, the key alone on stdout (one preset, one fill, two small
    probes: about ten seconds of calibration)."""
    runner = CliRunner()
    api = ["--api", stack.api_url]
    scene_file = tmp_path / "room.json"
    scene_file.write_text(json.dumps(ROOM))
    path = tmp_path / "path.json"
    path.write_text(json.dumps(_frames(4)))
    walk = ["walkthrough", str(scene_file), "--path", str(path), "--chunk-frames", "2"]

    # no walkthrough calibration yet: exit 2 saying how to make one
    res = runner.invoke(app, [*walk, "--quality-error", "0.9", *api])
    assert res.exit_code == 2, res.output
    assert "walkthrough calibration" in res.stderr and "ibr calibrate-walkthroughs" in res.stderr

    params = {"presets": ["low"], "fills": ["both"], "probes": 2, "size": 32, "path_noises": []}
    calibrate = ["calibrate-walkthroughs", str(scene_file), "--presets", "low", "--fills", "both", "--probes", "2",
                 "--size", "32", "--path-noises", "none", *api]
    res = runner.invoke(app, [*calibrate, "--wait"])
    assert res.exit_code == 0, res.output
    cal_key = res.stdout.strip()
    assert len(cal_key) == 64 and "\n" not in cal_key
    assert "low/both: LRMS " in res.stderr and "ms / frame at 32 x 24; bake " in res.stderr, res.stderr
    res = runner.invoke(app, [*calibrate, "--no-wait"])  # the same calibration: cached, nothing queued
    assert res.exit_code == 0 and res.stdout.strip() == cal_key and "(cached)" in res.stderr, res.output

    with Client(stack.api_url) as c:
        sid = c.create_scene(ROOM).id
        cal = c.get_walkthrough_calibration(sid)
        assert cal.state == "finished" and cal.key == cal_key and cal.model is not None
        again = c.calibrate_walkthroughs(sid, params)
        assert again.cached and again.key == cal_key
        assert c.wait_walkthrough_calibration(again).model == cal.model
    fit = cal.model["fits"]["low/both"]

    res = runner.invoke(app, [*walk, "--quality-error", "0.9", "--wait", *api])
    assert res.exit_code == 0, res.output
    key = res.stdout.strip()
    assert len(key) == 64 and "\n" not in key  # the key is the only output
    assert f"contract: low/both, predicted LRMS {fit['error']:.4f}, " in res.stderr, res.stderr
    assert "ms / frame (rule cheapest_meeting_error)" in res.stderr and "not met" not in res.stderr
    assert "finished: 4 frames" in res.stderr and "achieved: " in res.stderr
    # the settings it chooses are refused beside it; a target no setting reaches is a 422 naming it
    res = runner.invoke(app, [*walk, "--quality-error", "0.9", "--fill", "trace", *api])
    assert res.exit_code == 2 and "leave out --fill" in res.stderr
    if fit["error"] / 4 > 0:
        res = runner.invoke(app, [*walk, "--quality-error", f"{fit['error'] / 4:.6g}", *api])
        assert res.exit_code == 2 and "quality.max_error" in res.stderr and "low/both" in res.stderr, res.output

    res = runner.invoke(app, ["walkthroughs", "delete", key, *api])
    assert res.exit_code == 0, res.output
