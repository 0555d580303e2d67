"""Path-traced walkthrough frames (engine/walkthrough/ground_truth.py): the same image as the
converged frame, each frame's error at its noise target (its pilot sizes its paths), what they
reached reported."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from engine.metrics import lrms
from engine.reference import ReferenceRenderer
from engine.scene import CameraParams
from engine.walkthrough.ground_truth import (
    AREA_LIGHT_SAMPLES,
    SPLIT_ABOVE_PATHS,
    converged_frame,
    path_traced_frame,
)
from engine.walkthrough.path_settings import (
    PATH_TRACED_MAX_PATHS,
    PILOT_PATHS,
    PathTracedSettings,
    path_traced_settings,
    whole_rounds,
)
from tests.engine.scenes import box_room, mat, scene, sphere_mesh

CAM = CameraParams(kind="perspective", eye=(0.0, 1.0, 2.6), look_at=(0.0, 0.8, 0.0), up=(0.0, 1.0, 0.0),
                   fov_y_deg=50.0, width=32, height=24)


@pytest.fixture(scope="module")
def room() -> dict:
    rr = ReferenceRenderer(box_room())
    truth, covered, region, st = converged_frame(rr, CAM, 0, 99, 0.01, 2)
    return {"rr": rr, "truth": truth, "covered": covered, "region": region, "st": st}


def test_settings_scale_with_the_noise_target() -> None:
    # the paths a frame is expected to trace, (0.3 / noise)^2 in whole rounds (at least the pilot's);
    # area-light samples a power of 4, at least 64
    assert path_traced_settings(0.2) == PathTracedSettings(64, 4)
    assert path_traced_settings(0.1) == PathTracedSettings(64, 9)
    assert path_traced_settings(0.05) == PathTracedSettings(64, 36)
    assert path_traced_settings(0.02) == PathTracedSettings(64, 240)
    assert path_traced_settings(0.01) == PathTracedSettings(256, 960)
    assert path_traced_settings(0.001) == PathTracedSettings(AREA_LIGHT_SAMPLES, PATH_TRACED_MAX_PATHS)
    assert path_traced_settings(0.05).pilot_paths == PILOT_PATHS
    with pytest.raises(ValueError):
        path_traced_settings(0.0)


@pytest.mark.parametrize("paths", [0.5, 2, 3, 7, 8, 15, 16, 17, 100, 225, 1000, 4096])
def test_whole_rounds_cost_at_most_an_eighth_more(paths: float) -> None:
    n, r = whole_rounds(paths)
    assert n >= max(2, paths) and n % r == 0 and r & (r - 1) == 0 and n // r >= 2
    if paths >= 16:
        assert 8 <= n // r <= 16 and n < paths * 1.125 + r
    else:
        assert r == 1 and n == max(2, int(np.ceil(paths)))


def test_each_frame_reaches_its_noise_target(room: dict) -> None:
    """Against a converged frame of another seed, a frame's LRMS is about its target (at most the
    target with the converged frame's own 1 % noise in quadrature, and not far below it: the pilot
    sized the paths for it, unless the pilot alone is under it), the frame's own estimate says so,
    and a lower target is closer."""
    errs = {}
    for noise in (0.2, 0.05):
        img, covered, st = path_traced_frame(room["rr"], CAM, 0, 5, noise, 2)
        assert np.array_equal(covered, room["covered"])
        errs[noise] = lrms(img, room["truth"], room["region"])
        assert errs[noise] < np.hypot(1.15 * noise, 0.012), (noise, errs[noise])
        assert st["pilot_paths"] == PILOT_PATHS and st["paths_mean"] >= PILOT_PATHS
        assert 0.5 * noise < st["estimated_error"] <= 1.1 * noise or st["paths_mean"] == PILOT_PATHS, st
        if st["paths_mean"] > PILOT_PATHS:  # sized for the target: not far below it
            assert 0.6 * noise < errs[noise], (noise, errs[noise])
    assert errs[0.05] < errs[0.2] / 2
    # a fine target: the pilot asks for many paths as if the error fell as 1 / sqrt(paths); half of
    # them first, and the rest sized from those, land the estimate at the target with fewer paths
    _, _, st = path_traced_frame(room["rr"], CAM, 0, 5, 0.02, 2)
    want = PILOT_PATHS * (st["pilot_error"] / 0.02) ** 2
    assert want > 2 * SPLIT_ABOVE_PATHS and want / 2 <= st["paths_mean"] < want, (want, st["paths_mean"])
    assert 0.9 * 0.02 < st["estimated_error"] < 1.05 * 0.02, st
    # the mean agrees with the converged frame's
    img, _, _ = path_traced_frame(room["rr"], CAM, 0, 6, 0.03, 2)
    m = room["region"]
    assert abs(img[m].mean() / room["truth"][m].mean() - 1) < 0.01


def test_the_estimate_predicts_the_error_over_seeds(room: dict) -> None:
    """The frame's estimated LRMS against the measured one, over seeds: the estimate is not below the
    measured error by more than its own spread (a contract is planned on it) and not far above."""
    ratios = []
    for seed in range(6):
        img, _, st = path_traced_frame(room["rr"], CAM, 0, 100 + seed, 0.1, 2)
        measured = np.sqrt(max(lrms(img, room["truth"], room["region"]) ** 2 - 0.01 ** 2, 0.0))
        ratios.append(measured / st["estimated_error"])
    assert 0.6 < float(np.mean(ratios)) < 1.1, ratios


def test_deterministic_per_seed_and_frame(room: dict) -> None:
    a = path_traced_frame(room["rr"], CAM, 3, 1, 0.1, 2)[0]
    b = path_traced_frame(room["rr"], CAM, 3, 1, 0.1, 2)[0]
    c = path_traced_frame(room["rr"], CAM, 4, 1, 0.1, 2)[0]
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_no_indirect_paths_where_none_can_arrive() -> None:
    """One convex closed object lit from outside under a black background: every path leaving it
    escapes, so a path-traced frame traces none (its stats say why) and is the same image as one
    forced to trace them; the room above is traced."""
    ball = scene([(sphere_mesh(radius=0.5, subdivisions=3), mat("d", kd=(0.7, 0.6, 0.5)))],
                 [dict(type="point", position=(0.0, 2.0, 2.0), intensity=(5.0, 5.0, 5.0))])
    rr = ReferenceRenderer(ball)
    cam = CameraParams(kind="perspective", eye=(0.0, 0.3, 2.5), look_at=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                       fov_y_deg=40.0, width=24, height=24)
    skipped, covered, st = path_traced_frame(rr, cam, 0, 3, 0.05, 2)
    assert covered.any() and skipped[covered].max() > 0
    assert "convex" in st["indirect_skip"] and st["paths_mean"] == 0
    forced, _, st_forced = path_traced_frame(rr, cam, 0, 3, 0.05, 2, indirect_skip="")
    assert st_forced["indirect_skip"] == "" and st_forced["paths_mean"] >= PILOT_PATHS
    assert np.array_equal(skipped, forced)
    _, _, st_room = path_traced_frame(ReferenceRenderer(box_room()), CAM, 0, 3, 0.2, 2)
    assert st_room["indirect_skip"] == "" and st_room["paths_mean"] >= PILOT_PATHS


def test_a_frame_cut_by_its_budget_ends_within_it(room: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    """A stage cut to the time left must leave room for the paths whole rounds add (up to 1/8 more
    than it asks for): with a clock that advances exactly 1 ms per traced path, a 105 ms budget cut
    to 101 more paths after the pilot's 4 would trace 104 and end at 108 ms. The frame ends within
    its budget and spends most of it."""
    from engine.walkthrough import ground_truth

    clock = [0.0]
    trace = ground_truth.trace_indirect_points

    def timed_trace(*args: Any, **kwargs: Any) -> Any:
        clock[0] += 1e-3 * args[6].max_paths  # the stage's paths (IndirectParams), 1 ms each
        return trace(*args, **kwargs)

    monkeypatch.setattr(ground_truth, "time", SimpleNamespace(perf_counter=lambda: clock[0]))
    monkeypatch.setattr(ground_truth, "trace_indirect_points", timed_trace)
    st = path_traced_frame(room["rr"], CAM, 0, 5, 0.005, 2, max_ms=105.0)[2]
    assert st["stopped_by"] == "time"
    assert 0.7 * 105.0 <= 1000.0 * clock[0] <= 105.0


def test_a_time_budget_stops_the_paths_and_the_frame_says_so(room: dict) -> None:
    """With a budget a frame cannot keep, it traces its direct light and pilot, stops there, and its
    estimate states the error it reached; without one (or with room to spare) it reaches the target."""
    free = path_traced_frame(room["rr"], CAM, 0, 5, 0.02, 2)[2]
    assert free["stopped_by"] == "noise" and free["paths_mean"] > 2 * PILOT_PATHS
    tight = path_traced_frame(room["rr"], CAM, 0, 5, 0.02, 2, max_ms=1e-3)[2]
    assert tight["stopped_by"] == "time" and tight["paths_mean"] == PILOT_PATHS
    assert tight["estimated_error"] == pytest.approx(tight["pilot_error"]) and tight["estimated_error"] > 0.02
    roomy = path_traced_frame(room["rr"], CAM, 0, 5, 0.02, 2, max_ms=600_000.0)[2]
    assert roomy["stopped_by"] == "noise" and roomy["paths_mean"] == free["paths_mean"]
