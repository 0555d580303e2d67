"""What served walkthroughs measured corrects the walkthrough planner's frame times
(producer/walkthrough_calibrations.py): the slowest frame of each walkthrough planned from a contract
(each chunk's first frame left out) against its prediction, a running factor per setting (one for
every path-traced noise target)."""

from __future__ import annotations

from pathlib import Path

import pytest

from api_schemas.walkthrough import WalkthroughRequest
from engine import ENGINE_VERSION
from engine.quality import CandidateFit
from engine.walkthrough.quality import WalkthroughModel
from producer.errors import ContractUnmet
from producer.store import LocalStore
from producer.walkthrough_calibrations import (
    plan_walkthrough_request,
    read_served_walkthroughs,
    record_served_walkthrough,
    write_walkthrough_calibration,
)

SCENE = "a" * 64


def _model() -> WalkthroughModel:
    fits = {"path/0.2": CandidateFit("path/0.2", 0.2, 0.0, 0.05, margin=1.0),
            "path/0.05": CandidateFit("path/0.05", 0.05, 0.0, 0.5, margin=1.0)}
    return WalkthroughModel(scene_id=SCENE, fits=fits, excluded={}, bake_keys={}, bake_cost_s={}, cost_s=1.0,
                            probe={"frames": []}, engine_version=ENGINE_VERSION)


def _request(max_ms: float | None = None) -> WalkthroughRequest:
    frames = [{"time": 0.0, "camera": {"type": "perspective", "eye": [0, 0, 0], "look_at": [0, 0, 1], "width": 16,
                                       "height": 12}} for _ in range(4)]
    quality = {"max_error": 0.3} if max_ms is None else {"max_ms": max_ms}
    return WalkthroughRequest.model_validate({"scene_id": SCENE, "frames": frames, "quality": quality})


@pytest.fixture
def store(tmp_path: Path) -> LocalStore:
    s = LocalStore(tmp_path)
    write_walkthrough_calibration(s, SCENE, "k" * 64, {}, _model())
    return s


def test_slow_frames_raise_the_prediction_after_two_walkthroughs(store: LocalStore) -> None:
    _, c = plan_walkthrough_request(store, _request())
    assert c.path_noise == 0.2 and c.predicted_frame_ms == pytest.approx(0.05 * 192)
    assert c.calibration["time_corrections"] == {}
    slow = 2 * c.predicted_frame_ms
    # each chunk's first frame (its process loading the kernels) is left out: 300 ms counts for nothing
    doc = record_served_walkthrough(store, SCENE, c, [[300.0, slow, 0.5 * slow], [300.0, slow]])
    assert doc is not None and doc["time"]["path"]["n"] == 1
    _, c1 = plan_walkthrough_request(store, _request())
    assert c1.predicted_frame_ms == pytest.approx(c.predicted_frame_ms)  # one observation applies nothing
    record_served_walkthrough(store, SCENE, c1, [[300.0, slow, slow]])
    _, c2 = plan_walkthrough_request(store, _request())
    assert c2.predicted_frame_ms == pytest.approx(2 * c.predicted_frame_ms)
    assert c2.calibration["time_corrections"] == {"path": pytest.approx(2.0)}  # every noise target's
    # folded raw again: a walkthrough planned with the factor, as slow as the factor says, keeps it at 2
    record_served_walkthrough(store, SCENE, c2, [[300.0, c2.predicted_frame_ms]])
    _, c3 = plan_walkthrough_request(store, _request())
    assert c3.predicted_frame_ms == pytest.approx(2 * c.predicted_frame_ms)


def test_a_budget_follows_the_corrected_times(store: LocalStore) -> None:
    # 0.05 * 192 = 9.6 ms per frame at noise 0.2 fits 12 ms (and so does a noise target a little finer,
    # between the calibrated ones); twice that does not, and the planner says so
    _, c = plan_walkthrough_request(store, _request(max_ms=12.0))
    assert c.path_noise is not None and 0.05 < c.path_noise <= 0.2 and c.met
    for _ in range(2):
        record_served_walkthrough(store, SCENE, c, [[1.0, 2 * c.predicted_frame_ms]])
    with pytest.raises(ContractUnmet) as exc:
        plan_walkthrough_request(store, _request(max_ms=12.0))
    assert "no walkthrough setting renders a frame within 12 ms" in str(exc.value) and "19 ms" in str(exc.value)


def test_nothing_to_fold_and_another_calibration_starts_afresh(store: LocalStore) -> None:
    _, c = plan_walkthrough_request(store, _request())
    assert record_served_walkthrough(store, SCENE, c, [[5.0], [6.0]]) is None  # first frames only
    for _ in range(2):
        record_served_walkthrough(store, SCENE, c, [[1.0, 3 * c.predicted_frame_ms]])
    assert read_served_walkthroughs(store, SCENE, "k" * 64)["time"]["path"]["n"] == 2
    write_walkthrough_calibration(store, SCENE, "j" * 64, {}, _model())
    assert read_served_walkthroughs(store, SCENE, "j" * 64) == {}
    _, c2 = plan_walkthrough_request(store, _request())
    assert c2.predicted_frame_ms == pytest.approx(c.predicted_frame_ms)


def test_a_time_budget_planned_onto_path_traced_frames_bounds_each_frame(store: LocalStore) -> None:
    planned, c = plan_walkthrough_request(store, _request(max_ms=12.0))
    assert c.path_noise is not None and planned.path_traced is not None
    assert planned.path_traced.max_ms == 12.0 and planned.path_traced.noise == c.path_noise
    planned, c = plan_walkthrough_request(store, _request())  # an error target alone: no budget
    assert planned.path_traced is not None and planned.path_traced.max_ms is None
