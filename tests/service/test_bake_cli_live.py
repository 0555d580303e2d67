"""``ibr bake --wait`` and ``ibr render --method ldc`` (and the Python client's bake calls) against a live
local stack (embedded Redis, real bake and render workers, uvicorn API)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from engine.imageio import read_image
from service.cli import app
from service.client import ApiError, Client
from tests.service.test_client_cli_live import SMALL

# Everyday runs skip this file (make test-fast): the whole service started as processes, driven through the CLI.
pytestmark = pytest.mark.slow


@pytest.mark.slow
def test_bake_and_ldc_render_from_the_command_line(stack: Any, tmp_path: Path) -> None:
    runner = CliRunner()
    api = ["--api", stack.api_url]
    scene_file = tmp_path / "small.json"
    scene_file.write_text(json.dumps(SMALL))
    with Client(stack.api_url) as c:
        with pytest.raises(ApiError) as e:  # no bake yet: a clear 409
            c.render(c.create_scene(SMALL).id, method="ldc", bake={"ldc_resolution": 24})
        assert e.value.status == 409 and "bakes" in e.value.detail

    res = runner.invoke(app, ["bake", str(scene_file), "--ldc-resolution", "24", "--wait", *api])
    assert res.exit_code == 0, res.output
    key = res.stdout.strip().splitlines()[-1]
    assert len(key) == 64
    assert "light field no" in res.stderr and "ldc-axis-2" in res.stderr
    res = runner.invoke(app, ["bake", str(scene_file), "--ldc-resolution", "24", *api])  # now cached
    assert res.exit_code == 0 and "cached" in res.stderr and res.stdout.strip() == key

    out = tmp_path / "ldc.png"
    res = runner.invoke(app, ["render", str(scene_file), "--method", "ldc", "--ldc-resolution", "24", "-o", str(out),
                              *api])
    assert res.exit_code == 0, res.output
    assert "hole pixels" in res.stderr and "warp=" in res.stderr
    img, _meta = read_image(out)
    assert img.shape[:2] == (24, 32)

    res = runner.invoke(app, ["render", str(scene_file), "--method", "ldc+ibrt:9", *api])
    assert res.exit_code == 2 and "method" in res.output

    with Client(stack.api_url) as c:
        sid = c.create_scene(SMALL).id
        listed = c.list_bakes(sid).items
        assert [b.key for b in listed] == [key] and listed[0].state == "finished"
        c.delete_bake(sid, key)
        assert c.list_bakes(sid).items == []
