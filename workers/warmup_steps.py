"""The render worker warm-up's steps: names, the order they run in, what each needs, the lanes.

Engine-free (no numba import), so the render worker can start its warm-up processes before it
imports the engine itself (``workers.runner.start_background_warm_up``), and the readiness
documents can name the steps before any of them ran. ``workers.warmup`` maps each name to the
step's function (module docstring there: what each step runs).
"""

from __future__ import annotations

RELIGHT_STORE_STEPS: tuple[str, ...] = ("relight-float16-pixel_major", "relight-float16-tiled",
                                        "relight-float32-pixel_major", "relight-float32-tiled",
                                        "relight-lowrank")
"""One relight step per store kind the service can produce (``workers.warmup._RELIGHT_STORES``)."""

NEEDS: dict[str, tuple[str, ...]] = {
    "scene": (),
    "reference": ("scene",),
    "reference-pipelined": ("scene",),
    "ldc-bake": ("scene",),
    "ldc": ("ldc-bake",),
    "ldc-without-llf": ("ldc-bake",),
    "ldc+llf": ("ldc-bake",),
    "ldc+ibrt:1": ("ldc-bake",),
    "ldc+ibrt:2": ("ldc-bake",),
    "relight-bake": (),
    **dict.fromkeys(RELIGHT_STORE_STEPS, ("relight-bake",)),
    "composite": ("relight-bake",),
    "walkthrough": (),
}
"""The steps each step needs run before it, by step name, in the order the steps run (the order a
user is likely to need them: reference, the LDC methods, relighting, compositing, walkthroughs)."""

STEPS: tuple[str, ...] = tuple(NEEDS)
"""Names of the warm-up steps, in the order they run."""


def needs_of(step: str) -> tuple[str, ...]:
    """The warm-up steps ``step`` needs run before it (KeyError for an unknown step)."""
    return NEEDS[step]


LANES: tuple[tuple[str, ...], ...] = (
    STEPS[:STEPS.index("relight-bake")],  # reference, then the LDC methods
    STEPS[STEPS.index("relight-bake"):],  # relighting, compositing, walkthroughs
)
"""The steps split in two lanes that need no step of the other, for two processes (numba compiles
on one core per process): the reference and LDC kernels in one, the relighting and walkthrough
kernels in the other. Their cold compile costs are about equal (docs/performance.md)."""


def lanes_for(cores: int) -> tuple[tuple[str, ...], ...]:
    """:data:`LANES` on a machine with 2 or more cores, one lane of every step on a single core."""
    return LANES if cores >= len(LANES) else (STEPS,)
