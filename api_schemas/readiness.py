"""``GET /v1/methods``: which render methods and job kinds a render worker can run without first
compiling its numba kernels (the background warm-up, docs/service-design.md "Warm-up")."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from api_schemas.common import FrozenModel

ReadinessState = Literal["ready", "compiling", "failed", "unknown"]
"""``ready``: a render worker's warm-up compiled (or loaded) this kind's kernels, its first job runs
at full speed. ``compiling``: the warm-up has not reached or finished it yet; a request still works,
its job compiles what it needs (it may take up to ``seconds_left``). ``failed``: the warm-up step
failed; the first job compiles the kernels itself. ``unknown``: no render worker reported a warm-up
(none is running, or warm-up is off)."""

READINESS_METHODS: tuple[str, ...] = ("reference", "ldc", "ldc+llf", "ldc+ibrt", "relight", "composite",
                                      "walkthrough")
"""The kinds readiness is reported for, in the order the warm-up compiles them."""


class MethodReadiness(FrozenModel):
    method: str
    """A render method (``reference``, ``ldc``, ``ldc+llf``, ``ldc+ibrt`` for every ``k``) or a job
    kind (``relight``, ``composite``, ``walkthrough``)."""
    state: ReadinessState
    seconds_left: float | None = Field(default=None, ge=0)
    """While ``compiling``: the estimated seconds until it is ready (from the measured cold compile
    cost of each warm-up step, scaled by how fast this machine ran the steps done so far)."""


class MethodsReadiness(FrozenModel):
    methods: list[MethodReadiness]
    """One entry per kind, in warm-up order; the best state over the live render workers."""
    workers: int = Field(ge=0)
    """Live render workers that published a warm-up state."""
