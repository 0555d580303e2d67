"""Per-method readiness of a warm-up (workers/warmup_readiness.py): states in warm-up order,
estimates from the cold step costs scaled by the run's own speed, failures."""

from __future__ import annotations

import pytest

from api_schemas.readiness import READINESS_METHODS
from workers import warmup
from workers.warmup_readiness import COLD_STEP_SECONDS, METHOD_STEPS, ReadinessTracker


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_every_step_has_a_cold_cost_and_every_kind_its_steps() -> None:
    assert list(COLD_STEP_SECONDS) == list(warmup.STEPS)  # in step order (the runner's first document)
    assert set(METHOD_STEPS) == set(READINESS_METHODS)
    for steps in METHOD_STEPS.values():
        assert set(steps) <= set(warmup.STEPS)
    # the user's order: reference, then the LDC methods, then relighting, then walkthroughs
    last = {m: max(warmup.STEPS.index(s) for s in steps) for m, steps in METHOD_STEPS.items()}
    assert last["reference"] < last["ldc"] < last["ldc+llf"] < last["ldc+ibrt"] < last["relight"] < last["walkthrough"]


def test_lanes_split_the_steps_and_keep_each_kind_and_its_needs_together() -> None:
    assert [s for lane in warmup.LANES for s in lane] == list(warmup.STEPS)
    assert warmup.lanes_for(1) == (warmup.STEPS,) and warmup.lanes_for(2) == warmup.LANES
    needs = {name: deps for name, _, deps in warmup._plan(warmup._Run(None))}
    for lane in warmup.LANES:
        assert all(set(needs[s]) <= set(lane) for s in lane)
    for method, steps in METHOD_STEPS.items():
        assert sum(set(steps) <= set(lane) for lane in warmup.LANES) == 1, method
    kinds = [set(ReadinessTracker(lane, "w").states()) for lane in warmup.LANES]
    assert kinds[0] | kinds[1] == set(READINESS_METHODS) and not kinds[0] & kinds[1]
    assert "reference" in kinds[0] and "relight" in kinds[1]


def test_states_and_estimates_follow_the_steps() -> None:
    clock = Clock()
    cold = {"a": 10.0, "b": 20.0, "c": 40.0}
    tr = ReadinessTracker(["a", "b", "c"], "w1", cold=cold, clock=clock)
    assert tr.seconds_until("a") == 10.0 and tr.seconds_until("c") == 70.0
    tr.started("a")
    clock.t += 4.0
    assert tr.seconds_until("a") == pytest.approx(6.0)
    assert tr.seconds_until("b") == pytest.approx(26.0)
    tr.finished("a", 5.0, True)  # twice as fast as the cold cost: later steps scaled by 0.5
    assert tr.seconds_until("a") == 0.0
    assert tr.seconds_until("c") == pytest.approx(30.0)
    tr.started("b")
    clock.t += 30.0  # far past its estimate: the running step counts 0, never negative
    assert tr.seconds_until("b") == 0.0 and tr.seconds_until("c") == pytest.approx(20.0)
    tr.finished("b", 30.0, False)
    tr.end()  # c never ran: failed
    assert tr.seconds_until("c") == 0.0 and tr.finished_all


def test_document_per_kind() -> None:
    clock = Clock()
    tr = ReadinessTracker(list(warmup.STEPS), "w1", clock=clock)
    doc = tr.document()
    assert doc["worker"] == "w1" and doc["finished"] is False
    assert list(doc["methods"]) == list(READINESS_METHODS)
    assert all(v["state"] == "compiling" for v in doc["methods"].values())
    ref_cold = sum(COLD_STEP_SECONDS[s] for s in METHOD_STEPS["reference"])
    assert doc["methods"]["reference"]["seconds_left"] == pytest.approx(ref_cold, abs=0.1)
    left = [doc["methods"][m]["seconds_left"] for m in ("reference", "ldc+ibrt", "relight", "walkthrough")]
    assert left == sorted(left)
    for s in METHOD_STEPS["reference"]:
        tr.started(s)
        tr.finished(s, COLD_STEP_SECONDS[s], True)
    tr.started("ldc-bake")
    tr.finished("ldc-bake", 1.0, False)
    states = tr.document()["methods"]
    assert states["reference"] == {"state": "ready", "seconds_left": None}
    assert states["ldc"]["state"] == states["ldc+llf"]["state"] == "failed"
    assert states["relight"]["state"] == "compiling" and states["relight"]["seconds_left"] > 0
    tr.end()
    assert tr.document()["finished"] is True
    assert tr.document()["methods"]["walkthrough"]["state"] == "failed"


def test_the_step_graph_is_engine_free_and_names_every_relight_store() -> None:
    """``workers.warmup_steps`` lets the render worker start its warm-up before importing the engine:
    it imports no numba; its relight steps are the warm-up's store kinds, one each."""
    import subprocess
    import sys

    code = "import sys, workers.warmup_steps, workers.warmup_readiness; print('numba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    from workers.warmup_steps import RELIGHT_STORE_STEPS

    assert [f"relight-{suffix}" for suffix, _, _ in warmup._RELIGHT_STORES] == list(RELIGHT_STORE_STEPS)
