"""Slow, obvious relighting references for tests (stumpy ``tests/naive.py`` style).

``lambert_sphere_images``: an analytic illumination dataset (unit Lambertian sphere seen by an
orthographic camera along -z, no shadows besides attached ones). ``naive_relight``: eq. 1 of
the paper pixel by pixel, with a linear search over every covered triangle and np.linalg.solve.
"""

from __future__ import annotations

import numpy as np

ALBEDO = 0.8


def sphere_points(h: int, half_width: float = 1.2):
    """Surface points (h, h, 3) of the unit sphere under an orthographic camera (NaN off it), mask."""
    ys, xs = np.mgrid[0:h, 0:h]
    x = (xs + 0.5) / h * 2 * half_width - half_width
    y = half_width - (ys + 0.5) / h * 2 * half_width
    r2 = x * x + y * y
    mask = r2 < 0.98  # keep away from the silhouette, where the normal is ill-defined
    z = np.sqrt(np.clip(1 - r2, 0, None))
    pts = np.stack([x, y, z], axis=-1)
    pts[~mask] = np.nan
    return pts, mask


def lat_long_lights(spacing_deg: float, radius: float, lat_min: float = -90.0, lat_max: float = 90.0,
                    lon_min: float = 0.0, lon_max: float = 360.0):
    """Lights on a latitude/longitude grid (latitude about +y), roughly uniform spacing."""
    out = []
    for lat in np.arange(lat_min, lat_max + 1e-9, spacing_deg):
        if abs(abs(lat) - 90) < 1e-9:
            out.append([0.0, np.sign(lat), 0.0])
            continue
        c = np.cos(np.radians(lat))
        full = abs(lon_max - lon_min - 360) < 1e-9
        n = max(1, int(round((lon_max - lon_min) * c / spacing_deg)))
        lons = lon_min + np.arange(n) * (lon_max - lon_min) / n if full else np.linspace(lon_min, lon_max, n + 1)
        for lon in lons:
            out.append([c * np.cos(np.radians(lon)), np.sin(np.radians(lat)), c * np.sin(np.radians(lon))])
    return np.asarray(out) * radius


def lambert_point(pts, mask, light, intensity=1.0):
    """(h, w, 3) float32 image of the Lambertian unit sphere (normal = point) under a point light."""
    p = np.where(mask[..., None], pts, 0.0)
    d = np.asarray(light, float) - p
    d2 = np.sum(d * d, axis=-1)
    cos = np.clip(np.sum(p * d, axis=-1) / np.sqrt(d2), 0, None)
    v = ALBEDO / np.pi * cos / d2
    return (np.where(mask, v, 0.0)[..., None] * np.broadcast_to(intensity, (3,))).astype(np.float32)


def lambert_directional(pts, mask, toward, irradiance=1.0):
    p = np.where(mask[..., None], pts, 0.0)
    t = np.asarray(toward, float) / np.linalg.norm(toward)
    cos = np.clip(p @ t, 0, None)
    return (np.where(mask, ALBEDO / np.pi * cos, 0.0)[..., None] * np.broadcast_to(irradiance, (3,))).astype(
        np.float32)


def _locate_naive(baked, s):
    for t, tri in enumerate(baked.triangles):
        m = baked.directions[tri].T  # columns = vertices
        a = np.linalg.solve(m, s)
        if a.sum() > 0 and np.all(a >= -1e-12 * a.sum()):
            a = np.clip(a, 0, None)
            return t, a / a.sum()
    return -1, None


def naive_relight(baked, point_lights=(), toward_lights=(), rows=None):
    """Eq. 1 per pixel. point_lights: [(position, intensity rgb)], toward_lights: [(dir toward light,
    irradiance rgb)]. Returns (h, w, 3) float64 and the outside mask. ``rows``: only these store rows
    (the other pixels stay 0 / not outside), to keep larger datasets affordable."""
    h, w = baked.shape
    out = np.zeros((h * w, 3))
    outside = np.zeros(h * w, bool)
    store = np.stack([baked.light_values(k) for k in range(len(baked.light_positions))], axis=1).astype(np.float64)
    c, r = baked.sphere_center, baked.sphere_radius
    lights = [(np.asarray(p, float), np.asarray(i, float), False) for p, i in point_lights]
    lights += [(np.asarray(d, float) / np.linalg.norm(d), np.asarray(e, float), True) for d, e in toward_lights]
    for row in (range(len(baked.pixel_index)) if rows is None else rows):
        pix = baked.pixel_index[row]
        p = baked.points[row]
        for pos, inten, directional in lights:
            if directional:
                u, g = pos, inten
            else:
                u = (pos - p) / np.linalg.norm(pos - p)
                g = inten / np.sum((pos - p) ** 2)
            if baked.distant:
                s = u
            else:
                o = p - c
                b = o @ u
                t = -b + np.sqrt(b * b - (o @ o - r * r))
                s = o + t * u
            tri, wts = _locate_naive(baked, s)
            if tri < 0:
                outside[pix] = True
                continue
            for q in range(3):
                k = baked.triangles[tri, q]
                dist2 = 1.0 if baked.distant else np.sum((baked.light_positions[k] - p) ** 2)
                out[pix] += wts[q] * dist2 / baked.intensities[k] * store[row, k] * g
    return out.reshape(h, w, 3), outside.reshape(h, w)
