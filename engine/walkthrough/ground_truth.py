"""Path-traced walkthrough frames: the converged frame a frame reconstructed from the bases is
measured against, and the frames a walkthrough renders without a bake.

The image model is the one the image-based methods render, one point sample at each pixel centre
(the reference renderer with ``pixel_jitter=False``, 1 spp): direct light with area-light samples
per pixel, plus indirect light traced per visible surface point with the reference renderer's own
indirect paths (``engine.newviews.indirect.trace_indirect_points``).

- :func:`converged_frame`: :data:`AREA_LIGHT_SAMPLES` area-light samples, and indirect paths until
  each pixel's relative standard error reaches a target (at least :data:`MIN_PATHS`), for ground
  truths (the walkthrough calibration, ``workers/jobs/calibrate_walkthrough.py``, and
  ``bench/walkthrough_accuracy.py``);
- :func:`path_traced_frame`: the same estimate to a target LRMS of the whole frame, every pixel
  tracing the paths a pilot of the frame says that target needs (``engine.walkthrough.path_settings``):
  a walkthrough frame that needs no bake (``WalkthroughRequest.path_traced``), converging to the
  same image as the noise target falls.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.camera import camera_rays, pixel_centers
from engine.metrics import REC709_WEIGHTS
from engine.newviews.effects import analyze
from engine.newviews.indirect import IndirectParams, trace_indirect_points
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.sampler import sample_key
from engine.scene import CameraParams
from engine.walkthrough.path_settings import (
    CONVERGED_AREA_LIGHT_SAMPLES,
    WHOLE_ROUNDS_MAX_EXCESS,
    path_traced_settings,
    whole_rounds,
)
from engine.walkthrough.range_images import surface_points

__all__ = ["AREA_LIGHT_SAMPLES", "GROUND_TRUTH_STREAM", "converged_frame", "path_traced_frame"]

AREA_LIGHT_SAMPLES = CONVERGED_AREA_LIGHT_SAMPLES
"""Area-light samples per pixel of the converged frame's direct light (a 32 x 32 jittered grid)."""
GROUND_TRUTH_STREAM = 6
"""Sampler stream of the indirect paths: ``sample_key(seed, 6, frame)`` (the bases' own use 5)."""
MIN_PATHS = 256
MAX_PATHS = 65536
PATH_TIME_SHARE = 0.9
"""A stage cut to the frame's time budget traces paths for this share of the time left, at the
stage before's time per path: a stage's paths cost more or less than the one before's, and the
frame's last steps follow it (sized to the whole time left, frames ended up to 5.6 % past their
budgets)."""
SPLIT_ABOVE_PATHS = 16
"""A path-traced frame whose pilot asks for more paths than this traces half of them first and sizes
the rest from those: the pilot sizes as if the error fell as 1 / sqrt(paths), and past ~16 paths the
stratified samples make it fall faster (a frame sized from its pilot alone landed at 0.65x a target
of 0.02 on the Cornell box, tracing ~1.6x the paths it needed)."""


def path_traced_frame(rr: ReferenceRenderer, cam: CameraParams, frame: int, seed: int, noise: float,
                      bounces: int, indirect_skip: str | None = None, max_ms: float | None = None
                      ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """A walkthrough frame path-traced to an estimated LRMS of ``noise`` against the converged frame
    (``engine.walkthrough.path_settings``): radiance (h, w, 3) float32, the mask of the pixels it
    covers, and the stats of :func:`converged_frame` plus ``estimated_error`` (the frame's LRMS
    estimated from its pixels' standard errors over its error region), ``pilot_paths`` and
    ``pilot_error``. Deterministic in ``seed``; ``frame`` decorrelates the frames.

    Every pixel traces the pilot's paths, then as many more as the pilot's estimate of the frame's
    LRMS says the target needs (at most ``max_paths``; above :data:`SPLIT_ABOVE_PATHS` half of them,
    then the rest as the estimate of those says): one count for the whole frame. The count depends
    on the spread over thousands of pixels and each pixel keeps every path it traced: what one
    pixel's own paths move of that count is far below its noise.

    ``max_ms``: the frame's time budget: no more paths than the time left at the last stage's
    time per path allows (the direct light and the pilot are always traced), so a frame that runs out
    of time ends above ``noise`` and says so (``stopped_by``: ``time``; else ``noise``).

    ``indirect_skip``: why no surface of the scene can receive indirect light
    (``engine.newviews.effects.analyze``; None: analysed here, "" forces the indirect paths): such a
    frame traces none, and its stats say why (``indirect_skip``)."""
    ps = path_traced_settings(noise)
    skip = analyze(rr.scene).indirect_skip if indirect_skip is None else indirect_skip
    t0 = time.perf_counter()
    fp = _frame_points(rr, cam, seed, ps.area_light_samples)
    st: dict[str, Any] = {**_UNTRACED, "estimated_error": 0.0, "pilot_paths": 0, "pilot_error": 0.0,
                          "stopped_by": "noise"}
    if len(fp.idx) and not skip:
        region = rr.error_region(cam, fp.direct.object_id, fp.direct.depth, ReferenceParams().max_depth)
        in_region = region.reshape(-1)[fp.idx]
        luma = np.asarray(REC709_WEIGHTS)
        y_direct = fp.out @ luma

        def trace(paths: float, part: int) -> tuple[np.ndarray, np.ndarray, int]:
            n, r = whole_rounds(paths)
            ip = IndirectParams(noise=noise, sampling="adaptive", min_paths=n, max_paths=n, bounces=bounces,
                                round_paths=r, seed=seed, area_light_samples=4, caustics="paths")
            ind = trace_indirect_points(rr, fp.p, fp.g, fp.s, fp.mat, fp.base, ip,
                                        key=sample_key(seed, GROUND_TRUTH_STREAM, frame, part), brightness=fp.bright)
            return ind.radiance.astype(np.float64), ind.stderr.astype(np.float64), n

        def frame_error(radiance: np.ndarray, se: np.ndarray) -> float:
            # LRMS = RMS(Y - Y_true) / mean(Y_true) over the error region: a pixel's expected square
            # error is its indirect estimate's variance (the direct light's 64+ samples add little)
            y = y_direct.copy()
            y[fp.idx] += radiance @ luma
            mean = float(y[region.reshape(-1)].mean()) if region.any() else 0.0
            return math.sqrt(float(np.sum(se[in_region] ** 2)) / max(1, int(region.sum()))) / mean if mean > 0 else 0.0

        t_stage = time.perf_counter()
        radiance, se, n_total = trace(ps.pilot_paths, 0)
        s_per_path = (time.perf_counter() - t_stage) / n_total
        pilot_error = frame_error(radiance, se)
        per_path = n_total * pilot_error ** 2  # the frame's relative variance of one path
        for stage in (1, 2):
            # the total N at which the paths so far plus N - n_total more at per_path each reach the
            # target: (n^2 V + (N - n) per_path) / N^2 = noise^2
            known = n_total ** 2 * frame_error(radiance, se) ** 2 - n_total * per_path
            disc = per_path ** 2 + 4.0 * noise ** 2 * known
            need = (per_path + math.sqrt(max(disc, 0.0))) / (2.0 * noise ** 2)
            extra = min(float(ps.max_paths), need) - n_total
            if extra <= 1e-9:
                break
            if stage == 1 and extra > SPLIT_ABOVE_PATHS:
                extra /= 2.0  # see SPLIT_ABOVE_PATHS
            if max_ms is not None:
                # whole rounds add up to WHOLE_ROUNDS_MAX_EXCESS more paths than asked for
                left = max_ms / 1000.0 - (time.perf_counter() - t0)
                affordable = PATH_TIME_SHARE * left / s_per_path / (1.0 + WHOLE_ROUNDS_MAX_EXCESS)
                if affordable < extra:
                    st["stopped_by"] = "time"
                    if affordable < 2.0:
                        break
                    extra = affordable
            t_stage = time.perf_counter()
            more, se_more, n_more = trace(extra, stage)
            s_per_path = (time.perf_counter() - t_stage) / n_more
            per_path = n_more * frame_error(more, se_more) ** 2
            radiance = (n_total * radiance + n_more * more) / (n_total + n_more)
            se = np.hypot(n_total * se, n_more * se_more) / (n_total + n_more)
            n_total += n_more
        fp.out[fp.idx] += radiance
        traced = fp.receives
        rel = se[traced] / np.maximum((fp.base[traced] + radiance[traced]) @ luma, max(0.25 * fp.bright, 1e-300))
        if rel.size:
            st.update(rel_stderr_median=float(np.median(rel)), rel_stderr_p95=float(np.percentile(rel, 95)),
                      rel_stderr_max=float(rel.max()), met_target=float(np.mean(rel <= noise)),
                      paths_mean=float(n_total), paths_max=int(n_total))
        st.update(estimated_error=frame_error(radiance, se), pilot_paths=ps.pilot_paths, pilot_error=pilot_error)
    st.update(seconds=time.perf_counter() - t0, direct_seconds=fp.direct_seconds,
              area_light_samples=ps.area_light_samples, indirect_skip=skip)
    return fp.out.reshape(cam.height, cam.width, 3).astype(np.float32), fp.direct.object_id >= 0, st


def converged_frame(rr: ReferenceRenderer, cam: CameraParams, frame: int, seed: int, noise: float,
                    bounces: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """The converged frame seen by ``cam`` in the scene of ``rr`` (already at the frame's time):
    radiance (h, w, 3) float32, the mask of the pixels it covers, the error region (covered and
    not on or next to an emitter: ``ReferenceRenderer.error_region``, where the project's errors
    are measured; the quality contracts' frame error is), and stats (the indirect pass's
    relative standard error median / p95 / max, the fraction of pixels that met ``noise``, paths
    per pixel, seconds). ``noise``: target relative standard error of each pixel's luminance;
    ``bounces``: diffuse vertices of the indirect paths (the bake's ``indirect_bounces``)."""
    img, covered, st = _traced(rr, cam, frame, seed, noise, bounces, AREA_LIGHT_SAMPLES, MIN_PATHS, MAX_PATHS, 16)
    region = rr.error_region(cam, st.pop("object_id"), st.pop("depth"), ReferenceParams().max_depth)
    return img, covered, region, st


_UNTRACED: dict[str, Any] = {"rel_stderr_median": 0.0, "rel_stderr_p95": 0.0, "rel_stderr_max": 0.0,
                             "met_target": 1.0, "paths_mean": 0.0, "paths_max": 0}
"""The indirect stats of a frame that traced no paths."""


@dataclass
class _FramePoints:
    """A frame's direct light (``out``: (h * w, 3) float64, the indirect light is added to it) and the
    surface points its pixels see (``idx`` their pixels; ``base`` their direct radiance; ``receives``
    those whose material has kd > 0, the ones that trace indirect paths)."""

    direct: Any
    direct_seconds: float
    out: np.ndarray
    idx: np.ndarray
    p: np.ndarray
    g: np.ndarray
    s: np.ndarray
    mat: np.ndarray
    base: np.ndarray
    receives: np.ndarray
    bright: float


def _frame_points(rr: ReferenceRenderer, cam: CameraParams, seed: int, area_light_samples: int) -> _FramePoints:
    t0 = time.perf_counter()
    direct = rr.render(cam, ReferenceParams(spp=1, pixel_jitter=False, area_light_samples=area_light_samples,
                                            indirect_samples=0, seed=seed))
    t_direct = time.perf_counter() - t0
    px, py = pixel_centers(cam)
    o, d = camera_rays(cam, px, py)
    idx, p, g, s, mat = surface_points(rr, o, d)
    out = direct.radiance.reshape(-1, 3).astype(np.float64)
    base = out[idx]
    receives = np.any(rr.scene.materials.kd[mat] > 0.0, axis=1)
    bright = float((base[receives] @ np.asarray(REC709_WEIGHTS)).mean()) if receives.any() else 0.0
    return _FramePoints(direct, t_direct, out, idx, p, g, s, mat, base, receives, bright)


def _traced(rr: ReferenceRenderer, cam: CameraParams, frame: int, seed: int, noise: float, bounces: int,
            area_light_samples: int, min_paths: int, max_paths: int, round_paths: int
            ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    t0 = time.perf_counter()
    fp = _frame_points(rr, cam, seed, area_light_samples)
    st: dict[str, Any] = dict(_UNTRACED)
    if len(fp.idx):
        # paths alone, caustics included: a ground truth must not share the photon map's blur with
        # the bases it measures
        ip = IndirectParams(noise=noise, sampling="adaptive", min_paths=min_paths, max_paths=max_paths, bounces=bounces,
                            round_paths=round_paths, seed=seed, area_light_samples=4, caustics="paths")
        ind = trace_indirect_points(rr, fp.p, fp.g, fp.s, fp.mat, fp.base, ip,
                                    key=sample_key(seed, GROUND_TRUTH_STREAM, frame), brightness=fp.bright)
        fp.out[fp.idx] += ind.radiance
        st = {k: ind.stats[k] for k in st}
    st.update(seconds=time.perf_counter() - t0, direct_seconds=fp.direct_seconds, area_light_samples=area_light_samples,
              indirect_skip="", object_id=fp.direct.object_id, depth=fp.direct.depth)
    return fp.out.reshape(cam.height, cam.width, 3).astype(np.float32), fp.direct.object_id >= 0, st
