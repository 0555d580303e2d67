"""The pixels an image's error is measured on: covered pixels that neither show an emitter nor
touch one.

Every error this project quotes (a quality contract's LRMS, a calibration's fit, a benchmark's
comparison with a converged image or with Mitsuba) leaves out the pixels whose 3 x 3
neighbourhood shows an emitter: an emissive surface along the pixel-centre ray, or a rect light's
emitting side anywhere in the pixel's square (``sees_rect_light``):

- an emitter is 50-100x brighter than the room it lights, so its pixels would set the LRMS
  denominator (the image's mean luminance; on a Cornell box view the luminaire's 2 % of the
  pixels nearly triple it) and so make any relative error look smaller;
- the pixels on its outline hold a coverage fraction of that radiance, whose Monte Carlo noise
  (the antialiasing of a 100x step) exceeds 1 % LRMS at any affordable sample count, so every
  method's error would be that outline.

The emitter's radiance is a constant every renderer copies from the scene; what it lights is what
the comparison is about. The same holds for an emitter's image in a mirror (a luminaire seen in a
mirror sphere): finding those needs rays through the mirrors, so ``ReferenceRenderer.error_region``
(engine/reference.py) adds them to this module's region; it is the region every error is measured
on, and this module's functions are its ray-free part. The progressive reference
(engine/progressive.py) estimates its error over that region, so an adaptive render told
``max_error`` meets it on the metric the contracts and the benchmarks measure, and spends its
samples where that metric needs them, not on the luminaire's outline.

Pure NumPy and SciPy (no numba): the API process may import it.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_dilation, maximum_filter

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
    """(h, w) bool: the pixel shows some of a rect light's emitting side (either side if the light is
    two-sided) in front of the surfaces around it (``depth``, the pixel-centre ray's distance to its
    first surface; 0 = none): its centre ray meets the light before its surface, or its square
    overlaps the light's projection where the light's plane lies in front of the farthest first
    surface of its 3 x 3 neighbourhood. The second test catches a corner or a sliver of the
    luminaire seen at a grazing angle that covers part of a pixel whose centre, and whose
    neighbours' centres, miss it: such a pixel holds a fraction of a radiance ~250x the image's
    mean, which no renderer resolves at an affordable sample count (two such pixels made one view's
    LRMS 7.7 % instead of 2.3 %)."""
    lt = scene.lights
    shape = depth.shape
    seen = np.zeros(depth.size, dtype=bool)
    if lt.n_rect == 0:
        return seen.reshape(shape)
    o, d = camera_rays(camera, *pixel_centers(camera))
    flat = depth.reshape(-1)
    t_surf = np.where(flat > 0, flat, np.inf)
    t_near = maximum_filter(t_surf.reshape(shape), size=3, mode="nearest").reshape(-1)
    right, up, fwd = camera.basis()
    eye = np.asarray(camera.eye, dtype=np.float64)
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
        faces = (eye - c) @ n > 0 if camera.kind == "perspective" else -fwd @ n > 0
        if not (faces or lt.rect_two_sided[q]):
            continue
        corners = np.array([c, c + u, c + u + v, c + v], dtype=np.float64)
        over = _overlapped_pixels(camera, corners, right, up, fwd, eye).reshape(-1)
        seen |= over & (t > 0) & (t <= t_near * (1 + 1e-5))
    return seen.reshape(shape)


def _overlapped_pixels(camera: CameraParams, corners: np.ndarray, right: np.ndarray, up: np.ndarray,
                       fwd: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """(h, w) bool: the pixels whose square overlaps (by more than a millionth of a pixel) the image
    of the convex planar polygon ``corners`` (k, 3), clipped to the space in front of the camera."""
    w, h = camera.width, camera.height
    out = np.zeros((h, w), dtype=bool)
    rel = corners - eye
    xc, yc, zc = rel @ right, rel @ up, rel @ fwd
    aspect = w / h
    if camera.kind == "perspective":
        poly = _clip_in_front(np.stack([xc, yc, zc], axis=1), 1e-9 * max(float(np.abs(rel).max()), 1e-300))
        if len(poly) < 3:
            return out
        th = np.tan(np.radians(camera.fov_y_deg) * 0.5)
        sx, sy = poly[:, 0] / (poly[:, 2] * th * aspect), poly[:, 1] / (poly[:, 2] * th)
    else:
        hh = 0.5 * camera.ortho_height
        sx, sy = xc / (hh * aspect), yc / hh
    px, py = (sx + 1.0) * 0.5 * w, (1.0 - sy) * 0.5 * h
    x0, x1 = max(int(np.floor(px.min())), 0), min(int(np.ceil(px.max())), w)
    y0, y1 = max(int(np.floor(py.min())), 0), min(int(np.ceil(py.max())), h)
    if x0 >= x1 or y0 >= y1:
        return out
    gy, gx = np.mgrid[y0:y1, x0:x1].astype(np.float64)
    # separating axis test of each pixel square against the polygon: the bounding box (done above)
    # and each edge's outward normal
    sign = 1.0 if np.sum(px * np.roll(py, -1) - np.roll(px, -1) * py) > 0 else -1.0
    hit = np.ones(gx.shape, dtype=bool)
    eps = 1e-6
    for i in range(len(px)):
        ex, ey = px[(i + 1) % len(px)] - px[i], py[(i + 1) % len(px)] - py[i]
        nx, ny = sign * ey, -sign * ex  # outward normal
        norm = float(np.hypot(nx, ny))
        if norm == 0.0:
            continue
        nx, ny = nx / norm, ny / norm
        # the square's corner deepest inside this edge: min over corners of the outward distance
        inside = np.minimum(gx * nx, (gx + 1) * nx) + np.minimum(gy * ny, (gy + 1) * ny) - (px[i] * nx + py[i] * ny)
        hit &= inside < -eps
    sub = out[y0:y1, x0:x1]
    sub |= hit & (gx + 1 > px.min() + eps) & (gx < px.max() - eps) & (gy + 1 > py.min() + eps) & (gy < py.max() - eps)
    return out


def _clip_in_front(poly: np.ndarray, z_min: float) -> np.ndarray:
    """The polygon (k, 3) in camera space (x right, y up, z forward) clipped to z >= z_min
    (Sutherland-Hodgman against one plane)."""
    out = []
    k = len(poly)
    for i in range(k):
        a, b = poly[i], poly[(i + 1) % k]
        ina, inb = a[2] >= z_min, b[2] >= z_min
        if ina:
            out.append(a)
        if ina != inb:
            f = (z_min - a[2]) / (b[2] - a[2])
            out.append(a + f * (b - a))
    return np.array(out).reshape(-1, 3)


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
