"""How many indirect paths an LDC sample side traces: numba-free, so the API prices a bake
(``producer/costs.py``, ``workers/jobs/bake.py``) with the rule the bake traces by
(``engine/newviews/indirect.py``).

Two samplers, ``IndirectParams.sampling``:

- ``fixed`` (the default): every traced side takes the same count, sized from the noise target:
  ``(FIXED_PATHS_SCALE / noise)^2`` rounded to the nearest power of two, within ``min_paths`` ..
  ``max_paths``; no pilot. The count's paths are the estimate, and the spread of their round means
  its reported standard error.
- ``adaptive``: a pilot of ``min_paths`` paths per side sizes the side's own estimate for the noise
  target (relative to its brightness), on fresh paths, up to ``max_paths`` in all.

Why fixed is the default (``python -m bench.indirect_sampling``, ``docs/accuracy/gi.md``,
"Sampling the indirect pass"): what a view's error measures is the absolute error summed over
the pixels (LRMS is relative to the image, not to each sample), and the adaptive sampler spends
its paths on the sides whose relative error is large: dark sides and the sides whose pilot caught a
rare bright path (through a mirror), while a side whose pilot missed those paths gets a small
estimate and, if its fresh paths meet one, ends as a bright speckle. Its discarded pilot costs
another 64 paths a side. At equal view error the fixed count baked the Cornell box in 0.63x the time
(256 paths against the adaptive sampler at noise 0.02) and the mirror / glossy Cornell box in 0.43x
(128 paths against noise 0.05). ``FIXED_PATHS_SCALE`` puts noise 0.02, the API's default, at the
256 paths that matched the adaptive sampler's view error there.
"""

from __future__ import annotations

import math

__all__ = ["FIXED_PATHS_SCALE", "SAMPLINGS", "expected_paths_per_side", "fixed_paths"]

SAMPLINGS = ("fixed", "adaptive")

FIXED_PATHS_SCALE = 0.32
"""The fixed sampler traces ``(FIXED_PATHS_SCALE / noise)^2`` paths per side (nearest power of
two): noise 0.02 -> 256, 0.014 -> 512, 0.03 -> 128 (the module docstring)."""

ADAPTIVE_SHARE = 0.2
"""The adaptive sampler's expected paths per side, as a share of the way from ``min_paths`` to
``max_paths``: a rough figure for the bake's cost estimate, which its CPU limit checks against."""


def fixed_paths(noise: float, min_paths: int, max_paths: int, round_paths: int) -> int:
    """Paths per side of the fixed sampler: the power of two nearest ``(FIXED_PATHS_SCALE / noise)^2``
    (on a log scale), at least ``min_paths``, at most ``max_paths`` rounded down to whole rounds of
    ``round_paths`` (and at least two rounds, whose spread gives the standard error)."""
    if not 0.0 < noise < 1.0:
        raise ValueError(f"noise must be in (0, 1), got {noise!r}")
    want = (FIXED_PATHS_SCALE / noise) ** 2
    n = 1 << max(0, round(math.log2(want)))
    n = max(n, min_paths, 2 * round_paths)
    top = max(2 * round_paths, max_paths // round_paths * round_paths)
    n = min(n, top)
    return -(-n // round_paths) * round_paths


def expected_paths_per_side(sampling: str, noise: float, min_paths: int, max_paths: int, round_paths: int) -> float:
    """Expected paths a traced side takes: the fixed count, or the adaptive sampler's pilot plus
    :data:`ADAPTIVE_SHARE` of the rest."""
    if sampling == "fixed":
        return float(fixed_paths(noise, min_paths, max_paths, round_paths))
    if sampling == "adaptive":
        return min_paths + ADAPTIVE_SHARE * (max_paths - min_paths)
    raise ValueError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")
