"""How a path-traced walkthrough frame samples at a noise target (``WalkthroughRequest.path_traced``):
numba-free, so the API sizes a path-traced walkthrough's cost (``producer/costs.py``) with the rule
the frames are rendered with (``engine/walkthrough/ground_truth.py``)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["ADAPTIVE_FROM_PATHS", "CONVERGED_AREA_LIGHT_SAMPLES", "PATH_TRACED_MAX_PATHS", "PathTracedSettings",
           "path_traced_settings"]

CONVERGED_AREA_LIGHT_SAMPLES = 1024
"""Area-light samples per pixel of a converged frame, the most a path-traced frame takes."""
PATH_TRACED_MAX_PATHS = 4096
"""Most indirect paths a pixel of a path-traced walkthrough frame traces (its time bound): a pixel
that needs more stops short of the target, which the frame's stats report."""


@dataclass(frozen=True)
class PathTracedSettings:
    """How a path-traced frame at a noise target samples: the direct light's area-light samples,
    and the indirect paths per pixel (``engine.newviews.indirect.IndirectParams``: a pilot of
    ``min_paths`` sizing each pixel's estimate up to ``max_paths``; equal, a fixed count)."""

    area_light_samples: int
    min_paths: int
    max_paths: int
    round_paths: int
    expected_paths: float
    """Paths per pixel to expect: the fixed count, or about ``(0.5 / noise)^2`` (the pilot and at
    least as many again, at most ``max_paths``)."""

    @property
    def adaptive(self) -> bool:
        return self.max_paths > self.min_paths


ADAPTIVE_FROM_PATHS = 64
"""Below this many expected paths per pixel a frame traces a fixed count: the pilot (32 paths, and
as many again for the estimate) would cost more than the estimate needs."""


def path_traced_settings(noise: float) -> PathTracedSettings:
    """The sampling of a path-traced frame at relative standard error ``noise`` per pixel: area-light
    samples a power of 4 with the direct light's own noise (penumbrae only) about a fifth of
    ``noise`` (``(0.2 / noise)^2``, 4 .. 1024). Indirect paths: each pixel's are expected to number
    about ``(0.5 / noise)^2`` (a path's relative spread against the frame's brightness is about 0.5
    on the sample scenes: 71, 125 and 587 paths at 0.1, 0.05 and 0.02 on ``cornell_animated``); from
    :data:`ADAPTIVE_FROM_PATHS` on, a pilot of 32 paths (8 rounds of 4) sizes each pixel's estimate
    (at most :data:`PATH_TRACED_MAX_PATHS`); below, every pixel traces that many, a power of two
    (at least 4), in 4 rounds."""
    if not 0.0 < noise < 1.0:
        raise ValueError(f"noise must be in (0, 1), got {noise!r}")
    want = (0.2 / noise) ** 2
    area = 4
    while area < want and area < CONVERGED_AREA_LIGHT_SAMPLES:
        area *= 4
    paths = (0.5 / noise) ** 2
    if paths >= ADAPTIVE_FROM_PATHS:
        return PathTracedSettings(area, 32, PATH_TRACED_MAX_PATHS, 4, min(float(PATH_TRACED_MAX_PATHS), paths))
    n = 4
    while n < paths:
        n *= 2
    return PathTracedSettings(area, n, n, n // 4, float(n))
