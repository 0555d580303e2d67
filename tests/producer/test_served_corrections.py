"""What served contract renders measure is folded into their calibration's corrections
(``producer.calibrations.record_served``), kept beside it, and dropped with a new calibration."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from engine.quality import correction_factor
from producer.calibrations import read_served, record_served, served_path
from producer.store.local import LocalStore

SID, BKEY = "a" * 64, "b" * 64


def _contract(**changes: Any) -> dict[str, Any]:
    doc: dict[str, Any] = {"method": "reference", "params": {"spp": 16}, "predicted_ms": 100.0,
                           "predicted_error": 0.05, "estimated_error": 0.05,
                           "calibration": {"key": "k1", "bake_key": BKEY}}
    doc.update(changes)
    return doc


def test_served_times_and_verified_errors_become_correction_factors(tmp_path: Path) -> None:
    store = LocalStore(tmp_path)
    assert read_served(store, SID, BKEY, "k1") == {}
    record_served(store, SID, _contract(), achieved_ms=300.0)
    record_served(store, SID, _contract(), achieved_ms=300.0)
    served = read_served(store, SID, BKEY, "k1")
    assert served["time"]["reference"]["n"] == 2
    assert correction_factor(served, "time", "reference") == pytest.approx(3.0)
    assert correction_factor(served, "error", "reference") == 1.0  # no verified error yet
    # a plan made with that factor predicted 300 ms: a render of 300 ms confirms it, not 9x
    applied = _contract(predicted_ms=300.0, calibration={"key": "k1", "bake_key": BKEY,
                                                         "corrections": {"time": 3.0, "error": 1.0}})
    record_served(store, SID, applied, achieved_ms=300.0)
    assert correction_factor(read_served(store, SID, BKEY, "k1"), "time", "reference") == pytest.approx(3.0)
    # verified errors of the adaptive reference: measured over the answer's estimate
    adaptive = _contract(params={"spp": 256, "max_error": 0.02}, estimated_error=0.04)
    record_served(store, SID, adaptive, measured_error=0.05)
    doc = record_served(store, SID, adaptive, measured_error=0.05)
    assert doc is not None and doc["error"]["reference@adaptive"]["log"] == pytest.approx(math.log(1.25))
    assert correction_factor(read_served(store, SID, BKEY, "k1"), "error", "reference@adaptive") == \
        pytest.approx(1.25)
    # nothing to fold: no observation, no document written
    assert record_served(store, SID, _contract(calibration={}), achieved_ms=1.0) is None
    assert record_served(store, SID, _contract(estimated_error=None), measured_error=0.01) is None
    # a new calibration (another key) starts afresh
    assert read_served(store, SID, BKEY, "k2") == {}
    record_served(store, SID, _contract(calibration={"key": "k2", "bake_key": BKEY}), achieved_ms=50.0)
    assert read_served(store, SID, BKEY, "k2")["time"]["reference"]["n"] == 1
    assert read_served(store, SID, BKEY, "k1") == {}
    assert store.exists(served_path(SID, BKEY))
