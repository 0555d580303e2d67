"""Calibration of quality contracts on tiny scenes: the fitted model predicts a held-out view's
error within a stated factor, its time fit is positive and grows with the image, and a method that
does not render what the scene holds (``ldc`` on a mirror scene) is excluded with the reason.

The held-out view is turned by 4 degrees, between the probes (8 and -8 degrees), and its ground
truth has a seed of its own; measured errors have that ground truth's noise removed in quadrature
(the noise is measured, as the spread between two ground truths of different seeds)."""

from __future__ import annotations

import math
import statistics

import pytest

from api_schemas.service import CalibrationParams
from engine.error_region import error_region
from engine.metrics import lrms
from engine.newviews.effects import analyze
from engine.newviews.ldc import bake_ldc
from engine.newviews.llf import bake_llf
from engine.newviews.renderer import LDCViewRenderer
from engine.quality import extra_candidates, plan
from engine.raycast import EmbreeCaster
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.scene import CameraParams
from tests.engine.scenes import mat, quad, scene, sphere_mesh
from workers.jobs.calibrate import calibrate_scene, turned_camera, view_pivot

LIGHTS = [dict(type="point", position=(1.5, 2.5, 2.0), intensity=(4.0, 4.0, 4.0)),
          dict(type="directional", direction=(0.2, -1.0, -0.5), irradiance=(0.5, 0.4, 0.3))]
CAMERA = CameraParams("perspective", (0.0, 1.2, 3.2), (0.0, -0.1, 0.0), (0.0, 1.0, 0.0), 48, 32, 45.0)
PARAMS = CalibrationParams(probes=2, size=32, time_scale=4, truth_spp=64, ibrt_ks=[1])
FACTOR = 2.0
"""Stated accuracy of a calibrated error prediction on a held-out view: within a factor of 2 either way
(the predictions are conservative: the largest over the probe views)."""


def _diffuse():
    return scene([(quad((0, -0.5, 0), 3.0, normal_axis=1), mat("floor", kd=(0.6, 0.6, 0.55))),
                  (sphere_mesh((0.0, 0.0, 0.0), 0.5, subdivisions=3), mat("ball", kd=(0.2, 0.3, 0.7)))],
                 LIGHTS)


def _mirror():
    return scene([(quad((0, -0.5, 0), 3.0, normal_axis=1), mat("floor", kd=(0.6, 0.6, 0.55))),
                  (sphere_mesh((0.0, 0.0, 0.0), 0.5, subdivisions=3), mat("ball", kd=(0.05, 0.05, 0.05),
                                                                          kr=(0.8, 0.8, 0.8)))],
                 LIGHTS)


def _truth(ref: ReferenceRenderer, cam: CameraParams, spp: int, seed: int, gi: bool, bounces: int):
    return ref.render(cam, ReferenceParams(spp=spp, indirect_samples=spp if gi else 0, indirect_bounces=bounces,
                                           seed=seed))


@pytest.mark.slow
def test_calibrated_model_predicts_a_held_out_view_within_a_factor_of_two() -> None:
    sc = _diffuse()
    caster = EmbreeCaster(sc)
    effects = analyze(sc)
    renderer = LDCViewRenderer(sc, bake_ldc(sc, caster, 24, plan=effects), None, effects)
    ref = ReferenceRenderer(sc, caster)
    model = calibrate_scene(sc, CAMERA, renderer, params=PARAMS, bake_plan={}, indirect_bounces=2, reference=ref,
                            bake_cost_s=12.0)
    # diffuse: no light field, no IBRT; ldc at each antialiasing level
    assert set(model.methods) == {"ldc", "ldc@2x2", "ldc@4x4"} and not model.excluded
    assert [model.methods[k].supersample for k in ("ldc", "ldc@2x2", "ldc@4x4")] == [1, 2, 4]
    assert model.methods["ldc@4x4"].error < model.methods["ldc"].error  # the edges' sub-pixels pay on the probes
    assert model.cost_s > 0 and model.probe["views"] == 2 and model.probe["width"] == 32
    assert model.reference.b_ms >= 0 and model.reference.c_ms > 0
    gi = bool(model.reference_params["indirect_per_spp"])

    held = turned_camera(CAMERA, 4.0, 32, view_pivot(CAMERA, *sc.bounds))
    truth = _truth(ref, held, 64, 101, gi, 2)
    other = _truth(ref, held, 64, 202, gi, 2)
    mask = error_region(sc, held, truth.object_id, truth.depth)
    truth_noise = lrms(other.radiance, truth.radiance, mask) / math.sqrt(2.0)  # one ground truth's noise

    def measured(img) -> float:
        e = lrms(img, truth.radiance, mask)
        return math.sqrt(max(e * e - truth_noise * truth_noise, 0.0))

    checks = {"ldc": (measured(renderer.render(held, "ldc").radiance), model.methods["ldc"].error)}
    for spp in (1, 4, 16):
        img = ref.render(held, ReferenceParams(**model.reference_request_params(spp))).radiance
        checks[f"reference@{spp}"] = (measured(img), model.reference.error_at(spp))
    print({k: (round(m, 4), round(p, 4)) for k, (m, p) in checks.items()})
    for name, (got, predicted) in checks.items():
        assert predicted / FACTOR <= got <= predicted * FACTOR, (name, got, predicted)

    # the planner's choice for a target between the two methods' errors meets it on the held-out view
    px = held.width * held.height
    target = 0.5 * (model.methods["ldc"].error + model.reference.error_at(1))
    p = plan(model, px, max_error=target)
    assert p.met and p.choice is not None
    s = p.choice.setting
    got = measured(ref.render(held, ReferenceParams(**model.reference_request_params(s.spp))).radiance
                   if s.spp is not None else renderer.render(held, s.method, supersample=s.supersample,
                                                              antialias="edges").radiance)
    assert got <= target * FACTOR, (s, got, target)
    # the reference's time fit reproduces its measurements and grows with the samples: per spp and size,
    # the median of its renders (probes x seeds; on a shared machine one render now and then waits for a
    # core, 41 ms for a predicted 9 ms in one CI run) within 3x, give or take the 2 ms a busy scheduler
    # adds to a 1-spp render of ~1 ms; the LDC views' few milliseconds at these sizes are mostly their
    # fixed part
    by_setting: dict[tuple[int, int], list[float]] = {}
    for pt in model.reference.points:
        by_setting.setdefault((int(pt["pixels"]), int(pt["spp"])), []).append(float(pt["ms"]))
    for (pixels, spp), times in by_setting.items():
        measured_ms, predicted = statistics.median(times), model.reference.ms_at(pixels, spp)
        assert measured_ms / 3 - 2.0 <= predicted <= measured_ms * 3 + 2.0, (pixels, spp, times, predicted)
    assert model.reference.ms_at(64 * 64, 64) > 4 * model.reference.ms_at(64 * 64, 1)
    ldc_ms = [pt["ms"] for pt in model.methods["ldc"].points]
    assert model.methods["ldc"].b_ms > 0
    assert min(ldc_ms) / 3 <= model.methods["ldc"].ms_at(32 * 32, None) <= 3 * max(ldc_ms)

    # the adaptive reference was measured on every probe; told a target through the planner, it meets it on the
    # held-out view, and its own estimate (times the calibrated scale) is the measured error within the factor
    fit = model.adaptive
    # at two error levels (the fit's at 16 and 64 spp), each with its scale; the margin from their spread
    assert fit is not None and fit.error_scale > 0 and fit.time_ratio > 0 and len(fit.points) == 4
    assert [lv["error"] for lv in fit.levels] == pytest.approx([model.reference.error_at(64),
                                                                model.reference.error_at(16)])
    assert all(lv["scale"] > 0 and lv["time_ratio"] > 0 for lv in fit.levels)
    assert fit.margin is not None and 0.5 <= fit.margin <= 1.0
    assert model.reference.margin is not None and model.methods["ldc"].margin is not None
    assert model.probe["cost_breakdown_s"]["adaptive"] > 0
    target = model.reference.error_at(8)
    (cand,) = extra_candidates(model, px, target)
    assert cand.setting.adaptive and cand.setting.max_error == pytest.approx(target / fit.scale_at(target))
    out = ref.render(held, ReferenceParams(**model.setting_params(cand.setting)))
    assert out.adaptive is not None
    got, estimated = measured(out.radiance), fit.scale_at(target) * out.adaptive["estimated_error"]
    print("adaptive", round(target, 4), round(got, 4), round(estimated, 4), fit)
    assert got <= target * FACTOR and estimated / FACTOR <= got <= estimated * FACTOR, (target, got, estimated)


@pytest.mark.slow
def test_ldc_is_excluded_on_a_mirror_scene_and_the_gathering_methods_are_calibrated() -> None:
    sc = _mirror()
    caster = EmbreeCaster(sc)
    effects = analyze(sc)
    ldc = bake_ldc(sc, caster, 24, plan=effects)
    llf = bake_llf(sc, caster, 2, 16, params=ReferenceParams(spp=1, max_depth=2, glossy_samples=2,
                                                              area_light_samples=1))
    renderer = LDCViewRenderer(sc, ldc, llf, effects)
    model = calibrate_scene(sc, CAMERA, renderer, params=PARAMS, bake_plan={"material_kinds": ["diffuse", "mirror"]},
                            indirect_bounces=2)
    assert "mirror" in model.excluded["ldc"] and "ldc" not in model.methods
    assert set(model.methods) == {f"{m}{aa}" for m in ("ldc+llf", "ldc+ibrt:1") for aa in ("", "@2x2", "@4x4")}
    p = plan(model, 32 * 32, max_error=0.999, best_effort=True)
    assert p.choice is not None and p.choice.setting.method != "ldc"


def test_an_ldc_view_is_timed_by_the_median_of_its_renders(monkeypatch: pytest.MonkeyPatch) -> None:
    """The model predicts what a served render takes: of three timings 2, 9 and 4 ms the calibration
    keeps 4 (the median), not 2 (the fastest), and the first render's output."""
    import workers.jobs.calibrate as calibrate

    durations = iter([0.002, 0.009, 0.004])
    clock = [0.0]

    def perf_counter() -> float:
        return clock[0]

    def render(tag: str) -> str:
        clock[0] += next(durations)
        return tag

    monkeypatch.setattr("workers.jobs.calibrate.time.perf_counter", perf_counter)
    assert calibrate.LDC_REPEATS == 3
    out, ms = calibrate.timed_median(render, "first")
    assert out == "first"
    assert ms == pytest.approx(4.0)
