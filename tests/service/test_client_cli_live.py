"""The Python client and the ``ibr`` client commands against a live local stack
(``ibr up``'s start_stack: embedded Redis, real bake and render workers, uvicorn API)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from engine.imageio import read_image
from samples import SAMPLES_DIR
from service.cli import app
from service.client import ApiError, Client
from service.up import free_port, load_samples

# Everyday runs skip this file (make test-fast): the whole service started as processes, driven through the CLI.
pytestmark = pytest.mark.slow

SMALL = {
    "camera": {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0], "width": 32, "height": 24},
    "materials": [{"name": "red", "kd": [0.7, 0.1, 0.1]}, {"name": "floor", "kd": [0.5, 0.5, 0.5]}],
    "objects": [{"type": "sphere", "material": "red", "center": [0, 0.5, 0], "radius": 0.5, "subdivisions": 3},
                {"type": "plane", "material": "floor", "size": [6, 6]}],
    "lights": [{"type": "point", "position": [2, 3, 2], "intensity": [8, 8, 8]}],
}


def test_client_round_trip(stack):
    with Client(stack.api_url) as c:
        assert c.ready()
        scene = c.create_scene(SMALL)
        assert c.get_scene(scene.id).id == scene.id
        r = c.render(scene.id, params={"spp": 1}, wait=30)
        seen = []
        man = c.wait_render(r, on_progress=seen.append)
        assert {b.name for b in man.blobs} >= {"radiance.exr", "preview.png"}
        png = c.download(man.key, "png")
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        again = c.render(scene.id, params={"spp": 1})
        assert again.status == "cached" and again.job is None
        assert any(j.id.endswith(man.key) for j in c.jobs().items)
        with pytest.raises(ApiError) as e:
            c.render("0" * 64)
        assert e.value.status == 404


def test_samples_with_meshes_upload_and_render(stack):
    ids = load_samples(stack.api_url, log=lambda s: None)
    assert {"teapot_glossy", "cornell_box", "mirror_box"} <= set(ids)
    with Client(stack.api_url) as c:
        cam = json.loads((SAMPLES_DIR / "scenes" / "teapot_glossy.json").read_text())["camera"]
        cam.update(width=24, height=24)
        r = c.render(ids["teapot_glossy"], camera=cam, params={"spp": 1, "glossy_samples": 2}, wait=60)
        man = c.wait_render(r)
        assert man.result["mesh_reports"][0]["source"] == "meshes/teapot.ply"


def test_cli_client_commands(stack, tmp_path):
    runner = CliRunner()
    env = {"IBR_API_URL": stack.api_url}
    scene_file = tmp_path / "s.json"
    scene_file.write_text(json.dumps(SMALL))
    r = runner.invoke(app, ["scenes", "add", str(scene_file)], env=env)
    assert r.exit_code == 0, r.output
    sid = r.stdout.strip().splitlines()[-1]
    assert len(sid) == 64
    out = tmp_path / "img.exr"
    r = runner.invoke(app, ["render", sid, "--spp", "2", "-o", str(out)], env=env)
    assert r.exit_code == 0, r.output
    img, meta = read_image(out)
    assert img.shape == (24, 32, 3) and meta["render_params"]["spp"] == 2
    r = runner.invoke(app, ["jobs", "list"], env=env)
    assert r.exit_code == 0 and "finished" in r.stdout
    r = runner.invoke(app, ["scenes", "list"], env=env)
    assert sid in r.stdout
    # batch: two scenes and their renders in one call
    other = tmp_path / "t.json"
    other.write_text(json.dumps(dict(SMALL, lights=[{"type": "point", "position": [0, 3, 0],
                                                     "intensity": [5, 5, 5]}])))
    r = runner.invoke(app, ["batch", str(scene_file), str(other), "--spp", "1", "--follow"], env=env)
    assert r.exit_code == 0, r.output
    # a scene with a mesh file goes too: stored with its mesh in the batch, then rendered
    pyramid = Path(__file__).resolve().parents[2] / "examples" / "scenes" / "pyramid.json"
    r = runner.invoke(app, ["batch", str(pyramid), str(scene_file), "--spp", "1", "--follow"], env=env)
    assert r.exit_code == 0, r.output
    r_add = runner.invoke(app, ["scenes", "add", str(pyramid)], env=env)
    pid = r_add.stdout.strip()
    with Client(stack.api_url) as c:
        b = c.get_batch(r.stdout.strip().splitlines()[-1])
        assert len(b.renders) == 2 and b.counts == {"finished": 1, "cached": 1}, b.counts  # scene_file: cached
        pyr = next(x for x in b.renders if x.status == "finished")
        man = c.wait_render(pyr)
        assert man.inputs["scene"] == pid and man.result["mesh_reports"][0]["source"] == "meshes/pyramid.obj"
    # bad input: exit code 2 with the field
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(dict(SMALL, camera=dict(SMALL["camera"], width=0))))
    r = runner.invoke(app, ["scenes", "add", str(bad)], env=env)
    assert r.exit_code == 2 and "camera.width" in r.output
    r = runner.invoke(app, ["render", "f" * 64], env=env)
    assert r.exit_code == 2


def test_unreachable_api_exits_3(tmp_path):
    r = CliRunner().invoke(app, ["jobs", "list"], env={"IBR_API_URL": f"http://127.0.0.1:{free_port()}"})
    assert r.exit_code == 3 and "cannot reach" in r.output
