"""``ibr datasets ...``, ``ibr relight`` and the Python client's dataset / relight calls against a live
local stack (``ibr up``'s start_stack: embedded Redis, real bake and render workers, uvicorn API), on a
tiny real dataset: 12 photographs of DiLiGenT's ball cropped to 40x40 (tests/service/api/test_datasets.py)."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from engine.imageio import read_image
from service.cli import app
from service.client import ApiError, Client, read_dataset_dir, with_sha256s
from tests.service.api.test_datasets import diligent_ball, subset

# Everyday runs skip this file (make test-fast): the whole service started as processes, driven through the CLI.
pytestmark = pytest.mark.slow


def _dataset_dir(root: Path, k: int = 12, drop: tuple[int, ...] = ()) -> tuple[Path, dict[str, Any]]:
    manifest, files = subset(k, drop)
    root.mkdir(parents=True, exist_ok=True)
    (root / "manifest.json").write_text(json.dumps(manifest))
    for name, data in files.items():
        (root / name).write_bytes(data)
    return root, manifest


def test_dataset_upload_relight_from_the_command_line(stack: Any, tmp_path: Path) -> None:
    runner = CliRunner()
    api = ["--api", stack.api_url]
    ddir, manifest = _dataset_dir(tmp_path / "ball")

    # resumable upload (the default) with the files read next to the manifest; multipart gives the same id
    res = runner.invoke(app, ["datasets", "upload", str(ddir), *api])
    assert res.exit_code == 0, res.output
    did = res.stdout.strip().splitlines()[-1]
    assert len(did) == 64 and "12 images 40x40, distant lights" in res.stderr
    res = runner.invoke(app, ["datasets", "upload", str(ddir / "manifest.json"), "--multipart", *api])
    assert res.exit_code == 0, res.output
    assert res.stdout.strip().splitlines()[-1] == did
    res = runner.invoke(app, ["datasets", "list", *api])
    assert res.exit_code == 0 and did in res.stdout and "images=12" in res.stdout
    res = runner.invoke(app, ["datasets", "show", did, *api])
    assert res.exit_code == 0 and json.loads(res.stdout)["n_images"] == 12

    # relight under dataset light 3 (directional: the direction it travels is minus the direction toward
    # it): not baked yet, so the CLI bakes first (float32 store), then the stored image comes back
    img3 = manifest["images"][3]
    toward = img3["direction"]
    spec = json.dumps({"type": "directional", "direction": [-x for x in toward], "irradiance": img3["intensity"]})
    out, outside = tmp_path / "relit.exr", tmp_path / "outside.png"
    res = runner.invoke(app, ["relight", did, "--light", spec, "--no-half", "-o", str(out), "--outside",
                              str(outside), *api])
    assert res.exit_code == 0, res.output
    assert "not baked" in res.stderr and "exact: True" in res.stderr and "n_outside=0" in res.stderr
    relit, _ = read_image(out)
    truth = diligent_ball()[2][img3["file"]]
    mask = read_image(ddir / "mask.png", transfer="linear")[0][:, :, 0] > 0.5
    # the photograph itself (up to one float32 ulp: the upload's linearisation is float64 here)
    np.testing.assert_allclose(relit[mask], truth[mask], rtol=1e-6, atol=1e-7)
    assert not np.any(relit[~mask])
    assert read_image(outside, transfer="linear")[0].max() == 0.0
    # the bake exists now: 'datasets bake' answers at once (cached) with the same key
    res = runner.invoke(app, ["datasets", "bake", did, "--no-half", *api])
    assert res.exit_code == 0 and "(cached)" in res.stderr and "n_lights=12" in res.stderr

    # shorthand lights, superposed; without --bake-missing a dataset baked otherwise is a 409 -> exit 2
    png = tmp_path / "two.png"
    res = runner.invoke(app, ["relight", did, "--light", "directional:0.2,-0.3,-1:2", "--light",
                              "point:10,5,300:90000", "--no-half", "-o", str(png), *api])
    assert res.exit_code == 0, res.output
    assert png.read_bytes()[:4] == b"\x89PNG"
    # an environment map (uploaded by the CLI) and a lights file, superposed
    from tests.service.api.test_datasets import write_bytes

    sky = tmp_path / "sky.exr"
    sky.write_bytes(write_bytes(np.full((8, 16, 3), 0.5, np.float32), ".exr", "float"))
    (tmp_path / "lights.json").write_text(json.dumps({"lights": [json.loads(spec)]}))  # dataset light 3 again
    res = runner.invoke(app, ["relight", did, "--light", f"env:{sky}:8", "--lights", str(tmp_path / "lights.json"),
                              "--no-half", "-o", str(tmp_path / "env.exr"), *api])
    assert res.exit_code == 0, res.output
    assert "n_lights_expanded=9" in res.stderr, res.stderr
    # the sky's 8 directions all lie outside the 12 lights' narrow cone: counted, never extrapolated
    assert f"n_outside={int(mask.sum())}" in res.stderr
    np.testing.assert_allclose(read_image(tmp_path / "env.exr")[0][mask], relit[mask], rtol=1e-6, atol=1e-7)
    res = runner.invoke(app, ["relight", did, "--light", f"env:{tmp_path / 'nope.exr'}", *api])
    assert res.exit_code == 2 and "nope.exr" in res.output
    res = runner.invoke(app, ["relight", did, "--light", "directional:0,0,-1", "--layout", "tiled",
                              "--fail-missing", *api])
    assert res.exit_code == 2 and "dataset_id" in res.output and "not baked" in res.output

    # bad input: exit 2 naming the field (server side) or the option / file (client side)
    res = runner.invoke(app, ["relight", did, "--light", '{"type": "point", "position": [0, 0]}', "--no-half", *api])
    assert res.exit_code == 2 and "lights.0.position" in res.output
    res = runner.invoke(app, ["relight", did, "--light", "spot:1,2,3", *api])
    assert res.exit_code == 2 and "--light #1" in res.output
    res = runner.invoke(app, ["relight", did, *api])
    assert res.exit_code == 2 and "--light" in res.output
    dup = dict(manifest["images"][2], direction=manifest["images"][0]["direction"])
    bad = dict(manifest, images=[*manifest["images"][:2], dup])
    (ddir / "bad.json").write_text(json.dumps(bad))
    res = runner.invoke(app, ["datasets", "upload", str(ddir / "bad.json"), *api])
    assert res.exit_code == 2 and "manifest.images.2.direction" in res.output and "duplicates" in res.output
    (ddir / "missing.json").write_text(json.dumps(dict(manifest, mask={"file": "nope.png"})))
    res = runner.invoke(app, ["datasets", "upload", str(ddir / "missing.json"), *api])
    assert res.exit_code == 2 and "mask.file" in res.output and "nope.png" in res.output
    res = runner.invoke(app, ["datasets", "show", "0" * 64, *api])
    assert res.exit_code == 2

    res = runner.invoke(app, ["datasets", "delete", did, *api])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["datasets", "list", *api])
    assert did not in res.stdout


def test_client_resumable_upload_and_relight(stack: Any, tmp_path: Path) -> None:
    ddir, manifest = _dataset_dir(tmp_path / "ball", k=20, drop=tuple(range(12)))  # images 12..19
    m, files = read_dataset_dir(ddir)
    with Client(stack.api_url) as c:
        # an interrupted upload: two files went through before; the resumed one sends only the rest
        full = with_sha256s(m, files)
        first = c.dataset_upload_status(full)
        assert first.state == "pending" and len(first.missing) >= 8  # (+ depth and mask unless stored before)
        for item in first.missing[:2]:
            assert c.upload_file(files[item.name]).sha256 == item.sha256
        sent: list[str] = []
        ds = c.upload_dataset_resumable(m, files, on_progress=lambda done, total, name: sent.append(name))
        assert ds.id == first.dataset_id and ds.n_images == 8
        assert len(sent) == len(first.missing) - 2 and not {i.name for i in first.missing[:2]} & set(sent)
        assert c.upload_dataset_resumable(m, files).id == ds.id  # committed: nothing sent

        with pytest.raises(ApiError) as e:  # not baked: 409 naming dataset_id
            c.relight(ds.id, [{"type": "directional", "direction": [0, 0, -1]}])
        assert e.value.status == 409 and e.value.errors[0]["field"] == "dataset_id"
        bake = c.wait_dataset_bake(c.bake_dataset(ds.id))
        assert bake.artifact is not None and bake.artifact.result["counts"]["n_lights"] == 8
        seen: list[Any] = []
        rel = c.wait_relight(c.relight(ds.id, [{"type": "directional", "direction": [0, 0, -1]}]),
                             on_progress=seen.append)
        assert rel.result["counts"]["n_outside"] >= 0
        assert c.download_relight(rel.key, "png")[:4] == b"\x89PNG"
        assert c.download_relight(rel.key, "exr")[:4] == b"v/1\x01"
        assert c.download_relight(rel.key, "outside")[:4] == b"\x89PNG"
        got = c.download_dataset_file(ds.id, ds.manifest.images[0].sha256 or "")
        assert got == files[manifest["images"][0]["file"]].read_bytes()
        assert ds.id in {d.id for d in c.list_datasets().items}
        c.delete_dataset(ds.id)
        with pytest.raises(ApiError) as e:
            c.get_dataset(ds.id)
        assert e.value.status == 404


def test_generate_bake_composite_from_the_command_line(stack: Any, tmp_path: Path) -> None:
    """Object (sphere on a floor) and background (the floor alone) datasets generated from scenes with the
    same lights, baked, and the object composited into a grey plate: object pixels are the relit object,
    the plate is darkened in the sphere's shadow."""
    from tests.service.api.conftest import small_scene
    from tests.service.api.test_datasets import write_bytes

    runner = CliRunner()
    api = ["--api", stack.api_url]
    scene = small_scene()
    floor = small_scene(objects=[o for o in scene["objects"] if o["type"] == "plane"])
    params = json.dumps({"spp": 1, "max_depth": 1, "glossy_samples": 1, "area_light_samples": 1, "seed": 3})
    ids = []
    for name, sc in (("object", scene), ("floor", floor)):
        f = tmp_path / f"{name}.json"
        f.write_text(json.dumps(sc))
        res = runner.invoke(app, ["datasets", "generate", str(f), "--region", "hemisphere", "--spacing", "30",
                                  "--center", "0,0.5,0", "--radius", "3", "--params", params, *api])
        assert res.exit_code == 0, res.output
        ids.append(res.stdout.strip().splitlines()[-1])
        res = runner.invoke(app, ["datasets", "bake", ids[-1], *api])
        assert res.exit_code == 0, res.output
    obj_id, bg_id = ids
    res = runner.invoke(app, ["datasets", "generate", str(tmp_path / "object.json"), "--region", "hemisphere",
                              "--spacing", "30", "--center", "0,0.5", *api])
    assert res.exit_code == 2 and "--center" in res.output
    with Client(stack.api_url) as c:  # a stored scene given by id, its camera resized (GET .../document)
        sid = c.create_scene(floor).id
    res = runner.invoke(app, ["datasets", "generate", sid, "--region", "hemisphere", "--spacing", "45",
                              "--center", "0,0.5,0", "--radius", "3", "--params", params, "--width", "12",
                              "--height", "8", *api])
    assert res.exit_code == 0, res.output
    with Client(stack.api_url) as c:
        small = c.get_dataset(res.stdout.strip().splitlines()[-1])
        assert (small.width, small.height) == (12, 8)
    with Client(stack.api_url) as c:
        obj_ds, bg_ds = c.get_dataset(obj_id), c.get_dataset(bg_id)
        assert obj_ds.source["kind"] == "generated" and obj_ds.n_images == bg_ds.n_images > 10
        depth = [read_image_bytes(c.download_dataset_file(d.id, getattr(d.manifest.geometry, "sha256", "")))
                 for d in (obj_ds, bg_ds)]
    obj_mask = np.abs(depth[0][:, :, 0] - depth[1][:, :, 0]) > 1e-4
    assert 10 < obj_mask.sum() < obj_mask.size // 2
    plate, mask = tmp_path / "plate.exr", tmp_path / "mask.exr"
    plate.write_bytes(write_bytes(np.full((16, 24, 3), 0.25, np.float32), ".exr", "float"))
    mask.write_bytes(write_bytes(obj_mask.astype(np.float32), ".exr", "float"))
    light = "point:1.5,2.5,1.0:9"
    out = tmp_path / "comp.exr"
    res = runner.invoke(app, ["composite", "--object", obj_id, "--background", bg_id, "--plate", str(plate),
                              "--mask", str(mask), "--margin", "6", "--light", light, "-o", str(out), *api])
    assert res.exit_code == 0, res.output
    assert f"n_object={int(obj_mask.sum())}" in res.stderr
    comp, _ = read_image(out)
    relit = tmp_path / "relit.exr"
    res = runner.invoke(app, ["relight", obj_id, "--light", light, "-o", str(relit), *api])
    assert res.exit_code == 0, res.output
    assert np.array_equal(comp[obj_mask], read_image(relit)[0][obj_mask])
    assert comp[~obj_mask].min() < 0.25 * 0.9 and comp[~obj_mask].max() == pytest.approx(0.25)
    res = runner.invoke(app, ["composite", "--object", obj_id, "--background", "4" * 64, "--plate", str(plate),
                              "--mask", str(mask), "--light", light, *api])
    assert res.exit_code == 2


def read_image_bytes(data: bytes) -> np.ndarray:
    with tempfile.NamedTemporaryFile(suffix=".exr") as f:
        f.write(data)
        f.flush()
        return read_image(f.name, transfer="linear")[0]
