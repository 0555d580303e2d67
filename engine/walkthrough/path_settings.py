"""How a path-traced walkthrough frame samples at a noise target (``WalkthroughRequest.path_traced``):
numba-free, so the API sizes a path-traced walkthrough's cost (``producer/costs.py``) with the rule
the frames are rendered with (``engine/walkthrough/ground_truth.py``).

A path-traced frame aims at a frame LRMS of ``noise`` against the converged frame, frame by frame:
every pixel first traces :data:`PILOT_PATHS` indirect paths, the spread of their rounds estimates
the whole frame's LRMS at that count (the pixels' standard errors over the mean brightness), and
every pixel then traces the paths that bring that estimate to ``noise`` (error ~ 1 / sqrt(paths)),
the pilot's included; when that is many, half of them first and the rest sized from those
(``engine.walkthrough.ground_truth.SPLIT_ABOVE_PATHS``). Why per frame and not per pixel: a
per-pixel count (a 32-path pilot sizing each pixel's estimate) reached the same LRMS at 3-6x the
time, since a frame's LRMS weighs every pixel's absolute error against the frame's mean brightness;
and why not one rule for every frame:
a fixed ``(0.3 / noise)^2`` paths per pixel (the count measured on frames of both walkthrough sample
scenes, 0.3 / sqrt(n) being their typical LRMS at n paths) left the worst frames at up to 1.3x the
error the rule expected (docs/accuracy/walkthrough_contracts.md), so a contract had to plan for them.

:data:`PATH_ERROR_PER_PATH` remains the rule a cost estimate uses before a frame is traced; the
direct light's area-light samples are sized from the target alone (they cost little next to the
paths: 4 -> 64 samples, +10-40 ms a frame at 96 x 72, while 4 of them leave a floor of 5-7 %).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["CONVERGED_AREA_LIGHT_SAMPLES", "PATH_ERROR_PER_PATH", "PATH_TRACED_MAX_PATHS", "PILOT_PATHS",
           "WHOLE_ROUNDS_MAX_EXCESS", "PathTracedSettings", "path_traced_settings", "whole_rounds"]

CONVERGED_AREA_LIGHT_SAMPLES = 1024
"""Area-light samples per pixel of a converged frame, the most a path-traced frame takes."""
PATH_TRACED_MAX_PATHS = 4096
"""Most indirect paths a pixel of a path-traced walkthrough frame traces (its time bound)."""
PATH_ERROR_PER_PATH = 0.3
"""A frame's LRMS is typically this over the square root of the paths per pixel (the module
docstring): what a frame is expected to trace before its pilot measures it."""
PILOT_PATHS = 4
"""Paths per pixel of a frame's pilot, in four rounds of one (their spread is the estimate)."""
MIN_AREA_LIGHT_SAMPLES = 64
WHOLE_ROUNDS_MAX_EXCESS = 0.125
"""The most :func:`whole_rounds` adds to the paths asked for, as a fraction of them (8 to 16 rounds)."""


def whole_rounds(paths: float) -> tuple[int, int]:
    """``(count, round)``: at least ``paths`` paths (and at least 2) in whole rounds of a power of two
    paths, 8 to 16 rounds once there are 8 paths or more, so that rounding costs at most
    :data:`WHOLE_ROUNDS_MAX_EXCESS` more paths (the indirect pass draws a round as one stratified
    block of its sequence and needs two rounds for a standard error)."""
    n = max(2, math.ceil(paths - 1e-9))
    r = 1
    while 16 * r <= n:
        r *= 2
    return -(-n // r) * r, r


@dataclass(frozen=True)
class PathTracedSettings:
    """How a path-traced frame at a noise target samples: the direct light's area-light samples per
    pixel, the pilot's paths, and the paths a pixel is expected to trace in all (:data:`PATH_ERROR_PER_PATH`;
    the frame's pilot decides), at most :data:`PATH_TRACED_MAX_PATHS`."""

    area_light_samples: int
    expected_paths: int
    pilot_paths: int = PILOT_PATHS
    max_paths: int = PATH_TRACED_MAX_PATHS


def path_traced_settings(noise: float) -> PathTracedSettings:
    """The sampling of a path-traced frame whose LRMS should be ``noise``: area-light samples a power
    of 4 from ``(0.16 / noise)^2``, at least 64 (at most 1024), and ``(0.3 / noise)^2`` paths per pixel
    expected (in whole rounds, at least the pilot's, at most :data:`PATH_TRACED_MAX_PATHS`)."""
    if not 0.0 < noise < 1.0:
        raise ValueError(f"noise must be in (0, 1), got {noise!r}")
    want = (0.16 / noise) ** 2
    area = MIN_AREA_LIGHT_SAMPLES
    while area < want and area < CONVERGED_AREA_LIGHT_SAMPLES:
        area *= 4
    expected = min(whole_rounds(max(PILOT_PATHS, (PATH_ERROR_PER_PATH / noise) ** 2))[0], PATH_TRACED_MAX_PATHS)
    return PathTracedSettings(area, expected)
