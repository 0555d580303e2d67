"""Per-method readiness of a running warm-up, with an estimate of the seconds left.

The warm-up (``workers.warmup``) runs its steps in the order a user is likely to need them:
reference, the LDC methods, relighting, compositing, walkthroughs. :class:`ReadinessTracker` is
told when each step starts and ends and turns that into the document ``producer.readiness``
stores: per kind (``api_schemas.readiness.READINESS_METHODS``) ``ready`` once every step it needs
has run, ``failed`` when one of them failed, else ``compiling`` with the seconds until its last
step ends.

The estimate: each step's cold compile cost measured on the 2-core reference machine
(:data:`COLD_STEP_SECONDS`, from ``python -m bench.compile_profile``: an empty numba cache),
scaled by how fast this run went so far (seconds taken / cold cost of the steps done; with a warm
disk cache the steps only load their kernels and the scale drops far below 1 after the first
step), minus the time the running step has already taken.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from api_schemas.readiness import READINESS_METHODS
from workers.warmup_steps import RELIGHT_STORE_STEPS

METHOD_STEPS: dict[str, tuple[str, ...]] = {
    "reference": ("scene", "reference", "reference-pipelined"),
    "ldc": ("scene", "ldc-bake", "ldc", "ldc-without-llf"),
    "ldc+llf": ("scene", "ldc-bake", "ldc+llf"),
    "ldc+ibrt": ("scene", "ldc-bake", "ldc+ibrt:1", "ldc+ibrt:2"),
    "relight": ("relight-bake", *RELIGHT_STORE_STEPS),
    "composite": ("relight-bake", "relight-float16-pixel_major", "composite"),
    "walkthrough": ("walkthrough",),
}
"""The warm-up steps whose kernels each kind's jobs run."""

COLD_STEP_SECONDS: dict[str, float] = {
    "scene": 0.1,
    "reference": 49.0,
    "reference-pipelined": 23.0,
    "ldc-bake": 13.0,
    "ldc": 84.0,
    "ldc-without-llf": 0.5,
    "ldc+llf": 0.5,
    "ldc+ibrt:1": 38.0,
    "ldc+ibrt:2": 0.5,
    "relight-bake": 8.0,
    "relight-float16-pixel_major": 45.0,
    "relight-float16-tiled": 33.0,
    "relight-float32-pixel_major": 36.0,
    "relight-float32-tiled": 28.0,
    "relight-lowrank": 28.0,
    "composite": 0.5,
    "walkthrough": 30.0,
}
"""Seconds of each warm-up step (in the order they run) with an empty numba cache on one idle core of
the 2-core reference machine: ``python -m bench.compile_profile``'s step times (docs/performance.md,
"First run") scaled by that run's CPU / wall time (the machine was shared), the ``ldc`` step without
the duplicate axis specialisations removed since, ``walkthrough`` without the reference kernels the
other lane compiles. Only the ratios matter much: the estimate rescales them by the run's own speed."""

_MIN_SCALE, _MAX_SCALE = 0.01, 10.0


class ReadinessTracker:
    """Readiness of one warm-up run (module docstring). Thread-safe: the warm-up calls
    :meth:`started` / :meth:`finished`, a publisher thread calls :meth:`document`."""

    def __init__(self, steps: Sequence[str], worker: str, *, cold: dict[str, float] | None = None,
                 clock: Callable[[], float] = time.monotonic):
        self.steps = list(steps)
        self.worker = worker
        self.cold = dict(COLD_STEP_SECONDS if cold is None else cold)
        self._clock = clock
        self._lock = threading.Lock()
        self._done: dict[str, tuple[float, bool]] = {}  # step -> (seconds, ok)
        self._running: tuple[str, float] | None = None  # (step, started at)
        self.finished_all = False

    def started(self, step: str) -> None:
        with self._lock:
            self._running = (step, self._clock())

    def finished(self, step: str, seconds: float, ok: bool) -> None:
        with self._lock:
            self._done[step] = (seconds, ok)
            self._running = None

    def end(self) -> None:
        """The warm-up is over: steps that never ran count as failed (their kinds compile in their jobs)."""
        with self._lock:
            for s in self.steps:
                self._done.setdefault(s, (0.0, False))
            self._running = None
            self.finished_all = True

    def _scale(self) -> float:
        spent = sum(sec for s, (sec, _) in self._done.items() if s in self.cold)
        expected = sum(self.cold[s] for s in self._done if s in self.cold)
        if expected < 1.0:
            return 1.0
        return min(_MAX_SCALE, max(_MIN_SCALE, spent / expected))

    def seconds_until(self, step: str) -> float:
        """Estimated seconds until ``step`` has run (0 when it has)."""
        with self._lock:
            return self._seconds_until(step, self._scale())

    def _seconds_until(self, step: str, scale: float) -> float:
        if step in self._done:
            return 0.0
        left = 0.0
        for s in self.steps:
            if s in self._done:
                continue
            cost = self.cold.get(s, 0.0) * scale
            if self._running is not None and self._running[0] == s:
                cost = max(cost - (self._clock() - self._running[1]), 0.0)
            left += cost
            if s == step:
                break
        return left

    def states(self) -> dict[str, dict[str, Any]]:
        """Per kind whose steps this run has ``{"state": ..., "seconds_left": ...}`` (module docstring)."""
        with self._lock:
            scale = self._scale()
            out: dict[str, dict[str, Any]] = {}
            for method in READINESS_METHODS:
                needs = list(METHOD_STEPS[method])
                if not set(needs) <= set(self.steps):
                    continue  # another lane's kind
                if any(s in self._done and not self._done[s][1] for s in needs):
                    out[method] = {"state": "failed", "seconds_left": None}
                elif all(s in self._done for s in needs):
                    out[method] = {"state": "ready", "seconds_left": None}
                else:
                    last = max(needs, key=self.steps.index)
                    out[method] = {"state": "compiling",
                                   "seconds_left": round(max(1.0, self._seconds_until(last, scale)), 1)}
            return out

    def document(self) -> dict[str, Any]:
        """The document ``producer.readiness.publish_readiness`` stores."""
        return {"worker": self.worker, "updated_at": time.time(), "finished": self.finished_all,
                "methods": self.states()}
