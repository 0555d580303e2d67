"""View spaces: the region a walkthrough viewer may move in (engine-side, no schema types).

``PathSpace`` (a polyline, optional radius), ``BoxSpace`` (axis-aligned, possibly flat) and
``PolygonSpace`` (a simple polygon in the plane y = eye_height). Each answers ``contains``
(with a relative tolerance), ``distance`` and gives the corner / end points the view-space
decomposition starts from.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.errors import InvalidInputError

__all__ = ["BoxSpace", "PathSpace", "PolygonSpace", "ViewSpace"]

_REL = 1e-9


def _scale(*arrays: np.ndarray) -> float:
    return max(max(float(np.abs(a).max()) for a in arrays), 1.0)


@dataclass(frozen=True)
class PathSpace:
    points: np.ndarray  # (n, 3) float64
    radius: float = 0.0

    def __post_init__(self) -> None:
        p = np.asarray(self.points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 2 or not np.all(np.isfinite(p)):
            raise InvalidInputError("view_space.points: need >= 2 finite 3D points")
        object.__setattr__(self, "points", p)
        if self.length <= _REL * _scale(p) and self.radius <= 0:
            raise InvalidInputError("view_space: the view space has no room (all path points coincide)")

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())

    def point_at(self, s: float) -> np.ndarray:
        """Point at arc length s in [0, length]."""
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        s = min(max(s, 0.0), cum[-1])
        i = int(min(np.searchsorted(cum, s, side="right") - 1, len(seg) - 1))
        a = 0.0 if seg[i] == 0 else (s - cum[i]) / seg[i]
        return (1 - a) * self.points[i] + a * self.points[i + 1]

    def distance(self, p: np.ndarray) -> float:
        p = np.asarray(p, dtype=np.float64)
        best = np.inf
        for a, b in zip(self.points[:-1], self.points[1:], strict=True):
            ab = b - a
            den = float(ab @ ab)
            u = 0.0 if den == 0 else min(max(float((p - a) @ ab) / den, 0.0), 1.0)
            best = min(best, float(np.linalg.norm(p - (a + u * ab))))
        return best

    def contains(self, p: np.ndarray, tol: float = 1e-6) -> bool:
        return self.distance(p) <= self.radius + tol * _scale(self.points)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.points.min(axis=0) - self.radius, self.points.max(axis=0) + self.radius


@dataclass(frozen=True)
class BoxSpace:
    lo: np.ndarray
    hi: np.ndarray

    def __post_init__(self) -> None:
        lo = np.asarray(self.lo, dtype=np.float64).reshape(3)
        hi = np.asarray(self.hi, dtype=np.float64).reshape(3)
        if np.any(hi < lo):
            raise InvalidInputError("view_space.max must be >= view_space.min on every axis")
        if float((hi - lo).max()) <= _REL * _scale(lo, hi):
            raise InvalidInputError("view_space: the view space has no room (min == max)")
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)

    def distance(self, p: np.ndarray) -> float:
        p = np.asarray(p, dtype=np.float64)
        return float(np.linalg.norm(p - np.clip(p, self.lo, self.hi)))

    def contains(self, p: np.ndarray, tol: float = 1e-6) -> bool:
        return self.distance(p) <= tol * _scale(self.lo, self.hi)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.lo, self.hi


@dataclass(frozen=True)
class PolygonSpace:
    vertices: np.ndarray  # (n, 2) float64, (x, z)
    eye_height: float

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 2 or v.shape[0] < 3 or not np.all(np.isfinite(v)):
            raise InvalidInputError("view_space.vertices: need >= 3 finite (x, z) points")
        object.__setattr__(self, "vertices", v)
        if self.area <= 1e-12 * _scale(v) ** 2:
            raise InvalidInputError("view_space: the view space has no room (zero-area polygon)")

    @property
    def area(self) -> float:
        x, z = self.vertices[:, 0], self.vertices[:, 1]
        return 0.5 * abs(float(np.sum(x * np.roll(z, -1) - np.roll(x, -1) * z)))

    def _inside2(self, x: float, z: float) -> bool:
        v = self.vertices
        inside = False
        n = len(v)
        for i in range(n):
            x0, z0 = v[i]
            x1, z1 = v[(i + 1) % n]
            if (z0 > z) != (z1 > z):
                xc = x0 + (z - z0) * (x1 - x0) / (z1 - z0)
                if x < xc:
                    inside = not inside
        return inside

    def closest(self, p: np.ndarray) -> np.ndarray:
        """The point of the (closed) polygon at eye height closest to p."""
        p = np.asarray(p, dtype=np.float64)
        q = np.array([p[0], p[2]])
        if self._inside2(q[0], q[1]):
            return np.array([p[0], self.eye_height, p[2]])
        v = self.vertices
        best, bp = np.inf, v[0]
        for i in range(len(v)):
            a, b = v[i], v[(i + 1) % len(v)]
            ab = b - a
            u = min(max(float((q - a) @ ab) / float(ab @ ab), 0.0), 1.0) if ab @ ab > 0 else 0.0
            c = a + u * ab
            d = float(np.linalg.norm(q - c))
            if d < best:
                best, bp = d, c
        return np.array([bp[0], self.eye_height, bp[1]])

    def distance(self, p: np.ndarray) -> float:
        return float(np.linalg.norm(np.asarray(p, dtype=np.float64) - self.closest(p)))

    def contains(self, p: np.ndarray, tol: float = 1e-6) -> bool:
        return self.distance(p) <= tol * _scale(self.vertices, np.array([self.eye_height]))

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo = self.vertices.min(axis=0)
        hi = self.vertices.max(axis=0)
        return np.array([lo[0], self.eye_height, lo[1]]), np.array([hi[0], self.eye_height, hi[1]])


ViewSpace = PathSpace | BoxSpace | PolygonSpace
