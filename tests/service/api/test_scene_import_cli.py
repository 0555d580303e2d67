"""``ibr scenes add FILE.gltf|.glb|.obj`` against the real API (uvicorn in a thread, no workers): the
id alone on stdout, what the import left out on stderr, the buffers and MTL files read from beside
the file."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from typer.testing import CliRunner

from service.cli import app as cli_app
from service.client import Client

FIX = Path(__file__).resolve().parents[2] / "fixtures" / "scene_import"
runner = CliRunner()


def ibr(api_url: str, *args: str) -> Any:
    return runner.invoke(cli_app, list(args), env={"IBR_API_URL": api_url, "IBR_API_KEY": ""})


def test_scenes_add_imports_gltf_glb_and_obj(api_url: str, tmp_path: Path) -> None:
    lamp = FIX / "gltf" / "lights-punctual-lamp" / "LightsPunctualLamp.gltf"
    r = ibr(api_url, "scenes", "add", str(lamp), "--width", "48")
    assert r.exit_code == 0, r.stderr
    scene_id = r.stdout.strip()
    assert len(scene_id) == 64 and "\n" not in scene_id
    assert "import: textures:" in r.stderr and "materials[0].pbrMetallicRoughness.baseColorTexture" in r.stderr
    with Client(api_url) as c:
        doc = c.get_scene_document(scene_id)
    assert doc["camera"]["width"] == 48 and len(doc["lights"]) == 5

    r = ibr(api_url, "scenes", "add", str(FIX / "gltf" / "box-glb" / "Box.glb"))
    assert r.exit_code == 0 and len(r.stdout.strip()) == 64, r.stderr

    r = ibr(api_url, "scenes", "add", str(FIX / "obj" / "CornellBox-Original.obj"), "--name", "cbox")
    assert r.exit_code == 0, r.stderr
    with Client(api_url) as c:
        assert c.get_scene(r.stdout.strip()).name == "cbox"


def test_scenes_add_names_a_missing_companion_and_a_refused_part(api_url: str, tmp_path: Path) -> None:
    obj = tmp_path / "box.obj"
    shutil.copy(FIX / "obj" / "CornellBox-Original.obj", obj)  # without its .mtl beside it
    r = ibr(api_url, "scenes", "add", str(obj))
    assert r.exit_code == 2 and "CornellBox-Original.mtl" in r.stderr and r.stdout == ""
    bad = tmp_path / "bad.gltf"
    bad.write_text('{"asset": {"version": "2.0"}, "buffers": [{"uri": "http://example.com/a.bin", "byteLength": 4}]}')
    r = ibr(api_url, "scenes", "add", str(bad))
    assert r.exit_code == 2 and "buffers[0].uri" in r.stderr and "nothing is fetched" in r.stderr
    r = ibr(api_url, "scenes", "add", str(FIX / "obj" / "CornellBox-Original.obj"), "--width", "0")
    assert r.exit_code == 2 and "width" in r.stderr
