"""Walkthrough bake (base range images at chosen viewpoints and times) and frame renderer.

Public API (docs/walkthrough.md)::

    params = walkthrough_preset("medium", face_res=128)          # or WalkthroughParams(...)
    bake = bake_walkthrough(animated_scene, view_space, params, progress=cb)
    bake.save(path); bake = WalkthroughBake.load(path)
    wr = WalkthroughRenderer(bake, animated_scene)               # scene only needed for fill="trace"
    frame = wr.render(camera, t, fill="both")                    # FrameResult

Quality presets map to the decomposition thresholds and resolutions (``PRESETS``).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from engine.camera import camera_rays, pixel_centers
from engine.errors import InvalidInputError
from engine.newviews.indirect import IndirectParams, merge_summaries
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.sampler import sample_key
from engine.scene import CameraParams
from engine.walkthrough.animation import AnimatedScene
from engine.walkthrough.decompose import GeometryProbe, choose_base_views, choose_time_samples
from engine.walkthrough.range_images import render_cube, trace_cube_indirect
from engine.walkthrough.reconstruct import FILL_MODES, PROV_HOLE, PROV_TRACED, FrameResult, _Buffers, reproject
from engine.walkthrough.viewspace import BoxSpace, PathSpace, PolygonSpace, ViewSpace

__all__ = ["PRESETS", "WalkthroughBake", "WalkthroughParams", "WalkthroughRenderer", "bake_walkthrough",
           "render_bases", "space_from_dict", "walkthrough_preset"]

Progress = Callable[[float, str], None]


INDIRECT_NOISE_RANGE = (0.001, 0.5)
"""Allowed ``indirect_noise`` (relative standard error per base pixel)."""
INDIRECT_MAX_PATHS_RANGE = (128, 65536)
"""Allowed ``indirect_max_paths``."""
INDIRECT_MIN_PATHS = 128
"""The fewest paths a base pixel traces: eight rounds of ``INDIRECT_ROUND_PATHS``, whose spread
gives its standard error (from two rounds, one degree of freedom, the estimate is often far too
small: an adaptive pass that stopped on it left a cube's RMS error ~2x its target,
tests/engine/test_walkthrough_indirect.py's scene; from eight, 0.9x)."""
INDIRECT_ROUND_PATHS = 16
INDIRECT_FLOOR = 0.25
"""The brightness a pixel's noise is measured against is at least this fraction of its cube's
mean direct brightness (dark pixels do not run to the path cap for light nobody sees)."""
_INDIRECT_STREAM = 5
"""Sampler stream of the bases' indirect paths: sample_key(seed, 5, view, indirect time sample)
(the reference renderer's camera paths use 0, shade_hits 1, the LDC's indirect pass 3)."""


@dataclass(frozen=True)
class WalkthroughParams:
    """q: coherence threshold of the view-space and direct temporal decompositions (0..1);
    q_indirect: threshold of the (sparser) indirect temporal decomposition; face_res: base
    cube face size; indirect_res_div: indirect light is rendered at face_res / div and
    upsampled (it is smooth); probe_res: face size of the geometry probes used by the
    decompositions; spp / area_light_samples / indirect_bounces: reference renderer settings of
    the base images; indirect_samples: 0 = no global illumination, > 0 = indirect light on (the
    bases' indirect part is then traced to ``indirect_noise``; holes traced by fill="trace" use
    indirect_samples paths per pixel); indirect_noise: the noise level that sizes the paths every
    base pixel traces (``indirect_params``; the bake reports each pixel's achieved relative standard
    error, measured against its brightness: direct + indirect, at least ``INDIRECT_FLOOR`` times its
    cube's mean direct brightness); indirect_max_paths: the most paths any base pixel traces (the
    bake's cost bound); max_views / max_time_samples: caps; min_spacing: smallest base
    spacing (None: view-space diagonal / 32); depth_tol: relative depth tolerance of the
    reprojection; n_bases: bases reprojected per frame."""

    quality: str = "custom"
    q: float = 0.7
    q_indirect: float = 0.5
    face_res: int = 128
    indirect_res_div: int = 2
    probe_res: int = 32
    spp: int = 2
    area_light_samples: int = 16
    indirect_samples: int = 16
    indirect_bounces: int = 2
    indirect_noise: float = 0.02
    indirect_max_paths: int = 1024
    max_views: int = 16
    max_time_samples: int = 33
    min_spacing: float | None = None
    depth_tol: float = 0.02
    n_bases: int = 2
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("q", "q_indirect"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise InvalidInputError(f"{name} must be in [0, 1], got {v}")
        ints = {"face_res": (4, 4096), "indirect_res_div": (1, 16), "probe_res": (4, 512), "spp": (1, 1024),
                "area_light_samples": (1, 4096), "indirect_samples": (0, 1 << 16), "indirect_bounces": (1, 16),
                "indirect_max_paths": INDIRECT_MAX_PATHS_RANGE,
                "max_views": (1, 4096), "max_time_samples": (1, 4097), "n_bases": (1, 16)}
        for name, (lo, hi) in ints.items():
            v = getattr(self, name)
            if not isinstance(v, int) or not lo <= v <= hi:
                raise InvalidInputError(f"{name} must be an integer in [{lo}, {hi}], got {v!r}")
        if self.face_res % self.indirect_res_div:
            raise InvalidInputError(f"face_res ({self.face_res}) must be a multiple of indirect_res_div "
                                    f"({self.indirect_res_div})")
        lo_n, hi_n = INDIRECT_NOISE_RANGE
        v = self.indirect_noise
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo_n <= v <= hi_n:
            raise InvalidInputError(f"indirect_noise must be a number in [{lo_n:g}, {hi_n:g}], got {v!r}")
        if not 0.0 <= self.depth_tol < 1.0:
            raise InvalidInputError(f"depth_tol must be in [0, 1), got {self.depth_tol}")

    def reference_params(self, indirect: bool) -> ReferenceParams:
        return ReferenceParams(spp=self.spp, area_light_samples=self.area_light_samples,
                               indirect_samples=self.indirect_samples if indirect else 0,
                               indirect_bounces=self.indirect_bounces, seed=self.seed)

    def indirect_params(self) -> IndirectParams:
        """Settings of the bases' converged indirect pass: the reference renderer's paths
        (``indirect_bounces`` diffuse vertices, its light sampling and mirror / glossy depth)
        traced per base pixel, a fixed count sized from ``indirect_noise`` (``(0.32 / noise)^2``, a
        power of two within ``INDIRECT_MIN_PATHS`` .. ``indirect_max_paths``,
        ``engine/newviews/indirect_sampling.py``): on both walkthrough sample scenes it gave the
        frames the adaptive sampler's error in 0.49-0.60x the bake time (docs/walkthrough.md)."""
        return IndirectParams(noise=float(self.indirect_noise), min_paths=INDIRECT_MIN_PATHS,
                              max_paths=self.indirect_max_paths, bounces=self.indirect_bounces,
                              round_paths=INDIRECT_ROUND_PATHS, floor=INDIRECT_FLOOR, seed=self.seed,
                              area_light_samples=min(self.area_light_samples, 1024),
                              max_depth=ReferenceParams().max_depth)


PRESETS: dict[str, dict[str, object]] = {
    "low": dict(q=0.5, q_indirect=0.3, face_res=96, spp=1, indirect_samples=8, indirect_noise=0.05,
                indirect_max_paths=256, max_views=4, max_time_samples=5),
    "medium": dict(q=0.7, q_indirect=0.5, face_res=160, spp=2, indirect_samples=16, indirect_noise=0.02,
                   indirect_max_paths=1024, max_views=8, max_time_samples=9),
    "high": dict(q=0.85, q_indirect=0.65, face_res=256, spp=4, indirect_samples=32, indirect_noise=0.01,
                 indirect_max_paths=4096, max_views=12, max_time_samples=17),
}
"""Worst-case base image memory (every view at every time): low 35 MB, medium 0.35 GB, high 2.6 GB."""


def walkthrough_preset(quality: str, **overrides: object) -> WalkthroughParams:
    """Parameters of a quality preset (low / medium / high), with optional overrides."""
    if quality not in PRESETS:
        raise InvalidInputError(f"quality must be one of {', '.join(PRESETS)}; got {quality!r}")
    return WalkthroughParams(quality=quality, **{**PRESETS[quality], **overrides})  # type: ignore[arg-type]


@dataclass
class WalkthroughBake:
    """Base images. views (V, 3) float64; direct_times (Td,), indirect_times (Ti,) (a subset);
    direct (V, Td, 6, R, R, 3) float32; indirect (V, Ti, 6, R, R, 3) float32 (Ti = 1 and all
    zero without global illumination); depth, object_id (V, Td, 6, R, R); background (3,);
    start / end of the animation; timings (seconds per phase); params (WalkthroughParams as a dict);
    indirect_stats: the achieved noise of the indirect pass over all its base pixels
    (``engine.newviews.indirect.merge_summaries``: relative standard error median / p95 of the
    cubes, max, the fraction of pixels that met ``indirect_noise``, paths traced) and per cube
    (``cubes``: view index, animation time ``at``, its own summary and seconds)."""

    views: np.ndarray
    direct_times: np.ndarray
    indirect_times: np.ndarray
    direct: np.ndarray
    indirect: np.ndarray
    depth: np.ndarray
    object_id: np.ndarray
    background: np.ndarray
    start: float
    end: float
    view_space: dict[str, object] = field(default_factory=dict)
    params: dict[str, object] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    indirect_stats: dict[str, object] = field(default_factory=dict)

    @property
    def res(self) -> int:
        return int(self.depth.shape[-1])

    @property
    def n_views(self) -> int:
        return int(self.views.shape[0])

    @property
    def nbytes(self) -> int:
        return int(self.direct.nbytes + self.indirect.nbytes + self.depth.nbytes + self.object_id.nbytes)

    def meta(self) -> dict[str, object]:
        return {"views": self.views.tolist(), "direct_times": self.direct_times.tolist(),
                "indirect_times": self.indirect_times.tolist(), "background": self.background.tolist(),
                "start": self.start, "end": self.end, "res": self.res, "view_space": self.view_space,
                "params": self.params, "timings": self.timings,
                "indirect_stats": self.indirect_stats}

    def save(self, path: str | os.PathLike[str]) -> None:
        """One uncompressed .npz (arrays + a JSON ``meta`` entry), written atomically."""
        p = Path(path)
        tmp = p.with_name(p.name + ".tmp.npz")
        np.savez(tmp, direct=self.direct, indirect=self.indirect, depth=self.depth, object_id=self.object_id,
                 meta=np.frombuffer(json.dumps(self.meta()).encode(), np.uint8))
        os.replace(tmp, p)

    @staticmethod
    def load(path: str | os.PathLike[str]) -> WalkthroughBake:
        with np.load(path) as z:
            meta = json.loads(bytes(z["meta"]).decode())
            return WalkthroughBake(np.asarray(meta["views"], np.float64), np.asarray(meta["direct_times"]),
                                   np.asarray(meta["indirect_times"]), z["direct"], z["indirect"], z["depth"],
                                   z["object_id"], np.asarray(meta["background"], np.float64), meta["start"],
                                   meta["end"], meta["view_space"], meta["params"], meta["timings"],
                                   meta.get("indirect_stats", {}))


def _space_dict(space: ViewSpace) -> dict[str, object]:
    if isinstance(space, PathSpace):
        return {"type": "path", "points": space.points.tolist(), "radius": space.radius}
    if isinstance(space, BoxSpace):
        return {"type": "box", "min": space.lo.tolist(), "max": space.hi.tolist()}
    return {"type": "polygon", "vertices": space.vertices.tolist(), "eye_height": space.eye_height}


def space_from_dict(d: dict[str, object]) -> ViewSpace:
    """Inverse of the ``view_space`` entry of a bake's meta."""
    kind = d.get("type")
    if kind == "path":
        return PathSpace(np.asarray(d["points"], np.float64), float(d.get("radius", 0.0)))  # type: ignore[arg-type]
    if kind == "box":
        return BoxSpace(np.asarray(d["min"], np.float64), np.asarray(d["max"], np.float64))
    if kind == "polygon":
        return PolygonSpace(np.asarray(d["vertices"], np.float64), float(d["eye_height"]))  # type: ignore[arg-type]
    raise InvalidInputError(f"unknown view space type {kind!r}")


def bake_walkthrough(animated: AnimatedScene, space: ViewSpace, params: WalkthroughParams,
                     progress: Progress | None = None) -> WalkthroughBake:
    """Choose base viewpoints and time samples, then render every base cube."""
    timings: dict[str, float] = {}
    t_all = time.perf_counter()

    def report(frac: float, msg: str) -> None:
        if progress is not None:
            progress(frac, msg)

    probe = GeometryProbe(animated, params.probe_res)
    t0 = time.perf_counter()
    views = choose_base_views(space, probe, params.q, time_value=animated.start, min_spacing=params.min_spacing,
                              max_views=params.max_views)
    timings["view_decomposition"] = time.perf_counter() - t0
    report(0.02, f"{len(views)} base views")
    t0 = time.perf_counter()
    gi = params.indirect_samples > 0
    d_times, i_times = choose_time_samples(animated, views, probe, params.q, q_indirect=params.q_indirect,
                                           max_samples=params.max_time_samples)
    timings["time_decomposition"] = time.perf_counter() - t0
    report(0.04, f"{len(d_times)} direct / {len(i_times) if gi else 0} indirect time samples")
    bake = render_bases(animated, views, d_times, i_times, params, space=space,
                        progress=None if progress is None else lambda f, m: report(0.05 + 0.95 * f, m))
    bake.timings.update(timings)
    bake.timings["total"] = time.perf_counter() - t_all
    return bake


def render_bases(animated: AnimatedScene, views: np.ndarray | list[list[float]], d_times: list[float],
                 i_times: list[float], params: WalkthroughParams, *, space: ViewSpace | None = None,
                 progress: Progress | None = None) -> WalkthroughBake:
    """Render the base cubes at given viewpoints and times (no decomposition): direct light
    at every time of ``d_times`` (sorted), indirect at ``i_times`` (a subset of them) when
    ``params.indirect_samples > 0``.

    The direct part is a reference render of each face. The indirect part is traced at
    face_res / indirect_res_div per base pixel to ``params.indirect_noise``
    (``range_images.trace_cube_indirect``: one surface point per pixel, the first hit of its
    centre ray, measured against the direct light averaged over the pixel's block) and repeated
    over each block; the cube of view v at indirect time sample k draws its paths from the
    sampler stream sample_key(seed, 5, v, k), so a bake is deterministic."""
    views = np.asarray(views, np.float64).reshape(-1, 3)
    d_times = [float(t) for t in d_times]
    i_times = [float(t) for t in i_times]
    if not d_times or any(b <= a for a, b in zip(d_times, d_times[1:], strict=False)):
        raise InvalidInputError("direct time samples must be a non-empty, strictly increasing list")
    if not set(i_times) <= set(d_times) or not i_times:
        raise InvalidInputError("indirect time samples must be a non-empty subset of the direct ones")
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    gi = params.indirect_samples > 0

    def report(frac: float, msg: str) -> None:
        if progress is not None:
            progress(frac, msg)

    R = params.face_res
    V, Td = len(views), len(d_times)
    Ti = len(i_times) if gi else 1
    direct = np.zeros((V, Td, 6, R, R, 3), np.float32)
    indirect = np.zeros((V, Ti, 6, R, R, 3), np.float32)
    depth = np.zeros((V, Td, 6, R, R), np.float32)
    oid = np.full((V, Td, 6, R, R), -1, np.int32)
    timings["direct"] = 0.0
    timings["indirect"] = 0.0
    # the indirect pass costs several direct renders per cube: weigh it so in the progress
    w_ind = 4.0
    total = V * Td + (w_ind * V * Ti if gi else 0)
    done = 0.0
    rdiv = params.indirect_res_div
    ri = R // rdiv
    iparams = params.indirect_params()
    cube_stats: list[dict] = []
    for ti, t in enumerate(d_times):
        renderer = ReferenceRenderer(animated.scene_at(t))
        for vi, eye in enumerate(views):
            t0 = time.perf_counter()
            cube = render_cube(renderer, eye, R, params.reference_params(False), time_value=t)
            direct[vi, ti], depth[vi, ti], oid[vi, ti] = cube.direct, cube.depth, cube.object_id
            timings["direct"] += time.perf_counter() - t0
            done += 1
            report(done / total, f"direct base {vi} at t={t:g}")
            if gi and t in i_times:
                t0 = time.perf_counter()
                k = i_times.index(t)
                low = cube.direct.reshape(6, ri, rdiv, ri, rdiv, 3).mean(axis=(2, 4))
                d0 = done

                def cube_progress(f: float, vi: int = vi, t: float = t, d0: float = d0) -> None:
                    report((d0 + w_ind * f) / total, f"indirect base {vi} at t={t:g}")

                ic = trace_cube_indirect(renderer, eye, ri, low, iparams,
                                         key=sample_key(params.seed, _INDIRECT_STREAM, vi, k),
                                         progress=cube_progress if progress is not None else None)
                up = ic.radiance
                if rdiv > 1:
                    up = np.repeat(np.repeat(up, rdiv, axis=1), rdiv, axis=2)
                indirect[vi, k] = up
                cube_stats.append({**ic.stats, "view": vi, "at": t, "seconds": ic.stats["time"]})
                timings["indirect"] += time.perf_counter() - t0
                done = d0 + w_ind
                report(done / total, f"indirect base {vi} at t={t:g}")
    timings["total"] = time.perf_counter() - t_all
    istats: dict[str, object] = {}
    if gi:
        istats = {**merge_summaries(cube_stats, iparams), "res": ri,
                  "cubes": [{k2: c[k2] for k2 in ("view", "at", "sides", "rel_stderr_median", "rel_stderr_p95",
                                                   "rel_stderr_max", "met_target", "paths_mean", "paths_max",
                                                   "seconds") if k2 in c} for c in cube_stats]}
    sc0 = animated.scene_at(animated.start)
    return WalkthroughBake(np.asarray(views, np.float64), np.asarray(d_times, np.float64),
                           np.asarray(i_times if gi else [d_times[0]], np.float64), direct, indirect, depth, oid,
                           np.asarray(sc0.background, np.float64), animated.start, animated.end,
                           _space_dict(space) if space is not None else {}, asdict(params), timings, istats)


def _bracket(times: np.ndarray, t: float) -> tuple[int, int, float]:
    if times.size == 1 or t <= times[0]:
        return 0, 0, 0.0
    if t >= times[-1]:
        n = times.size - 1
        return n, n, 0.0
    i = int(np.searchsorted(times, t, side="right") - 1)
    a = (t - times[i]) / (times[i + 1] - times[i])
    if a == 0.0:
        return i, i, 0.0
    return i, i + 1, float(a)


class WalkthroughRenderer:
    """Reconstructs frames from a bake. ``animated`` (the same scene) is needed for fill="trace"."""

    def __init__(self, bake: WalkthroughBake, animated: AnimatedScene | None = None):
        self.bake = bake
        self.animated = animated
        self.space = space_from_dict(bake.view_space) if bake.view_space else None
        self._buffers = _Buffers()
        self._renderer: tuple[float, ReferenceRenderer] | None = None
        lo, hi = bake.views.min(axis=0), bake.views.max(axis=0)
        self._scale = max(float(np.abs(bake.views).max()), float(np.linalg.norm(hi - lo)), 1e-300)

    def check_time(self, t: float, field_name: str = "time") -> float:
        t = float(t)
        if not math.isfinite(t) or not self.bake.start <= t <= self.bake.end:
            raise InvalidInputError(f"{field_name}: {t:g} is outside the animation interval "
                                    f"[{self.bake.start:g}, {self.bake.end:g}]")
        return t

    def check_eye(self, eye: np.ndarray | tuple[float, float, float], field_name: str = "camera.eye",
                  tol: float = 1e-6) -> None:
        """InvalidInputError when ``eye`` lies outside the view space (relative tolerance)."""
        if self.space is not None and not self.space.contains(np.asarray(eye, np.float64), tol):
            d = self.space.distance(np.asarray(eye, np.float64))
            lo, hi = self.space.bounds
            raise InvalidInputError(f"{field_name}: {[round(float(c), 6) for c in eye]} is outside the view "
                                    f"space ({d:.6g} away; its bounds are {lo.tolist()} .. {hi.tolist()})")

    def nearest_bases(self, eye: np.ndarray, n: int) -> list[int]:
        d = np.linalg.norm(self.bake.views - np.asarray(eye, np.float64)[None, :], axis=1)
        order = [int(i) for i in np.argsort(d, kind="stable")]
        if d[order[0]] <= 1e-12 * self._scale:
            return order[:1]  # at a base viewpoint its cube sees everything the camera sees
        return order[:n]

    def render(self, camera: CameraParams, t: float = 0.0, *, fill: str = "both", n_bases: int | None = None,
               strict: bool = True) -> FrameResult:
        """The frame seen by ``camera`` at time ``t``. ``strict``: reject eyes outside the view
        space and times outside the animation with InvalidInputError."""
        if fill not in FILL_MODES:
            raise InvalidInputError(f"fill must be one of {', '.join(FILL_MODES)}; got {fill!r}")
        if fill == "trace" and self.animated is None:
            raise InvalidInputError("fill='trace' needs the animated scene (WalkthroughRenderer(bake, animated))")
        b = self.bake
        if strict:
            self.check_time(t)
            self.check_eye(camera.eye)
        t0 = time.perf_counter()
        views = self.nearest_bases(np.asarray(camera.eye, np.float64), n_bases or int(b.params.get("n_bases", 2)))
        d0, d1, ad = _bracket(b.direct_times, t)
        i0, i1, ai = _bracket(b.indirect_times, t)
        g = d0 if ad < 0.5 else d1
        nv = len(views)
        frame = reproject(camera, b.views, b.depth, b.object_id, b.direct, b.indirect, views, [g] * nv,
                          [(d0, d1, ad)] * nv, [(i0, i1, ai)] * nv, background=b.background, fill=fill,
                          depth_tol=float(b.params.get("depth_tol", 0.02)), buffers=self._buffers)  # type: ignore[arg-type]
        if fill == "trace":
            t1 = time.perf_counter()
            self._trace_holes(frame, camera, t)
            frame.timings["trace"] = time.perf_counter() - t1
        frame.timings["total"] = time.perf_counter() - t0
        frame.counts = {name: int(np.count_nonzero(frame.provenance == k)) for k, name in
                        enumerate(("hole", "reprojected", "foreground", "background_fill", "traced", "sky"))}
        return frame

    def _trace_holes(self, frame: FrameResult, camera: CameraParams, t: float) -> None:
        assert self.animated is not None
        holes = np.flatnonzero(frame.provenance.ravel() == PROV_HOLE)
        if holes.size == 0:
            return
        if self._renderer is None or self._renderer[0] != t:
            self._renderer = (t, ReferenceRenderer(self.animated.scene_at(t)))
        rr = self._renderer[1]
        px, py = pixel_centers(camera)
        o, d = camera_rays(camera, px[holes], py[holes])
        hits = rr.caster.intersect(o, d)
        hit = hits.prim >= 0
        p = self.bake.params
        rp = ReferenceParams(spp=1, area_light_samples=int(p.get("area_light_samples", 16)),  # type: ignore[arg-type]
                             indirect_samples=int(p.get("indirect_samples", 0)),  # type: ignore[arg-type]
                             indirect_bounces=int(p.get("indirect_bounces", 2)),  # type: ignore[arg-type]
                             seed=int(p.get("seed", 0)))  # type: ignore[arg-type]
        rad = np.empty((holes.size, 3))
        rad[:] = self.bake.background[None, :]
        if np.any(hit):
            hi = np.flatnonzero(hit)
            rad[hi] = rr.shade_hits(hits.prim[hi], hits.u[hi].astype(np.float32), hits.v[hi].astype(np.float32),
                                    d[hi], rp)
        out = frame.radiance.reshape(-1, 3)
        out[holes] = rad.astype(np.float32)
        dep = frame.depth.reshape(-1)
        dep[holes] = np.where(hit, hits.t, 0.0).astype(np.float32)
        ids = frame.object_id.reshape(-1)
        sc = rr.scene
        ids[holes] = np.where(hit, sc.tri_object[np.where(hit, hits.prim, 0)] if sc.n_triangles else -1, -1)
        frame.provenance.reshape(-1)[holes] = PROV_TRACED


