"""The contracts benchmark plans as the service does: served renders' measured times fold into the
model it plans the next request from (through the service's own ``record_served``), and a kept run
can be planned again without them."""

from __future__ import annotations

import pytest

from bench.contracts import _Served, replay_unserved
from engine.quality import CandidateFit, SceneModel, Setting, plan

PX = 64 * 64


def _model() -> SceneModel:
    # reference: 40 % at 1 spp, 1 ms per spp per 1000 pixels, no fixed part; no LDC method
    return SceneModel(scene_id="0" * 64, bake_key="1" * 64, reference=CandidateFit("reference", 0.4, 0.0, 1e-3),
                      methods={}, excluded={}, reference_params={"max_depth": 4}, bake_cost_s=0.0, cost_s=1.0,
                      probe={"views": 4, "width": 64, "height": 64})


def test_served_times_correct_the_next_plans(tmp_path) -> None:
    served = _Served(_model(), str(tmp_path))
    s8 = Setting("reference", 8)
    predicted = served.model().reference.ms_at(PX, 8)  # 32.8 ms
    assert plan(served.model(), PX, max_ms=40.0).choice.setting.spp == 8  # type: ignore[union-attr]
    # the machine is twice as slow as at calibration: one render is noise, the second applies the factor
    served.fold({}, served.model(), s8, predicted, 2 * predicted)
    assert served.model().reference.ms_at(PX, 8) == pytest.approx(predicted)
    applied = served.corrections()
    served.fold(applied, served.model(), s8, predicted, 2 * predicted)
    assert served.folded == 2 and served.model().reference.ms_at(PX, 8) == pytest.approx(2 * predicted)
    assert plan(served.model(), PX, max_ms=40.0).choice.setting.spp == 4  # type: ignore[union-attr]
    # a render planned from the corrected model is made raw again with the factor it applied
    applied = served.corrections()
    served.fold(applied, served.model(), s8, 2 * predicted, 2 * predicted)
    assert served.model().reference.ms_at(PX, 8) == pytest.approx(2 * predicted)
    # switched off (--no-served): the calibration alone
    off = _Served(_model(), str(tmp_path / "off"), enabled=False)
    off.fold({}, off.model(), s8, predicted, 2 * predicted)
    off.fold({}, off.model(), s8, predicted, 2 * predicted)
    assert off.folded == 0 and off.model().reference.ms_at(PX, 8) == pytest.approx(predicted)


def test_a_kept_run_is_planned_again_without_the_corrections() -> None:
    m = _model()
    # a time budget the corrected run met with 4 spp; from the calibration alone 8 spp (32.8 ms <= 0.7 x 50)
    # is chosen, which the view measured at 60 ms: not met
    rows = [{"view": 4.0, "max_error": None, "max_ms": 50.0, "choice": "reference@4spp", "error": 0.2, "ms": 30.0,
             "met": True, "grid_can": True}]
    grids = {"+4": {"reference@8spp": {"error": 0.14, "ms": 60.0}, "reference@4spp": {"error": 0.2, "ms": 30.0}}}
    out = replay_unserved([{"scene": "s", "model": m.to_json(), "requests": rows, "grids": grids}])
    assert out["s"] == {"requests": 1, "met": 0, "unknown": 0, "changed": 1, "met_served": 1}
    # without the view's grid that setting is unknown, not guessed
    out = replay_unserved([{"scene": "s", "model": m.to_json(), "requests": rows}])
    assert out["s"]["unknown"] == 1 and out["s"]["met"] == 0
