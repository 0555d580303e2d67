"""Path-traced walkthrough frames (engine/walkthrough/ground_truth.py): the same image as the
converged frame, their error falling with the noise target, what they reached reported."""

from __future__ import annotations

import numpy as np
import pytest

from engine.metrics import lrms
from engine.reference import ReferenceRenderer
from engine.scene import CameraParams
from engine.walkthrough.ground_truth import AREA_LIGHT_SAMPLES, converged_frame, path_traced_frame
from engine.walkthrough.path_settings import PATH_TRACED_MAX_PATHS, PathTracedSettings, path_traced_settings
from tests.engine.scenes import box_room, mat, scene, sphere_mesh

CAM = CameraParams(kind="perspective", eye=(0.0, 1.0, 2.6), look_at=(0.0, 0.8, 0.0), up=(0.0, 1.0, 0.0),
                   fov_y_deg=50.0, width=32, height=24)


@pytest.fixture(scope="module")
def room() -> dict:
    rr = ReferenceRenderer(box_room())
    truth, covered, region, st = converged_frame(rr, CAM, 0, 99, 0.01, 2)
    return {"rr": rr, "truth": truth, "covered": covered, "region": region, "st": st}


def test_settings_scale_with_the_noise_target() -> None:
    # a fixed count per pixel, a power of two from (0.3 / noise)^2; area-light samples at least 64
    assert path_traced_settings(0.2) == PathTracedSettings(64, 4, 1)
    assert path_traced_settings(0.1) == PathTracedSettings(64, 16, 4)
    assert path_traced_settings(0.05) == PathTracedSettings(64, 64, 16)
    assert path_traced_settings(0.02) == PathTracedSettings(64, 256, 64)
    assert path_traced_settings(0.01) == PathTracedSettings(256, 1024, 256)
    assert path_traced_settings(0.001) == PathTracedSettings(AREA_LIGHT_SAMPLES, PATH_TRACED_MAX_PATHS, 1024)
    assert path_traced_settings(0.05).expected_paths == 64
    assert path_traced_settings(0.001).area_light_samples == AREA_LIGHT_SAMPLES
    with pytest.raises(ValueError):
        path_traced_settings(0.0)


def test_error_falls_with_the_noise_target_toward_the_converged_frame(room: dict) -> None:
    """Against a converged frame of another seed, the LRMS tracks the target (the converged frame's
    own 1 % noise adds in quadrature) and a lower target is closer; the stats say what each pixel
    traced and reached."""
    errs = {}
    for noise in (0.2, 0.03):
        img, covered, st = path_traced_frame(room["rr"], CAM, 0, 5, noise, 2)
        assert np.array_equal(covered, room["covered"])
        errs[noise] = lrms(img, room["truth"], room["region"])
        assert errs[noise] < 1.5 * noise + 0.01, (noise, errs[noise])
        assert st["paths_mean"] == path_traced_settings(noise).paths
    assert errs[0.03] < errs[0.2] and errs[0.2] > 0.01
    # the mean agrees with the converged frame's (no bias from stopping per pixel)
    img, _, _ = path_traced_frame(room["rr"], CAM, 0, 6, 0.03, 2)
    m = room["region"]
    assert abs(img[m].mean() / room["truth"][m].mean() - 1) < 0.01


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
    assert st_forced["indirect_skip"] == "" and st_forced["paths_mean"] == 64
    assert np.array_equal(skipped, forced)
    _, _, st_room = path_traced_frame(ReferenceRenderer(box_room()), CAM, 0, 3, 0.2, 2)
    assert st_room["indirect_skip"] == "" and st_room["paths_mean"] == 4
