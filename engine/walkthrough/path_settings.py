"""How a path-traced walkthrough frame samples at a noise target (``WalkthroughRequest.path_traced``):
numba-free, so the API sizes a path-traced walkthrough's cost (``producer/costs.py``) with the rule
the frames are rendered with (``engine/walkthrough/ground_truth.py``).

The rule is measured, not derived (``docs/walkthrough.md``, "Path-traced frames"): on frames of both
walkthrough sample scenes at 96 x 72, a fixed count of ``n`` indirect paths per pixel gives an LRMS
against the converged frame of about ``0.3 / sqrt(n)`` (0.10-0.12 at 8 paths, 0.031-0.035 at 64,
0.016-0.024 at 128, with 64 area-light samples), and the direct light's area-light samples cost
little next to the paths (4 -> 64 samples: +10-40 ms a frame) while 4 of them leave a floor of 5-7 %.
A per-pixel adaptive count (a 32-path pilot sizing each pixel's estimate, the pilot's paths
discarded so that stopping does not bias it) reached the same LRMS at 3-6x the time, so the frames
trace a fixed count.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["CONVERGED_AREA_LIGHT_SAMPLES", "PATH_TRACED_MAX_PATHS", "PathTracedSettings", "path_traced_settings"]

CONVERGED_AREA_LIGHT_SAMPLES = 1024
"""Area-light samples per pixel of a converged frame, the most a path-traced frame takes."""
PATH_TRACED_MAX_PATHS = 4096
"""Most indirect paths a pixel of a path-traced walkthrough frame traces (its time bound)."""
PATH_ERROR_PER_PATH = 0.3
"""A frame's LRMS is about this over the square root of the paths per pixel (the module docstring)."""
MIN_AREA_LIGHT_SAMPLES = 64


@dataclass(frozen=True)
class PathTracedSettings:
    """How a path-traced frame at a noise target samples: the direct light's area-light samples per
    pixel, and the indirect paths every pixel traces (``engine.newviews.indirect.IndirectParams``
    with ``min_paths = max_paths``: a fixed count, in 4 rounds whose spread gives each pixel's
    estimated standard error)."""

    area_light_samples: int
    paths: int
    round_paths: int

    @property
    def expected_paths(self) -> float:
        return float(self.paths)


def path_traced_settings(noise: float) -> PathTracedSettings:
    """The sampling of a path-traced frame whose LRMS should be about ``noise``: ``(0.3 / noise)^2``
    paths per pixel rounded up to a power of two (4 .. :data:`PATH_TRACED_MAX_PATHS`), and area-light
    samples a power of 4 from ``(0.16 / noise)^2``, at least 64 (at most 1024)."""
    if not 0.0 < noise < 1.0:
        raise ValueError(f"noise must be in (0, 1), got {noise!r}")
    want = (0.16 / noise) ** 2
    area = MIN_AREA_LIGHT_SAMPLES
    while area < want and area < CONVERGED_AREA_LIGHT_SAMPLES:
        area *= 4
    paths = (PATH_ERROR_PER_PATH / noise) ** 2
    n = 4
    while n < paths and n < PATH_TRACED_MAX_PATHS:
        n *= 2
    return PathTracedSettings(area, n, n // 4)
