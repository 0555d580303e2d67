"""Illumination datasets generated from a scene (docs/relighting.md).

The scene is rendered by the reference renderer (``engine.reference``) once per point light,
the lights placed over a chosen part of a sphere around the visible surface. The result is an
:class:`engine.relighting.dataset.IlluminationDataset` in exactly the upload format (K images, one light
position and intensity each, the surface points from the renderer's depth AOV, the mask of
pixels that hit geometry), plus ground-truth renders under any other lights for testing.

What is replaced in the scene for a dataset image (docs/relighting.md "Generated datasets"):
the scene's own lights are dropped and the one dataset light is the only light; the ambient
term, the background colour and material emission are set to 0, because each of them would
add the same constant to every image (image k must be lit *only* by light k, so that sums of
images are sums of lights). Geometry, materials (other than emission) and the camera are
unchanged; reflections, glossy lobes and indirect paths (``ReferenceParams``) stay on and are
linear in the light, so they belong in the dataset.

Public: :class:`LightPlacement`, :func:`place_lights`, :func:`generate_dataset`,
:func:`render_ground_truth`, :func:`scene_with_lights`, :func:`scene_without_objects`,
:func:`surface_aovs`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from engine.camera import camera_rays, pixel_centers
from engine.errors import InvalidInputError
from engine.raycast import RayCaster, make_caster
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.relighting.dataset import IlluminationDataset, points_from_depth
from engine.relighting.lights import PointLight, light_table
from engine.scene import CameraParams, RuntimeScene

REGIONS = ("sphere", "hemisphere", "upper_front_quarter")
LAYOUTS = ("grid", "geodesic")
SPACING_RANGE = (0.5, 90.0)  # degrees
MAX_LIGHTS = 200_000  # a 0.5 deg full-sphere grid has ~165k lights
_ICO_EDGE_DEG = 63.43494882292201  # angle between neighbouring icosahedron vertices

Progress = Callable[[float, str], None]


# ============================================================================ placement


def _vec(name: str, v, *, unit: bool = False) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name}: expected 3 finite numbers, got {v!r}") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InvalidInputError(f"{name}: expected 3 finite numbers, got {v!r}")
    if unit:
        n = float(np.linalg.norm(a))
        if n == 0:
            raise InvalidInputError(f"{name}: must be a non-zero vector")
        a = a / n
    return a


@dataclass(frozen=True)
class LightPlacement:
    """Where the dataset's point lights go: a part of a sphere, a layout, a density.

    region: ``"sphere"`` (all directions), ``"hemisphere"`` (elevation >= 0 about ``up``) or
        ``"upper_front_quarter"`` (the paper's: elevation >= 0 and azimuth within +-90 deg of
        ``front``, the side facing the camera).
    layout: ``"grid"`` = regular grid in degrees: rings of constant elevation every
        ``spacing_deg`` (0, +-s, +-2s, ... and the pole(s)), on each ring lights every
        ~``spacing_deg`` of arc (azimuth step ``spacing / cos(elevation)``, rounded so the ring
        or the half ring closes exactly; azimuth 0 = ``front``). ``"geodesic"`` = the vertices of
        a frequency-f subdivided icosahedron (f = round(63.4 deg / spacing), one vertex at the
        zenith, one toward ``front``), near-uniform; for a partial region the geodesic points
        within spacing/2 of the region's boundary are replaced by lights every ``spacing_deg``
        along the boundary, so the region is covered up to its edge.
    spacing_deg: neighbour spacing in degrees, in [0.5, 90].
    center: sphere centre (3,); None = the centroid of the visible surface points.
    radius: sphere radius; None = 1.5 x the distance of the farthest visible surface point
        from the centre (the sphere must enclose every visible surface point).
    intensity: W/sr of every light, a number or RGB; None = radius^2 (irradiance 1 at the
        centre).
    up: the zenith (default +y, the scene convention). front: None = toward the camera (the
        centre-to-eye direction made perpendicular to ``up``).
    """

    region: str = "upper_front_quarter"
    layout: str = "grid"
    spacing_deg: float = 10.0
    center: tuple[float, float, float] | None = None
    radius: float | None = None
    intensity: float | tuple[float, float, float] | None = None
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    front: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.region not in REGIONS:
            raise InvalidInputError(f"placement.region must be one of {list(REGIONS)}, got {self.region!r}")
        if self.layout not in LAYOUTS:
            raise InvalidInputError(f"placement.layout must be one of {list(LAYOUTS)}, got {self.layout!r}")
        sp = self.spacing_deg
        if isinstance(sp, bool) or not isinstance(sp, (int, float)) or not (
                SPACING_RANGE[0] <= float(sp) <= SPACING_RANGE[1]):
            raise InvalidInputError(f"placement.spacing_deg must be a number in [{SPACING_RANGE[0]:g}, "
                                    f"{SPACING_RANGE[1]:g}], got {sp!r}")
        object.__setattr__(self, "spacing_deg", float(sp))
        if self.center is not None:
            object.__setattr__(self, "center", tuple(float(x) for x in _vec("placement.center", self.center)))
        if self.radius is not None:
            r = self.radius
            if isinstance(r, bool) or not isinstance(r, (int, float)) or not (math.isfinite(r) and r > 0):
                raise InvalidInputError(f"placement.radius must be a finite number > 0, got {r!r}")
            object.__setattr__(self, "radius", float(r))
        if self.intensity is not None:
            i = np.asarray(self.intensity, dtype=np.float64) if not isinstance(self.intensity, bool) else None
            if i is None or i.shape not in ((), (3,)) or not np.all(np.isfinite(i)) or np.any(i <= 0):
                raise InvalidInputError("placement.intensity must be a number or 3 numbers, finite and > 0, "
                                        f"got {self.intensity!r}")
            object.__setattr__(self, "intensity", float(i) if i.shape == () else tuple(float(x) for x in i))
        object.__setattr__(self, "up", tuple(float(x) for x in _vec("placement.up", self.up, unit=True)))
        if self.front is not None:
            f = _vec("placement.front", self.front, unit=True)
            if np.linalg.norm(np.cross(f, np.asarray(self.up))) < 1e-6:
                raise InvalidInputError("placement.front must not be parallel to placement.up")
            object.__setattr__(self, "front", tuple(float(x) for x in f))

    @classmethod
    def from_dict(cls, d: dict) -> LightPlacement:
        """From JSON (``{"region": ..., "layout": ..., "spacing_deg": ...}``); unknown keys are errors."""
        if not isinstance(d, dict):
            raise InvalidInputError(f"placement: expected an object, got {type(d).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise InvalidInputError(f"placement: unknown field(s) {unknown}; allowed: {sorted(names)}")
        return cls(**d)

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        for k in ("center", "up", "front", "intensity"):
            if isinstance(out[k], tuple):
                out[k] = list(out[k])
        return out

    def frame(self, front_hint=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(front, up, right) orthonormal; ``front_hint`` (e.g. centre-to-eye) when ``front`` is None."""
        up = np.asarray(self.up)
        f = np.asarray(self.front if self.front is not None else
                       (front_hint if front_hint is not None else (0.0, 0.0, 1.0)), dtype=np.float64)
        f = f - up * float(f @ up)
        if np.linalg.norm(f) < 1e-9:  # camera straight above/below: any horizontal direction
            if self.region == "upper_front_quarter":
                raise InvalidInputError("placement.front: the camera looks along placement.up, so 'front' is "
                                        "undefined; give placement.front")
            f = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
        f = f / np.linalg.norm(f)
        return f, up, np.cross(f, up)

    def directions(self, front_hint=None) -> np.ndarray:
        """Unit light directions (K, 3) from the centre, deterministic order."""
        f, u, r = self.frame(front_hint)
        local = _grid_local(self.region, self.spacing_deg) if self.layout == "grid" else \
            _geodesic_local(self.region, self.spacing_deg)
        # local coordinates: x = front, y = up, z = right
        return np.ascontiguousarray(local[:, :1] * f + local[:, 1:2] * u + local[:, 2:3] * r)

    def light_count(self) -> int:
        """Number of lights this placement makes (to check a request's size before rendering)."""
        return int(self.directions().shape[0])


def _dir(el_deg, az_deg) -> np.ndarray:
    el, az = np.radians(el_deg), np.radians(az_deg)
    return np.stack([np.cos(el) * np.cos(az), np.sin(el) * np.ones_like(az), np.cos(el) * np.sin(az)], axis=-1)


def _ring_count(extent_deg: float, el_deg: float, spacing: float) -> int:
    return max(1, int(round(extent_deg * math.cos(math.radians(el_deg)) / spacing)))


def _grid_local(region: str, spacing: float) -> np.ndarray:
    n_up = int(math.floor(90.0 / spacing + 1e-9))
    els = [spacing * i for i in range(n_up + 1) if spacing * i < 90.0 - 1e-9]
    if region == "sphere":
        els = sorted(set(els) | {-e for e in els})
    out = []
    for el in els:
        if region == "upper_front_quarter":
            n = _ring_count(180.0, el, spacing)
            az = -90.0 + 180.0 * np.arange(n + 1) / n
        else:
            n = _ring_count(360.0, el, spacing)
            az = 360.0 * np.arange(n) / n
        out.append(_dir(el, az))
    out.append(np.array([[0.0, 1.0, 0.0]]))  # zenith
    if region == "sphere":
        out.append(np.array([[0.0, -1.0, 0.0]]))  # nadir
    return np.concatenate(out)


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    """12 vertices (x front, y up, z right; one at the zenith, one ring vertex toward front), 20 faces."""
    e = math.degrees(math.atan(0.5))
    v = [np.array([0.0, 1.0, 0.0])]
    v += list(_dir(e, 72.0 * np.arange(5)))
    v += list(_dir(-e, 36.0 + 72.0 * np.arange(5)))
    v.append(np.array([0.0, -1.0, 0.0]))
    v = np.asarray(v)
    faces = []
    for i in range(5):
        a, b = 1 + i, 1 + (i + 1) % 5
        c, d = 6 + i, 6 + (i + 1) % 5
        faces += [(0, a, b), (a, c, b), (b, c, d), (c, 11, d)]
    return v, np.asarray(faces)


def _geodesic_local(region: str, spacing: float) -> np.ndarray:
    freq = max(1, int(round(_ICO_EDGE_DEG / spacing)))
    v, faces = _icosahedron()
    pts = []
    for fa in faces:
        a, b, c = v[fa[0]], v[fa[1]], v[fa[2]]
        for i in range(freq + 1):
            for j in range(freq + 1 - i):
                k = freq - i - j
                pts.append((i * a + j * b + k * c) / freq)
    p = np.asarray(pts)
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    # shared edge points: keep the first of each (positions agree to rounding)
    from scipy.spatial import cKDTree

    keep = np.ones(len(p), bool)
    for a, b in sorted(cKDTree(p).query_pairs(1e-9)):
        if keep[a]:
            keep[b] = False
    p = p[keep]
    if region == "sphere":
        return p
    half = math.sin(math.radians(0.5 * spacing))
    inside = p[:, 1] >= half  # clear of the horizon by spacing/2
    bnd = []
    if region == "hemisphere":
        n = _ring_count(360.0, 0.0, spacing)
        bnd.append(_dir(0.0, 360.0 * np.arange(n) / n))
    else:
        inside &= p[:, 0] >= half  # clear of the great circle perpendicular to front
        n = _ring_count(180.0, 0.0, spacing)
        bnd.append(_dir(0.0, -90.0 + 180.0 * np.arange(n + 1) / n))  # horizon, front half
        m = max(1, int(round(90.0 / spacing)))
        el = 90.0 * np.arange(1, m + 1) / m  # the two quarter meridians at azimuth +-90 up to the zenith
        bnd.append(_dir(el[:-1], np.full(m - 1, -90.0)))
        bnd.append(_dir(el[:-1], np.full(m - 1, 90.0)))
        bnd.append(np.array([[0.0, 1.0, 0.0]]))
    return np.concatenate([p[inside]] + bnd)


def place_lights(placement: LightPlacement, center, radius: float, front_hint=None) -> np.ndarray:
    """Light positions (K, 3) float64 = ``center + radius * placement.directions(front_hint)``."""
    c = _vec("center", center)
    return c + float(radius) * placement.directions(front_hint)


# ============================================================================ scenes


def _zero_emission(scene: RuntimeScene):
    return dataclasses.replace(scene.materials, emission=np.zeros_like(scene.materials.emission))


def scene_with_lights(scene: RuntimeScene, lights) -> RuntimeScene:
    """The scene lit only by ``lights`` (relighting light specs or their dicts): its own lights,
    ambient, background and emission removed (see the module docstring)."""
    return dataclasses.replace(scene, lights=light_table(lights),
                               ambient=np.zeros(3), background=np.zeros(3), materials=_zero_emission(scene))


def scene_without_objects(scene: RuntimeScene, names: Sequence[str]) -> RuntimeScene:
    """A copy without the named objects (e.g. the background scene for compositing: the same
    scene with the inserted object removed). Object ids of the remaining triangles are kept."""
    names = [names] if isinstance(names, str) else list(names)
    unknown = [n for n in names if n not in scene.object_names]
    if unknown:
        raise InvalidInputError(f"objects {unknown} are not in the scene (objects: {list(scene.object_names)})")
    drop = [scene.object_names.index(n) for n in names]
    keep = ~np.isin(scene.tri_object, drop)
    p = np.ascontiguousarray(scene.tri_p[keep])
    if p.shape[0]:
        lo, hi = p.reshape(-1, 3).min(axis=0), p.reshape(-1, 3).max(axis=0)
        center, extent = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))
    else:
        center, extent = np.zeros(3), 0.0
    return dataclasses.replace(scene, tri_p=p, tri_n=np.ascontiguousarray(scene.tri_n[keep]),
                               tri_ng=np.ascontiguousarray(scene.tri_ng[keep]),
                               tri_material=np.ascontiguousarray(scene.tri_material[keep]),
                               tri_object=np.ascontiguousarray(scene.tri_object[keep]),
                               tri_local32=np.ascontiguousarray((p - center).astype(np.float32)),
                               center=center, extent=extent)


def surface_aovs(scene: RuntimeScene, camera: CameraParams, caster: RayCaster | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(depth (h, w) float32, object_id (h, w) int32) of the pixel-centre rays, exactly the
    reference renderer's depth and object-id AOVs (depth 0 and id -1 where nothing is hit)."""
    caster = caster if caster is not None else make_caster(scene)
    o, d = camera_rays(camera, *pixel_centers(camera))
    hits = caster.intersect(o, d)
    hit = hits.prim >= 0
    h, w = camera.height, camera.width
    depth = np.where(hit, hits.t, 0.0).astype(np.float32).reshape(h, w)
    prim = np.where(hit, hits.prim, 0)
    oid = np.where(hit, scene.tri_object[prim] if scene.n_triangles else -1, -1).astype(np.int32).reshape(h, w)
    return depth, oid


def object_mask(scene: RuntimeScene, camera: CameraParams, names: Sequence[str]) -> np.ndarray:
    """(h, w) bool: pixels whose centre ray first hits one of the named objects."""
    names = [names] if isinstance(names, str) else list(names)
    unknown = [n for n in names if n not in scene.object_names]
    if unknown:
        raise InvalidInputError(f"objects {unknown} are not in the scene (objects: {list(scene.object_names)})")
    _, oid = surface_aovs(scene, camera)
    return np.isin(oid, [scene.object_names.index(n) for n in names])


# ============================================================================ generation


def generate_dataset(scene: RuntimeScene, camera: CameraParams, placement: LightPlacement | dict,
                     params: ReferenceParams | None = None, progress: Progress | None = None
                     ) -> IlluminationDataset:
    """Render ``scene`` from ``camera`` once per light of ``placement`` -> an IlluminationDataset.

    Image k is the reference render (``params``) of the scene lit only by point light k (see the
    module docstring for what is replaced). Surface points: the depth AOV of the pixel-centre rays
    through :func:`engine.relighting.dataset.points_from_depth` (``depth_kind="distance"``); mask: pixels
    whose centre ray hits geometry. ``progress(fraction, stage)`` is called after every image; an
    exception raised by it (cancellation) stops the generation. The dataset's ``sphere_center`` is
    the placement centre (the bake's default) and ``meta`` records the resolved placement, the
    render parameters, the light count and the timings.
    """
    if isinstance(placement, dict):
        placement = LightPlacement.from_dict(placement)
    if not isinstance(placement, LightPlacement):
        raise InvalidInputError("placement: expected a LightPlacement or its dict")
    if not isinstance(camera, CameraParams):
        raise InvalidInputError("camera: expected CameraParams")
    params = params or ReferenceParams()
    t0 = time.perf_counter()
    if scene.n_triangles == 0:
        raise InvalidInputError("scene: no geometry to light")
    caster = make_caster(scene)
    depth, oid = surface_aovs(scene, camera, caster)
    pts, valid = points_from_depth(depth, camera, depth_kind="distance")
    mask = valid & (oid >= 0)
    if not np.any(mask):
        raise InvalidInputError("camera: no pixel sees the scene's geometry")
    vis = pts[mask]
    center = vis.mean(axis=0) if placement.center is None else np.asarray(placement.center)
    far = float(np.max(np.linalg.norm(vis - center, axis=1)))
    if placement.radius is None:
        radius = 1.5 * far if far > 0 else 1.0
    else:
        radius = placement.radius
        if far >= radius:
            raise InvalidInputError(f"placement.radius: the light sphere (radius {radius:.6g}) does not enclose "
                                    f"the visible surface (farthest point at {far:.6g} from the centre)")
    eye_dir = np.asarray(camera.eye, dtype=np.float64) - center
    lights = place_lights(placement, center, radius, front_hint=eye_dir)
    k = lights.shape[0]
    if k > MAX_LIGHTS:
        raise InvalidInputError(f"placement.spacing_deg: {k} lights exceed the limit of {MAX_LIGHTS}")
    inten = np.broadcast_to(np.asarray(radius * radius if placement.intensity is None else placement.intensity,
                                       np.float64), (3,)).copy()
    h, w = camera.height, camera.width
    images = np.empty((k, h, w, 3), np.float32)  # the dataset keeps this array (no copy)
    t1 = time.perf_counter()
    for j in range(k):
        sc = scene_with_lights(scene, PointLight(tuple(lights[j]), tuple(inten)))
        images[j] = ReferenceRenderer(sc, caster).render(camera, params).radiance
        if progress is not None:
            progress((j + 1) / k, "render dataset images")
    resolved = dataclasses.replace(placement, center=tuple(float(x) for x in center), radius=float(radius),
                                   intensity=tuple(float(x) for x in inten),
                                   front=tuple(float(x) for x in placement.frame(eye_dir)[0]))
    meta = dict(source="generated", placement=placement.to_dict(), resolved_placement=resolved.to_dict(),
                reference_params=params.to_dict(), n_lights=int(k), camera=camera.to_dict(),
                farthest_surface_point=far, n_surface_pixels=int(mask.sum()),
                replaced="scene lights -> one point light per image; ambient, background, emission -> 0",
                time_aov_s=t1 - t0, time_render_s=time.perf_counter() - t1)
    return IlluminationDataset(images, lights, np.repeat(inten[None], k, axis=0), pts, mask,
                               sphere_center=center, meta=meta)


def render_ground_truth(scene: RuntimeScene, camera: CameraParams, lights,
                        params: ReferenceParams | None = None, progress: Progress | None = None) -> np.ndarray:
    """(h, w, 3) float32 reference render of ``scene`` lit only by ``lights`` (relighting specs:
    point, directional, rect, environment — an environment map as the same directional lights the
    relighting makes of it), with the same replacements as the dataset images, so it is the ground
    truth a relit image of a :func:`generate_dataset` dataset is compared with."""
    sc = scene_with_lights(scene, lights)
    return ReferenceRenderer(sc, make_caster(sc)).render(camera, params or ReferenceParams(), progress).radiance


__all__ = ["LAYOUTS", "MAX_LIGHTS", "REGIONS", "LightPlacement", "generate_dataset", "object_mask", "place_lights",
           "render_ground_truth", "scene_with_lights", "scene_without_objects", "surface_aovs"]
