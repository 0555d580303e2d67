"""The files in examples/ (the README's commands use them; tests/service/test_readme_live.py runs
those commands): the scenes load with their meshes, the broken one fails on exactly the fields
examples/README.md names, the camera path stays inside the walkthrough scene's view space and
animation, and the ball dataset is what examples/ball/SOURCES.md says it is: the shared DiLiGenT
photographs cropped and downscaled, every second light, decoded pixel for pixel."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pydantic
import pytest

from api_schemas import format_validation_error, load_scene_file
from api_schemas.datasets import DatasetManifest
from engine.imageio import read_image
from service.client import read_dataset_dir, with_sha256s
from tests.service.api.test_datasets import diligent_ball

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


@pytest.mark.parametrize("name", ["spheres", "pyramid"])
def test_example_scenes_load_with_their_meshes(name: str) -> None:
    from workers.scene_loader import directory_resolver, load_scene

    path = EXAMPLES / "scenes" / f"{name}.json"
    loaded = load_scene(load_scene_file(path), directory_resolver(path.parent))
    assert loaded.runtime.n_triangles > 0
    if name == "pyramid":  # the OBJ's six faces, read from the file next to the scene
        assert [r["n_faces_out"] for r in loaded.mesh_reports] == [6]


def test_broken_example_fails_on_the_fields_the_readme_names() -> None:
    with pytest.raises(pydantic.ValidationError) as e:
        load_scene_file(EXAMPLES / "scenes" / "broken.json")
    assert {err["field"] for err in format_validation_error(e.value)} == {"camera.width", "objects.0.radius"}


def test_walkthrough_path_stays_in_the_view_space_and_the_animation() -> None:
    scene = load_scene_file(EXAMPLES / "walkthrough" / "room.json")
    assert scene.view_space is not None and scene.animation is not None
    frames = json.loads((EXAMPLES / "walkthrough" / "path.json").read_text())
    assert len(frames) >= 2
    sizes = {(f["camera"]["width"], f["camera"]["height"]) for f in frames}
    assert len(sizes) == 1 and all(v % 2 == 0 for v in next(iter(sizes)))  # one even size (the MP4 needs it)
    for f in frames:
        assert scene.view_space.distance(f["camera"]["eye"]) <= 1e-9, f
        assert scene.animation.start <= f["time"] <= scene.animation.end, f
    times = [f["time"] for f in frames]
    assert times == sorted(times) and times[0] == scene.animation.start and times[-1] == scene.animation.end


def test_ball_dataset_is_the_stated_derivation_of_diligent() -> None:
    manifest, files = read_dataset_dir(EXAMPLES / "ball")
    DatasetManifest.model_validate(with_sha256s(manifest, files))
    source_manifest, _, source_linear = diligent_ball()  # from ../shared/data/diligent-ball
    every_second = source_manifest["images"][::2]
    assert len(manifest["images"]) == len(every_second) == 48
    for img, src in zip(manifest["images"], every_second, strict=True):
        assert img == src  # file name, direction toward the light, RGB intensity
        shipped, _ = read_image(EXAMPLES / "ball" / img["file"], transfer="linear")
        # the same 16-bit codes (the float values differ in the last bit between the two decodings)
        np.testing.assert_array_equal(np.round(shipped * 65535.0), np.round(source_linear[img["file"]] * 65535.0))
    assert {k: v for k, v in manifest.items() if k != "images"} == {
        k: v for k, v in source_manifest.items() if k != "images"}
    mask = read_image(EXAMPLES / "ball" / "mask.png", transfer="linear")[0][:, :, 0] > 0.5
    depth = read_image(EXAMPLES / "ball" / "depth.exr")[0][:, :, 0]
    assert mask.shape == depth.shape == (40, 40)
    assert np.all(depth[mask] > 0) and not np.any(depth[~mask])
    assert sum(p.stat().st_size for p in (EXAMPLES / "ball").iterdir()) < 1_000_000
