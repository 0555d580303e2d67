"""The bake request's indirect settings against the engine's: the API's ranges and defaults are the
engine's ``IndirectParams`` (the API process cannot import it); what the worker derives from them
(the engine's settings, the light field's indirect paths, the plan's estimates) follows the request."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pydantic import ValidationError

from api_schemas.scene import Scene
from api_schemas.service import INDIRECT_RANGES, BakeParams, IndirectBakeParams
from engine.newviews.indirect import IndirectParams
from tests.workers.queue.jobs_for_tests import tiny_scene


def test_ranges_and_defaults_are_the_engines() -> None:
    for name, rng in INDIRECT_RANGES.items():
        assert IndirectParams.RANGES[name] == rng, name
    engine_defaults = {f.name: f.default for f in dataclasses.fields(IndirectParams)}
    api = IndirectBakeParams()
    for name in [*INDIRECT_RANGES, "sampling", "caustics"]:
        assert getattr(api, name) == engine_defaults[name], name


@pytest.mark.parametrize(("field", "value"), [("noise", 0.0005), ("noise", 0.6), ("bounces", 0), ("bounces", 17),
                                              ("max_paths", 70000), ("round_paths", 512),
                                              ("stride", 0), ("stride", 9)])
def test_out_of_range_names_the_range(field: str, value: float) -> None:
    lo, hi = INDIRECT_RANGES[field]
    with pytest.raises(ValidationError) as e:
        BakeParams.model_validate({"indirect": {field: value}})
    err = e.value.errors()[0]
    assert err["loc"] == ("indirect", field) and f"[{lo}, {hi}]" in err["msg"], err


def test_combinations_the_engine_refuses_are_refused_up_front() -> None:
    """Every accepted combination constructs the engine's class; the refused ones say why."""
    from workers.jobs.bake import indirect_params

    for bad, words in [({"round_paths": 3}, "power of two"), ({"min_paths": 36}, "multiple of round_paths"),
                       ({"round_paths": 16, "min_paths": 16}, "at least 32"),
                       ({"min_paths": 64, "max_paths": 48}, "at least min_paths")]:
        with pytest.raises(ValidationError, match=words):
            BakeParams.model_validate({"indirect": bad})
    ok = BakeParams.model_validate({"seed": 7, "indirect": {"noise": 0.01, "min_paths": 4, "max_paths": 4,
                                                            "round_paths": 2, "bounces": 5, "stride": 2}})
    ip = indirect_params(ok)
    assert ip is not None and (ip.noise, ip.min_paths, ip.max_paths, ip.round_paths, ip.bounces, ip.stride,
                               ip.seed) == (0.01, 4, 4, 2, 5, 2, 7)
    assert indirect_params(BakeParams.model_validate({"indirect": {"mode": "off"}})) is None


def _mirror_room() -> Scene:
    doc = tiny_scene().model_dump(mode="json")
    doc["materials"][0] = {"name": "m", "kd": [0.0, 0.0, 0.0], "kr": [0.9, 0.9, 0.9]}
    doc["objects"].append({"type": "box", "center": [1.6, 0.6, 0], "size": [0.4, 1.2, 1.2], "material": "floor"})
    return Scene.model_validate(doc)


def test_light_field_views_carry_indirect_light_when_the_bake_does() -> None:
    """The LLF's radiance is the reference renderer's with ``indirect_samples = min_paths`` paths of
    ``bounces`` bounces when the bake has indirect light: a mirror sphere reflecting a floor lit
    directly and by a box beside it is brighter in every view than with indirect light off (the
    added light is non-negative, and positive where the floor sees the box)."""
    from engine.newviews.effects import analyze
    from engine.newviews.llf import bake_llf_views
    from engine.raycast import make_caster
    from workers.jobs.bake import _reference_params, bake_plan_doc
    from workers.scene_loader import load_scene

    rt = load_scene(_mirror_room(), lambda p: (b"", "")).runtime
    plan = analyze(rt)
    assert not plan.indirect_skip and plan.needs_llf
    on = BakeParams.model_validate({"llf_params": {"area_light_samples": 1, "glossy_samples": 1},
                                    "indirect": {"min_paths": 8, "round_paths": 4, "bounces": 2}})
    off = BakeParams.model_validate({**on.model_dump(), "indirect": {"mode": "off"}})
    p_on, p_off = (_reference_params(b, bake_plan_doc(rt, b, plan)) for b in (on, off))
    assert (p_on.indirect_samples, p_on.indirect_bounces, p_off.indirect_samples) == (8, 2, 0)
    assert bake_plan_doc(rt, on, plan)["indirect"]["llf_indirect_samples"] == 8
    caster = make_caster(rt, "embree")
    views = {name: bake_llf_views(rt, caster, 1, 12, [0, 2], params=p, max_layers=4)
             for name, p in (("on", p_on), ("off", p_off))}
    for v_on, v_off in zip(views["on"], views["off"], strict=True):
        assert np.array_equal(v_on.ldi.depth, v_off.ldi.depth)
        diff = v_on.radiance.astype(np.float64) - v_off.radiance
        assert diff.min() >= -1e-6 and diff.sum() > 0.01 * max(float(v_off.radiance.sum()), 1e-9), (
            diff.sum(), float(v_off.radiance.sum()))
