"""The illumination dataset: what the relighting starts from.

Owns :class:`IlluminationDataset` (K images of one fixed view, image k lit only by light k, plus the
surface point of every pixel; validated on construction) and :func:`points_from_depth` (surface points
from a depth map and a camera). No numba: building a dataset compiles nothing. The bake
(``engine.relighting.bake``) turns a dataset into what the relight kernel reads.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from engine.errors import InvalidInputError
from engine.scene import CameraParams


def checked_array(name: str, a, dtype, ndim: int | None = None) -> np.ndarray:
    """``a`` as a numpy array of ``dtype`` (and ``ndim`` dimensions), or InvalidInputError naming it."""
    try:
        arr = np.asarray(a, dtype=dtype)
    except (TypeError, ValueError) as e:
        raise InvalidInputError(f"{name}: not a numeric array ({e})") from None
    if ndim is not None and arr.ndim != ndim:
        raise InvalidInputError(f"{name}: expected {ndim} dimensions, got shape {arr.shape}")
    return arr


@dataclass(frozen=True)
class IlluminationDataset:
    """K images of one fixed view, image k lit only by light k, plus the surface points.

    images: (K, h, w, 3) float32 linear radiance.
    light_positions: (K, 3) float64; world positions of isotropic point lights, or, when
        ``distant`` is True, directions *toward* distant lights (normalised on entry).
    intensities: (K, 3) float64 > 0; W/sr for point lights, irradiance for distant lights.
    points: (h, w, 3) float64 surface point of every pixel, in the lights' frame.
    mask: (h, w) bool or None; pixels without a surface point (background) are False.
        Points of masked-out pixels are ignored (they may be NaN).
    distant: one flag for the whole dataset (a photometric-stereo rig has only distant
        lights, a light stage only near ones; mixed datasets are not supported).
    sphere_center: (3,) or None; the centre of the sphere the lights were placed on, when
        known (a light stage, a generated dataset); the bake's default centre.
    meta: JSON-serialisable facts about where the dataset came from (generation placement,
        render parameters, timings); not used by the bake.
    """

    images: np.ndarray
    light_positions: np.ndarray
    intensities: np.ndarray
    points: np.ndarray
    mask: np.ndarray | None = None
    distant: bool = False
    sphere_center: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if isinstance(self.images, (list, tuple)):
            shapes = [np.shape(a) for a in self.images]
            for i, sh in enumerate(shapes):
                if sh != shapes[0]:
                    raise InvalidInputError(f"images[{i}]: shape {sh} differs from images[0] {shapes[0]} "
                                            "(all images must have the same size)")
        imgs = checked_array("images", self.images, np.float32, 4)
        if imgs.shape[-1] != 3:
            raise InvalidInputError(f"images: expected (K, h, w, 3), got shape {imgs.shape}")
        k, h, w = imgs.shape[:3]
        if k < 3:
            raise InvalidInputError(f"images: at least 3 lit images are needed, got {k}")
        if h < 1 or w < 1:
            raise InvalidInputError(f"images: empty image size {h}x{w}")
        if not np.all(np.isfinite(imgs)):
            bad = np.unique(np.nonzero(~np.isfinite(imgs))[0])
            raise InvalidInputError(f"images: non-finite values in image(s) {bad[:10].tolist()}")
        pos = checked_array("light_positions", self.light_positions, np.float64, 2)
        if pos.shape != (k, 3):
            raise InvalidInputError(f"light_positions: light count {pos.shape[0] if pos.ndim else 0} "
                                    f"does not match image count {k} (shape {pos.shape}, expected ({k}, 3))")
        if not np.all(np.isfinite(pos)):
            bad = np.nonzero(~np.all(np.isfinite(pos), axis=1))[0]
            raise InvalidInputError(f"light_positions: NaN/Inf in light(s) {bad[:10].tolist()}")
        if self.distant:
            n = np.linalg.norm(pos, axis=1)
            if np.any(n == 0):
                raise InvalidInputError(f"light_positions: zero direction for distant light(s) "
                                        f"{np.nonzero(n == 0)[0][:10].tolist()}")
            pos = pos / n[:, None]
        inten = checked_array("intensities", self.intensities, np.float64)
        if inten.ndim == 1 and inten.shape == (k,):
            inten = np.repeat(inten[:, None], 3, axis=1)
        if inten.shape != (k, 3):
            raise InvalidInputError(f"intensities: expected ({k}, 3) or ({k},), got shape {inten.shape}")
        if not np.all(np.isfinite(inten)) or np.any(inten <= 0):
            raise InvalidInputError("intensities: must be finite and > 0 in every channel")
        pts = checked_array("points", self.points, np.float64, 3)
        if pts.shape != (h, w, 3):
            raise InvalidInputError(f"points: surface points of shape {pts.shape} do not match the "
                                    f"image size {h}x{w} (expected ({h}, {w}, 3))")
        if self.mask is None:
            m = np.ones((h, w), dtype=bool)
        else:
            m = np.asarray(self.mask)
            if m.shape != (h, w):
                raise InvalidInputError(f"mask: shape {m.shape} does not match the image size {h}x{w}")
            m = m.astype(bool)
        finite = np.all(np.isfinite(pts), axis=2)
        if np.any(m & ~finite):
            raise InvalidInputError(f"points: {int(np.sum(m & ~finite))} masked-in pixel(s) have NaN/Inf "
                                    "surface points (mask them out)")
        if not np.any(m):
            raise InvalidInputError("mask: no pixel has a surface point")
        pts = np.where(m[:, :, None], pts, 0.0)
        if self.sphere_center is not None:
            sc = checked_array("sphere_center", self.sphere_center, np.float64, 1)
            if sc.shape != (3,) or not np.all(np.isfinite(sc)):
                raise InvalidInputError("sphere_center: expected 3 finite numbers")
            object.__setattr__(self, "sphere_center", sc)
        object.__setattr__(self, "images", np.ascontiguousarray(imgs))
        object.__setattr__(self, "light_positions", np.ascontiguousarray(pos))
        object.__setattr__(self, "intensities", np.ascontiguousarray(inten))
        object.__setattr__(self, "points", np.ascontiguousarray(pts))
        object.__setattr__(self, "mask", m)
        object.__setattr__(self, "distant", bool(self.distant))

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.images.shape[1]), int(self.images.shape[2])


def points_from_depth(depth, camera: CameraParams | None = None, *, depth_kind: str = "z",
                      intrinsics=None, world_from_camera=None) -> tuple[np.ndarray, np.ndarray]:
    """Surface points (h, w, 3) float64 and validity (h, w) bool from a depth map (h, w).

    Either ``camera`` (this project's :class:`CameraParams`, perspective or orthographic;
    pixel centres as in ``engine.camera``) or ``intrinsics`` = 3x3 pinhole matrix K in the
    OpenCV camera frame (x right, y down, z forward) with optional ``world_from_camera``
    (4, 4). ``depth_kind``: ``"z"`` = distance along the optical axis, ``"distance"`` =
    distance along the pixel's ray. For an orthographic camera both are the same. Pixels
    whose depth is NaN, Inf or <= 0 are invalid (their point is NaN).
    """
    from engine.camera import camera_rays, pixel_centers

    d = checked_array("depth", depth, np.float64, 2)
    h, w = d.shape
    if depth_kind not in ("z", "distance"):
        raise InvalidInputError(f"depth_kind must be 'z' or 'distance', got {depth_kind!r}")
    if (camera is None) == (intrinsics is None):
        raise InvalidInputError("points_from_depth: give exactly one of camera or intrinsics")
    valid = np.isfinite(d) & (d > 0)
    dd = np.where(valid, d, np.nan)
    if camera is not None:
        if (camera.height, camera.width) != (h, w):
            raise InvalidInputError(f"depth: depth map is {h}x{w} but the camera is "
                                    f"{camera.height}x{camera.width}")
        px, py = pixel_centers(camera)
        o, dirs = camera_rays(camera, px, py)
        if camera.kind == "perspective" and depth_kind == "z":
            fwd = camera.basis()[2]
            t = dd.ravel() / (dirs @ fwd)
        else:
            t = dd.ravel()
        pts = o + dirs * t[:, None]
        return pts.reshape(h, w, 3), valid
    kmat = checked_array("intrinsics", intrinsics, np.float64, 2)
    if kmat.shape != (3, 3) or kmat[0, 0] == 0 or kmat[1, 1] == 0:
        raise InvalidInputError("intrinsics: expected a 3x3 pinhole matrix with fx, fy != 0")
    ys, xs = np.mgrid[0:h, 0:w]
    x = (xs + 0.5 - kmat[0, 2]) / kmat[0, 0]
    y = (ys + 0.5 - kmat[1, 2]) / kmat[1, 1]
    rays = np.stack([x, y, np.ones_like(x)], axis=-1)
    if depth_kind == "distance":
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    pts = rays * dd[:, :, None]
    if world_from_camera is not None:
        m = checked_array("world_from_camera", world_from_camera, np.float64, 2)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise InvalidInputError("world_from_camera: expected a finite (4, 4) matrix")
        pts = pts @ m[:3, :3].T + m[:3, 3]
    return pts, valid

