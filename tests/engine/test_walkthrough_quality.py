"""The walkthrough contract planner (engine/walkthrough/quality.py): its rules on a hand-made model,
the bake's cost in the ranking, the safety margins, and the probe frames' eyes and times."""

from __future__ import annotations

import numpy as np
import pytest

from engine.quality import CandidateFit
from engine.walkthrough.quality import (
    WalkthroughModel,
    plan_walkthrough,
    predict_walkthrough,
    probe_eyes,
    probe_times,
)
from engine.walkthrough.viewspace import BoxSpace, PathSpace, PolygonSpace


def _fit(name: str, error: float, b_ms: float, c_ms: float, margin: float | None = 0.9) -> CandidateFit:
    return CandidateFit(name, error, b_ms, c_ms, margin=margin)


def _model(**overrides: object) -> WalkthroughModel:
    fits = {"low/both": _fit("low/both", 0.20, 2.0, 1e-5), "medium/both": _fit("medium/both", 0.12, 3.0, 2e-5),
            "high/both": _fit("high/both", 0.08, 4.0, 4e-5), "high/trace": _fit("high/trace", 0.06, 10.0, 2e-4)}
    doc = dict(scene_id="s" * 64, fits=fits, excluded={}, bake_keys={p: p[0] * 64 for p in ("low", "medium", "high")},
               bake_cost_s={"low": 5.0, "medium": 60.0, "high": 600.0}, cost_s=1.0, probe={})
    doc.update(overrides)
    return WalkthroughModel(**doc)  # type: ignore[arg-type]


PX = 320 * 240
ALL = {"low", "medium", "high"}


def test_error_target_gets_the_cheapest_setting_that_meets_it() -> None:
    p = plan_walkthrough(_model(), PX, 100, max_error=0.15, bakes_ready=ALL)
    assert p.met and p.rule == "cheapest_meeting_error" and p.choice is not None
    assert p.choice.name == "medium/both"  # 0.12 <= 0.15 x 0.9; low's 0.20 does not
    assert p.planned_for == {"max_error": pytest.approx(0.135)}
    p = plan_walkthrough(_model(), PX, 100, max_error=0.07, bakes_ready=ALL)
    assert p.choice is not None and p.choice.name == "high/trace"


def test_time_budget_gets_the_most_accurate_setting_within_it() -> None:
    # per-frame times at 76,800 px: low 2.8, medium 4.5, high 7.1, high/trace 25.4 ms; planned x 0.7
    p = plan_walkthrough(_model(), PX, 100, max_ms=12.0, time_margin=0.7, bakes_ready=ALL)
    assert p.rule == "most_accurate_within_time" and p.choice is not None and p.choice.name == "high/both"
    both = plan_walkthrough(_model(), PX, 100, max_error=0.15, max_ms=12.0, time_margin=0.7, bakes_ready=ALL)
    assert both.rule == "cheapest_meeting_error_within_time" and both.choice is not None
    assert both.choice.name == "medium/both"


def test_a_missing_bake_is_priced_into_the_whole_walkthrough() -> None:
    # nothing baked yet: high's 600 s bake loses to medium for a short walkthrough ...
    m = _model(fits={"medium/both": _fit("medium/both", 0.12, 3.0, 2e-5),
                     "high/both": _fit("high/both", 0.08, 2.0, 1e-5)})
    short = plan_walkthrough(m, PX, 10, max_error=0.15, bakes_ready=set())
    assert short.choice is not None and short.choice.name == "medium/both"
    assert short.choice.bake_ms == 60_000.0 and short.choice.total_ms == pytest.approx(60_000 + 10 * 4.536)
    # ... and with high's bake in the store, high is cheaper (faster frames, no bake to wait for)
    ready = plan_walkthrough(m, PX, 10, max_error=0.15, bakes_ready={"high"})
    assert ready.choice is not None and ready.choice.name == "high/both" and ready.choice.bake_ms == 0
    # without waiting for bakes only the stored presets are candidates
    only = predict_walkthrough(m, PX, 10, bakes_ready={"medium"}, allow_bake=False)
    assert [c.name for c in only] == ["medium/both"]


def test_unmeetable_targets_say_why_and_best_effort_marks_them() -> None:
    m = _model()
    p = plan_walkthrough(m, PX, 10, max_error=0.01, bakes_ready=ALL)
    assert p.choice is None and p.unmet == ("max_error",)
    assert "no walkthrough setting reaches LRMS 0.01" in p.reason and "high/trace" in p.reason
    p = plan_walkthrough(m, PX, 10, max_error=0.01, best_effort=True, bakes_ready=ALL)
    assert p.rule == "best_effort_most_accurate" and p.choice is not None and p.choice.name == "high/trace"
    assert not p.met
    p = plan_walkthrough(m, PX, 10, max_ms=1.0, bakes_ready=ALL)
    assert p.choice is None and p.unmet == ("max_ms",)
    assert "below this scene's fixed overhead" in p.reason and "2 ms per frame" in p.reason
    p = plan_walkthrough(m, PX, 10, max_error=0.05, max_ms=8.0, best_effort=True, bakes_ready=ALL)
    assert p.rule == "most_accurate_within_time_error_unmet" and p.choice is not None
    assert p.choice.name == "high/both" and p.unmet == ("max_error",)


def test_a_plan_without_the_safety_margin_is_best_effort_only() -> None:
    m = _model(fits={"high/both": _fit("high/both", 0.095, 4.0, 4e-5, margin=0.9)})
    p = plan_walkthrough(m, PX, 10, max_error=0.1, bakes_ready=ALL)  # 0.095 > 0.1 x 0.9, but <= 0.1
    assert p.choice is None and p.unmet == ("max_error",)
    assert "high/both" in p.reason and "not with the safety margin" in p.reason and "error x 0.9" in p.reason
    p = plan_walkthrough(m, PX, 10, max_error=0.1, best_effort=True, bakes_ready=ALL)
    assert p.met and p.choice is not None and p.planned_for == {"max_error": 0.1}
    assert "not with the safety margin" in p.reason
    # a time budget kept only without its margin (7.1 ms > 8 x 0.7)
    p = plan_walkthrough(m, PX, 10, max_ms=8.0, time_margin=0.7, bakes_ready=ALL)
    assert p.choice is None and p.unmet == ("max_ms",)
    flat = _model(fits={"high/both": _fit("high/both", 0.095, 4.0, 4e-5, margin=None)})
    p = plan_walkthrough(flat, PX, 10, max_error=0.12, flat_margin=0.85, bakes_ready=ALL)
    assert p.planned_for == {"max_error": pytest.approx(0.102)}


def test_excluded_settings_are_no_candidates_and_are_named() -> None:
    m = _model(excluded={"high/trace": "its error on the probe frames (60%) exceeds 50%"})
    assert "high/trace" not in {c.name for c in predict_walkthrough(m, PX, 1, bakes_ready=ALL)}
    p = plan_walkthrough(m, PX, 1, max_error=0.01, bakes_ready=ALL)
    assert "excluded: high/trace: its error" in p.reason


def test_the_model_round_trips_through_json() -> None:
    m = _model()
    back = WalkthroughModel.from_json(m.to_json())
    assert back == m
    with pytest.raises(ValueError, match="version"):
        WalkthroughModel.from_json({**m.to_json(), "version": 99})


def test_bad_planner_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="needs max_error, max_ms or both"):
        plan_walkthrough(_model(), PX, 1)
    with pytest.raises(ValueError, match="time_margin"):
        plan_walkthrough(_model(), PX, 1, max_ms=10, time_margin=0)
    with pytest.raises(ValueError, match=">= 1"):
        predict_walkthrough(_model(), PX, 0, bakes_ready=ALL)


@pytest.mark.parametrize("space", [
    PathSpace(np.array([[0.0, 1, 0], [4, 1, 0], [4, 1, 3]])),
    BoxSpace(np.array([0.0, 0, 0]), np.array([2.0, 1, 3])),
    PolygonSpace(np.array([[0.0, 0], [6, 0], [6, 2], [2, 2], [2, 6], [0, 6]]), 1.6),  # an L
])
def test_probe_eyes_lie_inside_the_view_space_and_spread(space: object) -> None:
    eyes = probe_eyes(space, 5)
    assert len(eyes) == 5 and len(set(eyes)) == 5
    assert all(space.contains(np.asarray(e)) for e in eyes)  # type: ignore[attr-defined]
    assert probe_eyes(space, 5) == eyes  # deterministic
    lo, hi = (np.asarray(b) for b in space.bounds)  # type: ignore[attr-defined]
    spread = np.ptp(np.asarray(eyes), axis=0)
    assert spread.max() > 0.4 * (hi - lo).max()


def test_probe_times_cover_the_animation() -> None:
    assert probe_times(0.0, 4.0, 4) == [0.5, 1.5, 2.5, 3.5]
    assert probe_times(1.0, 1.0, 2) == [1.0, 1.0]
    with pytest.raises(ValueError):
        probe_times(2.0, 1.0, 2)


def test_the_frame_time_is_planned_for_the_slowest_probe_frame() -> None:
    from engine.walkthrough.quality import fit_setting

    points = [{"error": 0.1, "pixels": 4096, "ms": ms} for ms in (4.0, 5.0, 9.0)]
    points.append({"error": None, "pixels": 65536, "ms": 20.0})
    fit = fit_setting("low", "both", points, 0.0)
    assert fit.key == "low/both" and fit.error == pytest.approx(0.1)
    assert all(fit.ms_at(p["pixels"], None) >= p["ms"] - 1e-9 for p in points)
    assert fit.ms_at(4096, None) == pytest.approx(9.0, rel=0.05)  # the slowest probe, not the middle one


def _path_model() -> WalkthroughModel:
    """Path-traced frames calibrated at noise 0.05 and 0.1 (their probes' errors 0.8x the target, margins
    0.9 and 0.8, 4x the time per pixel at the finer one) and one bake preset."""
    fits = {"path/0.05": _fit("path/0.05", 0.04, 0.0, 4e-3, margin=0.9),
            "path/0.1": _fit("path/0.1", 0.08, 0.0, 1e-3, margin=0.8),
            "low/both": _fit("low/both", 0.20, 2.0, 1e-5)}
    return _model(fits=fits)


def test_path_traced_targets_between_the_calibrated_ones_are_planned() -> None:
    from engine.walkthrough.quality import PATH_STEPS_PER_OCTAVE, interpolated_path_fit

    m = _path_model()
    mid = interpolated_path_fit(m, 0.0707)
    # halfway in log noise: the error over the noise (0.8), the margin and log time interpolated
    assert mid.error == pytest.approx(0.8 * 0.0707) and mid.margin == pytest.approx(0.85, abs=1e-3)
    assert mid.c_ms == pytest.approx(2e-3, rel=0.01)
    assert interpolated_path_fit(m, 0.1) is m.fits["path/0.1"]
    with pytest.raises(ValueError, match="outside"):
        interpolated_path_fit(m, 0.2)
    noises = sorted(float(c.fill) for c in predict_walkthrough(m, PX, 10, bakes_ready=ALL) if c.preset == "path")
    assert len(noises) == PATH_STEPS_PER_OCTAVE + 1 and noises[0] == 0.05 and noises[-1] == 0.1
    # a target of 0.07: the calibrated 0.05 meets it (0.04 <= 0.063), but a coarser target between
    # them meets it too and costs less; the plan takes the coarsest that does, not the next calibrated
    p = plan_walkthrough(m, PX, 10, max_error=0.07, bakes_ready=ALL)
    assert p.met and p.choice is not None and p.choice.preset == "path"
    n = float(p.choice.fill)
    assert 0.05 < n < 0.1
    assert p.choice.error <= 0.07 * p.choice.margin
    coarser = interpolated_path_fit(m, min(n * 2 ** (1 / PATH_STEPS_PER_OCTAVE), 0.1))  # the next step would miss
    assert coarser.margin is not None and coarser.error > 0.07 * coarser.margin


def test_served_path_traced_times_fold_under_one_key() -> None:
    from engine.walkthrough.quality import apply_time_corrections, time_key

    assert time_key("path/0.0707") == time_key("path/0.05") == "path" and time_key("low/both") == "low/both"
    m = _path_model()
    corrected, applied = apply_time_corrections(m, {"time": {"path": {"log": float(np.log(2.0)), "n": 5}}})
    assert applied == {"path": pytest.approx(2.0)}
    assert corrected.fits["path/0.1"].c_ms == pytest.approx(2e-3) and corrected.fits["low/both"] == m.fits["low/both"]
