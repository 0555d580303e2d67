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
- :func:`path_traced_frame`: the same estimate at a looser target, a fixed count of paths and
  area-light samples per pixel sized for it (``engine.walkthrough.path_settings``): a walkthrough
  frame that needs no bake (``WalkthroughRequest.path_traced``), converging to the same image as
  the noise target falls.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from engine.camera import camera_rays, pixel_centers
from engine.metrics import REC709_WEIGHTS
from engine.newviews.effects import analyze
from engine.newviews.indirect import IndirectParams, trace_indirect_points
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.sampler import sample_key
from engine.scene import CameraParams
from engine.walkthrough.path_settings import CONVERGED_AREA_LIGHT_SAMPLES, path_traced_settings
from engine.walkthrough.range_images import surface_points

__all__ = ["AREA_LIGHT_SAMPLES", "GROUND_TRUTH_STREAM", "converged_frame", "path_traced_frame"]

AREA_LIGHT_SAMPLES = CONVERGED_AREA_LIGHT_SAMPLES
"""Area-light samples per pixel of the converged frame's direct light (a 32 x 32 jittered grid)."""
GROUND_TRUTH_STREAM = 6
"""Sampler stream of the indirect paths: ``sample_key(seed, 6, frame)`` (the bases' own use 5)."""
MIN_PATHS = 256
MAX_PATHS = 65536


def path_traced_frame(rr: ReferenceRenderer, cam: CameraParams, frame: int, seed: int, noise: float,
                      bounces: int, indirect_skip: str | None = None) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """A walkthrough frame path-traced for an LRMS of about ``noise`` (the module docstring,
    ``engine.walkthrough.path_settings.path_traced_settings``): radiance (h, w, 3) float32, the mask
    of the pixels it covers, and the stats of :func:`converged_frame`. Deterministic in ``seed``;
    ``frame`` decorrelates the frames.

    ``indirect_skip``: why no surface of the scene can receive indirect light
    (``engine.newviews.effects.analyze``; None: analysed here, "" forces the indirect paths): such a
    frame traces none, and its stats say why (``indirect_skip``)."""
    ps = path_traced_settings(noise)
    skip = analyze(rr.scene).indirect_skip if indirect_skip is None else indirect_skip
    return _traced(rr, cam, frame, seed, noise, bounces, ps.area_light_samples, ps.paths, ps.paths, ps.round_paths,
                   skip)


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


def _traced(rr: ReferenceRenderer, cam: CameraParams, frame: int, seed: int, noise: float, bounces: int,
            area_light_samples: int, min_paths: int, max_paths: int, round_paths: int, indirect_skip: str = ""
            ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    t0 = time.perf_counter()
    direct = rr.render(cam, ReferenceParams(spp=1, pixel_jitter=False, area_light_samples=area_light_samples,
                                            indirect_samples=0, seed=seed))
    t_direct = time.perf_counter() - t0
    px, py = pixel_centers(cam)
    o, d = camera_rays(cam, px, py)
    idx, p, g, s, mat = surface_points(rr, o, d)
    base = direct.radiance.reshape(-1, 3)[idx].astype(np.float64)
    out = direct.radiance.reshape(-1, 3).astype(np.float64)
    st: dict[str, Any] = {"rel_stderr_median": 0.0, "rel_stderr_p95": 0.0, "rel_stderr_max": 0.0, "met_target": 1.0,
                          "paths_mean": 0.0, "paths_max": 0}
    if len(idx) and not indirect_skip:
        receives = np.any(rr.scene.materials.kd[mat] > 0.0, axis=1)
        bright = float((base[receives] @ np.asarray(REC709_WEIGHTS)).mean()) if receives.any() else 0.0
        # paths alone, caustics included: a ground truth must not share the photon map's blur with
        # the bases it measures
        ip = IndirectParams(noise=noise, sampling="adaptive", min_paths=min_paths, max_paths=max_paths, bounces=bounces,
                            round_paths=round_paths, seed=seed, area_light_samples=4, caustics="paths")
        ind = trace_indirect_points(rr, p, g, s, mat, base, ip, key=sample_key(seed, GROUND_TRUTH_STREAM, frame),
                                    brightness=bright)
        out[idx] += ind.radiance
        st = {k: ind.stats[k] for k in st}
    st.update(seconds=time.perf_counter() - t0, direct_seconds=t_direct, area_light_samples=area_light_samples,
              indirect_skip=indirect_skip, object_id=direct.object_id, depth=direct.depth)
    return out.reshape(cam.height, cam.width, 3).astype(np.float32), direct.object_id >= 0, st
