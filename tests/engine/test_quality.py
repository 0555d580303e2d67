"""The quality-contract planner on synthetic models (pure, no rendering): every rule picks what an
exhaustive search over the candidates' predictions picks, the fits recover known coefficients, and
every target no setting meets is said, never silently missed."""

from __future__ import annotations

import itertools
import math

import pytest

from engine.quality import (
    REFERENCE_SPP_LADDER,
    CandidateFit,
    SceneModel,
    check_targets,
    fit_ldc,
    fit_reference,
    fit_time,
    ldc_settings,
    plan,
    predict,
)

PX = 256 * 256


def _model(**changes) -> SceneModel:
    # reference: 40 % LRMS at 1 spp, 5 ms + 1 us per sample; ldc: 6 % at 20 ms + 0.1 us per pixel;
    # ldc+llf: 4 % at 30 ms + 0.2 us per pixel
    doc = dict(scene_id="0" * 64, bake_key="1" * 64,
               reference=CandidateFit("reference", 0.4, 5.0, 1e-3),
               methods={"ldc": CandidateFit("ldc", 0.06, 20.0, 1e-4),
                        "ldc+llf": CandidateFit("ldc+llf", 0.04, 30.0, 2e-4)},
               excluded={}, reference_params={"max_depth": 4, "indirect_per_spp": 1, "indirect_bounces": 3},
               bake_cost_s=90.0, cost_s=12.0, probe={"views": 2})
    doc.update(changes)
    return SceneModel(**doc)


def _brute(model: SceneModel, max_error, max_ms, **kw):
    """The obvious search the planner must agree with."""
    cands = predict(model, PX, **kw)
    ok = [p for p in cands if (max_error is None or p.error <= max_error) and (max_ms is None or p.ms <= max_ms)]
    if max_error is not None and ok:
        return min(ok, key=lambda p: (p.ms, p.error))
    if max_error is None and ok:
        return min(ok, key=lambda p: (p.error, p.ms))
    return None


def test_predictions_follow_the_model() -> None:
    m = _model()
    preds = {p.setting.name: p for p in predict(m, PX)}
    assert set(preds) == {f"reference@{s}spp" for s in REFERENCE_SPP_LADDER} | {"ldc", "ldc+llf"}
    r16 = preds["reference@16spp"]
    assert r16.error == pytest.approx(0.4 / 4) and r16.ms == pytest.approx(5.0 + 1e-3 * 16 * PX)
    assert preds["ldc"].ms == pytest.approx(20.0 + 1e-4 * PX) and preds["ldc"].error == 0.06
    # a missing bake prices its methods with the bake; not allowed to wait: they are left out
    waiting = {p.setting.name: p for p in predict(m, PX, bake_ready=False)}
    assert waiting["ldc"].ms == pytest.approx(preds["ldc"].ms + 90_000.0) and waiting["ldc"].bake_ms == 90_000.0
    assert not any(p.setting.needs_bake for p in predict(m, PX, bake_ready=False, allow_bake=False))
    assert m.reference_request_params(8) == {"max_depth": 4, "indirect_bounces": 3, "spp": 8, "indirect_samples": 8}


@pytest.mark.parametrize("max_error,max_ms", list(itertools.product(
    [None, 0.005, 0.02, 0.05, 0.07, 0.15, 0.5], [None, 3.0, 10.0, 30.0, 60.0, 100.0, 2000.0, 60_000.0])))
def test_plan_agrees_with_an_exhaustive_search(max_error, max_ms) -> None:
    if max_error is None and max_ms is None:
        return
    m = _model()
    want = _brute(m, max_error, max_ms)
    got = plan(m, PX, max_error=max_error, max_ms=max_ms)
    if want is None:
        assert got.choice is None and not got.met and got.unmet and got.reason
    else:
        assert got.met and got.choice == want, (got, want)


def test_rules_are_named() -> None:
    m = _model()
    p = plan(m, PX, max_error=0.05)
    assert p.rule == "cheapest_meeting_error" and p.choice is not None and p.choice.setting.name == "ldc+llf"
    p = plan(m, PX, max_error=0.1)  # ldc (6 %) is cheaper than ldc+llf; reference@16 = 10 % costs 1 s
    assert p.choice is not None and p.choice.setting.name == "ldc"
    p = plan(m, PX, max_ms=40.0)
    assert p.rule == "most_accurate_within_time" and p.choice is not None and p.choice.setting.name == "ldc"
    p = plan(m, PX, max_error=0.05, max_ms=100.0)
    assert p.rule == "cheapest_meeting_error_within_time" and p.choice.setting.name == "ldc+llf"  # type: ignore[union-attr]


def test_error_not_reachable_within_the_time_is_said_and_best_effort_marks_it() -> None:
    m = _model()
    p = plan(m, PX, max_error=0.01, max_ms=100.0)
    assert p.choice is None and p.unmet == ("max_error",) and "within 100 ms" in p.reason and "ldc+llf" in p.reason
    p = plan(m, PX, max_error=0.01, max_ms=100.0, best_effort=True)
    assert p.rule == "most_accurate_within_time_error_unmet" and not p.met
    assert p.choice is not None and p.choice.setting.name == "ldc+llf"
    p = plan(m, PX, max_error=0.001)  # 0.1 %: not even 4096 spp (0.625 %)
    assert p.choice is None and p.unmet == ("max_error",) and "reference@4096spp" in p.reason
    p = plan(m, PX, max_error=0.001, best_effort=True)
    assert p.rule == "best_effort_most_accurate" and p.choice.setting.name == "reference@4096spp"  # type: ignore[union-attr]


def test_time_budget_below_the_fixed_overhead_says_so() -> None:
    m = _model()
    p = plan(m, PX, max_ms=2.0)  # every setting needs at least 5 ms
    assert p.choice is None and p.unmet == ("max_ms",) and "fixed overhead" in p.reason and "5 ms" in p.reason
    p = plan(m, PX, max_ms=10.0)  # above the overhead, but nothing renders 65536 pixels in 10 ms
    assert p.choice is None and "fixed overhead" not in p.reason and "fastest" in p.reason
    p = plan(m, PX, max_ms=10.0, best_effort=True)
    assert p.rule == "best_effort_fastest" and not p.met and p.choice is not None
    assert p.choice.setting.name == "ldc"  # 26.6 ms: the fastest


def test_excluded_methods_are_never_chosen() -> None:
    m = _model(excluded={"ldc": "the scene has mirror materials"})
    for e, t in [(0.1, None), (None, 40.0), (0.99, None)]:
        p = plan(m, PX, max_error=e, max_ms=t, best_effort=True)
        assert p.choice is not None and p.choice.setting.name != "ldc"


def test_a_missing_bake_is_priced_with_the_bake() -> None:
    m = _model()
    # 5 %: with the bake ready ldc+llf (43 ms); with 90 s of bake to wait for, reference@64 (4.2 s) is cheaper
    assert plan(m, PX, max_error=0.05).choice.setting.name == "ldc+llf"  # type: ignore[union-attr]
    p = plan(m, PX, max_error=0.05, bake_ready=False)
    assert p.choice is not None and p.choice.setting.name == "reference@64spp"
    p = plan(m, PX, max_error=0.045, max_ms=5_000.0, bake_ready=False)  # reference@128 (3.5 %) needs 8.4 s
    assert p.choice is None and p.unmet == ("max_error",)
    p = plan(m, PX, max_error=0.045, bake_ready=False)
    assert p.choice is not None and p.choice.setting.name == "reference@128spp"
    p = plan(_model(bake_cost_s=2.0), PX, max_error=0.045, bake_ready=False)  # a cheap bake: worth waiting for
    assert p.choice is not None and p.choice.setting.name == "ldc+llf" and p.choice.bake_ms == 2_000.0


def test_fits_recover_known_coefficients() -> None:
    b, c = fit_time([100.0, 400.0, 1600.0], [12.0, 18.0, 42.0])  # 10 + 0.02 x
    assert b == pytest.approx(10.0) and c == pytest.approx(0.02)
    assert fit_time([1.0, 2.0], [5.0, 4.0]) == (4.5, 0.0)  # noise making the slope negative: a constant
    b, c = fit_time([1.0, 2.0], [1.0, 3.0])  # a negative intercept: through the origin
    assert b == 0.0 and c == pytest.approx(7.0 / 5.0)
    a, s_truth = 0.3, 256
    pts = [{"spp": s, "pixels": 100, "ms": 1.0 + 0.01 * s * 100, "error": a * math.sqrt(1 / s + 1 / s_truth)}
           for s in (1, 4, 16)]
    fit = fit_reference(pts, s_truth)
    assert fit.error == pytest.approx(a) and fit.error_at(4) == pytest.approx(0.15) and fit.exponent == 0.5
    # stratified sampling converging as s^-0.75: the exponent is found; past 16 spp the fit goes on at 0.5
    pts = [{"spp": s, "pixels": 100, "ms": 1.0 + s, "error": a * math.sqrt(s ** -1.5 + s_truth ** -1.5)}
           for s in (1, 4, 16)]
    fit = fit_reference(pts, s_truth)
    assert fit.exponent == pytest.approx(0.75) and fit.error == pytest.approx(a) and fit.knee_spp == 16
    assert fit.error_at(16) == pytest.approx(a / 8) and fit.error_at(64) == pytest.approx(a / 16)
    assert fit.b_ms == pytest.approx(1.0) and fit.c_ms == pytest.approx(0.01)
    # an LDC method: the ground truth's noise removed in quadrature, the worst probe kept
    fit = fit_ldc("ldc", [{"pixels": 100, "ms": 3.0, "error": 0.05}, {"pixels": 100, "ms": 3.0, "error": 0.1},
                          {"pixels": 400, "ms": 6.0, "error": None}], truth_noise=0.06)
    assert fit.error == pytest.approx(0.08) and fit.c_ms == pytest.approx(0.01)


def test_model_round_trips_through_json() -> None:
    import json

    m = _model()
    again = SceneModel.from_json(json.loads(json.dumps(m.to_json())))
    assert again == m
    with pytest.raises(ValueError, match="version"):
        SceneModel.from_json({**m.to_json(), "version": 99})


def test_candidates_from_the_registry() -> None:
    assert [s.name for s in ldc_settings(False, False)] == ["ldc"]
    assert [s.name for s in ldc_settings(True, False)] == ["ldc", "ldc+llf"]
    assert [s.name for s in ldc_settings(True, True, (2, 1))] == ["ldc", "ldc+llf", "ldc+ibrt:1", "ldc+ibrt:2"]
    with pytest.raises(ValueError):
        ldc_settings(True, True, (9,))


@pytest.mark.parametrize("max_error,max_ms,fields", [
    (0.0, None, {"quality.max_error"}), (1.0, None, {"quality.max_error"}), (-0.1, None, {"quality.max_error"}),
    (None, 0.0, {"quality.max_ms"}), (None, 600_001.0, {"quality.max_ms"}), (None, -5.0, {"quality.max_ms"}),
    (math.nan, None, {"quality.max_error"}), (None, None, {"quality"}), (0.05, 100.0, set()),
    (0.999, 600_000.0, set())])
def test_target_ranges(max_error, max_ms, fields) -> None:
    got = check_targets(max_error, max_ms, 600_000.0)
    assert {f for f, _ in got} == fields
    for _, message in got:
        assert "(0, 1)" in message or "(0, 600000]" in message or "max_error, max_ms or both" in message
