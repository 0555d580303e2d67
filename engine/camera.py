"""Camera rays. Pixel (0, 0) is the top-left; pixel centres are at (x + 0.5, y + 0.5)."""

from __future__ import annotations

import numpy as np

from engine.scene import CameraParams


def camera_rays(cam: CameraParams, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays through continuous pixel coordinates.

    px, py: (n,) float64 in [0, width] x [0, height]. Returns origins (n, 3) and unit
    directions (n, 3), float64. Perspective rays start at the eye; orthographic rays
    start on the image plane through the eye and all travel along the view direction.
    """
    right, up, fwd = cam.basis()
    sx = 2.0 * np.asarray(px, dtype=np.float64) / cam.width - 1.0
    sy = 1.0 - 2.0 * np.asarray(py, dtype=np.float64) / cam.height
    aspect = cam.width / cam.height
    eye = np.asarray(cam.eye, dtype=np.float64)
    n = sx.shape[0]
    if cam.kind == "perspective":
        th = np.tan(np.radians(cam.fov_y_deg) * 0.5)
        d = fwd[None, :] + (sx * th * aspect)[:, None] * right[None, :] + (sy * th)[:, None] * up[None, :]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(eye, (n, 3)).copy()
    else:
        hh = 0.5 * cam.ortho_height
        o = eye[None, :] + (sx * hh * aspect)[:, None] * right[None, :] + (sy * hh)[:, None] * up[None, :]
        d = np.broadcast_to(fwd, (n, 3)).copy()
    return np.ascontiguousarray(o), np.ascontiguousarray(d)


def pixel_centers(cam: CameraParams) -> tuple[np.ndarray, np.ndarray]:
    """(px, py) of every pixel centre in row-major order, each (h*w,) float64."""
    ys, xs = np.mgrid[0:cam.height, 0:cam.width]
    return xs.ravel() + 0.5, ys.ravel() + 0.5
