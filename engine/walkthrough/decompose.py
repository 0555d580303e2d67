"""View-space and temporal decomposition (docs/algorithms.md part C).

Both work on cheap *geometry cubes*: cube maps of depth and object id only (one ray per
pixel, ``probe_res`` pixels per face edge), cached per (position, time).

- **Surface coherence of two viewpoints** (``view_coherence``): the fraction of the pixels of
  each cube whose surface point is seen by the other viewpoint too (same object id, distance
  within ``depth_tol`` relative), the smaller of the two directions. This is the paper's
  "neighbouring bases see enough of the same surfaces".
- **Temporal coherence at one viewpoint** (``time_coherence``): the fraction of pixels that
  see the same object at both ends of an interval (same id and distance within
  ``depth_tol``: a moving object that stays under the same pixels but moves in depth fails).
- **View-space decomposition** (``choose_base_views``): a path is bisected along its arc
  length, a box / polygon is split as a k-d tree of cells (longest axis first) until every
  pair of neighbouring base viewpoints (the ends of a segment, the corners joined by a cell
  edge) has coherence >= q, or cells reach ``min_spacing``. Polygon cells wholly outside the
  polygon are dropped and corners outside it move to the nearest polygon point.
- **Temporal decomposition** (``choose_time_samples``): [start, end] is bisected where, from
  any base viewpoint (visible-object coherence) or from any light (direct-illumination
  coherence: a point light's cube at its position, a rect light's cube just in front of its
  centre, a directional light an orthographic probe along its direction), the fraction falls
  below q. Intervals in which no object and no light moves are coherent without any test,
  so a static scene gets one time sample, and only moving objects and changing lights cause
  samples. The indirect time samples use the lower threshold ``q_indirect`` on the same
  bisection, so they are a (sparser) subset of the direct ones.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from engine.reference import ReferenceRenderer
from engine.scene import RuntimeScene
from engine.walkthrough.animation import AnimatedScene
from engine.walkthrough.range_images import _BASIS, CubeRangeImage, render_cube, seen_fraction
from engine.walkthrough.viewspace import PathSpace, PolygonSpace, ViewSpace

__all__ = ["GeometryProbe", "choose_base_views", "choose_time_samples", "time_coherence", "view_coherence"]


def view_coherence(a: CubeRangeImage, b: CubeRangeImage, depth_tol: float = 0.1) -> float:
    """min(fraction of a's surfaces b sees, fraction of b's surfaces a sees)."""
    if a.res != b.res:
        raise ValueError("view_coherence needs cubes of the same resolution")
    fa = seen_fraction(a.eye, a.depth, a.object_id, b.eye, b.depth, b.object_id, a.res, _BASIS, depth_tol)
    fb = seen_fraction(b.eye, b.depth, b.object_id, a.eye, a.depth, a.object_id, a.res, _BASIS, depth_tol)
    return float(min(fa, fb))


def time_coherence(depth0: np.ndarray, oid0: np.ndarray, depth1: np.ndarray, oid1: np.ndarray,
                   depth_tol: float = 0.05) -> float:
    """Fraction of pixels seeing the same object (and distance within depth_tol) in both images."""
    same = (oid0 == oid1) & (np.abs(depth0 - depth1) <= depth_tol * np.maximum(depth0, depth1))
    return float(np.mean(same))


class GeometryProbe:
    """Geometry cubes (depth + object id) of an animated scene, cached per (position, time)."""

    def __init__(self, animated: AnimatedScene, probe_res: int = 32):
        self.animated = animated
        self.res = probe_res
        self._renderers: dict[float, ReferenceRenderer] = {}
        self._cubes: dict[tuple[float, float, float, float], CubeRangeImage] = {}
        self.cubes_rendered = 0

    def renderer(self, t: float) -> ReferenceRenderer:
        r = self._renderers.get(t)
        if r is None:
            if len(self._renderers) > 4:
                self._renderers.clear()
            r = ReferenceRenderer(self.animated.scene_at(t))
            self._renderers[t] = r
        return r

    def scene(self, t: float) -> RuntimeScene:
        return self.renderer(t).scene

    def cube(self, eye: np.ndarray, t: float) -> CubeRangeImage:
        key = (float(eye[0]), float(eye[1]), float(eye[2]), float(t))
        c = self._cubes.get(key)
        if c is None:
            from engine.reference import ReferenceParams

            c = render_cube(self.renderer(t), np.asarray(eye, np.float64), self.res, ReferenceParams(spp=1),
                            time_value=t, direct=False)
            self._cubes[key] = c
            self.cubes_rendered += 1
        return c

    def ortho_probe(self, direction: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(depth, object id) of a res x res orthographic view along ``direction`` covering the scene."""
        sc = self.scene(t)
        lo, hi = sc.bounds
        c = 0.5 * (lo + hi)
        rad = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-12)
        d = np.asarray(direction, np.float64)
        d = d / np.linalg.norm(d)
        helper = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        u = np.cross(d, helper)
        u /= np.linalg.norm(u)
        v = np.cross(u, d)
        g = (np.arange(self.res) + 0.5) / self.res * 2.0 - 1.0
        o = (c - 2.0 * rad * d)[None, None, :] + rad * (g[None, :, None] * u + g[:, None, None] * v)
        o = o.reshape(-1, 3)
        hits = self.renderer(t).caster.intersect(o, np.broadcast_to(d, o.shape).copy())
        hit = hits.prim >= 0
        oid = np.where(hit, sc.tri_object[np.where(hit, hits.prim, 0)] if sc.n_triangles else -1, -1)
        return np.where(hit, hits.t, 0.0), oid


def _light_probes(probe: GeometryProbe, t: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """(depth, object id) seen from every light at time t."""
    lt = probe.scene(t).lights
    out = []
    for i in range(lt.n_point):
        c = probe.cube(lt.point_position[i], t)
        out.append((c.depth, c.object_id))
    for i in range(lt.n_directional):
        out.append(probe.ortho_probe(lt.dir_direction[i], t))
    for i in range(lt.n_rect):
        n = np.cross(lt.rect_edge_u[i], lt.rect_edge_v[i])
        n /= max(np.linalg.norm(n), 1e-300)
        size = float(np.linalg.norm(lt.rect_edge_u[i]) + np.linalg.norm(lt.rect_edge_v[i]))
        centre = lt.rect_corner[i] + 0.5 * (lt.rect_edge_u[i] + lt.rect_edge_v[i]) + 1e-3 * size * n
        c = probe.cube(centre, t)
        out.append((c.depth, c.object_id))
    return out


def choose_time_samples(animated: AnimatedScene, views: np.ndarray, probe: GeometryProbe, q: float,
                        *, q_indirect: float | None = None, min_step: float | None = None,
                        max_samples: int = 65, depth_tol: float = 0.05,
                        progress: Callable[[str], None] | None = None) -> tuple[list[float], list[float]]:
    """(direct time samples, indirect time samples), sorted; the indirect ones are a subset.

    A static scene (or one whose tracks never change) gets ``[start]`` for both."""
    t0, t1 = animated.start, animated.end
    if animated.is_static or t1 <= t0:
        return [t0], [t0]
    if min_step is None:
        min_step = (t1 - t0) / 64.0
    scores: dict[tuple[float, float], float] = {}

    def score(a: float, b: float) -> float:
        key = (a, b)
        if key in scores:
            return scores[key]
        moving = animated.moving_objects(a, b)
        lights = animated.changing_lights(a, b)
        if not moving and not lights:
            s = 1.0
        else:
            s = 1.0
            if moving:  # the viewpoints only see a change when an object moves
                for v in views:
                    ca, cb = probe.cube(v, a), probe.cube(v, b)
                    s = min(s, time_coherence(ca.depth, ca.object_id, cb.depth, cb.object_id, depth_tol))
            for (da, oa), (db, ob) in zip(_light_probes(probe, a), _light_probes(probe, b), strict=True):
                s = min(s, time_coherence(da, oa, db, ob, depth_tol))
        scores[key] = s
        return s

    def split(threshold: float) -> list[float]:
        times = {t0, t1}
        stack = [(t0, t1)]
        while stack and len(times) < max_samples:
            a, b = stack.pop(0)  # breadth first
            if b - a <= min_step * (1 + 1e-9) or score(a, b) >= threshold:
                continue
            m = 0.5 * (a + b)
            times.add(m)
            stack += [(a, m), (m, b)]
        return sorted(times)

    direct = split(q)
    indirect = split(q if q_indirect is None else min(q, q_indirect))
    indirect = [t for t in indirect if t in set(direct)] or [t0]
    if progress is not None:
        progress(f"time samples: {len(direct)} direct, {len(indirect)} indirect")
    return direct, indirect


def choose_base_views(space: ViewSpace, probe: GeometryProbe, q: float, *, time_value: float,
                      min_spacing: float | None = None, max_views: int = 64,
                      depth_tol: float = 0.1) -> np.ndarray:
    """(V, 3) float64 base viewpoints covering ``space`` with neighbour coherence >= q."""
    lo, hi = space.bounds
    span = float(np.linalg.norm(hi - lo))
    if min_spacing is None:
        min_spacing = span / 32.0 if span > 0 else 1.0

    def coh(a: np.ndarray, b: np.ndarray) -> float:
        return view_coherence(probe.cube(a, time_value), probe.cube(b, time_value), depth_tol)

    if isinstance(space, PathSpace):
        length = space.length
        if length == 0.0:
            return space.points[:1].copy()
        svals = {0.0, length}
        stack = [(0.0, length)]
        while stack and len(svals) < max_views:
            a, b = stack.pop(0)  # breadth first: the budget refines the whole path evenly
            if b - a <= min_spacing or coh(space.point_at(a), space.point_at(b)) >= q:
                continue
            m = 0.5 * (a + b)
            svals.add(m)
            stack += [(a, m), (m, b)]
        return np.array([space.point_at(s) for s in sorted(svals)])

    # box / polygon: k-d cells over the axes with extent
    axes = [k for k in range(3) if hi[k] - lo[k] > 1e-12 * max(span, 1e-300)]

    def place(p: np.ndarray) -> np.ndarray:
        return space.closest(p) if isinstance(space, PolygonSpace) else p

    def corners(clo: np.ndarray, chi: np.ndarray) -> list[np.ndarray]:
        pts = [clo.copy()]
        for k in axes:
            pts = pts + [np.where(np.arange(3) == k, chi, p) for p in pts]
        return pts

    def cell_alive(clo: np.ndarray, chi: np.ndarray) -> bool:
        if not isinstance(space, PolygonSpace):
            return True
        # keep cells that touch the polygon: a corner or the centre inside, or a polygon vertex inside
        for p in corners(clo, chi) + [0.5 * (clo + chi)]:
            if space.contains(p):
                return True
        for x, z in space.vertices:
            if clo[0] <= x <= chi[0] and clo[2] <= z <= chi[2]:
                return True
        return False

    def edges_ok(clo: np.ndarray, chi: np.ndarray) -> bool:
        cs = corners(clo, chi)
        for i in range(len(cs)):
            for j in range(i + 1, len(cs)):
                diff = np.count_nonzero(np.abs(cs[i] - cs[j]) > 0)
                if diff == 1 and coh(place(cs[i]), place(cs[j])) < q:
                    return False
        return True

    leaves: list[tuple[np.ndarray, np.ndarray]] = []
    stack2 = [(lo.astype(np.float64), hi.astype(np.float64))]
    points: dict[tuple[float, float, float], np.ndarray] = {}
    # every split adds at most 2^(k-1) corners (k = axes with extent): stop before max_views
    n_corners = 2 ** len(axes)
    grow = max(1, 2 ** (len(axes) - 1))
    while stack2:
        clo, chi = stack2.pop(0)  # breadth first
        if not cell_alive(clo, chi):
            continue
        size = chi - clo
        k = int(np.argmax(size))
        if size[k] / 2 >= min_spacing and n_corners + grow <= max_views and not edges_ok(clo, chi):
            n_corners += grow
            mid = 0.5 * (clo[k] + chi[k])
            a_hi = chi.copy()
            a_hi[k] = mid
            b_lo = clo.copy()
            b_lo[k] = mid
            stack2 += [(clo, a_hi), (b_lo, chi)]
            continue
        leaves.append((clo, chi))
        for p in corners(clo, chi):
            pp = place(p)
            points.setdefault((round(pp[0], 9), round(pp[1], 9), round(pp[2], 9)), pp)
    return np.array(list(points.values()))
