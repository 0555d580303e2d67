"""Walkthrough bases with converged indirect light: the traced cube reaches its noise target
against an independent high-sample reference render of the same base view, bakes are
deterministic, and the noise target's range is checked (engine and API schema)."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pydantic
import pytest

from api_schemas.scene import load_scene_json
from api_schemas.walkthrough import INDIRECT_MAX_PATHS_RANGE, INDIRECT_NOISE_RANGE, WalkthroughSettings
from engine.errors import InvalidInputError
from engine.metrics import REC709_WEIGHTS
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.sampler import sample_key
from engine.walkthrough import bake as wbake
from engine.walkthrough.bake import WalkthroughParams, render_bases, walkthrough_preset
from engine.walkthrough.range_images import face_camera, trace_cube_indirect
from workers.scene_loader import load_animated_scene

Y = np.asarray(REC709_WEIGHTS, np.float64)


def room_doc() -> dict:
    """A closed 4 x 3 x 4 room (seen from inside: surfaces are two-sided) with a red block, lit by
    one point light: every base pixel sees a surface, and much of the light is interreflected."""
    return {
        "camera": {"type": "perspective", "eye": [0, 0, 0], "look_at": [0, 0, 1], "width": 8, "height": 8},
        "materials": [{"name": "white", "kd": [0.75, 0.75, 0.7]}, {"name": "red", "kd": [0.7, 0.15, 0.1]}],
        "objects": [
            {"type": "box", "name": "room", "material": "white", "center": [0, 0, 0], "size": [4, 3, 4]},
            {"type": "box", "name": "block", "material": "red", "center": [1, -1, 1], "size": [1, 1, 1]},
        ],
        "lights": [{"type": "point", "name": "key", "position": [-1, 1, -1], "intensity": [8, 8, 8]}],
        "view_space": {"type": "path", "points": [[-0.5, 0, -0.5], [0.5, 0, -0.5]]},
    }


@pytest.fixture(scope="module")
def room():
    return load_animated_scene(load_scene_json(json.dumps(room_doc())))


RES = 6
EYE = np.array([-0.3, 0.2, -0.4])


def reference_indirect(rr: ReferenceRenderer, k: int, seed: int) -> np.ndarray:
    """The indirect part of the base cube by the reference renderer's own camera paths: at the
    pixel centres (1 spp, no jitter), a render with k indirect paths per pixel minus the same
    render without them (same seed: on diffuse surfaces the difference is exactly the path-traced
    part)."""
    out = np.zeros((6, RES, RES, 3))
    for f in range(6):
        cam = face_camera(EYE, f, RES)
        base = ReferenceParams(spp=1, pixel_jitter=False, area_light_samples=1, indirect_bounces=2, seed=seed)
        full = rr.render(cam, ReferenceParams(**{**base.to_dict(), "indirect_samples": k}))
        direct = rr.render(cam, base)
        out[f] = full.radiance.astype(np.float64) - direct.radiance
    return out


@pytest.mark.slow
def test_converged_cube_reaches_its_noise_target(room) -> None:
    rr = ReferenceRenderer(room.scene_at(0.0))
    direct = np.stack([rr.render(face_camera(EYE, f, RES), ReferenceParams(spp=1, pixel_jitter=False,
                                                                            area_light_samples=1)).radiance
                       for f in range(6)])
    noise = 0.03
    # the adaptive sampler (the bases trace a fixed count, checked at the end; the adaptive one is
    # what a converged frame uses, engine/walkthrough/ground_truth.py)
    params = replace(WalkthroughParams(face_res=RES, indirect_res_div=1, spp=1, area_light_samples=1,
                                       indirect_noise=noise, indirect_max_paths=65536,
                                       indirect_bounces=2).indirect_params(), sampling="adaptive")
    cube = trace_cube_indirect(rr, EYE, RES, direct, params, key=sample_key(7, 5, 0))
    # the pilot sizes each pixel's estimate with a margin: the median pixel meets the target, most do,
    # and the rest land near it (measured: median 0.026, p95 0.046, 66 % met)
    st = cube.stats
    assert st["rel_stderr_median"] <= noise and st["met_target"] >= 0.6 and st["rel_stderr_p95"] <= 2 * noise
    assert cube.paths.min() >= 128  # every pixel sees the room

    # an independent high-sample estimate of the same base view, twice (its own noise measured)
    k = 8192
    ref_a, ref_b = reference_indirect(rr, k, 11), reference_indirect(rr, k, 12)
    ref = 0.5 * (ref_a + ref_b)
    y_dir = direct.reshape(-1, 3).astype(np.float64) @ Y
    y_ind = cube.radiance.reshape(-1, 3).astype(np.float64) @ Y
    bright = np.maximum(y_dir + y_ind, wbake.INDIRECT_FLOOR * y_dir.mean())  # what the target is relative to
    e_ref = (ref_a - ref_b).reshape(-1, 3) @ Y / 2.0 / bright  # the averaged reference's own error
    ref_noise = float(np.sqrt(np.mean(e_ref ** 2)))
    assert ref_noise < noise / 2, ref_noise  # the reference is good enough to judge the target
    err = (y_ind - ref.reshape(-1, 3) @ Y) / bright
    rms = float(np.sqrt(np.mean(err ** 2)))
    # the target bounds each pixel's standard error: the RMS error over 216 pixels stays below it
    # (plus the reference's share), with a margin for the estimate of the standard error itself
    assert rms <= 1.25 * math.hypot(noise, ref_noise), (rms, ref_noise)
    # and the errors are that size, not far smaller (the stopping rule does not waste paths)
    assert rms >= 0.2 * noise, rms
    # no bias: the mean error is within a few standard errors of zero
    assert abs(float(err.mean())) <= 4.0 * math.hypot(noise, ref_noise) / math.sqrt(err.size)
    # each pixel's own estimated standard error describes its error (estimated from 8 round means:
    # a t distribution with 7 degrees of freedom, 2 % beyond 3 sigma, 0.01 % beyond 8)
    z = np.abs(err) / np.sqrt((cube.stderr.reshape(-1) / bright) ** 2 + ref_noise ** 2)
    assert float(np.mean(z > 3.0)) <= 0.05 and float(z.max()) <= 8.0, (float(np.mean(z > 3.0)), float(z.max()))
    # a target of four times the noise traces fewer paths and reaches a larger error
    loose = trace_cube_indirect(rr, EYE, RES, direct, replace(WalkthroughParams(
        face_res=RES, indirect_res_div=1, spp=1, area_light_samples=1, indirect_noise=4 * noise,
        indirect_max_paths=65536).indirect_params(), sampling="adaptive"), key=sample_key(7, 5, 0))
    assert loose.paths.sum() < cube.paths.sum() / 2
    err_loose = (loose.radiance.reshape(-1, 3).astype(np.float64) @ Y - ref.reshape(-1, 3) @ Y) / bright
    assert float(np.sqrt(np.mean(err_loose ** 2))) > rms

    # the bases' own sampler: (0.32 / 0.03)^2 -> 128 paths on every pixel, unbiased, and each
    # pixel's estimated standard error describes its error as well
    fixed = trace_cube_indirect(rr, EYE, RES, direct, WalkthroughParams(
        face_res=RES, indirect_res_div=1, spp=1, area_light_samples=1, indirect_noise=noise,
        indirect_max_paths=65536, indirect_bounces=2).indirect_params(), key=sample_key(7, 5, 0))
    assert np.all(fixed.paths == 128) and fixed.stats["sampling"] == "fixed"
    err_f = (fixed.radiance.reshape(-1, 3).astype(np.float64) @ Y - ref.reshape(-1, 3) @ Y) / bright
    rms_f = float(np.sqrt(np.mean(err_f ** 2)))
    assert abs(float(err_f.mean())) <= 4.0 * math.hypot(rms_f, ref_noise) / math.sqrt(err_f.size)
    z_f = np.abs(err_f) / np.sqrt((fixed.stderr.reshape(-1) / bright) ** 2 + ref_noise ** 2)
    assert float(np.mean(z_f > 3.0)) <= 0.05 and float(z_f.max()) <= 8.0


def test_bases_are_deterministic_and_report_their_noise(room) -> None:
    params = WalkthroughParams(face_res=8, indirect_res_div=2, spp=1, area_light_samples=1, indirect_samples=1,
                               indirect_noise=0.1, indirect_max_paths=256)
    views = [[-0.5, 0.0, -0.5], [0.5, 0.0, -0.5]]
    a = render_bases(room, views, [0.0], [0.0], params)
    b = render_bases(room, views, [0.0], [0.0], params)
    np.testing.assert_array_equal(a.indirect, b.indirect)
    np.testing.assert_array_equal(a.direct, b.direct)
    assert a.indirect.shape == (2, 1, 6, 8, 8, 3) and a.indirect.min() >= 0.0 and a.indirect.max() > 0.0
    # traced at face_res / 2 and repeated over each 2 x 2 block
    np.testing.assert_array_equal(a.indirect[..., ::2, ::2, :], a.indirect[..., 1::2, 1::2, :])
    st = a.indirect_stats
    assert st["noise_target"] == 0.1 and st["sides"] == 2 * 6 * 4 * 4 and len(st["cubes"]) == 2
    assert 0.0 < st["met_target"] <= 1.0 and st["paths_max"] <= 256 and st["rel_stderr_max"] > 0.0
    # every cube's stream is its own, and the seed changes them all
    assert not np.array_equal(a.indirect[0], a.indirect[1])
    c = render_bases(room, views, [0.0], [0.0], replace(params, seed=3))
    assert not np.array_equal(a.indirect, c.indirect)
    # no global illumination: no indirect pass, no summary
    flat = render_bases(room, views, [0.0], [0.0], replace(params, indirect_samples=0))
    assert not flat.indirect.any() and flat.indirect_stats == {}


@pytest.mark.parametrize("value", [0.0, 0.0009, 0.51, math.nan, math.inf, True, "0.1"])
def test_indirect_noise_out_of_range_is_rejected(value) -> None:
    with pytest.raises(InvalidInputError, match=r"indirect_noise must be a number in \[0.001, 0.5\]"):
        WalkthroughParams(indirect_noise=value)  # type: ignore[arg-type]
    if isinstance(value, float):
        with pytest.raises(pydantic.ValidationError, match="indirect_noise"):
            WalkthroughSettings(indirect_noise=value)


def test_indirect_ranges_agree_between_api_and_engine() -> None:
    assert INDIRECT_NOISE_RANGE == wbake.INDIRECT_NOISE_RANGE
    assert INDIRECT_MAX_PATHS_RANGE == wbake.INDIRECT_MAX_PATHS_RANGE
    lo, hi = INDIRECT_NOISE_RANGE
    for v in (lo, hi):  # the ends are allowed by both
        assert WalkthroughParams(indirect_noise=v).indirect_noise == v
        assert walkthrough_preset("low", **WalkthroughSettings(indirect_noise=v).overrides()).indirect_noise == v
    with pytest.raises(InvalidInputError, match=r"indirect_max_paths must be an integer in \[128, 65536\]"):
        WalkthroughParams(indirect_max_paths=64)
    with pytest.raises(pydantic.ValidationError, match="indirect_max_paths"):
        WalkthroughSettings(indirect_max_paths=70000)
    # presets tighten the target with quality
    noises = [walkthrough_preset(q).indirect_noise for q in ("low", "medium", "high")]
    assert noises == sorted(noises, reverse=True)
