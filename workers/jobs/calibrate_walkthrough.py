"""The walkthrough calibration job: measure each walkthrough setting (bake preset x hole fill) of a
scene on probe frames and fit the model walkthrough quality contracts are planned from
(``engine.walkthrough.quality``, ``docs/quality-contracts.md``, "Walkthroughs").

``calibrate_walkthrough_job(payload)`` runs on the ``bake`` queue:

1. probe frames: ``probes`` eyes spread over the scene's view space
   (``engine.walkthrough.quality.probe_eyes``) at times spread over the animation, each looking the
   way the scene's camera looks and, when that is another way, where there is most room in front
   (:func:`probe_views`), ``size`` pixels on the longest side;
2. a converged frame per probe (``engine.walkthrough.ground_truth.converged_frame``: the image
   model the walkthrough reconstructs, indirect light traced to ``truth_noise``) and its error
   region (covered pixels not on or next to an emitter, as for every error the project quotes);
3. per preset: its bake from the store, or baked and published under the key a walkthrough naming
   only that preset uses (so a walkthrough planned onto it renders at once), its cost the bake's
   wall time; then every fill on every probe: LRMS against the converged frame over its error
   region, render time the median of three; the first probe also at ``size x time_scale`` (the
   time's per-pixel part). Each setting renders a tiny frame first, untimed (compilation);
4. path-traced frames (``WalkthroughRequest.path_traced``) at each of ``path_noises``, on every
   probe with the service's seed (not the converged frames'): LRMS and render time, timed once
   (they take tenths of a second to seconds) as the chunk job renders them (``PathTracedFrames``: a
   frame of an animated scene builds the scene and BVH of its time);
5. fit (``engine.walkthrough.quality.fit_setting``, ``fit_path_setting``), exclude the settings
   whose error exceeds ``engine.quality.MAX_USEFUL_ERROR``, store the model
   (``producer.walkthrough_calibrations``).

What it costs is in the model (``cost_s``, ``probe.cost_breakdown_s``): the bakes it had to make and
the converged frames.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import replace
from datetime import UTC, datetime
from functools import partial
from typing import Any

import numpy as np
from pydantic import ValidationError
from rq import get_current_job

from api_schemas.walkthrough import WalkthroughCalibrationParams, WalkthroughSettings
from engine import ENGINE_VERSION
from engine.metrics import lrms
from engine.quality import MAX_USEFUL_ERROR, CandidateFit
from engine.reference import ReferenceRenderer
from engine.scene import CameraParams
from engine.walkthrough.animation import AnimatedScene
from engine.walkthrough.bake import WalkthroughBake, WalkthroughRenderer, walkthrough_preset
from engine.walkthrough.ground_truth import converged_frame
from engine.walkthrough.quality import WalkthroughModel, fit_path_setting, fit_setting, probe_eyes, probe_times
from producer.artifacts import read_manifest
from producer.payloads import InvalidPayload, WalkthroughCalibrateJobPayload, describe_validation_error
from producer.walkthrough_calibrations import walkthrough_calibration_key, write_walkthrough_calibration
from producer.walkthroughs import walkthrough_bake_key
from workers.jobs.calibrate import timed, timed_median
from workers.jobs.common import ProgressReporter, json_safe, worker_store
from workers.jobs.walkthrough import (
    PathTracedFrames,
    engine_space,
    load_stored_bake,
    load_walkthrough_scene,
    make_walkthrough_bake,
)
from workers.scene_loader import camera_params

__all__ = ["HEADINGS", "TRUTH_SEED", "calibrate_walkthrough", "calibrate_walkthrough_job",
           "probe_views", "roomiest_heading"]

TRUTH_SEED = 7_919
"""Seed of the converged frames (the bases render with the service's default seed 0)."""

BakeSource = Callable[[str, Callable[[float, str], None]], tuple[WalkthroughBake, str, float]]
"""``(preset, progress) -> (bake, its artifact key, its cost in seconds)``."""


HEADINGS = 16
"""Horizontal headings a probe camera chooses among (every 22.5 degrees about the camera's up axis)."""


def probe_views(camera: CameraParams, eye: tuple[float, float, float], longest: int,
                intersect: Callable[[np.ndarray, np.ndarray], Any] | None = None) -> list[CameraParams]:
    """The probe cameras at ``eye``, with ``camera``'s up axis, pitch and field of view, resized so
    that the longest side is ``longest`` pixels: one looking the way ``camera`` looks (what the
    scene's author framed) and, with ``intersect`` (``ReferenceRenderer.caster.intersect``: rays ->
    hits with ``t``, inf on a miss), one looking where there is most room (:func:`roomiest_heading`)
    when that is another way. A walkthrough looks both ways: at the action, and ahead along the way it walks. On
    ``static_room`` the author's direction from an eye beside the corridor's wall looked at that wall
    and the corridor's view looked along it; on a test room the roomy view grazed a wall and missed
    the object the frames looked at. One of them alone left the other kind of frame out of the model."""
    fwd = np.subtract(camera.look_at, camera.eye).astype(np.float64)
    fwd /= np.linalg.norm(fwd)
    scale = longest / max(camera.width, camera.height)
    w, h = max(2, round(camera.width * scale)), max(2, round(camera.height * scale))
    dirs = [fwd]
    if intersect is not None:
        roomy = roomiest_heading(camera, np.asarray(eye, np.float64), intersect)
        if float(roomy @ fwd) < 0.999:
            dirs.append(roomy)
    e = eye
    return [replace(camera, eye=e, look_at=(e[0] + float(d[0]), e[1] + float(d[1]), e[2] + float(d[2])),
                    width=w, height=h) for d in dirs]


def roomiest_heading(camera: CameraParams, eye: np.ndarray, intersect: Callable[[np.ndarray, np.ndarray], Any]
                     ) -> np.ndarray:
    """The view direction from ``eye``, at ``camera``'s pitch, of the one of :data:`HEADINGS` around
    its up axis with the most room in front: the mean distance to the first hit of five rays across
    the middle of the view (a miss counts as no room: a view of nothing is no walkthrough frame);
    ties go to ``camera``'s own heading."""
    up = np.asarray(camera.up, np.float64)
    up /= np.linalg.norm(up)
    fwd = np.subtract(camera.look_at, camera.eye).astype(np.float64)
    fwd /= np.linalg.norm(fwd)
    pitch = float(fwd @ up)
    ahead = fwd - pitch * up
    ahead = ahead / np.linalg.norm(ahead) if np.linalg.norm(ahead) > 1e-9 else np.cross(up, [1.0, 0.0, 0.0])
    side = np.cross(up, ahead)
    flat = math.sqrt(max(0.0, 1.0 - pitch * pitch))
    spread = 0.25 * math.radians(camera.fov_y_deg if camera.kind == "perspective" else 40.0)
    best, out = -1.0, fwd
    for k in range(HEADINGS):
        a = 2.0 * math.pi * k / HEADINGS
        centre = flat * (math.cos(a) * ahead + math.sin(a) * side) + pitch * up
        right = np.cross(centre, up)
        right /= np.linalg.norm(right)
        rays = np.array([centre] + [math.cos(spread) * centre + math.sin(spread) * v for v in (right, -right, up, -up)])
        t = np.asarray(intersect(np.repeat(eye[None], 5, axis=0), rays).t)
        room = float(np.where(np.isfinite(t), t, 0.0).mean())
        if room > best * (1 + 1e-9):
            best, out = room, centre
    return out


def calibrate_walkthrough(an: AnimatedScene, space: Any, camera: CameraParams, bake_for: BakeSource, *,
                          params: WalkthroughCalibrationParams, scene_id: str = "0" * 64,
                          progress: Callable[[float, str], None] | None = None) -> WalkthroughModel:
    """Measure and fit the walkthrough model of one scene (see the module docstring)."""
    t_start = time.perf_counter()
    report = progress or (lambda f, s: None)
    eye_times = probe_times(an.start, an.end, params.probes) if not an.is_static else [an.start] * params.probes
    cams: list[CameraParams] = []
    times: list[float] = []
    renderers: list[ReferenceRenderer] = []  # per probe frame: its eye's (one scene and BVH per eye)
    for e, t in zip(probe_eyes(space, params.probes), eye_times, strict=True):
        rr = ReferenceRenderer(an.scene_at(t))
        views = probe_views(camera, e, params.size, rr.caster.intersect)
        cams += views
        times += [t] * len(views)
        renderers += [rr] * len(views)
    bounces = walkthrough_preset(params.presets[0]).indirect_bounces
    n_steps = len(cams) + len(params.presets) + len(params.path_noises)
    truths: list[tuple[np.ndarray, np.ndarray]] = []
    truth_stats: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for i, (cam, rr) in enumerate(zip(cams, renderers, strict=True)):
        report(i / n_steps, f"converged probe frame {i + 1} of {len(cams)}")
        img, _, mask, st = converged_frame(rr, cam, i, TRUTH_SEED, params.truth_noise, bounces)
        truths.append((img, mask))
        truth_stats.append(st)
    truth_s = time.perf_counter() - t0
    # the converged frames' own noise, removed from the errors in quadrature: their pixels' median
    # relative standard error (the direct light, 1024 area samples, adds little)
    truth_noise = float(np.median([st["rel_stderr_median"] for st in truth_stats]))
    big = replace(cams[0], width=cams[0].width * params.time_scale, height=cams[0].height * params.time_scale)
    tiny = replace(cams[0], width=4, height=4)
    fits: dict[str, CandidateFit] = {}
    excluded: dict[str, str] = {}
    bake_keys: dict[str, str] = {}
    bake_cost: dict[str, float] = {}
    bakes_s = measure_s = 0.0
    for j, preset in enumerate(params.presets):
        step = len(cams) + j

        def sub(f: float, s: str, step: int = step, preset: str = preset) -> None:
            report((step + 0.8 * f) / n_steps, f"{preset} bake: {s}")

        t0 = time.perf_counter()
        bake, bkey, cost = bake_for(preset, sub)
        bakes_s += time.perf_counter() - t0
        bake_keys[preset], bake_cost[preset] = bkey, cost
        report((step + 0.8) / n_steps, f"measuring {preset}")
        t0 = time.perf_counter()
        for fill in params.fills:
            wr = WalkthroughRenderer(bake, an if fill == "trace" else None)
            wr.render(tiny, times[0], fill=fill, strict=False)  # untimed: compilation, lazy set-up
            points: list[dict[str, Any]] = []
            for i, (cam, t) in enumerate(zip(cams, times, strict=True)):
                fr, ms = timed_median(partial(wr.render, fill=fill, strict=False), cam, t)
                img, mask = truths[i]
                points.append({"error": float(lrms(fr.radiance, img, mask if mask.any() else None)),
                               "pixels": cam.width * cam.height, "ms": ms, "probe": i})
            _, ms = timed_median(partial(wr.render, fill=fill, strict=False), big, times[0])
            points.append({"error": None, "pixels": big.width * big.height, "ms": ms, "probe": 0})
            _keep(fit_setting(preset, fill, points, truth_noise), fits, excluded)
        measure_s += time.perf_counter() - t0
    t0 = time.perf_counter()
    if params.path_noises:  # untimed: compilation (the same kernels at every noise)
        PathTracedFrames(an, params.path_noises[0], 0, bounces).render(tiny, times[0], 0)
    for j, noise in enumerate(params.path_noises):
        report((len(cams) + len(params.presets) + j) / n_steps, f"measuring path-traced frames at noise {noise:g}")
        shared = PathTracedFrames(an, noise, 0, bounces)
        points = []
        for i, (cam, t) in enumerate(zip(cams, times, strict=True)):
            # as the chunk job renders: a frame of an animated scene builds its time's scene and BVH
            frames = shared if an.is_static else PathTracedFrames(an, noise, 0, bounces)
            (img_p, _, _), ms = timed(frames.render, cam, t, i)
            img, mask = truths[i]
            points.append({"error": float(lrms(img_p, img, mask if mask.any() else None)),
                           "pixels": cam.width * cam.height, "ms": ms, "probe": i})
        _keep(fit_path_setting(noise, points, truth_noise), fits, excluded)
    path_s = time.perf_counter() - t0
    cost = time.perf_counter() - t_start
    probe = {"frames": [{"eye": list(c.eye), "look_at": list(c.look_at), "time": t, "width": c.width,
                         "height": c.height} for c, t in zip(cams, times, strict=True)],
             "truth_noise": truth_noise, "truth_noise_target": params.truth_noise,
             "truth_paths_mean": float(np.mean([st["paths_mean"] for st in truth_stats])),
             "cost_breakdown_s": {"ground_truth": truth_s, "bakes": bakes_s, "settings": measure_s,
                                  "path_traced": path_s}}
    return WalkthroughModel(scene_id=scene_id, fits=fits, excluded=excluded, bake_keys=bake_keys,
                            bake_cost_s=bake_cost, cost_s=cost, probe=json_safe(probe),
                            engine_version=ENGINE_VERSION, created_at=datetime.now(UTC).isoformat())


def _keep(fit: CandidateFit, fits: dict[str, CandidateFit], excluded: dict[str, str]) -> None:
    """Add ``fit`` to ``fits``, and to ``excluded`` (with the reason) when its error exceeds
    ``engine.quality.MAX_USEFUL_ERROR``."""
    fits[fit.key] = fit
    if fit.error > MAX_USEFUL_ERROR:
        excluded[fit.key] = (f"its error on the probe frames ({fit.error:.0%}) exceeds "
                             f"{MAX_USEFUL_ERROR:.0%}: it does not render what the scene holds")


def _stored_bake_source(store: Any, scene_id: str) -> BakeSource:
    """Each preset's bake from the store (its cost: the bake job's wall time), else baked and
    published under the key of a walkthrough request naming only that preset."""

    def bake_for(preset: str, progress: Callable[[float, str], None]) -> tuple[WalkthroughBake, str, float]:
        settings = WalkthroughSettings(quality=preset)  # type: ignore[arg-type]
        bkey = walkthrough_bake_key(scene_id, settings)
        manifest = read_manifest(store, bkey)
        if manifest is not None:
            timings = manifest.result.get("timings") or {}
            return load_stored_bake(store, bkey), bkey, float(timings.get("job_total") or timings.get("total") or 0.0)
        t0 = time.perf_counter()
        bake, _ = make_walkthrough_bake(store, scene_id, bkey, settings, progress)
        return bake, bkey, time.perf_counter() - t0

    return bake_for


def calibrate_walkthrough_job(payload: dict[str, Any]) -> dict[str, Any]:
    """Calibrate a scene's walkthrough settings and store the model; returns a summary."""
    try:
        p = WalkthroughCalibrateJobPayload.model_validate(payload)
    except ValidationError as exc:
        raise InvalidPayload(f"invalid walkthrough calibration payload: {describe_validation_error(exc)}") from None
    if walkthrough_calibration_key(p.scene_id, p.request) != p.key:
        raise InvalidPayload("walkthrough calibration payload: the key does not match the request")
    store = worker_store()
    progress = ProgressReporter(get_current_job())
    progress.report(0.0, "loading the scene", force=True)
    scene, an = load_walkthrough_scene(store, p.scene_id)
    model = calibrate_walkthrough(an, engine_space(scene), camera_params(scene.camera),
                                  _stored_bake_source(store, p.scene_id), params=p.request.params,
                                  scene_id=p.scene_id, progress=lambda f, s: progress.report(0.02 + 0.96 * f, s))
    write_walkthrough_calibration(store, p.scene_id, p.key, p.request.params.model_dump(mode="json"), model)
    progress.report(1.0, "done", force=True, check=False)
    summary: dict[str, Any] = json_safe({"scene_id": p.scene_id, "key": p.key, "cost_s": model.cost_s,
                                         "errors": {k: f.error for k, f in model.fits.items()},
                                         "excluded": model.excluded})
    return summary
