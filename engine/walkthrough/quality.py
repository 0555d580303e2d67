"""Quality contracts for walkthroughs: a per-scene model of each walkthrough setting's frame error
and frame time, and the planner that picks a setting for an error target or a time budget.

Pure Python (no numba, no numpy): the API process plans a walkthrough request when it arrives; the
calibration job (``workers/jobs/calibrate_walkthrough.py``) measures what :func:`fit_setting` fits.

A walkthrough setting is a bake quality preset (``low`` / ``medium`` / ``high``, the bake's other
fields at their defaults) and a hole fill (``both``, ``trace``, ...): ``medium/both``; or frames
path-traced to a noise target without a bake (``WalkthroughRequest.path_traced``): ``path/0.05``.
Per scene:

- ``error``: the largest LRMS over the probe frames of a frame reconstructed with the setting
  against the converged frame (``engine.walkthrough.ground_truth``), the ground truth's noise removed
  in quadrature (:func:`engine.quality.fit_ldc`), taken as independent of the frame size;
- ``frame_ms(px) = b + c * px``, fitted on two frame sizes and raised to the slowest probe frame
  (``max_ms`` bounds every frame); for path-traced frames ``c * px``, ``c`` the slowest probe
  frame's time per pixel (each pixel traces paths to the same target), and the error at least the
  noise target (:func:`fit_path_setting`); noise targets between the calibrated ones are weighed
  too (:func:`interpolated_path_fit`);
- the bake's cost, measured when the calibration made (or found) the preset's bake (none for
  path-traced frames: for a short walkthrough they are the cheapest setting, for a long one the
  bake pays for itself).

A walkthrough contract's ``max_error`` bounds every frame's LRMS, ``max_ms`` every frame's render
time in the worker (the reconstruction, not the bake, queueing or encoding). "Cheapest" is the whole
walkthrough's predicted time: the bake's cost when its bake is not in the store, plus the frames.

The rules are those of a render contract (:mod:`engine.quality`): the cheapest setting predicted to
meet ``max_error``; the most accurate within ``max_ms``; with both the cheapest meeting the error
within the time, else (best effort) the most accurate within the time. Each setting is planned for
``max_error`` times its calibrated margin and ``max_ms`` times the server's time margin. Unlike a
render, a setting that meets the targets only without the margin is no plan (a walkthrough fails
with its worst frame): the answer says which one it would be, and ``best_effort`` renders it.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from engine.quality import CandidateFit, Rule, correction_factor, fit_ldc, select_meeting

__all__ = [
    "CALIBRATED_FILLS",
    "PATH",
    "PRESET_ORDER",
    "WALKTHROUGH_MODEL_VERSION",
    "WalkthroughModel",
    "WalkthroughPlan",
    "WalkthroughPrediction",
    "apply_time_corrections",
    "fit_path_setting",
    "fit_setting",
    "interpolated_path_fit",
    "path_noises",
    "path_setting_name",
    "plan_walkthrough",
    "predict_walkthrough",
    "probe_eyes",
    "probe_times",
    "setting_name",
    "time_key",
]

WALKTHROUGH_MODEL_VERSION = 2
PRESET_ORDER: tuple[str, ...] = ("low", "medium", "high")
CALIBRATED_FILLS: tuple[str, ...] = ("both", "trace")
"""The hole fills calibrated by default: ``both`` (the request's default; fills from the bases
alone) and ``trace`` (traces the holes: slower, closer where the bases saw nothing)."""


PATH = "path"
"""The "preset" of path-traced frames in a setting's name (``path/0.05``: its "fill" is the noise)."""


def setting_name(preset: str, fill: str) -> str:
    """``medium/both``: the bake preset and the fill."""
    return f"{preset}/{fill}"


def path_setting_name(noise: float) -> str:
    """``path/0.05``: frames path-traced to relative standard error ``noise`` per pixel."""
    return setting_name(PATH, f"{float(noise):g}")


def fit_setting(preset: str, fill: str, points: Sequence[Mapping[str, Any]], truth_noise: float) -> CandidateFit:
    """The fit of one setting from its probe frames' ``{"error", "pixels", "ms"}`` (time-only points
    at the other size have ``error`` None): the largest error with the ground truth's noise removed,
    the error margin from the probes' spread, and time ``b + c px`` raised until no probe frame took
    longer than it predicts. A frame's time depends on its view (how much of the bases it reprojects,
    how many holes it fills: 3.7-8.9 ms over one path's frames at one size) more than on its size,
    and ``max_ms`` bounds every frame: the line through the middle of the probes planned budgets
    that the slower half of the frames then missed."""
    fit = fit_ldc(setting_name(preset, fill), points, truth_noise)
    over = max(float(p["ms"]) - fit.ms_at(int(p["pixels"]), None) for p in points)
    return replace(fit, b_ms=fit.b_ms + max(0.0, over))


def fit_path_setting(noise: float, points: Sequence[Mapping[str, Any]], truth_noise: float) -> CandidateFit:
    """The fit of path-traced frames at ``noise`` from their probe frames' ``{"error", "pixels", "ms"}``:
    the error as :func:`fit_setting`'s but at least ``noise`` itself, the time proportional to the
    pixels at the slowest probe frame's time per pixel (the paths per pixel follow from the target
    and the frame, not from its size; a time measured at a second size would cost the calibration
    tens of seconds per setting).

    Why the floor: each frame traces the paths its own pilot says ``noise`` needs
    (``engine.walkthrough.path_settings``), so its error stays about ``noise`` wherever it looks (at
    most 0.94x it on 16 held-out frames of the two sample scenes at 14-15 targets, 1.04x at 0.02 where
    the converged frame's own noise counts), while the probes' own errors can sit well under that:
    on ``static_room`` they put the held-out frames at 0.68x the target where they measured up to
    0.82x, and 5 of 16 walkthroughs planned from the probes alone missed
    (docs/accuracy/walkthrough_contracts.md)."""
    fit = fit_ldc(path_setting_name(noise), points, truth_noise)
    per_px = max(float(p["ms"]) / max(int(p["pixels"]), 1) for p in points)
    return replace(fit, error=max(fit.error, float(noise)), b_ms=0.0, c_ms=per_px)


PATH_STEPS_PER_OCTAVE = 8
"""Path-traced noise targets the planner weighs between the calibrated ones: this many per halving
of the noise (each ~9 % finer than the one before), so a contract's error target lands on a noise
target at most ~9 % finer than it needs, not on the next calibrated one (up to ~1.4x finer, ~2x the
time)."""


def path_noises(model: WalkthroughModel) -> list[float]:
    """The calibrated path-traced noise targets of ``model``, ascending (none excluded)."""
    return sorted(float(name.split("/", 1)[1]) for name in model.fits
                  if name.startswith(f"{PATH}/") and name not in model.excluded)


def interpolated_path_fit(model: WalkthroughModel, noise: float) -> CandidateFit:
    """The fit of path-traced frames at a ``noise`` between two calibrated ones: the error over the
    noise, the margin and the time per pixel interpolated linearly in log noise between the nearest
    calibrated targets below and above (a calibrated target's own fit at it)."""
    noises = path_noises(model)
    if not noises or not noises[0] <= noise <= noises[-1]:
        raise ValueError(f"noise {noise!r} is outside the calibrated path-traced targets {noises}")
    hi = next(n for n in noises if n >= noise)
    if hi == noise:
        return model.fits[path_setting_name(hi)]
    lo = max(n for n in noises if n < noise)
    f_lo, f_hi = model.fits[path_setting_name(lo)], model.fits[path_setting_name(hi)]
    w = math.log(noise / lo) / math.log(hi / lo)

    def lerp(a: float, b: float) -> float:
        return (1.0 - w) * a + w * b

    margin = None if f_lo.margin is None or f_hi.margin is None else lerp(f_lo.margin, f_hi.margin)
    c_ms = math.exp(lerp(math.log(max(f_lo.c_ms, 1e-12)), math.log(max(f_hi.c_ms, 1e-12))))
    return CandidateFit(path_setting_name(noise), noise * lerp(f_lo.error / lo, f_hi.error / hi), 0.0, c_ms, [],
                        margin=margin)


def _path_grid(model: WalkthroughModel) -> list[float]:
    """The noise targets between the calibrated ones the planner weighs (:data:`PATH_STEPS_PER_OCTAVE`),
    rounded to three significant digits (a request carries them)."""
    noises = path_noises(model)
    out = []
    for lo, hi in zip(noises, noises[1:], strict=False):
        steps = max(1, math.ceil(PATH_STEPS_PER_OCTAVE * math.log2(hi / lo)))
        out += [float(f"{lo * (hi / lo) ** (i / steps):.3g}") for i in range(1, steps)]
    return sorted(set(out) - set(noises))


def time_key(setting: str) -> str:
    """The key a setting's served frame times fold under: ``path`` for every path-traced setting (the
    planner weighs noise targets between the calibrated ones, which share one time model), the
    setting's name otherwise."""
    return PATH if setting.startswith(f"{PATH}/") else setting


@dataclass
class WalkthroughModel:
    """What the walkthrough calibration measured on one scene: a fit per setting (keyed by
    :func:`setting_name`), the settings excluded and why, each preset's bake (its key and what it
    cost), the probe frames and what the calibration cost."""

    scene_id: str
    fits: dict[str, CandidateFit]
    excluded: dict[str, str]
    bake_keys: dict[str, str]
    """Per preset: the artifact key of the bake it was measured on (a request naming only the preset)."""
    bake_cost_s: dict[str, float]
    """Per preset: the bake's wall time (the job's, when the calibration found it in the store)."""
    cost_s: float
    probe: dict[str, Any]
    engine_version: str = ""
    created_at: str = ""
    version: int = WALKTHROUGH_MODEL_VERSION

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> WalkthroughModel:
        if doc.get("version") != WALKTHROUGH_MODEL_VERSION:
            raise ValueError(f"walkthrough calibration version {doc.get('version')!r}, "
                             f"expected {WALKTHROUGH_MODEL_VERSION}")
        d = dict(doc)
        d["fits"] = {k: CandidateFit(**v) for k, v in d["fits"].items()}
        return cls(**d)


def apply_time_corrections(model: WalkthroughModel, corrections: Mapping[str, Any] | None
                           ) -> tuple[WalkthroughModel, dict[str, float]]:
    """``model`` with what served walkthroughs measured folded in (``corrections``: ``{"time":
    {key: {"log", "n"}}}``, ``producer.walkthrough_calibrations``, keyed by :func:`time_key`): each
    setting's frame time times its factor (:func:`engine.quality.correction_factor`), as
    :func:`engine.quality.apply_corrections` does for a render's model; and the factors applied
    (those other than 1) by :func:`time_key`."""
    factors = {time_key(k): correction_factor(corrections, "time", time_key(k)) for k in model.fits}
    factors = {k: f for k, f in factors.items() if f != 1.0}
    if not factors:
        return model, {}
    scale = {k: factors.get(time_key(k), 1.0) for k in model.fits}
    fits = {k: replace(f, b_ms=f.b_ms * scale[k], c_ms=f.c_ms * scale[k]) for k, f in model.fits.items()}
    return replace(model, fits=fits), factors


@dataclass(frozen=True)
class WalkthroughPrediction:
    """A setting's predicted frame error and frame time for a walkthrough of ``frames`` frames;
    ``bake_ms`` is the bake's cost when its bake is still to be made; ``margin`` the error margin
    it is planned with."""

    preset: str
    fill: str
    error: float
    frame_ms: float
    frames: int
    bake_ms: float = 0.0
    margin: float = 1.0

    @property
    def name(self) -> str:
        return setting_name(self.preset, self.fill)

    @property
    def path_noise(self) -> float | None:
        """The noise target of path-traced frames (``path/0.05``); None for a bake preset."""
        return float(self.fill) if self.preset == PATH else None

    @property
    def total_ms(self) -> float:
        """What the walkthrough costs: the bake (when missing) plus every frame."""
        return self.bake_ms + self.frames * self.frame_ms

    def describe(self) -> str:
        bake = f", bake {self.bake_ms / 1000:.1f} s" if self.bake_ms else ""
        what = self.name if self.path_noise is None else f"path-traced frames at noise {self.path_noise:g}"
        return f"{what} (predicted LRMS {self.error:.3g}, {self.frame_ms:.0f} ms / frame{bake})"


@dataclass(frozen=True)
class WalkthroughPlan:
    """The planner's answer, as :class:`engine.quality.Plan` for a render."""

    choice: WalkthroughPrediction | None
    rule: Rule | None
    unmet: tuple[str, ...] = ()
    reason: str = ""
    candidates: int = 0
    planned_for: dict[str, float] = field(default_factory=dict)

    @property
    def met(self) -> bool:
        return self.choice is not None and not self.unmet


def predict_walkthrough(model: WalkthroughModel, pixels: int, frames: int, *, bakes_ready: Collection[str],
                        allow_bake: bool = True, flat_margin: float = 1.0,
                        calibrated_margins: bool = True) -> list[WalkthroughPrediction]:
    """Every setting of ``model`` for a walkthrough of ``frames`` frames of ``pixels`` pixels. A
    preset whose bake is not in ``bakes_ready`` is priced with its bake's cost when ``allow_bake``,
    left out otherwise. ``margin``: the fit's calibrated one (when ``calibrated_margins`` and it has
    one), else ``flat_margin``."""
    if pixels < 1 or frames < 1:
        raise ValueError("pixels and frames must be >= 1")
    out = []
    for name, fit in model.fits.items():
        if name in model.excluded:
            continue
        preset, fill = name.split("/", 1)
        ready = preset == PATH or preset in bakes_ready  # path-traced frames need no bake
        if not ready and not allow_bake:
            continue
        bake_ms = 0.0 if ready else 1000.0 * float(model.bake_cost_s.get(preset, 0.0))
        margin = fit.margin if calibrated_margins and fit.margin is not None else flat_margin
        out.append(WalkthroughPrediction(preset, fill, fit.error, fit.ms_at(pixels, None), frames, bake_ms, margin))
    for noise in _path_grid(model):
        fit = interpolated_path_fit(model, noise)
        margin = fit.margin if calibrated_margins and fit.margin is not None else flat_margin
        out.append(WalkthroughPrediction(PATH, f"{noise:g}", fit.error, fit.ms_at(pixels, None), frames, 0.0, margin))
    return out


def plan_walkthrough(model: WalkthroughModel, pixels: int, frames: int, *, max_error: float | None = None,
                     max_ms: float | None = None, best_effort: bool = False, bakes_ready: Collection[str] = (),
                     allow_bake: bool = True, flat_margin: float = 1.0, time_margin: float = 1.0,
                     calibrated_margins: bool = True) -> WalkthroughPlan:
    """Pick a setting for ``max_error`` (every frame's LRMS) and / or ``max_ms`` (every frame's
    render time): the module docstring's rules, first with the safety margins, then (nothing met
    them) with the targets themselves."""
    if max_error is None and max_ms is None:
        raise ValueError("plan_walkthrough needs max_error, max_ms or both")
    for name, m in (("flat_margin", flat_margin), ("time_margin", time_margin)):
        if not 0.0 < m <= 1.0:
            raise ValueError(f"{name} must be in (0, 1], got {m!r}")
    margined = predict_walkthrough(model, pixels, frames, bakes_ready=bakes_ready, allow_bake=allow_bake,
                                   flat_margin=flat_margin, calibrated_margins=calibrated_margins)
    t = None if max_ms is None else max_ms * time_margin
    p = _choose(model, margined, max_error, t, best_effort)
    if p.met and p.choice is not None:
        e = None if max_error is None else max_error * p.choice.margin
        return replace(p, planned_for={k: v for k, v in (("max_error", e), ("max_ms", t)) if v is not None})
    raw = [replace(c, margin=1.0) for c in margined]
    p = replace(_choose(model, raw, max_error, max_ms, best_effort),
                planned_for={k: v for k, v in (("max_error", max_error), ("max_ms", max_ms)) if v is not None})
    if p.met and p.choice is not None:
        c, margin = p.choice, next(m.margin for m in margined if m.name == p.choice.name)
        why = (f"{c.describe()} is predicted to meet the targets, but not with the safety margin (time x "
               f"{time_margin:g}, error x {margin:.2g}, its calibrated margin): nothing is")
        if not best_effort:
            # a walkthrough's contract holds for every frame, and frames scatter around the probes by
            # more than a render's views do: of 11 walkthroughs planned without the margin on the sample
            # scenes, 4 missed (docs/accuracy/walkthrough_contracts.md)
            unmet = tuple(t for t, miss in (("max_error", max_error is not None and c.error > max_error * margin),
                                            ("max_ms", max_ms is not None and c.frame_ms > max_ms * time_margin))
                          if miss)
            return WalkthroughPlan(None, None, unmet, why, p.candidates)
        p = replace(p, reason=why)
    return p


def _choose(model: WalkthroughModel, cands: list[WalkthroughPrediction], max_error: float | None,
            max_ms: float | None, best_effort: bool) -> WalkthroughPlan:
    n = len(cands)
    targets = tuple(t for t, v in (("max_error", max_error), ("max_ms", max_ms)) if v is not None)
    if not cands:
        why = ("no walkthrough setting of this scene is available: the calibration excluded every one"
               if model.fits else "the calibration measured no walkthrough setting")
        return WalkthroughPlan(None, None, targets, why + _excluded_text(model), 0)
    # every frame within max_ms; the cheapest is the whole walkthrough's time, its bake included
    choice, rule, in_time = select_meeting(cands, max_error, max_ms, error=lambda c: c.error,
                                           margin=lambda c: c.margin, time=lambda c: c.frame_ms,
                                           cost=lambda c: c.total_ms)
    if choice is not None:
        return WalkthroughPlan(choice, rule, candidates=n)
    if not in_time:
        fastest = min(cands, key=lambda c: (c.frame_ms, c.error))
        fixed = min(model.fits[c.name].b_ms if c.name in model.fits else 0.0 for c in cands)
        assert max_ms is not None
        if max_ms < fixed:
            why = (f"max_ms {max_ms:g} is below this scene's fixed overhead: every walkthrough setting needs at "
                   f"least {fixed:.0f} ms per frame however small the frame; the fastest is {fastest.describe()}")
        else:
            why = f"no walkthrough setting renders a frame within {max_ms:g} ms; the fastest is {fastest.describe()}"
        unmet = ("max_ms",) if max_error is None or fastest.error <= max_error else ("max_ms", "max_error")
        return WalkthroughPlan(fastest if best_effort else None, "best_effort_fastest" if best_effort else None,
                               unmet, why, n)
    assert max_error is not None
    best = min(in_time, key=lambda c: (c.error, c.total_ms))
    if max_ms is None:
        why = f"no walkthrough setting reaches LRMS {max_error:g} on this scene; the most accurate is {best.describe()}"
        rule_miss: Rule = "best_effort_most_accurate"
    else:
        why = (f"no walkthrough setting reaches LRMS {max_error:g} within {max_ms:g} ms per frame; the most "
               f"accurate within the time is {best.describe()}")
        rule_miss = "most_accurate_within_time_error_unmet"
    return WalkthroughPlan(best if best_effort else None, rule_miss if best_effort else None, ("max_error",),
                           why + _excluded_text(model), n)


def _excluded_text(model: WalkthroughModel) -> str:
    if not model.excluded:
        return ""
    return " (excluded: " + "; ".join(f"{k}: {v}" for k, v in sorted(model.excluded.items())) + ")"


# ------------------------------------------------------------------------------------ probe frames


def _halton(i: int, base: int) -> float:
    f, r = 1.0, 0.0
    while i > 0:
        f /= base
        r += f * (i % base)
        i //= base
    return r


def probe_eyes(space: Any, n: int) -> list[tuple[float, float, float]]:
    """``n`` eye positions spread over a view space (``engine.walkthrough.viewspace``): along a path
    at the middles of ``n`` equal arc-length pieces; in a box or a polygon the first points of a
    Halton sequence that fall inside (a polygon's at its eye height). Deterministic."""
    if n < 1:
        raise ValueError("n must be >= 1")
    if hasattr(space, "point_at"):
        return [tuple(float(x) for x in space.point_at(space.length * (i + 0.5) / n)) for i in range(n)]
    lo, hi = (list(map(float, b)) for b in space.bounds)
    out: list[tuple[float, float, float]] = []
    i = 0
    while len(out) < n and i < 4096 * n:
        i += 1
        u = [_halton(i, b) for b in (2, 3, 5)]
        p = tuple(lo[k] + u[k] * (hi[k] - lo[k]) for k in range(3))
        if hasattr(space, "eye_height"):
            p = (p[0], float(space.eye_height), p[2])
        if space.contains(p):
            out.append(p)  # type: ignore[arg-type]
    if len(out) < n:
        raise ValueError("found no points inside the view space")
    return out


def probe_times(start: float, end: float, n: int) -> list[float]:
    """``n`` animation times at the middles of ``n`` equal pieces of [start, end] (all ``start``
    for a static scene, ``end == start``)."""
    if not (math.isfinite(start) and math.isfinite(end)) or end < start:
        raise ValueError("need start <= end")
    return [start + (end - start) * (i + 0.5) / n for i in range(n)]
