"""``RenderRequest.view``: how an LDC method renders the view (antialiasing). Its ranges come from
the method registry, it is refused where it means nothing, a render at the default keeps the key it
had before the field existed, and the render's memory estimate counts its sub-pixels."""

from __future__ import annotations

from typing import get_args

import pytest
from pydantic import ValidationError

from api_schemas.service import Antialias, LDCViewParams, RenderRequest
from engine import ENGINE_VERSION
from engine.methods import ANTIALIAS_MODES, SUPERSAMPLE
from producer.artifacts import artifact_key
from producer.costs import estimate_render_bytes
from producer.renders import render_artifact_key, render_params

SID = "b" * 64


def test_the_view_params_are_the_registrys() -> None:
    assert set(get_args(Antialias)) == set(ANTIALIAS_MODES)
    assert LDCViewParams() == LDCViewParams(supersample=SUPERSAMPLE.default, antialias="edges")
    schema = LDCViewParams.model_json_schema()["properties"]["supersample"]
    assert (schema["minimum"], schema["maximum"]) == (SUPERSAMPLE.low, SUPERSAMPLE.high)


@pytest.mark.parametrize("view,needle", [({"supersample": 0}, "greater than or equal to 1"),
                                         ({"supersample": 5}, "less than or equal to 4"),
                                         ({"supersample": 2.5}, "integer"),
                                         ({"antialias": "everywhere"}, "'edges' or 'uniform'")])
def test_out_of_range_view_params_name_the_range(view: dict, needle: str) -> None:
    with pytest.raises(ValidationError) as exc:
        RenderRequest.model_validate({"scene_id": SID, "method": "ldc", "view": view})
    assert needle in str(exc.value) and exc.value.errors()[0]["loc"][0] == "view"


def test_view_is_refused_with_the_reference_renderer() -> None:
    for method in ({}, {"method": "reference"}):
        with pytest.raises(ValidationError, match="leave out view") as exc:
            RenderRequest.model_validate({"scene_id": SID, **method, "view": {"supersample": 2}})
        assert exc.value.errors()[0]["loc"] == ("view",)
    for method in ("ldc", "ldc+llf", "ldc+ibrt:2"):
        req = RenderRequest.model_validate({"scene_id": SID, "method": method,
                                            "view": {"supersample": 3, "antialias": "uniform"}})
        assert req.view == LDCViewParams(supersample=3, antialias="uniform")


def test_the_default_view_keeps_the_key_and_any_other_makes_its_own() -> None:
    plain = RenderRequest(scene_id=SID, method="ldc+llf")
    before = plain.model_dump(mode="json", exclude={"scene_id", "missing_bake", "quality", "outputs", "params",
                                                     "view"})
    assert render_artifact_key(plain) == artifact_key("render", {"scene": SID}, before, ENGINE_VERSION)
    assert render_artifact_key(RenderRequest.model_validate({"scene_id": SID, "method": "ldc+llf",
                                                             "view": {"supersample": 1}})) == render_artifact_key(plain)
    keys = {render_artifact_key(RenderRequest.model_validate({"scene_id": SID, "method": "ldc+llf", "view": v}))
            for v in ({"supersample": 2}, {"supersample": 4}, {"supersample": 4, "antialias": "uniform"})}
    assert len(keys) == 3 and render_artifact_key(plain) not in keys
    assert render_params(RenderRequest.model_validate({"scene_id": SID, "method": "ldc",
                                                       "view": {"supersample": 2}}))["view"] == {
        "supersample": 2, "antialias": "edges"}
    assert "view" not in render_params(RenderRequest(scene_id=SID))  # the reference has none


def test_the_memory_estimate_counts_the_sub_pixels() -> None:
    plain = RenderRequest(scene_id=SID, method="ldc")
    x4 = RenderRequest.model_validate({"scene_id": SID, "method": "ldc", "view": {"supersample": 4}})
    fixed = estimate_render_bytes(plain, 1, 1)
    one, four = estimate_render_bytes(plain, 512, 512) - fixed, estimate_render_bytes(x4, 512, 512) - fixed
    assert four == pytest.approx(16 * one, rel=1e-3)  # 4 x 4 sub-pixels per pixel, the fixed part once


def test_glossy_rays_need_a_traced_method_and_key_their_render() -> None:
    for method in ("ldc", "ldc+llf", "ldc+ibrt:0"):
        with pytest.raises(ValidationError, match="glossy_rays traces image-based rays") as exc:
            RenderRequest.model_validate({"scene_id": SID, "method": method, "view": {"glossy_rays": 16}})
        assert exc.value.errors()[0]["loc"] == ("view", "glossy_rays")
    for view, needle in (({"glossy_rays": 257}, "less than or equal to 256"), ({"glossy_filter": 9}, "less than"),
                         ({"glossy_rays": -1}, "greater than or equal to 0")):
        with pytest.raises(ValidationError, match=needle):
            RenderRequest.model_validate({"scene_id": SID, "method": "ldc+ibrt:1", "view": view})
    plain = RenderRequest(scene_id=SID, method="ldc+ibrt:1")
    traced = RenderRequest.model_validate({"scene_id": SID, "method": "ldc+ibrt:1", "view": {"glossy_rays": 16}})
    unfiltered = RenderRequest.model_validate({"scene_id": SID, "method": "ldc+ibrt:1",
                                               "view": {"glossy_rays": 16, "glossy_filter": 0}})
    assert len({render_artifact_key(r) for r in (plain, traced, unfiltered)}) == 3
    assert render_params(traced)["view"] == {"supersample": 1, "antialias": "edges", "glossy_rays": 16,
                                             "glossy_filter": 3}
    # without traced rays the filter means nothing; "auto" is the default and keeps the plain key
    gathered = [RenderRequest.model_validate({"scene_id": SID, "method": "ldc+ibrt:1", "view": v})
                for v in ({"glossy_rays": 0}, {"glossy_rays": 0, "glossy_filter": 5})]
    assert render_artifact_key(gathered[0]) == render_artifact_key(gathered[1]) != render_artifact_key(plain)
    assert render_params(gathered[1])["view"] == {"supersample": 1, "antialias": "edges", "glossy_rays": 0}
    assert render_artifact_key(RenderRequest.model_validate(
        {"scene_id": SID, "method": "ldc+ibrt:1", "view": {"glossy_rays": "auto"}})) == render_artifact_key(plain)
    # "auto" is no request for rays: any LDC method takes it
    for method in ("ldc", "ldc+llf"):
        RenderRequest.model_validate({"scene_id": SID, "method": method, "view": {"glossy_rays": "auto"}})


def test_the_cost_counts_the_glossy_rays() -> None:
    from producer.costs import render_cost

    plain = RenderRequest(scene_id=SID, method="ldc+ibrt:1", view={"glossy_rays": 0})
    traced = RenderRequest.model_validate({"scene_id": SID, "method": "ldc+ibrt:1", "view": {"glossy_rays": 16}})
    auto = RenderRequest(scene_id=SID, method="ldc+ibrt:1")
    assert render_cost(traced, 512, 512).cpu_s > render_cost(plain, 512, 512).cpu_s + 16 * 512 * 512 * 1e-6
    # "auto" is priced by what it means for the scene
    assert render_cost(auto, 512, 512, auto_glossy_rays=0).cpu_s == render_cost(plain, 512, 512).cpu_s
    assert render_cost(auto, 512, 512, auto_glossy_rays=16).cpu_s == render_cost(traced, 512, 512).cpu_s


def test_auto_glossy_rays_of_a_scene() -> None:
    from api_schemas import load_scene_file
    from producer.costs import scene_auto_glossy_rays
    from samples import sample_path

    assert scene_auto_glossy_rays(load_scene_file(sample_path("cornell_mirror_glossy"))) == 16
    for name in ("cornell_box", "mirror_box", "teapot_glossy"):  # no glossy, no rect light, no mirror
        assert scene_auto_glossy_rays(load_scene_file(sample_path(name))) == 0, name
