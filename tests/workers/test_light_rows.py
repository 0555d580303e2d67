"""workers.scene_loader.light_rows: the one conversion of schema lights (a scene's and a relight
request's) to the engine's lights."""

from __future__ import annotations

import numpy as np
import pytest

from api_schemas.datasets import RelightRequest
from api_schemas.scene import Scene
from engine.errors import InvalidInputError
from engine.relighting.lights import (
    DirectionalLight,
    EnvironmentLight,
    PointLight,
    RectLight,
    light_from_dict,
    light_table,
)
from engine.scene import LightTable
from workers.scene_loader import light_rows

CAMERA = {"type": "perspective", "eye": [0, 0, 5], "look_at": [0, 0, 0], "width": 4, "height": 4}
RECT = {"type": "rect", "corner": [-1, 2, -1], "edge_u": [2, 0, 0], "edge_v": [0, 0, 2], "radiance": [3, 2, 1],
        "two_sided": True}


def test_relight_lights_become_the_relighting_specs_field_for_field():
    env = np.full((4, 8, 3), 0.5)
    req = RelightRequest.model_validate({"dataset_id": "a" * 64, "lights": [
        {"type": "point", "position": [1, 2, 3], "intensity": [4, 5, 6]},
        {"type": "directional", "direction": [0, -1, 0]},
        {**RECT, "samples": 9, "seed": 7},
        {"type": "environment", "image_sha256": "b" * 64, "n_lights": 12, "method": "importance", "seed": 3,
         "scale": 2.0}]})
    seen = []

    def image(light):
        seen.append(light.image_sha256)
        return env

    specs = [light_from_dict(row) for row in light_rows(req.lights, image)]
    assert seen == ["b" * 64]
    assert specs[0] == PointLight((1.0, 2.0, 3.0), (4.0, 5.0, 6.0))
    assert specs[1] == DirectionalLight((0.0, -1.0, 0.0), (1.0, 1.0, 1.0))
    assert specs[2] == RectLight((-1.0, 2.0, -1.0), (2.0, 0.0, 0.0), (0.0, 0.0, 2.0), (3.0, 2.0, 1.0), True, 9, 7)
    assert isinstance(specs[3], EnvironmentLight) and specs[3].image is env
    assert (specs[3].n_lights, specs[3].method, specs[3].seed, specs[3].scale) == (12, "importance", 3, 2.0)


def test_environment_light_without_an_image_reader_is_refused():
    req = RelightRequest.model_validate({"dataset_id": "a" * 64,
                                         "lights": [{"type": "environment", "image_sha256": "b" * 64}]})
    with pytest.raises(InvalidInputError, match="environment"):
        light_rows(req.lights)


def test_scene_and_relight_lights_give_the_same_light_table():
    """The same three lights, described in a scene and in a relight request: the scene's LightTable
    (from its rows) equals the one the relighting builds from its specs (names aside)."""
    lights = [{"type": "point", "position": [1, 2, 3], "intensity": [4, 5, 6]},
              {"type": "directional", "direction": [0.3, -1, 0.2], "irradiance": [1, 2, 3]}, RECT]
    scene = Scene.model_validate({"camera": CAMERA, "lights": [{**lt, "name": f"l{i}"} for i, lt in
                                                               enumerate(lights)]})
    req = RelightRequest.model_validate({"dataset_id": "a" * 64, "lights": lights})
    from_scene = LightTable.from_rows(light_rows(scene.lights))
    from_specs = light_table([light_from_dict(row) for row in light_rows(req.lights)])
    assert from_scene.names == ("l0", "l1", "l2")
    for f in ("point_position", "point_intensity", "dir_direction", "dir_irradiance", "rect_corner", "rect_edge_u",
              "rect_edge_v", "rect_radiance", "rect_two_sided"):
        assert np.array_equal(getattr(from_scene, f), getattr(from_specs, f)), f
