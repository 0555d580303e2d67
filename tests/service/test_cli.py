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
        assert "--supersample/--antialias set how an LDC method" in r.stderr
