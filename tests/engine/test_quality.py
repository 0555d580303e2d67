"""The quality-contract planner on synthetic models (pure, no rendering): every rule picks what an
exhaustive search over the candidates' predictions picks, the fits recover known coefficients, and
every target no setting meets is said, never silently missed."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import pytest

from engine.quality import (
    REFERENCE_SPP_LADDER,
    AdaptiveFit,
    CandidateFit,
    SceneModel,
    check_targets,
    fit_ldc,
    fit_reference,
    fit_time,
    ldc_settings,
    plan,
    predict,
    spp_for_error,
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
    p = plan(m, PX, max_error=0.045, max_ms=5_000.0, bake_ready=False)  # reference@96 (4.1 %) needs 6.3 s
    assert p.choice is None and p.unmet == ("max_error",)
    p = plan(m, PX, max_error=0.045, bake_ready=False)  # half an octave short of 128 spp (3.5 %, 8.4 s)
    assert p.choice is not None and p.choice.setting.name == "reference@96spp"
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
    assert fit.tail_exponent == 0.5 and fit.error_at(64) == pytest.approx(a / 8)
    # stratified sampling converging as s^-0.75 all the way: the exponent is found, and past 16 spp the fit
    # goes on at the rate measured between 4 and 16 spp
    pts = [{"spp": s, "pixels": 100, "ms": 1.0 + s, "error": a * math.sqrt(s ** -1.5 + s_truth ** -1.5)}
           for s in (1, 4, 16)]
    fit = fit_reference(pts, s_truth)
    assert fit.exponent == pytest.approx(0.75) and fit.error == pytest.approx(a) and fit.knee_spp == 16
    assert fit.tail_exponent == pytest.approx(0.75)
    assert fit.error_at(16) == pytest.approx(a / 8) and fit.error_at(64) == pytest.approx(a / 8 / 4 ** 0.75)
    assert fit.b_ms == pytest.approx(1.0) and fit.c_ms == pytest.approx(0.01)
    # the gain of stratification fading: s^-0.8 up to 4 spp, s^-0.55 from there; the tail is the slower rate
    e4 = a * 4 ** -0.8
    slowing = [{"spp": 1, "error": a}, {"spp": 4, "error": e4}, {"spp": 16, "error": e4 * 4 ** -0.55}]
    fit = fit_reference([{**p, "pixels": 100, "ms": 1.0} for p in slowing], 1 << 20)
    assert 0.6 < fit.exponent < 0.8 and fit.tail_exponent == pytest.approx(0.55)
    assert fit.error_at(64) == pytest.approx(fit.error_at(16) * 4 ** -0.55)
    # a top octave dropping faster than the whole range (noise) does not make the tail faster than the fit;
    # one slower than s^-0.5 (the ground truth's noise in it) does not make it slower than 0.5
    for top, tail in ((4 ** -1.0, "exponent"), (4 ** -0.3, 0.5)):
        pts = [{"spp": 1, "error": 0.4}, {"spp": 4, "error": 0.2}, {"spp": 16, "error": 0.2 * top}]
        fit = fit_reference([{**p, "pixels": 100, "ms": 1.0} for p in pts], 1 << 20)
        assert fit.tail_exponent == pytest.approx(fit.exponent if tail == "exponent" else tail)
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


# ------------------------------------------------------------------------------------ adaptive reference, margins


def _adaptive_model(**changes) -> SceneModel:
    # the reference at s^-0.5 from 40 % (1 spp), as _model; the adaptive reference: the contract's error is 1.5x
    # the render's own estimate, and it takes 0.8x the spp model's time at the spp the target needs
    return _model(**{"adaptive": AdaptiveFit(error_scale=1.5, time_ratio=0.8), **changes})


def test_spp_for_error_inverts_the_reference_fit() -> None:
    for fit in (CandidateFit("reference", 0.4, 0, 0), CandidateFit("reference", 0.3, 0, 0, exponent=0.75, knee_spp=16),
                CandidateFit("reference", 0.3, 0, 0, exponent=0.7, knee_spp=16, tail_exponent=0.6)):
        for s in (1.0, 3.0, 16.0, 40.0, 1000.0):
            e = fit.error * (s ** -fit.exponent if s <= fit.knee_spp
                             else fit.knee_spp ** -fit.exponent * (fit.knee_spp / s) ** fit.tail_exponent)
            assert spp_for_error(fit, e) == pytest.approx(s)
            if s == int(s):
                assert fit.error_at(int(s)) == pytest.approx(e)
    assert spp_for_error(CandidateFit("reference", 0.4, 0, 0), 0.9) == 1.0  # never below one sample


def test_adaptive_reference_is_priced_at_the_spp_its_target_needs() -> None:
    m = _adaptive_model(methods={}, excluded={})
    # 3 % needs (0.4 / 0.03)^2 = 177.8 spp: 0.8 x (5 + 1e-3 x 177.8 x 65536) ms; the ladder's cheapest meeting it
    # is 256 spp (2.5 %), 1.8x the samples
    p = plan(m, PX, max_error=0.03)
    assert p.met and p.choice is not None and p.choice.setting.adaptive
    s = (0.4 / 0.03) ** 2
    assert p.choice.ms == pytest.approx(0.8 * (5.0 + 1e-3 * s * PX)) and p.choice.error == pytest.approx(0.03)
    # told the target over the error scale, capped at 4x the spp rounded up to a power of two
    assert p.choice.setting.max_error == pytest.approx(0.03 / 1.5) and p.choice.setting.spp == 1024
    assert m.setting_params(p.choice.setting) == {"max_depth": 4, "indirect_bounces": 3, "spp": 1024,
                                                  "indirect_samples": 1024, "max_error": pytest.approx(0.02)}
    # with a time budget it is told the budget too (the request's, not the margined one)
    p = plan(m, PX, max_error=0.03, max_ms=200_000.0, time_margin=0.5)
    assert p.choice is not None and p.choice.setting.max_ms == 200_000.0
    # a time-only contract never gets it (nothing to stop at but the time); nor a model without its fit
    assert not plan(m, PX, max_ms=5_000.0).choice.setting.adaptive  # type: ignore[union-attr]
    assert not any(c.setting.adaptive for c in predict(_model(), PX, aim_error=0.03))
    # beyond the reference's 4096 spp: no adaptive candidate either
    assert not any(c.setting.adaptive for c in predict(m, PX, aim_error=0.001))


def test_adaptive_reference_is_chosen_only_when_cheaper() -> None:
    m = _adaptive_model()
    # 5 %: ldc+llf (4 %, 43 ms) beats any reference
    assert plan(m, PX, max_error=0.05).choice.setting.name == "ldc+llf"  # type: ignore[union-attr]
    # exactly on a ladder step with a slow adaptive render (time ratio 3): the ladder's 64 spp
    slow = _adaptive_model(adaptive=AdaptiveFit(error_scale=1.0, time_ratio=3.0), methods={})
    assert plan(slow, PX, max_error=0.05).choice.setting.name == "reference@64spp"  # type: ignore[union-attr]


def test_margins_plan_for_a_tighter_target_and_fall_back_without_them() -> None:
    m = _model(methods={}, excluded={})
    # 10 %: 16 spp without a margin; x 0.85 = 8.5 %: 24 spp (8.2 %), half an octave up
    assert plan(m, PX, max_error=0.1).choice.setting.spp == 16  # type: ignore[union-attr]
    p = plan(m, PX, max_error=0.1, error_margin=0.85)
    assert p.met and p.choice is not None and p.choice.setting.spp == 24
    assert p.planned_for == {"max_error": pytest.approx(0.085)} and p.reason == ""
    # a time budget: 1 s x 0.7 = 700 ms fits 8 spp (529 ms), not 16 (1054 ms)
    p = plan(m, PX, max_ms=1100.0, time_margin=0.7)
    assert p.choice is not None and p.choice.setting.spp == 8 and p.planned_for == {"max_ms": pytest.approx(770.0)}
    # 0.7 %: only 4096 spp (0.625 %) meets it, not with the margin (0.595 %): chosen, and said
    p = plan(m, PX, max_error=0.007, error_margin=0.85)
    assert p.met and p.choice is not None and p.choice.setting.spp == 4096
    assert "not with the safety margin" in p.reason and p.planned_for == {"max_error": 0.007}
    # unmet either way: the plan for the request's targets, as without margins
    assert plan(m, PX, max_error=0.001, error_margin=0.85) == replace(plan(m, PX, max_error=0.001),
                                                                       planned_for={"max_error": 0.001})
    with pytest.raises(ValueError, match="error_margin"):
        plan(m, PX, max_error=0.1, error_margin=0.0)


def test_adaptive_model_round_trips_and_older_models_load() -> None:
    import json

    m = _adaptive_model()
    assert SceneModel.from_json(json.loads(json.dumps(m.to_json()))) == m
    doc = _model().to_json()
    del doc["adaptive"]  # a model stored before the adaptive fit existed
    assert SceneModel.from_json(doc).adaptive is None
    del doc["reference"]["tail_exponent"]  # ... or the fitted tail: it goes on at s^-0.5 past its knee
    assert SceneModel.from_json(doc).reference.tail_exponent == 0.5


# ------------------------------------------------------------------------------------ calibrated margins


def test_calibrated_margins_follow_the_probes_spread() -> None:
    from engine.quality import MARGIN_RANGE, calibrated_margin

    tight, loose = calibrated_margin([1.0, 0.98, 1.02, 1.0]), calibrated_margin([1.0, 0.7, 1.3, 1.0])
    assert loose < tight < 1.0  # even probes that agree leave a margin (MARGIN_MIN_SPREAD)
    # a model that over-predicts every probe plans closer to the target, never above it
    assert calibrated_margin([0.8, 0.82, 0.79]) > tight and calibrated_margin([0.3, 0.31]) == MARGIN_RANGE[1]
    assert calibrated_margin([1.0, 3.0, 0.3]) == MARGIN_RANGE[0]
    # the LDC fit: the largest error over the probes, its margin from the others' ratio to it
    fit = fit_ldc("ldc", [{"error": e, "pixels": 100, "ms": 1.0} for e in (0.1, 0.09, 0.05)], 0.0)
    assert fit.margin == pytest.approx(calibrated_margin([1.0, 0.9, 0.5]))
    ref = fit_reference([{"spp": s, "error": 0.4 * s ** -0.5 * f, "pixels": 100, "ms": 1.0}
                         for s in (1, 4, 16) for f in (0.9, 1.1)], 1 << 20)
    assert ref.margin is not None and ref.margin < calibrated_margin([1.0, 1.0])


def test_the_reference_margin_follows_each_spps_spread_over_probes_and_seeds() -> None:
    from engine.quality import calibrated_margin

    # two probes, four seeds each: the error at 1 spp scatters by +-40 % over seeds, at 16 spp by +-5 %
    spread = {1: (0.6, 1.4, 0.8, 1.2), 4: (0.8, 1.2, 0.9, 1.1), 16: (0.95, 1.05, 1.0, 1.0)}
    pts = [{"spp": s, "error": 0.4 * s ** -0.5 * f, "pixels": 100, "ms": 1.0, "probe": probe, "seed": seed}
           for s, fs in spread.items() for probe in (0, 1) for seed, f in enumerate(fs)]
    ref = fit_reference(pts, 1 << 20)
    by = {int(s): m for s, m in ref.margins_by_spp}
    assert set(by) == {1, 4, 16} and by[1] < by[4] < by[16]
    ratios_16 = [0.4 * 16 ** -0.5 * f / ref.error_at(16) for f in spread[16] * 2]
    assert by[16] == pytest.approx(calibrated_margin(ratios_16, 2), rel=1e-4)  # two probes behind the bound
    assert ref.margin_at(1) == by[1] and ref.margin_at(2) == pytest.approx(0.5 * (by[1] + by[4]))
    assert ref.margin_at(256) == by[16] and ref.margin is not None and by[1] < ref.margin < by[16]
    # the planner takes each ladder step's own margin: 20 % at 1-4 spp gets a lower aim than at 16
    m = _model(methods={}, excluded={}, reference=replace(_model().reference, margins_by_spp=ref.margins_by_spp,
                                                          margin=ref.margin))
    preds = {p.setting.spp: p for p in predict(m, PX, calibrated_margins=True)}
    assert preds[1].margin == by[1] and preds[16].margin == by[16] and preds[64].margin == by[16]
    assert preds[2].margin == pytest.approx(0.5 * (by[1] + by[4]))
    p = plan(m, PX, max_error=0.1)  # 16 spp is 10 % exactly: its margin asks for the next step
    assert p.choice is not None and p.choice.setting.spp == 24 and p.choice.margin == by[16]
    # a model without them plans with its one margin, and round-trips through JSON either way
    assert SceneModel.from_json(m.to_json()).reference.margins_by_spp == ref.margins_by_spp
    assert replace(m.reference, margins_by_spp=[]).margin_at(2) == ref.margin


def test_the_planner_uses_each_fits_calibrated_margin_else_the_flat_one() -> None:
    m = _model(methods={}, excluded={})
    # 10 %: 16 spp exactly; the reference's calibrated margin 0.95 (9.5 %): 24 spp; the flat 0.7 (7 %): 48 spp
    cal = replace(m, reference=replace(m.reference, margin=0.95))
    p = plan(cal, PX, max_error=0.1, error_margin=0.7)
    assert p.choice is not None and p.choice.setting.spp == 24 and p.planned_for == {"max_error": pytest.approx(0.095)}
    assert plan(cal, PX, max_error=0.1, error_margin=0.7, calibrated_margins=False).choice.setting.spp == 48  # type: ignore[union-attr]
    assert plan(m, PX, max_error=0.1, error_margin=0.7).choice.setting.spp == 48  # type: ignore[union-attr]
    # per method: ldc (6 %) with its margin 0.8 plans for 4.8 % and so misses a 7 % target; the reference meets it
    both = replace(cal, methods={"ldc": replace(_model().methods["ldc"], margin=0.8)})
    assert plan(both, PX, max_error=0.07).choice.setting.method == "reference"  # type: ignore[union-attr]
    assert plan(both, PX, max_error=0.08).choice.setting.method == "ldc"  # type: ignore[union-attr]


def test_the_adaptive_scale_is_interpolated_between_its_calibrated_levels() -> None:
    levels = [{"error": 0.04, "scale": 1.2, "time_ratio": 1.0}, {"error": 0.1, "scale": 1.8, "time_ratio": 2.0}]
    fit = AdaptiveFit(error_scale=1.9, time_ratio=2.0, levels=levels, margin=0.8)
    assert fit.scale_at(0.01) == 1.2 and fit.scale_at(0.2) == 1.8 and fit.scale_at(0.1) == pytest.approx(1.8)
    assert fit.scale_at(math.sqrt(0.004)) == pytest.approx(math.sqrt(1.2 * 1.8))
    assert fit.time_ratio_at(math.sqrt(0.004)) == pytest.approx(math.sqrt(2.0))
    assert AdaptiveFit(error_scale=1.9, time_ratio=2.0).scale_at(0.05) == 1.9  # one level, before levels existed
    m = _adaptive_model(adaptive=fit, methods={})
    # 3 %: the adaptive margin 0.8 -> aims at 2.4 %, told 2.4 % / 1.2
    p = plan(m, PX, max_error=0.03, error_margin=0.5)
    assert p.choice is not None and p.choice.setting.adaptive and p.choice.error == pytest.approx(0.024)
    assert p.choice.setting.max_error == pytest.approx(0.02) and p.planned_for == {"max_error": pytest.approx(0.024)}
    s = (0.4 / 0.024) ** 2
    assert p.choice.ms == pytest.approx(1.0 * (5.0 + 1e-3 * s * PX))


# ------------------------------------------------------------------------------------ served renders


def test_served_observations_correct_the_model_once_there_are_enough() -> None:
    from engine.quality import (
        CORRECTION_WINDOW,
        apply_corrections,
        correction_factor,
        correction_key,
        fold_observation,
    )

    assert correction_key("reference", {"spp": 4}) == "reference" and correction_key("ldc", None) == "ldc"
    assert correction_key("reference", {"spp": 64, "max_error": 0.02}) == "reference@adaptive"
    e = fold_observation(None, 2.0)
    assert e == {"log": pytest.approx(math.log(2.0)), "n": 1}
    assert correction_factor({"time": {"reference": e}}, "time", "reference") == 1.0  # one render is noise
    e = fold_observation(e, 2.0)
    assert correction_factor({"time": {"reference": e}}, "time", "reference") == pytest.approx(2.0)
    # a running geometric mean that forgets: after many renders at 1x, the factor returns towards 1
    for _ in range(4 * CORRECTION_WINDOW):
        e = fold_observation(e, 1.0)
    assert 1.0 <= correction_factor({"time": {"reference": e}}, "time", "reference") < 1.01
    assert correction_factor({"error": {"ldc": {"log": 5.0, "n": 3}}}, "error", "ldc") == 2.0  # clamped
    with pytest.raises(ValueError):
        fold_observation(None, 0.0)

    m = _adaptive_model(adaptive=AdaptiveFit(1.5, 0.8, levels=[{"error": 0.05, "scale": 1.5, "time_ratio": 0.8}]))
    twice = {"log": math.log(2.0), "n": 5}
    fixed = apply_corrections(m, {"time": {"reference": twice, "reference@adaptive": twice},
                                  "error": {"ldc": twice, "reference@adaptive": twice}})
    assert fixed.reference.ms_at(PX, 16) == pytest.approx(2 * m.reference.ms_at(PX, 16))
    assert fixed.reference.error == m.reference.error and fixed.methods["ldc"].error == pytest.approx(0.12)
    assert fixed.methods["ldc+llf"] == m.methods["ldc+llf"]
    assert fixed.adaptive is not None and fixed.adaptive.scale_at(0.05) == pytest.approx(3.0)
    assert fixed.adaptive.time_ratio_at(0.05) == pytest.approx(1.6)
    # the plan follows: ldc measured at twice its calibrated error no longer meets 10 %, ldc+llf (4 %) does
    assert plan(m, PX, max_error=0.1).choice.setting.method == "ldc"  # type: ignore[union-attr]
    assert plan(fixed, PX, max_error=0.1).choice.setting.method == "ldc+llf"  # type: ignore[union-attr]
    assert apply_corrections(m, {}) is m


def test_antialiased_ldc_settings_are_candidates_of_their_own() -> None:
    from engine.quality import Setting, correction_key, ldc_setting_name

    # ldc: 6 % at one sample per pixel; its 4 x 4 edge supersampling: 3 % at 3x the time
    aa = CandidateFit("ldc", 0.03, 60.0, 3e-4, supersample=4)
    m = _model(methods={"ldc": _model().methods["ldc"], aa.key: aa})
    assert aa.key == "ldc@4x4" == ldc_setting_name("ldc", 4) and ldc_setting_name("ldc", 1) == "ldc"
    preds = {p.setting.name: p for p in predict(m, PX)}
    assert preds["ldc@4x4"].setting == Setting("ldc", supersample=4) and preds["ldc@4x4"].error == 0.03
    assert preds["ldc@4x4"].setting.view == {"supersample": 4, "antialias": "edges"}
    assert preds["ldc"].setting.view is None
    # 4 %: the antialiased view (~80 ms) beats the reference at 100 spp (~6.5 s); 8 %: plain ldc
    p = plan(m, PX, max_error=0.04)
    assert p.choice is not None and p.choice.setting.name == "ldc@4x4"
    assert plan(m, PX, max_error=0.08).choice.setting.name == "ldc"  # type: ignore[union-attr]
    # a method excluded before it was measured takes its antialiased settings along; a one-sample view
    # excluded for its error leaves the antialiased ones (aliasing, not missing content); each setting
    # has its own served corrections
    unmeasured = replace(m, methods={aa.key: aa}, excluded={"ldc": "mirror materials"})
    assert not any(p.setting.method == "ldc" for p in predict(unmeasured, PX))
    aliased = {p.setting.name for p in predict(replace(m, excluded={"ldc": "measured LRMS 0.9"}), PX)}
    assert "ldc@4x4" in aliased and "ldc" not in aliased
    assert correction_key("ldc", None, {"supersample": 4, "antialias": "edges"}) == "ldc@4x4"
    assert correction_key("ldc", None, None) == "ldc" and correction_key("ldc", None, {"supersample": 1}) == "ldc"
    from engine.quality import apply_corrections
    slow = {"time": {"ldc@4x4": {"log": math.log(2.0), "n": 3}}}
    fixed = apply_corrections(m, slow)
    assert fixed.methods["ldc@4x4"].b_ms == 120.0 and fixed.methods["ldc"].b_ms == 20.0
    assert SceneModel.from_json(m.to_json()).methods["ldc@4x4"].supersample == 4
