"""A converged walkthrough frame: what a frame reconstructed from the bases is measured against.

The image model is the one the image-based methods render, one point sample at each pixel centre
(the reference renderer with ``pixel_jitter=False``, 1 spp): direct light with
:data:`AREA_LIGHT_SAMPLES` area-light samples per pixel, plus indirect light traced per visible
surface point with the reference renderer's own indirect paths
(``engine.newviews.indirect.trace_indirect_points``) until each pixel's relative standard error
reaches a target. Used by the walkthrough calibration (``workers/jobs/calibrate_walkthrough.py``)
and the accuracy benchmark (``bench/walkthrough_accuracy.py``).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from engine.camera import camera_rays, pixel_centers
from engine.metrics import REC709_WEIGHTS
from engine.newviews.indirect import IndirectParams, trace_indirect_points
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.sampler import sample_key
from engine.scene import CameraParams
from engine.walkthrough.range_images import surface_points

__all__ = ["AREA_LIGHT_SAMPLES", "GROUND_TRUTH_STREAM", "converged_frame"]

AREA_LIGHT_SAMPLES = 1024
"""Area-light samples per pixel of the direct light (a 32 x 32 jittered grid)."""
GROUND_TRUTH_STREAM = 6
"""Sampler stream of the indirect paths: ``sample_key(seed, 6, frame)`` (the bases' own use 5)."""
MIN_PATHS = 256
MAX_PATHS = 65536


def converged_frame(rr: ReferenceRenderer, cam: CameraParams, frame: int, seed: int, noise: float,
                    bounces: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """The converged frame seen by ``cam`` in the scene of ``rr`` (already at the frame's time):
    radiance (h, w, 3) float32, the mask of the pixels it covers, the error region (covered and
    not on or next to an emitter: ``ReferenceRenderer.error_region``, where the project's errors
    are measured; the quality contracts' frame error is), and stats (the indirect pass's
    relative standard error median / p95 / max, the fraction of pixels that met ``noise``, paths
    per pixel, seconds). ``noise``: target relative standard error of each pixel's luminance;
    ``bounces``: diffuse vertices of the indirect paths (the bake's ``indirect_bounces``)."""
    t0 = time.perf_counter()
    direct = rr.render(cam, ReferenceParams(spp=1, pixel_jitter=False, area_light_samples=AREA_LIGHT_SAMPLES,
                                            indirect_samples=0, seed=seed))
    t_direct = time.perf_counter() - t0
    px, py = pixel_centers(cam)
    o, d = camera_rays(cam, px, py)
    idx, p, g, s, mat = surface_points(rr, o, d)
    base = direct.radiance.reshape(-1, 3)[idx].astype(np.float64)
    receives = np.any(rr.scene.materials.kd[mat] > 0.0, axis=1)
    bright = float((base[receives] @ np.asarray(REC709_WEIGHTS)).mean()) if receives.any() else 0.0
    ip = IndirectParams(noise=noise, min_paths=MIN_PATHS, max_paths=MAX_PATHS, bounces=bounces, round_paths=16,
                        seed=seed, area_light_samples=4)
    ind = trace_indirect_points(rr, p, g, s, mat, base, ip, key=sample_key(seed, GROUND_TRUTH_STREAM, frame),
                                brightness=bright)
    out = direct.radiance.reshape(-1, 3).astype(np.float64)
    out[idx] += ind.radiance
    st = {k: ind.stats[k] for k in ("rel_stderr_median", "rel_stderr_p95", "rel_stderr_max", "met_target",
                                    "paths_mean", "paths_max")}
    st.update(seconds=time.perf_counter() - t0, direct_seconds=t_direct)
    region = rr.error_region(cam, direct.object_id, direct.depth, ReferenceParams().max_depth)
    return out.reshape(cam.height, cam.width, 3).astype(np.float32), direct.object_id >= 0, region, st
