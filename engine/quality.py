"""Quality contracts: a per-scene model of what each render setting costs and how close it comes
to the converged image, and the planner that picks a setting for an error target or a time budget.

Pure Python (no numba, no numpy): the API process imports it to plan a request when it arrives;
the calibration job (``workers/jobs/calibrate.py``) measures what :func:`fit_model` fits.

Candidates come from the render-method registry (:mod:`engine.methods`): ``reference`` at half-octave
steps of spp over its range (1, 2, 3, 4, 6, 8, 12, ...: a safety margin that moves the plan
past a power of two costs 1.5x, not 2x), ``ldc``, ``ldc+llf`` and ``ldc+ibrt:k`` for the calibrated k. The
model, per scene and bake:

- reference at ``s`` spp: ``error(s) = a s^-p`` (LRMS against the converged image; ``p`` in
  [0.5, 1] fitted on the calibrated spp; past the largest of them the rate measured between the
  two largest, at least 0.5 and at most ``p``; ``a`` fitted conservatively, the ground truth's own
  noise at ``S`` spp removed: :func:`fit_reference`),
  ``ms(s, px) = b + c * s * px``;
- an LDC method: ``error`` = its measured LRMS against the converged image (the largest over the
  probe views, the ground truth's noise removed in quadrature), taken as independent of the image
  size; ``ms(px) = b + c * px`` (fitted on two image sizes).

``plan(model, pixels, max_error=..., max_ms=...)`` applies one rule:

=========================  ================================================================
targets                    rule
=========================  ================================================================
``max_error``              the cheapest setting whose predicted error is at most the target
``max_ms``                 the most accurate setting whose predicted time fits the budget
both                       the cheapest meeting the error within the time; else (error not
                           reachable in time) the most accurate within the time, marked
=========================  ================================================================

"Cost" is the predicted time, plus the bake's measured cost when a setting needs a bake that is
not in the store yet and the caller allows waiting for it. A target no setting meets is never
missed silently: :class:`Plan` says which target is unmet and why; the service answers 422 or, on
request, the best effort marked as not meeting it.

For an error target the adaptive reference joins the candidates (:func:`extra_candidates`): a
progressive render (``engine/progressive.py``) told to stop at the target, whose time is predicted
from the spp model at the (not necessarily power-of-two) spp the target needs, times the ratio the
calibration measured between an adaptive render's time and that prediction (:class:`AdaptiveFit`).
The render estimates its own error over the whole image; the contract's error leaves out the
pixels next to emitters, so the render is told ``target / error_scale`` and its estimate is
reported times ``error_scale`` (both measured at calibration).

Safety margins: ``plan(..., error_margin=0.85, time_margin=0.7)`` plans for ``max_error x
error_margin`` and ``max_ms x time_margin`` (the service's defaults: ``producer.settings``); when no
setting is predicted to meet the margined targets but one meets the targets themselves, that one
is chosen and the plan says the margin was not kept.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Literal, TypeVar

from engine.methods import IBRT_GENERATIONS, LDC, LDC_IBRT, LDC_LLF, REFERENCE, parse_method

__all__ = [
    "ADAPTIVE_CAP_FACTOR",
    "ADAPTIVE_CORRECTION_KEY",
    "CALIBRATION_SPP",
    "CORRECTION_MIN_OBSERVATIONS",
    "CORRECTION_RANGE",
    "CORRECTION_WINDOW",
    "DEFAULT_IBRT_KS",
    "LDC_SUPERSAMPLE",
    "MARGIN_K",
    "MARGIN_MIN_SPREAD",
    "MARGIN_RANGE",
    "MAX_USEFUL_ERROR",
    "MODEL_VERSION",
    "REFERENCE_SPP_LADDER",
    "CandidateFit",
    "Plan",
    "Prediction",
    "AdaptiveFit",
    "Rule",
    "adaptive_scale",
    "apply_corrections",
    "calibrated_margin",
    "correction_factor",
    "correction_key",
    "fold_observation",
    "SceneModel",
    "Setting",
    "check_targets",
    "extra_candidates",
    "fit_ldc",
    "fit_reference",
    "fit_time",
    "ldc_setting_name",
    "ldc_settings",
    "ldc_view",
    "plan",
    "predict",
    "select_meeting",
    "spp_for_error",
]

MODEL_VERSION = 1

REFERENCE_SPP_LADDER: tuple[int, ...] = tuple(sorted(
    s for i in range(13) for s in {2 ** i, 3 * 2 ** i // 2} if s <= REFERENCE.param("spp").high))
"""The reference spp the planner offers, half an octave apart: 1, 2, 3, 4, 6, 8, 12, ..., 3072, 4096."""

CALIBRATION_SPP: tuple[int, ...] = (1, 4, 16)
"""The reference spp the calibration renders on each probe view (the ladder's error and time fit)."""

CALIBRATION_SEEDS: tuple[int, ...] = (0, 1, 2, 3)
"""The seeds the calibration renders the reference with at each of :data:`CALIBRATION_SPP` (0 first:
the service's default). A render at a few spp is one draw of a random error: on a scene whose light
arrives along rare bright paths (a mirror reflecting the light) one seed's error at 2 spp ranges over
0.7-1.9x another's on the same view, so the margin that covers the next view must see that spread,
not only the spread between views of one seed. Four seeds cost four times the ladder's 1 + 4 + 16
spp, a fraction of the ground truth's ``truth_spp``."""

LDC_SUPERSAMPLE: tuple[int, ...] = (1, 2, 4)
"""The antialiasing levels each LDC method is calibrated at (``supersample`` s with ``antialias``
"edges": s x s sub-pixel samples in the pixels at an edge of the one-sample image): each is a
candidate of its own, ``ldc@2x2``, ``ldc+llf@4x4``, ... (:attr:`Setting.name`)."""

DEFAULT_IBRT_KS: tuple[int, ...] = (1, 2, 4)
"""The ``ldc+ibrt:k`` generations calibrated by default (on mirror scenes only: elsewhere every k
renders the ``ldc+llf`` image)."""

MAX_USEFUL_ERROR = 0.5
"""A method whose measured error exceeds this on the probe views is excluded from planning: it does
not render what the scene holds (e.g. ``ldc`` on a mirror scene, or a bake without indirect light in
a room lit mostly indirectly), so no contract should be met with it."""

Rule = Literal["cheapest_meeting_error", "most_accurate_within_time", "cheapest_meeting_error_within_time",
               "most_accurate_within_time_error_unmet", "best_effort_most_accurate", "best_effort_fastest"]


ADAPTIVE_CAP_FACTOR = 4.0
"""An adaptive reference's cap on any pixel's samples: this many times the uniform spp its target
needs (rounded up to a power of two), so a render whose estimate never reaches the target stops."""


@dataclass(frozen=True)
class Setting:
    """A candidate: a wire method and, for ``reference``, its spp; for the adaptive reference
    ``spp`` is the cap on a pixel's samples and ``max_error`` / ``max_ms`` the render's own stopping
    criteria (``max_error`` in the render's metric: the contract's target over the model's
    ``error_scale``)."""

    method: str
    spp: int | None = None
    max_error: float | None = None
    max_ms: float | None = None
    supersample: int = 1
    """LDC methods: s x s sub-pixel samples in the edge pixels (``antialias`` "edges"); 1: none."""

    @property
    def adaptive(self) -> bool:
        return self.max_error is not None or self.max_ms is not None

    @property
    def name(self) -> str:
        if self.adaptive:
            budget = "" if self.max_ms is None else f", max_ms {self.max_ms:g}"
            return f"{self.method}@adaptive(max_error {self.max_error:.3g}{budget}, cap {self.spp}spp)"
        if self.spp is not None:
            return f"{self.method}@{self.spp}spp"
        return ldc_setting_name(self.method, self.supersample)

    @property
    def view(self) -> dict[str, Any] | None:
        """The render request's ``view`` of an antialiased LDC setting, else None (the default view)."""
        return ldc_view(self.supersample)

    @property
    def needs_bake(self) -> bool:
        return parse_method(self.method).needs_bake


def ldc_setting_name(method: str, supersample: int) -> str:
    """``ldc+llf`` at one sample per pixel, ``ldc+llf@4x4`` with 4 x 4 samples in the edge pixels."""
    return method if supersample <= 1 else f"{method}@{supersample}x{supersample}"


def ldc_view(supersample: int) -> dict[str, Any] | None:
    """The request ``view`` of an LDC setting antialiased at ``supersample`` (None: the default)."""
    return None if supersample <= 1 else {"supersample": int(supersample), "antialias": "edges"}


def ldc_settings(has_llf: bool, mirror: bool, ibrt_ks: Iterable[int] = DEFAULT_IBRT_KS) -> list[Setting]:
    """The LDC candidates of a bake: ``ldc``; ``ldc+llf`` when the bake has a light field
    (``has_llf``; without one it renders the ``ldc`` image); on a scene with mirrors ``ldc+ibrt:k``
    for each k (elsewhere IBRT changes nothing)."""
    out = [Setting(LDC.name)]
    if has_llf:
        out.append(Setting(LDC_LLF.name))
    if has_llf and mirror:
        for k in sorted(set(ibrt_ks)):
            IBRT_GENERATIONS.check(k)
            if k > 0:
                out.append(Setting(f"{LDC_IBRT.name}:{k}"))
    return out


# ------------------------------------------------------------------------------------ fits


@dataclass(frozen=True)
class CandidateFit:
    """The model of one method on one scene: ``error`` (LDC: the LRMS; reference: ``a`` of
    ``a / sqrt(spp)``) and time ``b_ms + c_ms * units`` (units: pixels, or spp x pixels for the
    reference). ``points`` keeps the measurements the fit came from."""

    method: str
    error: float
    b_ms: float
    c_ms: float
    points: list[dict[str, Any]] = field(default_factory=list)
    exponent: float = 0.5
    """Reference: the error falls as ``spp^-exponent`` up to ``knee_spp``, as ``spp^-tail_exponent``
    past it."""
    knee_spp: int = 1
    tail_exponent: float = 0.5
    """Reference: the exponent past ``knee_spp``: the convergence measured between the two largest
    calibrated spp, within [0.5, ``exponent``] (:func:`fit_reference`); 0.5 for a model calibrated
    before it was fitted."""
    margin: float | None = None
    """The error margin calibrated from the spread of the probe views' measured over predicted errors
    (:func:`calibrated_margin`); None (a model calibrated before margins were): the planner's flat one."""
    supersample: int = 1
    """LDC methods: the antialiasing level it was measured at (:data:`LDC_SUPERSAMPLE`)."""
    margins_by_spp: list[list[float]] = field(default_factory=list)
    """Reference: ``[spp, margin]`` per calibrated spp, each from the probes' ratios at that spp
    alone (every probe and seed): a render's error scatters more at a few samples per pixel than
    at many, so one margin for the whole ladder would be too loose at 1-4 spp or too tight at 16.
    Empty (an LDC method, or a model calibrated before them): ``margin`` at every spp."""

    @property
    def key(self) -> str:
        """The name of its setting (``SceneModel.methods``' key, the served corrections' key)."""
        return ldc_setting_name(self.method, self.supersample)

    def margin_at(self, spp: int | None) -> float | None:
        """The calibrated error margin at ``spp``: :attr:`margins_by_spp` interpolated linearly in
        log spp between the calibrated spp, the nearest one's beyond them; else :attr:`margin`."""
        pts = sorted((float(s), float(m)) for s, m in self.margins_by_spp)
        if spp is None or not pts:
            return self.margin
        if spp <= pts[0][0]:
            return pts[0][1]
        for (s0, m0), (s1, m1) in zip(pts, pts[1:], strict=False):
            if spp <= s1:
                t = math.log(spp / s0) / math.log(s1 / s0)
                return m0 + t * (m1 - m0)
        return pts[-1][1]

    def error_at(self, spp: int | None) -> float:
        if self.method == REFERENCE.name:
            assert spp is not None
            knee = max(self.knee_spp, 1)
            if spp <= knee:
                return self.error * spp ** -self.exponent
            return self.error * knee ** -self.exponent * (knee / spp) ** self.tail_exponent
        return self.error

    def ms_at(self, pixels: int, spp: int | None) -> float:
        units = pixels * (spp if self.method == REFERENCE.name and spp is not None else 1)
        return self.b_ms + self.c_ms * units


def fit_time(units: Sequence[float], ms: Sequence[float]) -> tuple[float, float]:
    """Least squares ``ms = b + c * units`` with ``b, c >= 0`` (a negative intercept, from timing
    noise, is refitted through the origin; a negative slope becomes a constant)."""
    n = len(units)
    if n == 0 or n != len(ms):
        raise ValueError("fit_time needs as many times as units, at least one")
    mu, mt = sum(units) / n, sum(ms) / n
    sxx = sum((u - mu) ** 2 for u in units)
    c = sum((u - mu) * (t - mt) for u, t in zip(units, ms, strict=True)) / sxx if sxx > 0 else 0.0
    b = mt - c * mu
    if c < 0:
        return max(mt, 0.0), 0.0
    if b < 0:
        suu = sum(u * u for u in units)
        return 0.0, sum(u * t for u, t in zip(units, ms, strict=True)) / suu if suu > 0 else 0.0
    return b, c


def fit_reference(points: Sequence[Mapping[str, Any]], truth_spp: int) -> CandidateFit:
    """The reference's fit from ``points`` ``{"spp", "error", "pixels", "ms"}`` (error measured
    against a ground truth of the same estimator at ``truth_spp``).

    The error falls as ``a s^-p``: ``p`` = 0.5 for independent samples, faster for stratified ones
    where the image is smooth. Both images' noise adds in quadrature, ``e^2 = a^2 (s^-2p + S^-2p)``;
    ``p`` is the exponent in [0.5, 1] that fits the per-spp RMS over the probe views best (log
    residuals), and ``a`` the largest ratio over the spp (conservative: the planner then
    over-predicts rather than misses). Past the largest calibrated spp (``knee_spp``) the fit
    continues at the rate measured between the two largest (``tail_exponent``: :func:`_tail_exponent`,
    at least 0.5, at most ``p``): convergence is never assumed faster than measured. ``margin``: from
    every probe point's measured over modelled error (:func:`calibrated_margin`); ``margins_by_spp``:
    the same from each spp's points alone (points with a ``probe`` index, e.g. several seeds per
    probe, count their distinct probes as the views behind the bound)."""
    by_spp: dict[int, list[float]] = {}
    for p in points:
        by_spp.setdefault(int(p["spp"]), []).append(float(p["error"]))
    rms = {s: math.sqrt(sum(e * e for e in errs) / len(errs)) for s, errs in by_spp.items()}
    best: tuple[float, float, float] | None = None
    for i in range(51):
        q = 0.5 + 0.01 * i
        scale = {s: math.sqrt(s ** (-2 * q) + truth_spp ** (-2 * q)) for s in rms}
        a = max(e / scale[s] for s, e in rms.items())
        if a <= 0:
            continue
        resid = sum(math.log(max(e, 1e-12) / (a * scale[s])) ** 2 for s, e in rms.items())
        if best is None or resid < best[0] - 1e-12:
            best = (resid, q, a)
    exponent, a = (0.5, 0.0) if best is None else (best[1], best[2])
    tail = _tail_exponent(rms, truth_spp, exponent)
    b, c = fit_time([float(p["spp"]) * float(p["pixels"]) for p in points], [float(p["ms"]) for p in points])
    ratios = {s: [e / (a * math.sqrt(s ** (-2 * exponent) + truth_spp ** (-2 * exponent))) for e in errs]
              for s, errs in by_spp.items()} if a > 0 else {}
    probes = {p["probe"] for p in points if "probe" in p}
    views = len(probes) if probes else max((len(errs) for errs in by_spp.values()), default=1)
    pooled = [r for rs in ratios.values() for r in rs]
    return CandidateFit(REFERENCE.name, a, b, c, [dict(p) for p in points], exponent=exponent,
                        knee_spp=max(rms) if rms else 1, tail_exponent=tail,
                        margin=calibrated_margin(pooled, views) if pooled else None,
                        margins_by_spp=[[s, calibrated_margin(rs, views)] for s, rs in sorted(ratios.items())])


def _tail_exponent(rms: Mapping[int, float], truth_spp: int, exponent: float) -> float:
    """The exponent the reference's error falls with past the calibrated spp: the one that fits the
    two largest calibrated spp's RMS errors (``e^2 ~ s^-2q + S^-2q``, the ground truth's noise at
    ``S`` = ``truth_spp`` in both), clamped to [0.5, ``exponent``]. Stratification's gain fades with
    more samples (the edge and smooth pixels converge faster than the shading's many dimensions), so
    the rate measured at the top of the calibrated range is the one to continue with, and never one
    faster than the fit over the whole range."""
    top = sorted(s for s, e in rms.items() if e > 0)[-2:]
    if len(top) < 2:
        return 0.5
    lo, hi = top
    target = math.log(rms[lo] / rms[hi])
    best = 0.5
    for i in range(51):
        q = 0.5 + 0.01 * i
        if q > exponent + 1e-9:
            break
        model = 0.5 * math.log((lo ** (-2 * q) + truth_spp ** (-2 * q)) / (hi ** (-2 * q) + truth_spp ** (-2 * q)))
        if model <= target + 1e-12:
            best = q  # the fastest rate the measured drop supports
    return best


def fit_ldc(method: str, points: Sequence[Mapping[str, Any]], truth_noise: float,
            supersample: int = 1) -> CandidateFit:
    """An LDC method's fit from ``points`` ``{"error", "pixels", "ms"}`` (``error`` measured on the
    probe views at the calibration size; time-only points, at other sizes, have ``error`` None), at
    the antialiasing level ``supersample``. The error is the largest over the probe views with the
    ground truth's noise ``truth_noise`` removed in quadrature; ``margin`` from each view's error over
    that (:func:`calibrated_margin`)."""
    errs = [float(p["error"]) for p in points if p.get("error") is not None]
    if not errs:
        raise ValueError(f"{method}: no error measured")
    clean = [math.sqrt(max(e * e - truth_noise * truth_noise, 0.25 * e * e)) for e in errs]
    err = max(clean)
    b, c = fit_time([float(p["pixels"]) for p in points], [float(p["ms"]) for p in points])
    margin = calibrated_margin([e / err for e in clean]) if err > 0 else None
    return CandidateFit(method, err, b, c, [dict(p) for p in points], margin=margin, supersample=supersample)


def spp_for_error(fit: CandidateFit, error: float) -> float:
    """The (real-valued) spp at which the reference's fit ``fit`` predicts ``error``: the inverse of
    :meth:`CandidateFit.error_at` (at least 1)."""
    if error <= 0:
        return math.inf
    knee = max(fit.knee_spp, 1)
    at_knee = fit.error * knee ** -fit.exponent
    if error >= at_knee:
        s = (fit.error / error) ** (1.0 / fit.exponent) if fit.error > 0 else 1.0
    else:
        s = knee * (at_knee / error) ** (1.0 / fit.tail_exponent)
    return max(1.0, s)


@dataclass(frozen=True)
class AdaptiveFit:
    """The adaptive reference on one scene, measured at calibration by adaptive renders of the probe
    views: ``error_scale``, the contract's error (against the ground truth, emitter pixels left out)
    over the render's own estimate (whole image), and ``time_ratio``, the render's time over what the
    spp model predicts at the spp that reaches the same contract error. ``points`` keeps the
    measurements.

    ``levels`` (one entry per error level the calibration told the render, ascending ``error``):
    ``{"error", "scale", "time_ratio"}``, the geometric mean of the probes' scales and the largest
    time ratio at that level. The scale depends on the level (told ~10 %, the first pass already
    stops and the estimate reads low), so :meth:`scale_at` interpolates between the levels (in log
    error, constant beyond them). ``margin``: the error margin from the spread of the probes'
    scales around their level's (:func:`calibrated_margin`). A fit without ``levels`` (calibrated at
    one level, before these existed) uses ``error_scale`` and ``time_ratio`` everywhere, the largest
    over its probes."""

    error_scale: float
    time_ratio: float
    points: list[dict[str, Any]] = field(default_factory=list)
    levels: list[dict[str, float]] = field(default_factory=list)
    margin: float | None = None

    def _at(self, error: float, key: str, default: float) -> float:
        lv = sorted((lv for lv in self.levels if lv["error"] > 0 and lv[key] > 0), key=lambda lv: lv["error"])
        if not lv or error <= 0:
            return default
        if error <= lv[0]["error"]:
            return float(lv[0][key])
        if error >= lv[-1]["error"]:
            return float(lv[-1][key])
        for lo, hi in zip(lv, lv[1:], strict=False):
            if lo["error"] <= error <= hi["error"]:
                t = math.log(error / lo["error"]) / math.log(hi["error"] / lo["error"])
                return float(math.exp((1 - t) * math.log(lo[key]) + t * math.log(hi[key])))
        return default  # pragma: no cover - the levels cover every error between their ends

    def scale_at(self, error: float) -> float:
        """The contract error over the render's estimate for a render told the contract error ``error``."""
        return self._at(error, "scale", self.error_scale)

    def time_ratio_at(self, error: float) -> float:
        """The render's time over the spp model's at ``error``."""
        return self._at(error, "time_ratio", self.time_ratio)


MARGIN_K = 1.645
"""One-sided 95 % quantile of a normal distribution: a calibrated margin covers this many standard
deviations of the probe views' log measured-over-predicted error (times the prediction interval's
``sqrt(1 + 1/n)`` for ``n`` probes' worth of points)."""
MARGIN_MIN_SPREAD = 0.06
"""The smallest spread (standard deviation of the log ratio) a calibrated margin assumes: a few
probes that happen to agree say little about the next view (the reference's error varies by ~10 %
from view to view)."""
MARGIN_RANGE = (0.5, 1.0)
"""A calibrated margin is clamped to this range."""


def calibrated_margin(ratios: Sequence[float], views: int | None = None) -> float:
    """The error margin for a setting whose measured over predicted errors on the probe views are
    ``ratios``: ``exp(-(mean + k s))`` of their logs, with ``s`` their standard deviation (at least
    :data:`MARGIN_MIN_SPREAD`) and ``k`` = :data:`MARGIN_K` x ``sqrt(1 + 1/views)`` (``views``: the
    independent views behind them, default ``len(ratios)``), clamped to :data:`MARGIN_RANGE`. A model
    that over-predicts every probe plans closer to the target, one whose probes scatter plans further
    below it."""
    logs = [math.log(r) for r in ratios if r > 0 and math.isfinite(r)]
    if not logs:
        return MARGIN_RANGE[0]
    n = len(logs)
    mean = sum(logs) / n
    sd = math.sqrt(sum((x - mean) ** 2 for x in logs) / (n - 1)) if n > 1 else 0.0
    k = MARGIN_K * math.sqrt(1.0 + 1.0 / max(1, views if views is not None else n))
    m = math.exp(-(mean + k * max(sd, MARGIN_MIN_SPREAD)))
    return min(MARGIN_RANGE[1], max(MARGIN_RANGE[0], m))


# ------------------------------------------------------------------------------------ the model


@dataclass
class SceneModel:
    """What the calibration measured on one scene and bake: the reference's fit, each LDC method's
    fit, the methods excluded and why, the bake's cost and what the calibration itself cost."""

    scene_id: str
    bake_key: str
    reference: CandidateFit
    methods: dict[str, CandidateFit]
    excluded: dict[str, str]
    reference_params: dict[str, int]
    """The reference's settings besides spp (indirect paths per pixel = spp when the scene has
    indirect light: ``indirect_per_spp``)."""
    bake_cost_s: float
    cost_s: float
    probe: dict[str, Any]
    engine_version: str = ""
    created_at: str = ""
    version: int = MODEL_VERSION
    adaptive: AdaptiveFit | None = None
    """The adaptive reference's fit; None: the calibration did not measure it (it is then no
    candidate)."""

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> SceneModel:
        if doc.get("version") != MODEL_VERSION:
            raise ValueError(f"calibration model version {doc.get('version')!r}, expected {MODEL_VERSION}")
        d = dict(doc)
        d["reference"] = CandidateFit(**d["reference"])
        d["methods"] = {k: CandidateFit(**v) for k, v in d["methods"].items()}
        if d.get("adaptive") is not None:
            d["adaptive"] = AdaptiveFit(**d["adaptive"])
        return cls(**d)

    def reference_request_params(self, spp: int, max_error: float | None = None,
                                 max_ms: float | None = None) -> dict[str, Any]:
        """The ``ReferenceRenderParams`` of the reference candidate at ``spp`` (the adaptive one:
        ``spp`` is the cap, with its ``max_error`` / ``max_ms``)."""
        out: dict[str, Any] = {k: v for k, v in self.reference_params.items() if k != "indirect_per_spp"}
        out["spp"] = spp
        if self.reference_params.get("indirect_per_spp"):
            out["indirect_samples"] = spp * int(self.reference_params["indirect_per_spp"])
        if max_error is not None:
            out["max_error"] = max_error
        if max_ms is not None:
            out["max_ms"] = max_ms
        return out

    def setting_params(self, setting: Setting) -> dict[str, Any] | None:
        """The reference's request params of ``setting`` (None for the LDC methods)."""
        if setting.spp is None:
            return None
        return self.reference_request_params(setting.spp, setting.max_error, setting.max_ms)


@dataclass(frozen=True)
class Prediction:
    """A candidate's predicted error and time at one image size. ``ms`` is the render time plus
    ``bake_ms`` (the bake's cost, when it is still to be made). ``margin``: the error margin it is
    planned with (its predicted error must be at most the target times it)."""

    setting: Setting
    error: float
    render_ms: float
    bake_ms: float = 0.0
    margin: float = 1.0

    @property
    def ms(self) -> float:
        return self.render_ms + self.bake_ms


def _margin(fit: CandidateFit | AdaptiveFit | None, flat: float, calibrated: bool, spp: int | None = None) -> float:
    """The fit's calibrated margin (the reference's at ``spp``: :meth:`CandidateFit.margin_at`) when
    ``calibrated`` and it has one, else ``flat``."""
    if not calibrated or fit is None:
        return flat
    m = fit.margin_at(spp) if isinstance(fit, CandidateFit) else fit.margin
    return flat if m is None else m


def adaptive_scale(model: SceneModel, aim_error: float) -> float:
    """The adaptive reference's ``error_scale`` for a render aiming at the contract error ``aim_error``
    (the model's scale at that level: :meth:`AdaptiveFit.scale_at`); 1 without an adaptive fit."""
    return model.adaptive.scale_at(aim_error) if model.adaptive is not None else 1.0


def extra_candidates(model: SceneModel, pixels: int, aim_error: float | None = None,
                     max_ms: float | None = None, margin: float = 1.0) -> list[Prediction]:
    """Candidates beyond the fitted ladder: the adaptive reference told to stop at ``aim_error x
    margin`` (the contract's error target times its margin), when the calibration measured it
    (``model.adaptive``) and the target is within the reference's reach. Predicted error: the aim
    (the render then estimates what it reached); time: the time ratio at that level x the spp
    model's time at the spp the aim needs. It is told the aim over the scale at that level
    (:func:`adaptive_scale`). Its cap is :data:`ADAPTIVE_CAP_FACTOR` x that spp; with a time budget
    ``max_ms`` the render also stops there."""
    fit = model.adaptive
    if fit is None or aim_error is None or fit.error_scale <= 0:
        return []
    aim = aim_error * margin
    high = REFERENCE.param("spp").high
    s = spp_for_error(model.reference, aim)
    if not math.isfinite(s) or s > high:
        return []
    cap = int(min(high, max(2, 2 ** math.ceil(math.log2(ADAPTIVE_CAP_FACTOR * s)))))
    render_error = min(aim / fit.scale_at(aim), 0.99)
    ms = fit.time_ratio_at(aim) * (model.reference.b_ms + model.reference.c_ms * s * pixels)
    return [Prediction(Setting(REFERENCE.name, cap, render_error, max_ms), aim, ms, margin=margin)]


def predict(model: SceneModel, pixels: int, *, bake_ready: bool = True, allow_bake: bool = True,
            allowed: Callable[[Setting], bool] | None = None, aim_error: float | None = None,
            max_ms: float | None = None, error_margin: float = 1.0,
            calibrated_margins: bool = False) -> list[Prediction]:
    """Every candidate of ``model`` at an image of ``pixels`` pixels. A method needing the bake
    when it is not ready: priced with the bake's cost when ``allow_bake``, left out otherwise.
    ``allowed``: the settings this server accepts (e.g. under its render memory limit); the others
    are left out. ``aim_error`` / ``max_ms``: the targets the adaptive reference is told (with an
    error target only: :func:`extra_candidates`). Each candidate's ``margin`` is its fit's
    calibrated one when ``calibrated_margins`` and the fit has one, else ``error_margin``."""
    if pixels < 1:
        raise ValueError("pixels must be >= 1")
    out = [Prediction(Setting(REFERENCE.name, s), model.reference.error_at(s), model.reference.ms_at(pixels, s),
                      margin=_margin(model.reference, error_margin, calibrated_margins, s))
           for s in REFERENCE_SPP_LADDER]
    if bake_ready or allow_bake:
        bake_ms = 0.0 if bake_ready else 1000.0 * model.bake_cost_s
        for name, fit in model.methods.items():
            # a setting measured too far off is excluded by its own name; a method excluded before it
            # was measured (no fit under its name: e.g. ``ldc`` on a mirror scene) takes its settings along
            if name in model.excluded or (fit.method in model.excluded and fit.method not in model.methods):
                continue
            out.append(Prediction(Setting(fit.method, supersample=fit.supersample), fit.error, fit.ms_at(pixels, None),
                                  bake_ms, margin=_margin(fit, error_margin, calibrated_margins)))
    out += extra_candidates(model, pixels, aim_error, max_ms, _margin(model.adaptive, error_margin, calibrated_margins))
    return out if allowed is None else [p for p in out if allowed(p.setting)]


@dataclass(frozen=True)
class Plan:
    """The planner's answer: ``choice`` (None when no setting meets the targets and no best effort
    was asked), the ``rule`` that picked it, ``unmet`` (the targets the choice does not meet, with
    ``reason`` in words)."""

    choice: Prediction | None
    rule: Rule | None
    unmet: tuple[str, ...] = ()
    reason: str = ""
    candidates: int = 0
    planned_for: dict[str, float] = field(default_factory=dict)
    """The targets the choice was planned against: the request's times the margins, or the request's
    own when no setting kept the margin (``reason`` then says so)."""

    @property
    def met(self) -> bool:
        return self.choice is not None and not self.unmet


def _fmt(p: Prediction) -> str:
    bake = f", {p.bake_ms / 1000:.1f} s of it the bake" if p.bake_ms else ""
    return f"{p.setting.name} (predicted LRMS {p.error:.3g}, {p.ms:.0f} ms{bake})"


def plan(model: SceneModel, pixels: int, *, max_error: float | None = None, max_ms: float | None = None,
         best_effort: bool = False, bake_ready: bool = True, allow_bake: bool = True,
         allowed: Callable[[Setting], bool] | None = None, error_margin: float = 1.0,
         time_margin: float = 1.0, calibrated_margins: bool = True) -> Plan:
    """Pick a setting for ``max_error`` (LRMS against the converged image) and / or ``max_ms``
    (milliseconds) at an image of ``pixels`` pixels; see the module docstring for the rules.
    ``best_effort``: when the targets cannot all be met, still choose (the most accurate, within the
    time when there is a time budget, else the fastest) and mark the unmet target; otherwise
    ``choice`` is None and ``reason`` says what the scene can do.

    Safety margins, so that a view a little worse than the probes or a worker a little busier than
    at calibration still meets the contract: each setting is planned for ``max_error`` times its
    fit's calibrated margin (:func:`calibrated_margin`) when ``calibrated_margins`` and the fit has
    one, else times ``error_margin``; and for ``max_ms x time_margin`` (both in (0, 1]). When
    nothing is predicted to meet the margined targets, the plan for the targets themselves is
    returned (met or not; its ``reason`` says when the margin was not kept)."""
    if max_error is None and max_ms is None:
        raise ValueError("plan needs max_error, max_ms or both")
    for name, m in (("error_margin", error_margin), ("time_margin", time_margin)):
        if not 0.0 < m <= 1.0:
            raise ValueError(f"{name} must be in (0, 1], got {m!r}")
    kw = dict(best_effort=best_effort, bake_ready=bake_ready, allow_bake=allow_bake, allowed=allowed)
    raw = {k: v for k, v in (("max_error", max_error), ("max_ms", max_ms)) if v is not None}
    t = None if max_ms is None else max_ms * time_margin
    margined = _plan_once(model, pixels, max_error, t, max_ms, error_margin=error_margin,  # type: ignore[arg-type]
                          calibrated_margins=calibrated_margins, **kw)
    if margined.met and margined.choice is not None:
        e = None if max_error is None else max_error * margined.choice.margin
        return replace(margined, planned_for={k: v for k, v in (("max_error", e), ("max_ms", t)) if v is not None})
    p = _plan_once(model, pixels, max_error, max_ms, max_ms, error_margin=1.0, calibrated_margins=False,
                   **kw)  # type: ignore[arg-type]
    p = replace(p, planned_for=raw)
    if p.met:
        p = replace(p, reason=f"predicted to meet the targets, but not with the safety margin (error x "
                              f"{_margins_text(model, error_margin, calibrated_margins)}, time x {time_margin:g}): "
                              "nothing does")
    return p


def _margins_text(model: SceneModel, flat: float, calibrated: bool) -> str:
    ms = {_margin(f, flat, calibrated) for f in [model.reference, *model.methods.values(), model.adaptive]
          if f is not None}
    if calibrated:
        ms |= {float(m) for _, m in model.reference.margins_by_spp}
    return f"{min(ms):.3g}" if len(ms) == 1 else f"{min(ms):.3g}-{max(ms):.3g}"


_C = TypeVar("_C")


def select_meeting(cands: Sequence[_C], max_error: float | None, max_ms: float | None, *,
                   error: Callable[[_C], float], margin: Callable[[_C], float], time: Callable[[_C], float],
                   cost: Callable[[_C], float]) -> tuple[_C | None, Rule | None, list[_C]]:
    """The contract rules shared by renders and walkthroughs: among the candidates whose ``time``
    fits ``max_ms`` and whose ``error`` is at most ``max_error`` times their ``margin``, the cheapest
    (by ``cost``, then error) for an error target, the most accurate (then cheapest) for a time
    budget alone. Returns (choice or None, its rule, the candidates within the time) so the caller
    can explain a miss."""
    in_time = [c for c in cands if max_ms is None or time(c) <= max_ms]
    good = [c for c in in_time if max_error is None or error(c) <= max_error * margin(c)]
    if not good:
        return None, None, in_time
    if max_error is None:
        return min(good, key=lambda c: (error(c), cost(c))), "most_accurate_within_time", in_time
    rule: Rule = "cheapest_meeting_error" if max_ms is None else "cheapest_meeting_error_within_time"
    return min(good, key=lambda c: (cost(c), error(c))), rule, in_time


def _plan_once(model: SceneModel, pixels: int, max_error: float | None, max_ms: float | None,
               render_ms: float | None, *, best_effort: bool, bake_ready: bool, allow_bake: bool,
               allowed: Callable[[Setting], bool] | None, error_margin: float, calibrated_margins: bool) -> Plan:
    """:func:`plan` for one pair of limits (``render_ms``: the time budget the adaptive reference is
    told, the request's own), each candidate's error against ``max_error`` times its margin."""
    cands = predict(model, pixels, bake_ready=bake_ready, allow_bake=allow_bake, allowed=allowed,
                    aim_error=max_error, max_ms=render_ms, error_margin=error_margin,
                    calibrated_margins=calibrated_margins)
    n = len(cands)
    if not cands:
        return Plan(None, None, tuple(t for t, v in (("max_error", max_error), ("max_ms", max_ms)) if v is not None),
                    "no setting of this scene can render this image on this server (its limits)", 0)
    cheapest = min(cands, key=lambda p: (p.ms, p.error))
    most_accurate = min(cands, key=lambda p: (p.error, p.ms))
    choice, rule, in_time = select_meeting(cands, max_error, max_ms, error=lambda p: p.error,
                                           margin=lambda p: p.margin, time=lambda p: p.ms, cost=lambda p: p.ms)
    if choice is not None:
        return Plan(choice, rule, candidates=n)
    if not in_time:  # a time budget nothing fits
        fixed = min([model.reference.b_ms] + [f.b_ms for k, f in model.methods.items() if k not in model.excluded])
        if max_ms is not None and max_ms < fixed:
            why = (f"max_ms {max_ms:g} is below this scene's fixed overhead: every setting needs at least "
                   f"{fixed:.0f} ms however small the image; the fastest at this size is {_fmt(cheapest)}")
        else:
            why = f"no setting renders {pixels} pixels within {max_ms:g} ms; the fastest is {_fmt(cheapest)}"
        unmet = ("max_ms",) if max_error is None or cheapest.error <= max_error else ("max_ms", "max_error")
        return Plan(cheapest if best_effort else None, "best_effort_fastest" if best_effort else None, unmet,
                    why, n)
    # the error is not reachable (within the time, when there is a budget)
    best = min(in_time, key=lambda p: (p.error, p.ms))
    assert max_error is not None
    if max_ms is None:
        why = (f"no setting reaches LRMS {max_error:g} on this scene; the most accurate is {_fmt(most_accurate)}")
        return Plan(best if best_effort else None, "best_effort_most_accurate" if best_effort else None,
                    ("max_error",), why, n)
    why = (f"no setting reaches LRMS {max_error:g} within {max_ms:g} ms; the most accurate within the time is "
           f"{_fmt(best)}")
    return Plan(best if best_effort else None, "most_accurate_within_time_error_unmet" if best_effort else None,
                ("max_error",), why, n)


def check_targets(max_error: float | None, max_ms: float | None, max_job_ms: float) -> list[tuple[str, str]]:
    """``(field, message)`` for each target out of range: ``0 < max_error < 1`` (LRMS is a fraction:
    0 is the converged image itself, 1 an error as large as the image's mean); ``0 < max_ms <=
    max_job_ms`` (a render job is stopped at its timeout)."""
    errors: list[tuple[str, str]] = []
    if max_error is None and max_ms is None:
        errors.append(("quality", "quality needs max_error, max_ms or both"))
    if max_error is not None and not (math.isfinite(max_error) and 0.0 < max_error < 1.0):
        errors.append(("quality.max_error", f"max_error must be in (0, 1) (LRMS, e.g. 0.05 for 5 %), "
                                            f"got {max_error!r}"))
    if max_ms is not None and not (math.isfinite(max_ms) and 0.0 < max_ms <= max_job_ms):
        errors.append(("quality.max_ms", f"max_ms must be in (0, {max_job_ms:g}] (milliseconds; the render job "
                                         f"timeout), got {max_ms!r}"))
    return errors


# ------------------------------------------------------------------------------------ served renders

CORRECTION_WINDOW = 8
"""A correction factor is the running geometric mean of the last ~this many observations (each new one
weighs ``1 / min(n, CORRECTION_WINDOW)``): it follows a worker whose load changed within a few renders."""
CORRECTION_MIN_OBSERVATIONS = 2
"""A correction is applied once it has this many observations (one render's time is noise)."""
CORRECTION_RANGE: dict[str, tuple[float, float]] = {"time": (0.25, 4.0), "error": (0.5, 2.0)}
"""A correction factor is clamped to this range per kind: a larger disagreement asks for a new
calibration, not a correction."""


ADAPTIVE_CORRECTION_KEY = f"{REFERENCE.name}@adaptive"
"""The correction key of the adaptive reference (:func:`correction_key`)."""


def correction_key(method: str, params: Mapping[str, Any] | None, view: Mapping[str, Any] | None = None) -> str:
    """What a served render's observation corrects: ``reference@adaptive`` for the adaptive reference
    (``params`` with ``max_error``), an antialiased LDC setting's name (``view`` with ``supersample``
    above 1: ``ldc+llf@4x4``), else the method (the whole ``reference`` ladder shares one)."""
    if method == REFERENCE.name and params is not None and params.get("max_error") is not None:
        return ADAPTIVE_CORRECTION_KEY
    if method != REFERENCE.name and view:
        return ldc_setting_name(method, int(view.get("supersample", 1)))
    return method


def fold_observation(entry: Mapping[str, Any] | None, ratio: float) -> dict[str, Any]:
    """``entry`` (``{"log", "n"}``: the running mean of log measured-over-uncorrected-prediction
    ratios and how many were folded) with ``ratio`` folded in."""
    if not (ratio > 0 and math.isfinite(ratio)):
        raise ValueError(f"a correction observation must be a positive ratio, got {ratio!r}")
    n = int(entry["n"]) + 1 if entry else 1
    old = float(entry["log"]) if entry else 0.0
    return {"log": old + (math.log(ratio) - old) / min(n, CORRECTION_WINDOW), "n": n}


def correction_factor(corrections: Mapping[str, Any] | None, kind: str, key: str) -> float:
    """The factor ``corrections[kind][key]`` applies to the model's prediction (1 until it has
    :data:`CORRECTION_MIN_OBSERVATIONS`; clamped to :data:`CORRECTION_RANGE`)."""
    entry = ((corrections or {}).get(kind) or {}).get(key)
    if not entry or int(entry.get("n", 0)) < CORRECTION_MIN_OBSERVATIONS:
        return 1.0
    lo, hi = CORRECTION_RANGE[kind]
    return min(hi, max(lo, math.exp(float(entry["log"]))))


def apply_corrections(model: SceneModel, corrections: Mapping[str, Any] | None) -> SceneModel:
    """``model`` with what served renders measured folded in: per setting (:func:`correction_key`),
    its predicted time times the ``time`` factor and its predicted error (the adaptive reference: its
    ``error_scale``) times the ``error`` factor (:func:`correction_factor`)."""
    if not corrections:
        return model

    def fix(fit: CandidateFit) -> CandidateFit:
        ft, fe = correction_factor(corrections, "time", fit.key), correction_factor(corrections, "error", fit.key)
        return replace(fit, error=fit.error * fe, b_ms=fit.b_ms * ft, c_ms=fit.c_ms * ft)

    adaptive = model.adaptive
    if adaptive is not None:
        key = ADAPTIVE_CORRECTION_KEY
        ft, fe = correction_factor(corrections, "time", key), correction_factor(corrections, "error", key)
        adaptive = replace(adaptive, error_scale=adaptive.error_scale * fe, time_ratio=adaptive.time_ratio * ft,
                           levels=[{**lv, "scale": lv["scale"] * fe, "time_ratio": lv["time_ratio"] * ft}
                                   for lv in adaptive.levels])
    return replace(model, reference=fix(model.reference), methods={k: fix(f) for k, f in model.methods.items()},
                   adaptive=adaptive)
