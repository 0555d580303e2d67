"""The walkthrough calibration (workers/jobs/calibrate_walkthrough.py) on a small animated scene:
every preset and fill gets a fit, and its predicted error holds on a frame it was not fitted on
(measured against that frame's own converged render)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from api_schemas.scene import Scene
from api_schemas.walkthrough import WalkthroughCalibrationParams
from engine.metrics import lrms
from engine.reference import ReferenceRenderer
from engine.walkthrough.bake import WalkthroughBake, WalkthroughRenderer, bake_walkthrough, walkthrough_preset
from engine.walkthrough.ground_truth import converged_frame, path_traced_frame
from engine.walkthrough.quality import plan_walkthrough
from tests.service.api.test_walkthroughs import ROOM
from workers.jobs.calibrate_walkthrough import calibrate_walkthrough, probe_views
from workers.jobs.walkthrough import engine_space
from workers.scene_loader import camera_params, directory_resolver, load_animated_scene

SMALL = {"face_res": 16, "max_views": 2, "max_time_samples": 3}
"""Bakes small enough for a test (the calibration measures whatever bake it is given)."""


@pytest.fixture(scope="module")
def calibrated() -> dict[str, Any]:
    scene = Scene.model_validate(ROOM)
    an = load_animated_scene(scene, directory_resolver(Path(".")))
    space = engine_space(scene)
    bakes: dict[str, WalkthroughBake] = {}

    def bake_for(preset: str, progress: Any) -> tuple[WalkthroughBake, str, float]:
        t0 = time.perf_counter()
        bakes[preset] = bake_walkthrough(an, space, walkthrough_preset(preset, **SMALL), progress=progress)
        return bakes[preset], preset[0] * 64, time.perf_counter() - t0

    params = WalkthroughCalibrationParams(presets=["low", "medium"], fills=["both", "trace"], probes=2, size=32,
                                          truth_noise=0.02, path_noises=[0.05, 0.2])
    stages: list[tuple[float, str]] = []
    model = calibrate_walkthrough(an, space, camera_params(scene.camera), bake_for, params=params,
                                  progress=lambda f, s: stages.append((f, s)))
    return {"model": model, "an": an, "space": space, "scene": scene, "bakes": bakes, "stages": stages,
            "params": params}


def test_every_preset_and_fill_is_measured(calibrated: dict[str, Any]) -> None:
    m = calibrated["model"]
    assert set(m.fits) == {"low/both", "low/trace", "medium/both", "medium/trace", "path/0.05", "path/0.2"}
    for fit in m.fits.values():
        assert 0.0 < fit.error < 0.5 and fit.b_ms >= 0 and fit.c_ms >= 0
        assert fit.margin is not None and 0.5 <= fit.margin <= 1.0
        assert len([p for p in fit.points if p["error"] is not None]) == 4  # two eyes, two views each
    assert m.bake_keys == {"low": "l" * 64, "medium": "m" * 64} and all(s > 0 for s in m.bake_cost_s.values())
    assert len(m.probe["frames"]) == 4 and m.cost_s > 0
    assert set(m.probe["cost_breakdown_s"]) == {"ground_truth", "bakes", "settings", "path_traced"}
    # path-traced frames: time per pixel only (this room's little indirect light leaves both targets at
    # their pilot paths: the noise ordering is tested on a closed box, tests/engine/test_walkthrough.py)
    fine, coarse = m.fits["path/0.05"], m.fits["path/0.2"]
    assert fine.b_ms == coarse.b_ms == 0 and fine.c_ms > 0 and coarse.c_ms > 0 and fine.error <= coarse.error
    assert 0 <= m.probe["truth_noise"] < 0.05
    stages = calibrated["stages"]
    converged = [s for _, s in stages if s.startswith("converged")]
    assert converged == [f"converged probe frame {i} of 4" for i in (1, 2, 3, 4)]
    fractions = [f for f, _ in stages]
    assert fractions == sorted(fractions) and 0 <= fractions[0] and fractions[-1] < 1
    # the probes move through the view space and the animation; at each eye one view looks the way the
    # scene camera looks (+z), the other where there is most room (diagonally along the 40 m wall)
    frames = m.probe["frames"]
    assert [f["time"] for f in frames] == [0.5, 0.5, 1.5, 1.5]
    assert [f["eye"] for f in frames] == [[-0.5, 0, 0], [-0.5, 0, 0], [0.5, 0, 0], [0.5, 0, 0]]
    dirs = [np.subtract(f["look_at"], f["eye"]) for f in frames]
    assert np.allclose(dirs[0], [0, 0, 1]) and np.allclose(dirs[2], [0, 0, 1])
    assert abs(dirs[1][0]) > 0.5 and dirs[1][2] > 0.5


def test_predicted_error_holds_on_a_held_out_frame(calibrated: dict[str, Any]) -> None:
    """A frame between the probes, at another time: each setting's measured error stays within its
    prediction (the worst probe's) times 1.5, and above a third of it (the model is not vacuous)."""
    m, an = calibrated["model"], calibrated["an"]
    cam = probe_views(camera_params(calibrated["scene"].camera), (0.1, 0.0, 0.0), 32)[0]
    t = 1.1
    truth, _, mask, _ = converged_frame(ReferenceRenderer(an.scene_at(t)), cam, 9, 123, 0.02, 2)
    ratios = {}
    rr = ReferenceRenderer(an.scene_at(t))
    for name, fit in m.fits.items():
        preset, fill = name.split("/")
        if preset == "path":
            img = path_traced_frame(rr, cam, 9, 0, float(fill), 2)[0]
            # each frame stops at its own estimate of the noise target (this room's little indirect light
            # leaves the pilot's paths far below it): the bound, and the target itself
            got = lrms(img, truth, mask)
            assert got < 1.5 * fit.error and got < float(fill), name
            continue
        wr = WalkthroughRenderer(calibrated["bakes"][preset], an if fill == "trace" else None)
        img = wr.render(cam, t, fill=fill, strict=False).radiance
        ratios[name] = lrms(img, truth, mask) / fit.error
    assert len(ratios) == 4 and all(1 / 3 < r < 1.5 for r in ratios.values()), ratios


def test_the_calibrated_model_plans_a_contract(calibrated: dict[str, Any]) -> None:
    m = calibrated["model"]
    errors = sorted(f.error for f in m.fits.values())
    p = plan_walkthrough(m, 16 * 12, 5, max_error=errors[-1] * 1.2, bakes_ready={"low", "medium"})
    assert p.met and p.choice is not None
    assert p.choice.error <= errors[-1] * 1.2 * p.choice.margin
    p = plan_walkthrough(m, 16 * 12, 5, max_error=errors[0] * 0.5, bakes_ready={"low", "medium"})
    assert p.choice is None and "no walkthrough setting reaches" in p.reason
    assert np.isfinite(m.fits["low/both"].ms_at(16 * 12, None))
