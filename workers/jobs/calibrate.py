"""The calibration job: measure every candidate render setting of a scene's bake on probe views and
fit the per-scene model of quality contracts (``engine.quality``, ``docs/quality-contracts.md``).

``calibrate_job(payload)`` runs on the ``bake`` queue after the bake it calibrates:

1. probe views: the scene's camera turned about its up axis by +-8 deg, +-16 deg, ... around
   the point of its view axis as deep as the scene's centre (never the scene's own view), at
   ``size`` pixels on the longest side;
2. a ground truth per probe: the reference at ``truth_spp`` spp with a seed of its own (and as
   many indirect paths per pixel when indirect light can arrive in the scene), so its noise is
   independent of the candidates';
3. every candidate on every probe: the reference at ``CALIBRATION_SPP`` spp, each with every seed of
   ``CALIBRATION_SEEDS`` (the error of a render at a few spp is a random draw: its spread over
   seeds sets the margin at each spp), and each LDC method of the bake at each antialiasing level of
   ``LDC_SUPERSAMPLE`` (edge supersampling: ``ldc``, ``ldc@2x2``, ``ldc@4x4``, ...)
   (``engine.quality.ldc_settings``), LRMS against the ground truth (over the pixels it covers,
   minus those on or next to an emitter: ``ReferenceRenderer.error_region``), wall time of the
   renderer's call (the LDC methods: the median of three); they are also timed at ``size x
   time_scale`` (the per-pixel part of their time). Each method renders once, untimed, on a tiny
   image first, so compile and lazy set-up never count as render time;
4. fit (``engine.quality.fit_reference`` / ``fit_ldc``), exclude the methods that do not render what
   the scene holds;
5. the adaptive reference (``engine/progressive.py``) on every probe, told to stop at the errors the
   fit predicts at each of :data:`ADAPTIVE_PROBE_SPP` spp (capped at ``truth_spp``): per level, its
   contract error over its own estimate (geometric mean over the probes; their spread sets its
   error margin) and its time over the spp model's time at that error (the largest)
   (``engine.quality.AdaptiveFit``); then store the model beside the bake (``producer.calibrations``).

What it costs is in the model (``cost_s`` and ``cost_breakdown_s``): mostly the ground truth
(``truth_spp`` x probes x pixels reference samples).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import replace
from datetime import UTC, datetime
from typing import Any

import numpy as np
from pydantic import ValidationError
from rq import get_current_job

from api_schemas.service import CalibrationParams, CalibrationRequest
from engine import ENGINE_VERSION
from engine.metrics import lrms
from engine.newviews.effects import analyze
from engine.newviews.renderer import LDCViewRenderer
from engine.quality import (
    CALIBRATION_SEEDS,
    CALIBRATION_SPP,
    LDC_SUPERSAMPLE,
    MAX_USEFUL_ERROR,
    AdaptiveFit,
    SceneModel,
    calibrated_margin,
    fit_ldc,
    fit_reference,
    fit_time,
    ldc_setting_name,
    ldc_settings,
    spp_for_error,
)
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.scene import CameraParams, RuntimeScene
from producer.artifacts import read_manifest
from producer.bakes import bake_complete, bake_key
from producer.calibrations import calibration_key, write_calibration
from producer.payloads import CalibrateJobPayload, InvalidPayload, describe_validation_error
from workers.jobs.bake import load_bake
from workers.jobs.common import ProgressReporter, json_safe, load_stored_scene, worker_store

__all__ = ["ADAPTIVE_PROBE_SPP", "PROBE_STEP_DEG", "TRUTH_SEED", "calibrate_job", "calibrate_scene",
           "probe_cameras", "probe_reference_params", "timed", "timed_median", "turned_camera", "view_pivot"]

PROBE_STEP_DEG = 8.0
"""Probe views turn the scene's camera by multiples of this angle (+8, -8, +16, -16, ...): near the
views callers ask for (a closed room seen from 24 degrees off shows its unlit outside, which is
not what a contract on the room is about)."""

ADAPTIVE_PROBE_SPP: tuple[int, ...] = (16, 64)
"""The adaptive reference is calibrated at the errors the reference's fit predicts at these many spp
(each capped at ``truth_spp``): ~10 % and a few per cent on the sample scenes. Its estimate reads
lower at the larger error, where its first pass already stops (the Cornell box: contract error over
estimate ~1.5 there, ~1.1 at the 64-spp error), so ``engine.quality.AdaptiveFit.scale_at``
interpolates between the levels. A lower level would sit near the ground truth's own noise (256 spp)
and cost most of the calibration."""

TRUTH_SEED = 7_919
"""Seed of the ground truth (the candidates render with the service's default seed 0)."""


def view_pivot(cam: CameraParams, lo: Any, hi: Any) -> np.ndarray:
    """The point the probe views turn around: on the camera's view axis, as deep as the centre of the
    scene's bounding box ``lo``..``hi`` (a camera whose look-at point is just in front of it, like the
    Cornell box's, then orbits the scene instead of turning in place)."""
    eye, at = np.asarray(cam.eye, float), np.asarray(cam.look_at, float)
    d = (at - eye) / np.linalg.norm(at - eye)
    centre = 0.5 * (np.asarray(lo, float) + np.asarray(hi, float))
    depth = float((centre - eye) @ d)
    pivot: np.ndarray = eye + d * (depth if depth > 0 else float(np.linalg.norm(at - eye)))
    return pivot


def turned_camera(cam: CameraParams, degrees: float, longest: int, pivot: Any = None) -> CameraParams:
    """``cam`` turned by ``degrees`` about its up axis through ``pivot`` (default: its look-at
    point), eye and look-at point alike, resized so that its longest side is ``longest`` pixels
    (same aspect ratio)."""
    up = np.asarray(cam.up, float)
    up = up / np.linalg.norm(up)
    c = np.asarray(cam.look_at if pivot is None else pivot, float)
    t = math.radians(degrees)

    def turn(p: Any) -> tuple[float, float, float]:
        v = np.asarray(p, float) - c
        v = v * math.cos(t) + np.cross(up, v) * math.sin(t) + up * float(up @ v) * (1.0 - math.cos(t))  # Rodrigues
        return (float(c[0] + v[0]), float(c[1] + v[1]), float(c[2] + v[2]))

    scale = longest / max(cam.width, cam.height)
    w, h = max(1, round(cam.width * scale)), max(1, round(cam.height * scale))
    return replace(cam, eye=turn(cam.eye), look_at=turn(cam.look_at), width=w, height=h)


def probe_cameras(cam: CameraParams, n: int, longest: int, pivot: Any = None) -> list[CameraParams]:
    """The ``n`` probe views: +8, -8, +16, -16, ... degrees from ``cam`` (see :func:`turned_camera`)."""
    angles = [PROBE_STEP_DEG * (i // 2 + 1) * (1 if i % 2 == 0 else -1) for i in range(n)]
    return [turned_camera(cam, a, longest, pivot) for a in angles]


def probe_reference_params(spp: int, gi: bool, indirect_bounces: int, seed: int = 0,
                           max_error: float | None = None) -> ReferenceParams:
    """How the calibration renders the reference on a probe view: the renderer's defaults, and with
    the scene's indirect light (``gi``) one indirect path per sample over ``indirect_bounces``."""
    base = ReferenceParams()
    return ReferenceParams(spp=spp, max_depth=base.max_depth, glossy_samples=base.glossy_samples,
                           area_light_samples=base.area_light_samples, indirect_samples=spp if gi else 0,
                           indirect_bounces=indirect_bounces if gi else base.indirect_bounces, seed=seed,
                           max_error=max_error)


def timed(fn: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """``fn(*args)`` and its wall time in ms (one run: renders long enough to time once)."""
    t0 = time.perf_counter()
    out = fn(*args)
    return out, 1000.0 * (time.perf_counter() - t0)


LDC_REPEATS = 3
"""The LDC methods render in milliseconds, where one timing is noise: each is timed this many times
and the median kept (the reference's renders are long enough to time once). The median, not the
fastest: the model predicts what a served render takes, and the fastest of three put the Cornell
box's LDC views at 0.68-0.71x the time served renders then took (docs/accuracy/contracts.md)."""


def timed_median(fn: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """``fn(*args)``'s first output and the median of :data:`LDC_REPEATS` timings of it, in ms (the
    renders that take milliseconds: LDC views, walkthrough frames)."""
    runs = [timed(fn, *args) for _ in range(LDC_REPEATS)]
    return runs[0][0], float(np.median([ms for _, ms in runs]))


def _error(img: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    return float(lrms(img, truth, mask if mask.any() else None))


def calibrate_scene(scene: RuntimeScene, camera: CameraParams, ldc_renderer: LDCViewRenderer, *,
                    params: CalibrationParams, bake_plan: dict[str, Any], indirect_bounces: int,
                    scene_id: str = "0" * 64, bake_key_: str = "0" * 64, bake_cost_s: float = 0.0,
                    reference: ReferenceRenderer | None = None,
                    progress: Callable[[float, str], None] | None = None) -> SceneModel:
    """Measure and fit the model of one scene and bake (see the module docstring)."""
    t_start = time.perf_counter()
    report = progress or (lambda f, s: None)
    ref = reference if reference is not None else ReferenceRenderer(scene)
    effects = analyze(scene)
    gi = effects.indirect_skip == ""
    base = ReferenceParams()
    ref_params: dict[str, int] = {"max_depth": base.max_depth, "glossy_samples": base.glossy_samples,
                                  "area_light_samples": base.area_light_samples,
                                  "indirect_bounces": indirect_bounces if gi else base.indirect_bounces,
                                  "indirect_per_spp": 1 if gi else 0}

    def ref_at(spp: int, seed: int = 0, max_error: float | None = None) -> ReferenceParams:
        return probe_reference_params(spp, gi, indirect_bounces, seed, max_error)

    mirror = "mirror" in bake_plan.get("material_kinds", effects.material_kinds)
    has_llf = ldc_renderer.llf is not None
    excluded: dict[str, str] = {}
    settings = ldc_settings(has_llf, mirror, params.ibrt_ks)
    if mirror:
        excluded["ldc"] = ("the scene has mirror materials, which ldc does not render (no reflections); "
                           "ldc+llf and ldc+ibrt:k do")
    if effects.needs_llf and not has_llf:
        why = "the bake has no light field (llf: never), which the scene's glossy or mirror materials need"
        excluded["ldc+llf"] = why
        for k in (params.ibrt_ks if mirror else []):
            excluded[f"ldc+ibrt:{k}"] = why
    methods = [s.method for s in settings if s.method not in excluded]
    # each LDC method at each antialiasing level: (setting name, method, supersample)
    variants = [(ldc_setting_name(m, ss), m, ss) for m in methods for ss in LDC_SUPERSAMPLE]

    def render_ldc(cam: CameraParams, m: str, ss: int) -> Any:
        return ldc_renderer.render(cam, m, supersample=ss, antialias="edges")

    pivot = view_pivot(camera, *scene.bounds)
    cams = probe_cameras(camera, params.probes, params.size, pivot)
    tiny = turned_camera(camera, PROBE_STEP_DEG, 8, pivot)
    cost: dict[str, float] = {"truth": 0.0, "reference": 0.0, "ldc": 0.0, "adaptive": 0.0, "warmup": 0.0}

    _, ms = timed(ref.render, tiny, ref_at(1))  # compile / build once, untimed
    cost["warmup"] += ms / 1000
    _, ms = timed(ref.render, tiny, ref_at(4, max_error=0.5))  # the progressive path too
    cost["warmup"] += ms / 1000
    for _, m, ss in variants:
        _, ms = timed(render_ldc, tiny, m, ss)
        cost["warmup"] += ms / 1000

    ref_points: list[dict[str, Any]] = []
    ldc_points: dict[str, list[dict[str, Any]]] = {name: [] for name, _, _ in variants}
    steps = len(cams) * (2 + len(CALIBRATION_SPP) + len(variants)) + len(variants)
    truths: list[tuple[np.ndarray, np.ndarray]] = []
    done = 0
    for probe, cam in enumerate(cams):
        px = cam.width * cam.height
        truth, ms = timed(ref.render, cam, ref_at(params.truth_spp, TRUTH_SEED))
        cost["truth"] += ms / 1000
        ref_points.append({"spp": params.truth_spp, "pixels": px, "ms": ms, "error": None})  # a time point
        mask = ref.error_region(cam, truth.object_id, truth.depth, base.max_depth)
        truths.append((truth.radiance, mask))
        done += 1
        report(done / steps, "ground truth")
        for spp in CALIBRATION_SPP:
            for seed in CALIBRATION_SEEDS:
                out, ms = timed(ref.render, cam, ref_at(spp, seed))
                cost["reference"] += ms / 1000
                ref_points.append({"spp": spp, "pixels": px, "ms": ms, "probe": probe, "seed": seed,
                                   "error": _error(out.radiance, truth.radiance, mask)})
            done += 1
            report(done / steps, f"reference {spp} spp")
        for name, m, ss in variants:
            out, ms = timed_median(render_ldc, cam, m, ss)
            cost["ldc"] += ms / 1000
            ldc_points[name].append({"pixels": px, "ms": ms, "error": _error(out.radiance, truth.radiance, mask),
                                     "probe": probe})
            done += 1
            report(done / steps, name)
    big = turned_camera(camera, PROBE_STEP_DEG, params.size * params.time_scale, pivot)
    for name, m, ss in variants:
        _, ms = timed_median(render_ldc, big, m, ss)
        cost["ldc"] += ms / 1000
        ldc_points[name].append({"pixels": big.width * big.height, "ms": ms, "error": None, "probe": 0})
        done += 1
        report(done / steps, f"{name} at {big.width} x {big.height}")

    ref_err = [p for p in ref_points if p["error"] is not None]
    reference_fit = fit_reference(ref_err, params.truth_spp)
    b_ms, c_ms = fit_time([float(p["spp"]) * float(p["pixels"]) for p in ref_points],
                          [float(p["ms"]) for p in ref_points])  # the ground truth's renders are time points too
    reference_fit = replace(reference_fit, b_ms=b_ms, c_ms=c_ms, points=ref_points)
    truth_noise = reference_fit.error * params.truth_spp ** -reference_fit.exponent  # as the fit models it
    fits = {}
    for name, m, ss in variants:
        pts = ldc_points[name]
        fit = fit_ldc(m, pts, truth_noise, ss)
        # the time's per-pixel part from one view at two sizes (views differ in cost more than sizes do
        # at probe sizes), the fixed part as the mean over the probes' time at their size
        same_view = [p for p in pts if p["probe"] == 0]
        b, c = fit_time([float(p["pixels"]) for p in same_view], [float(p["ms"]) for p in same_view])
        at_size = [p for p in pts if p["error"] is not None]
        b = max(0.0, sum(float(p["ms"]) for p in at_size) / len(at_size) - c * float(at_size[0]["pixels"]))
        fit = replace(fit, b_ms=b, c_ms=c)
        fits[name] = fit
        if fit.error > MAX_USEFUL_ERROR:
            excluded[name] = (f"measured LRMS {fit.error:.2f} on the probe views (over {MAX_USEFUL_ERROR:g}): it "
                              "does not render what this scene holds")
    adaptive_fit = _calibrate_adaptive(ref, cams, truths, reference_fit, truth_noise, params.truth_spp, ref_at,
                                       cost, lambda i: report((done + i + 1) / steps, "adaptive reference"))
    cost_s = time.perf_counter() - t_start
    return SceneModel(
        scene_id=scene_id, bake_key=bake_key_, reference=reference_fit, methods=fits, excluded=excluded,
        reference_params=ref_params, bake_cost_s=float(bake_cost_s), cost_s=cost_s,
        probe={"views": len(cams), "width": cams[0].width, "height": cams[0].height,
               "angles_deg": [PROBE_STEP_DEG * (i // 2 + 1) * (1 if i % 2 == 0 else -1) for i in range(len(cams))],
               "truth_spp": params.truth_spp, "truth_seed": TRUTH_SEED, "calibration_spp": list(CALIBRATION_SPP),
               "time_scale": params.time_scale, "indirect": gi, "cost_breakdown_s": cost},
        engine_version=ENGINE_VERSION, created_at=datetime.now(UTC).isoformat(), adaptive=adaptive_fit)


def _calibrate_adaptive(ref: ReferenceRenderer, cams: list[CameraParams], truths: list[tuple[np.ndarray, np.ndarray]],
                        reference_fit: Any, truth_noise: float, truth_spp: int,
                        ref_at: Callable[..., ReferenceParams], cost: dict[str, float],
                        report: Callable[[int], None]) -> AdaptiveFit | None:
    """The adaptive reference's fit (step 5 of the module docstring); None when the reference's
    fit is degenerate (no noise measured: nothing to stop at)."""
    aims = sorted({reference_fit.error_at(min(spp, truth_spp)) for spp in ADAPTIVE_PROBE_SPP}, reverse=True)
    aims = [a for a in aims if 0.0 < a < 1.0]
    if not aims:
        return None
    points: list[dict[str, Any]] = []
    for i, (cam, (truth, mask)) in enumerate(zip(cams, truths, strict=True)):
        for aim in aims:
            out, ms = timed(ref.render, cam, ref_at(max(2, truth_spp), max_error=aim))
            cost["adaptive"] += ms / 1000
            rep = out.adaptive or {}
            est = float(rep.get("estimated_error", 0.0))
            e = _error(out.radiance, truth, mask)
            err = math.sqrt(max(e * e - truth_noise * truth_noise, 0.25 * e * e))  # as fit_ldc removes it
            px = cam.width * cam.height
            spp = spp_for_error(reference_fit, err)
            model_ms = reference_fit.b_ms + reference_fit.c_ms * spp * px
            points.append({"pixels": px, "ms": ms, "error": err, "estimated_error": est, "told": aim, "probe": i,
                           "spp_mean": rep.get("spp_mean"), "stop_reason": rep.get("stop_reason"),
                           "uniform_spp": spp, "uniform_ms": model_ms})
        report(i)
    levels: list[dict[str, float]] = []
    spread: list[float] = []  # each probe's scale over its level's
    for aim in sorted(aims):
        at = [p for p in points if p["told"] == aim and p["estimated_error"] > 0 and p["error"] > 0]
        ratios = [p["ms"] / p["uniform_ms"] for p in points if p["told"] == aim and p["uniform_ms"] > 0]
        if not at or not ratios:
            continue
        logs = [math.log(p["error"] / p["estimated_error"]) for p in at]
        scale = math.exp(sum(logs) / len(logs))
        spread += [math.exp(x) / scale for x in logs]
        levels.append({"error": aim, "scale": scale, "time_ratio": max(ratios)})
    if not levels:
        return None
    scales = [p["error"] / p["estimated_error"] for p in points if p["estimated_error"] > 0]
    return AdaptiveFit(error_scale=max(scales), time_ratio=max(lv["time_ratio"] for lv in levels), points=points,
                       levels=levels, margin=calibrated_margin(spread, len(cams)))


def calibrate_job(payload: dict[str, Any]) -> dict[str, Any]:
    """Calibrate a scene's bake and store the model; returns a summary (errors, times, cost)."""
    try:
        p = CalibrateJobPayload.model_validate(payload)
    except ValidationError as exc:
        raise InvalidPayload(f"invalid calibration job payload: {describe_validation_error(exc)}") from None
    req: CalibrationRequest = p.request
    bkey = bake_key(p.scene_id, req.bake)
    if bkey != p.bake_key or calibration_key(p.scene_id, bkey, req) != p.key:
        raise InvalidPayload("calibration job payload: keys do not match the request")
    store = worker_store()
    progress = ProgressReporter(get_current_job())
    progress.report(0.0, "loading the scene and its bake", force=True)
    if not bake_complete(store, bkey):
        raise RuntimeError(f"bake {bkey} of scene {p.scene_id} is not available; request it with POST "
                           f"/v1/scenes/{p.scene_id}/bakes and calibrate again")
    loaded = load_stored_scene(store, p.scene_id)
    ldc, llf, plan_doc = load_bake(store, loaded.runtime, bkey)
    manifest = read_manifest(store, bkey)
    bake_cost = float((manifest.result.get("timings") or {}).get("parts_total") or 0.0) if manifest else 0.0
    renderer = LDCViewRenderer(loaded.runtime, ldc, llf, analyze(loaded.runtime),
                               area_light_samples=req.bake.area_light_samples, seed=req.bake.seed)
    model = calibrate_scene(loaded.runtime, loaded.camera, renderer, params=req.params, bake_plan=plan_doc,
                            indirect_bounces=req.bake.indirect.bounces, scene_id=p.scene_id, bake_key_=bkey,
                            bake_cost_s=bake_cost, progress=lambda f, s: progress.report(0.02 + 0.96 * f, s))
    write_calibration(store, p.scene_id, bkey, p.key, req.params.model_dump(mode="json"), model)
    progress.report(1.0, "done", force=True, check=False)
    summary: dict[str, Any] = json_safe({"scene_id": p.scene_id, "bake_key": bkey, "key": p.key, "cost_s": model.cost_s,
                      "errors": {"reference_a": model.reference.error,
                                 **{m: f.error for m, f in model.methods.items()}},
                      "excluded": model.excluded})
    return summary
