"""One light model: a relight request's point, directional and rect lights are the scene's, without a
name, with defaults (and a rect light's sampling); the same checks give the same errors."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from api_schemas.datasets import RelightDirectionalLight, RelightPointLight, RelightRectLight
from api_schemas.scene import (
    DirectionalLight,
    DirectionalLightFields,
    PointLight,
    PointLightFields,
    RectLight,
    RectLightFields,
)

BAD = [
    (RectLight, RelightRectLight, {"corner": [0, 0, 0], "edge_u": [1, 0, 0], "edge_v": [-3, 0, 0],
                                   "radiance": [1, 1, 1]}),
    (RectLight, RelightRectLight, {"corner": [0, 0, 0], "edge_u": [0, 0, 0], "edge_v": [0, 0, 0],
                                   "radiance": [1, 1, 1]}),
    (DirectionalLight, RelightDirectionalLight, {"direction": [0, 0, 0], "irradiance": [1, 1, 1]}),
    (PointLight, RelightPointLight, {"position": [0, 0, float("inf")], "intensity": [1, 1, 1]}),
]


@pytest.mark.parametrize(("scene_cls", "relight_cls", "data"), BAD)
def test_scene_and_relight_lights_refuse_the_same_input_the_same_way(scene_cls, relight_cls, data):
    errs = []
    for cls in (scene_cls, relight_cls):
        with pytest.raises(ValidationError) as e:
            cls.model_validate(data)
        errs.append(e.value.errors(include_url=False))
    assert errs[0] == errs[1]


def test_relight_lights_share_the_scene_lights_fields():
    for scene_cls, relight_cls, base in ((PointLight, RelightPointLight, PointLightFields),
                                         (DirectionalLight, RelightDirectionalLight, DirectionalLightFields),
                                         (RectLight, RelightRectLight, RectLightFields)):
        assert issubclass(scene_cls, base) and issubclass(relight_cls, base)
        assert list(scene_cls.model_fields) == [*base.model_fields, "name"]
        assert list(relight_cls.model_fields)[:len(base.model_fields)] == list(base.model_fields)
    assert list(RelightRectLight.model_fields)[-2:] == ["samples", "seed"]


def test_relight_lights_have_defaults_and_no_name():
    assert RelightPointLight.model_validate({"position": [1, 2, 3]}).intensity == (1.0, 1.0, 1.0)
    assert RelightDirectionalLight.model_validate({"direction": [0, -1, 0]}).irradiance == (1.0, 1.0, 1.0)
    with pytest.raises(ValidationError, match="intensity"):
        PointLight.model_validate({"position": [1, 2, 3]})
    with pytest.raises(ValidationError, match="name"):
        RelightPointLight.model_validate({"position": [1, 2, 3], "name": "key"})
