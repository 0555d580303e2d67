"""The ``ibr`` command line: renders, validates, and exits 2 with the field on bad input."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from engine.imageio import read_image
from service.cli import app

runner = CliRunner()


def test_render_sample_writes_image_with_metadata(tmp_path):
    out = tmp_path / "mirror.exr"
    r = runner.invoke(app, ["render-local", "mirror_box", "-o", str(out), "--width", "24", "--height", "16",
                            "--spp", "1", "--aovs"])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout[r.stdout.index("{"):])
    assert summary["width"] == 24 and summary["height"] == 16
    assert set(summary["timings_s"]) >= {"intersect", "shading", "shadow", "total"}
    img, meta = read_image(out)
    assert img.shape == (16, 24, 3) and img.max() > 0
    assert meta["scene_hash"] == summary["scene_hash"]
    assert meta["camera"]["width"] == 24
    assert meta["render_params"]["spp"] == 1
    assert (tmp_path / "mirror.depth.exr").exists()


def test_invalid_scene_exits_2_naming_the_field(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({
        "camera": {"type": "perspective", "eye": [0, 0, 1], "look_at": [0, 0, 0], "width": 8, "height": 8},
        "materials": [{"name": "m", "kd": [0.5, -1, 0.5]}],
    }))
    r = runner.invoke(app, ["render-local", str(bad), "-o", str(tmp_path / "x.png")])
    assert r.exit_code == 2
    assert "materials.0.kd" in r.output
    assert not (tmp_path / "x.png").exists()


def test_missing_scene_and_bad_mesh_exit_2(tmp_path):
    r = runner.invoke(app, ["validate", str(tmp_path / "nope.json")])
    assert r.exit_code == 2 and "nope.json" in r.output
    (tmp_path / "m.obj").write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "s.json").write_text(json.dumps({
        "camera": {"type": "perspective", "eye": [0, 0, 1], "look_at": [0, 0, 0], "width": 8, "height": 8},
        "materials": [{"name": "m"}],
        "objects": [{"type": "mesh_file", "material": "m", "path": "m.obj"}],
    }))
    r = runner.invoke(app, ["validate", str(tmp_path / "s.json")])
    assert r.exit_code == 2
    assert "m.obj" in r.output


def test_schema_and_samples_commands(tmp_path):
    r = runner.invoke(app, ["schema", "-o", str(tmp_path / "s.json")])
    assert r.exit_code == 0
    assert json.loads((tmp_path / "s.json").read_text())["title"] == "Scene"
    r = runner.invoke(app, ["samples"])
    assert "cornell_box" in r.output and "teapot_glossy" in r.output


def test_dataset_and_walkthrough_commands_check_their_input_before_calling(tmp_path):
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        env = {"IBR_API_URL": f"http://127.0.0.1:{s.getsockname()[1]}"}
    ds = "a" * 64
    r = runner.invoke(app, ["relight", ds, "--light", "point:1,2"], env=env)
    assert r.exit_code == 2 and "--light #1" in r.output and "3 numbers" in r.output
    r = runner.invoke(app, ["relight", ds, "--light", "point:1,2,3", "-o", str(tmp_path / "x.jpg")], env=env)
    assert r.exit_code == 2 and "x.jpg" in r.output
    (tmp_path / "lights.json").write_text('{"not": "a list"}')
    r = runner.invoke(app, ["relight", ds, "--lights", str(tmp_path / "lights.json")], env=env)
    assert r.exit_code == 2 and "--lights" in r.output
    r = runner.invoke(app, ["relight", ds, "--light", '{"type": "point", "position": [1, 2, 3]}'], env=env)
    assert r.exit_code == 3 and "cannot reach" in r.output  # well-formed: it got as far as the API
    r = runner.invoke(app, ["datasets", "upload", str(tmp_path / "none")], env=env)
    assert r.exit_code == 2 and "no such manifest" in r.output
    (tmp_path / "m.json").write_text(json.dumps({"images": [{"file": "a.png", "direction": [0, 0, 1],
                                                             "intensity": 1}]}))
    r = runner.invoke(app, ["datasets", "upload", str(tmp_path / "m.json")], env=env)
    assert r.exit_code == 2 and "images.0.file" in r.output and "a.png" in r.output
    r = runner.invoke(app, ["walkthrough", ds, "--path", str(tmp_path / "none.json")], env=env)
    assert r.exit_code == 2 and "--path" in r.output
    (tmp_path / "p.json").write_text(json.dumps([{"time": 0}]))
    r = runner.invoke(app, ["walkthrough", ds, "--path", str(tmp_path / "p.json")], env=env)
    assert r.exit_code == 2 and "frames.0" in r.output and "camera" in r.output
    r = runner.invoke(app, ["walkthroughs", "fetch", ds, "--frame-format", "gif"], env=env)
    assert r.exit_code == 2 and "png, exr or provenance" in r.output


def test_render_refuses_ldc_view_options_where_they_mean_nothing():
    # checked before any request: no service needed (the API would answer the same with a 422)
    for args in (["--supersample", "2"], ["--method", "reference", "--antialias", "uniform"],
                 ["--quality-error", "0.05", "--supersample", "4"]):
        r = runner.invoke(app, ["render", "mirror_box", *args, "--api", "http://127.0.0.1:9"])
        assert r.exit_code == 2, r.output
        assert "--supersample/--antialias/--glossy-rays set how an LDC method" in r.stderr


def _dead_api() -> dict[str, str]:
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        return {"IBR_API_URL": f"http://127.0.0.1:{s.getsockname()[1]}"}


def _path_file(tmp_path, **fields):
    frame = {"time": 0, "camera": {"eye": [0, 0, 0], "look_at": [0, 0, 1], "width": 16, "height": 12}}
    p = tmp_path / "path.json"
    p.write_text(json.dumps({"frames": [frame], **fields}))
    return p


def test_walkthrough_contract_options_refuse_the_settings_they_choose(tmp_path):
    # checked before any request: no service needed
    env, sid = _dead_api(), "a" * 64
    path = _path_file(tmp_path)
    for flag, value in (("--quality", "low"), ("--fill", "both"), ("--face-res", "32"), ("--indirect", "0"),
                        ("--max-views", "2"), ("--max-time-samples", "3")):
        for contract in (["--quality-error", "0.1"], ["--quality-ms", "20", "--best-effort"]):
            r = runner.invoke(app, ["walkthrough", sid, "--path", str(path), *contract, flag, value], env=env)
            assert r.exit_code == 2, r.output
            assert "let the planner choose the bake preset and the fill: leave out " + flag in r.stderr
    r = runner.invoke(app, ["walkthrough", sid, "--path", str(path), "--best-effort"], env=env)
    assert r.exit_code == 2 and "--best-effort applies to a quality contract" in r.stderr
    r = runner.invoke(app, ["render", sid, "--method", "reference", "--best-effort"], env=env)
    assert r.exit_code == 2 and "--best-effort applies to a quality contract" in r.stderr  # the same for a render
    # a path file's own contract refuses them too
    r = runner.invoke(app, ["walkthrough", sid, "--path", str(_path_file(tmp_path, quality={"max_error": 0.1})),
                            "--fill", "both"], env=env)
    assert r.exit_code == 2 and "'quality' let the planner choose" in r.stderr and "--fill" in r.stderr
    # a well-formed contract gets as far as the API; the path file's bake and fill are dropped, said on stderr
    r = runner.invoke(app, ["walkthrough", sid, "--path",
                            str(_path_file(tmp_path, bake={"quality": "high"}, fill="trace")),
                            "--quality-error", "0.1"], env=env)
    assert r.exit_code == 3 and "cannot reach" in r.stderr, r.output
    assert "its bake and fill are left out: the quality contract chooses them" in r.stderr


def test_walkthrough_path_noise_sends_path_traced_and_refuses_bake_options(tmp_path, monkeypatch):
    import httpx

    env, sid, key = _dead_api(), "a" * 64, "b" * 64
    path = _path_file(tmp_path, bake={"quality": "high"}, fill="trace")
    for flag, value in (("--quality", "low"), ("--fill", "both"), ("--face-res", "32")):
        r = runner.invoke(app, ["walkthrough", sid, "--path", str(path), "--path-noise", "0.05", flag, value], env=env)
        assert r.exit_code == 2 and "--path-noise path-traces every frame without a bake: leave out " + flag \
            in r.stderr, r.output
    r = runner.invoke(app, ["walkthrough", sid, "--path", str(path), "--path-noise", "0.05", "--quality-error", "0.1"],
                      env=env)
    assert r.exit_code == 2 and "leave out --path-noise" in r.stderr
    pub = {"key": key, "status": "queued", "progress": 0.0, "frames": 1, "frames_done": 0, "bake_key": None}
    seen = _mock_api(monkeypatch, lambda req: httpx.Response(202, json=pub))
    r = runner.invoke(app, ["walkthrough", sid, "--path", str(path), "--path-noise", "0.05"])
    assert r.exit_code == 0 and r.stdout == key + "\n", r.output
    body = json.loads(seen[0].content)
    assert body["path_traced"] == {"noise": 0.05} and "bake" not in body and "fill" not in body
    assert "path-traced" in r.stderr


def test_calibrate_walkthroughs_checks_its_params_before_calling():
    env, sid = _dead_api(), "a" * 64
    r = runner.invoke(app, ["calibrate-walkthroughs", sid, "--presets", "low,ultra", "--probes", "0"], env=env)
    assert r.exit_code == 2, r.output
    assert "--presets (params.presets.1)" in r.stderr and "--probes (params.probes)" in r.stderr
    r = runner.invoke(app, ["calibrate-walkthroughs", sid, "--fills", "both,both"], env=env)
    assert r.exit_code == 2 and "fills lists a value twice" in r.stderr
    r = runner.invoke(app, ["calibrate-walkthroughs", sid, "--presets", ","], env=env)
    assert r.exit_code == 2 and "comma-separated" in r.stderr
    r = runner.invoke(app, ["calibrate-walkthroughs", sid, "--path-noises", "0.05,big"], env=env)
    assert r.exit_code == 2 and "--path-noises (params.path_noises.1)" in r.stderr, r.output
    r = runner.invoke(app, ["calibrate-walkthroughs", sid, "--presets", "low", "--fills", "both"], env=env)
    assert r.exit_code == 3 and "cannot reach" in r.stderr


def _mock_api(monkeypatch, answer):
    """Route the commands' client to ``answer(request) -> httpx.Response``; returns the requests seen."""
    import httpx

    import ibr_client.cli as cli
    from ibr_client.client import Client

    seen: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return answer(request)

    monkeypatch.setattr(cli, "_client", lambda url, key: Client(url, api_key=key,
                                                                transport=httpx.MockTransport(handler)))
    return seen


def test_walkthrough_contract_request_and_plan_lines(tmp_path, monkeypatch):
    import httpx

    sid, key = "a" * 64, "b" * 64
    contract = {"max_error": 0.01, "on_miss": "best_effort", "rule": "best_effort_most_accurate", "met": False,
                "unmet": ["max_error"], "reason": "no walkthrough setting reaches LRMS 0.01 (low/both: 0.13)",
                "preset": "low", "fill": "both", "frames": 1, "width": 16, "height": 12, "predicted_error": 0.13,
                "predicted_frame_ms": 6.04, "predicted_bake_ms": 2500.0, "predicted_total_ms": 2506.0,
                "estimated_error": 0.13, "bake": "waited"}
    pub = {"key": key, "status": "queued", "progress": 0.0, "frames": 1, "frames_done": 0, "bake_key": "c" * 64,
           "contract": contract}
    seen = _mock_api(monkeypatch, lambda req: httpx.Response(202, json=pub))
    r = runner.invoke(app, ["walkthrough", sid, "--path", str(_path_file(tmp_path, fill="none", fps=12)),
                            "--quality-error", "0.01", "--best-effort"])
    assert r.exit_code == 0, r.output
    assert r.stdout == key + "\n"  # the key is the only output
    body = json.loads(seen[0].content)
    assert body["quality"] == {"max_error": 0.01, "on_miss": "best_effort"} and body["scene_id"] == sid
    assert "bake" not in body and "fill" not in body and body["fps"] == 12
    assert ("contract: low/both, predicted LRMS 0.1300, 6.0 ms / frame (rule best_effort_most_accurate; "
            "its bake is made first, predicted 2.5 s)") in r.stderr
    assert "not met: max_error: no walkthrough setting reaches LRMS 0.01 (low/both: 0.13)" in r.stderr

    # no calibration: exit 2 naming the command that makes one
    detail = (f"scene {sid} has no walkthrough calibration: ... request it with POST "
              f"/v1/scenes/{sid}/walkthrough-calibrations, or name \"bake\" and \"fill\" instead of quality")
    _mock_api(monkeypatch, lambda req: httpx.Response(409, json={"title": "Calibration missing", "detail": detail}))
    r = runner.invoke(app, ["walkthrough", sid, "--path", str(_path_file(tmp_path)), "--quality-ms", "20"])
    assert r.exit_code == 2 and "409 Calibration missing" in r.stderr
    assert f"ibr calibrate-walkthroughs {sid}" in r.stderr and r.stdout == ""


def test_calibrate_walkthroughs_prints_the_key_and_each_setting(monkeypatch):
    import httpx

    sid, key = "a" * 64, "d" * 64
    model = {"fits": {"low/both": {"method": "low/both", "error": 0.125, "b_ms": 2.0, "c_ms": 0.001},
                      "low/trace": {"method": "low/trace", "error": 0.6, "b_ms": 3.0, "c_ms": 0.002}},
             "excluded": {"low/trace": "its error on the probe frames (60%) exceeds 50%"},
             "bake_keys": {"low": "e" * 64}, "bake_cost_s": {"low": 4.25}, "cost_s": 9.5,
             "probe": {"frames": [{"width": 32, "height": 24}],
                       "cost_breakdown_s": {"ground_truth": 3.0, "bakes": 4.5, "settings": 2.0}}}
    states = iter(["queued", "running", "finished"])

    def answer(req: httpx.Request) -> httpx.Response:
        state = next(states)
        doc = {"scene_id": sid, "key": key, "state": state, "model": model if state == "finished" else None,
               "job": {"id": "calwt-1", "kind": "bake", "state": "started" if state == "running" else state,
                       "progress": {"fraction": 0.5, "stage": "measuring low"}}}
        return httpx.Response(202 if req.method == "POST" else 200, json=doc)

    seen = _mock_api(monkeypatch, answer)
    r = runner.invoke(app, ["calibrate-walkthroughs", sid, "--presets", "low", "--fills", "both,trace",
                            "--probes", "2", "--size", "32", "--api", "http://127.0.0.1:9"])
    assert r.exit_code == 0, r.output
    assert r.stdout == key + "\n"
    assert json.loads(seen[0].content) == {"params": {"presets": ["low"], "fills": ["both", "trace"], "probes": 2,
                                                      "size": 32}}
    assert [q.url.params.get("key") for q in seen[1:]] == [key, key]  # followed by its key
    assert f"walkthrough calibration {key} (queued)" in r.stderr
    assert "cost: 9.5 s (ground truth 3.0 s, bakes 4.5 s, settings 2.0 s)" in r.stderr
    assert "low/both: LRMS 0.1250, 2.8 ms / frame at 32 x 24; bake 4.2 s" in r.stderr
    assert "low/trace: LRMS 0.6000, 4.5 ms / frame at 32 x 24; bake 4.2 s; excluded (its error" in r.stderr
