"""The pixels an image's error is measured on: covered pixels that neither show an emitter nor
touch one.

Every error this project quotes (a quality contract's LRMS, a calibration's fit, a benchmark's
comparison with a converged image or with Mitsuba) leaves out the pixels whose 3 x 3
neighbourhood shows an emitter, an emissive surface or a rect light's emitting side, seen along
the pixel-centre ray:

- an emitter is 50-100x brighter than the room it lights, so its pixels would set the LRMS
  denominator (the image's mean luminance; on a Cornell box view the luminaire's 2 % of the
  pixels nearly triple it) and so make any relative error look smaller;
- the pixels on its outline hold a coverage fraction of that radiance, whose Monte Carlo noise
  (the antialiasing of a 100x step) exceeds 1 % LRMS at any affordable sample count, so every
  method's error would be that outline.

The emitter's radiance is a constant every renderer copies from the scene; what it lights is what
the comparison is about. The progressive reference (engine/progressive.py) estimates its error
over the same region, so an adaptive render told ``max_error`` meets it on the metric the
contracts and the benchmarks measure, and spends its samples where that metric needs them, not on
the luminaire's outline.

Pure NumPy and SciPy (no numba): the API process may import it.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_dilation

from engine.camera import camera_rays, pixel_centers
from engine.scene import CameraParams, RuntimeScene

__all__ = ["emissive_objects", "emitter_pixels", "error_region", "region_around", "sees_rect_light"]


def emissive_objects(scene: RuntimeScene) -> np.ndarray:
    """(n_objects,) bool: the object has a triangle whose material emits."""
    emissive_mat = np.any(scene.materials.emission > 0, axis=1)
    out = np.zeros(len(scene.object_names), dtype=bool)
    if scene.tri_object.size:
        hit = emissive_mat[scene.tri_material]
        out[np.unique(scene.tri_object[hit])] = True
    return out


def sees_rect_light(scene: RuntimeScene, camera: CameraParams, depth: np.ndarray) -> np.ndarray:
    """(h, w) bool: the pixel-centre ray meets a rect light's emitting side (either side if the
    light is two-sided) before its first surface (``depth``, the distance along that ray; 0 = none)."""
    lt = scene.lights
    shape = depth.shape
    seen = np.zeros(depth.size, dtype=bool)
    if lt.n_rect == 0:
        return seen.reshape(shape)
    o, d = camera_rays(camera, *pixel_centers(camera))
    flat = depth.reshape(-1)
    t_surf = np.where(flat > 0, flat, np.inf)
    for q in range(lt.n_rect):
        u, v, c = lt.rect_edge_u[q], lt.rect_edge_v[q], lt.rect_corner[q]
        n = np.cross(u, v)
        area = float(np.linalg.norm(n))
        n = n / area
        den = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((c - o) @ n) / den
            p = o + t[:, None] * d - c
        a = np.cross(p, v) @ n / area
        b = np.cross(u, p) @ n / area
        front = (den != 0) if lt.rect_two_sided[q] else (den < 0)
        seen |= front & (t > 0) & (t <= t_surf * (1 + 1e-5)) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
    return seen.reshape(shape)


def emitter_pixels(scene: RuntimeScene, camera: CameraParams, object_id: np.ndarray,
                   depth: np.ndarray) -> np.ndarray:
    """(h, w) bool: the pixel-centre ray shows an emissive surface (``object_id``, -1 = nothing)
    or a rect light (:func:`sees_rect_light`)."""
    covered = object_id >= 0
    shows = covered & emissive_objects(scene)[np.clip(object_id, 0, None)]
    return shows | sees_rect_light(scene, camera, depth)


def region_around(covered: np.ndarray, emitters: np.ndarray) -> np.ndarray:
    """The covered pixels whose 3 x 3 neighbourhood holds none of ``emitters`` (both (h, w) bool)."""
    near = binary_dilation(emitters, np.ones((3, 3), dtype=bool))
    region: np.ndarray = covered & ~near
    return region


def error_region(scene: RuntimeScene, camera: CameraParams, object_id: np.ndarray,
                 depth: np.ndarray) -> np.ndarray:
    """(h, w) bool: the pixels an error of this view is measured on (the module docstring): covered
    (``object_id`` >= 0) and not next to an emitter. ``object_id`` and ``depth`` are the
    pixel-centre ray's, as ``engine.reference.RenderOutput`` holds them."""
    return region_around(object_id >= 0, emitter_pixels(scene, camera, object_id, depth))
