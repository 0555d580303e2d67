"""Ray casting: one interface, two back ends (Embree for speed, a slow reference for tests).

Conventions
- Rays are given in world space, float64: origins (n, 3), unit directions (n, 3).
- ``t`` is the distance along the (unit) direction; misses have ``t = inf`` and ``prim = -1``.
- ``u, v`` are barycentrics of the hit: p = (1 - u - v) p0 + u p1 + v p2.
- The Embree back end works in float32 relative to ``scene.center``; the hit
  point should be rebuilt from (prim, u, v) in float64 (``hit_points``), which
  puts it on the triangle's plane, and secondary rays must start from
  ``spawn_origins`` (a scale-aware offset along the geometric normal), because
  embreex has no per-ray ``tnear`` (docs/hard-cases.md #1).
- Embree scenes are built lazily, once per process, and never pickled.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Protocol

import numba as nb
import numpy as np

from engine import (
    _numba_setup,  # noqa: F401  (numba's configuration before any kernel)
    embree,
)
from engine.errors import InvalidInputError
from engine.scene import RuntimeScene
from engine.sched import run_pieces_parallel

# Self-intersection offset = OFFSET_REL * (max |p - center|_inf + OFFSET_EXTENT * extent).
# float32 has 2^-24 relative rounding; Embree's watertight test and the cast of the
# origin to float32 each cost a few ulps, so 2^-16 (~256 ulps) leaves a wide margin
# while staying far below any feature size that float32 can represent at that magnitude.
OFFSET_REL = 2.0 ** -16
OFFSET_EXTENT = 1e-3
# Shadow rays stop this fraction short of the light (plus the offset) so the light's
# own emitter geometry, if the scene models one, doesn't occlude it.
SHADOW_SHORTEN = 1e-5
MAX_LAYERS_DEFAULT = 256


@dataclass(frozen=True)
class Hits:
    """First hits of a batch of rays. All arrays have length n."""

    t: np.ndarray  # float64, inf on miss
    prim: np.ndarray  # int32, -1 on miss
    u: np.ndarray  # float64
    v: np.ndarray  # float64

    @property
    def hit(self) -> np.ndarray:
        return self.prim >= 0


@dataclass(frozen=True)
class AllHits:
    """Every surface hit along each ray, sorted by t, stored flat (CSR).

    offsets: (n + 1,) int64, ray i owns entries offsets[i]:offsets[i+1];
    t, u, v: float64, prim: int32; truncated: (n,) bool rays that reached max_hits.
    """

    offsets: np.ndarray
    t: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray
    truncated: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.offsets)


class RayCaster(Protocol):
    scene: RuntimeScene

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> Hits: ...

    def intersect_local(self, o32: np.ndarray, d32: np.ndarray, serial: bool | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    def occluded_local(self, o32: np.ndarray, d32: np.ndarray, tmax32: np.ndarray, serial: bool | None = None
                       ) -> np.ndarray: ...

    def occluded(self, origins: np.ndarray, directions: np.ndarray, tmax: np.ndarray) -> np.ndarray: ...


def check_rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Contiguous float64 copies of (n, 3) finite ``origins`` and ``directions``; InvalidInputError otherwise."""
    o = np.ascontiguousarray(origins, dtype=np.float64)
    d = np.ascontiguousarray(directions, dtype=np.float64)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise InvalidInputError(f"rays must be (n, 3) origins and directions, got {o.shape} and {d.shape}")
    if not (np.all(np.isfinite(o)) and np.all(np.isfinite(d))):
        raise InvalidInputError("ray origins and directions must be finite")
    return o, d


# ----------------------------------------------------------------------------- offsets


@nb.njit(cache=True)
def _offset_magnitude(p: np.ndarray, center: np.ndarray, extent: float) -> float:
    m = 0.0
    for k in range(3):
        a = abs(p[k] - center[k])
        if a > m:
            m = a
    return OFFSET_REL * (m + OFFSET_EXTENT * extent)


_SPAWN_MIN_PIECE = 16384  # a few loads and stores per point: smaller pieces cost more to dispatch than they save


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _spawn_kernel(lo, hi, p, ng, d, center, extent, out):
    """Points lo .. hi - 1 of ``spawn_origins``."""
    for i in range(lo, hi):
        mag = _offset_magnitude(p[i], center, extent)
        s = ng[i, 0] * d[i, 0] + ng[i, 1] * d[i, 1] + ng[i, 2] * d[i, 2]
        sign = 1.0 if s >= 0.0 else -1.0
        for k in range(3):
            out[i, k] = p[i, k] + sign * mag * ng[i, k]


def spawn_origins(scene: RuntimeScene, p: np.ndarray, ng: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Origins for rays leaving surface points ``p`` (n, 3) in directions ``d``.

    Moves each point off its triangle's plane by a scale-aware distance, to the side
    the ray travels toward (so transmission-side and reflection-side both work).
    """
    p64 = np.ascontiguousarray(p, dtype=np.float64)
    ng64 = np.ascontiguousarray(ng, dtype=np.float64)
    d64 = np.ascontiguousarray(d, dtype=np.float64)
    out = np.empty_like(p64)
    run_pieces_parallel(lambda lo, hi: _spawn_kernel(lo, hi, p64, ng64, d64, scene.center, scene.extent, out),
                        p64.shape[0], _SPAWN_MIN_PIECE)
    return out


def offset_magnitudes(scene: RuntimeScene, p: np.ndarray) -> np.ndarray:
    """The spawn offset used at each point (n,), exposed for tests and shadow-ray lengths."""
    q = np.abs(np.asarray(p, dtype=np.float64) - scene.center).max(axis=1)
    return OFFSET_REL * (q + OFFSET_EXTENT * scene.extent)


def hit_points(scene: RuntimeScene, hits: Hits) -> np.ndarray:
    """World-space hit points rebuilt in float64 from barycentrics (n, 3); zeros on misses."""
    ok = hits.prim >= 0
    out = np.zeros((hits.prim.shape[0], 3))
    tri = scene.tri_p[hits.prim[ok]]
    u = hits.u[ok][:, None]
    v = hits.v[ok][:, None]
    out[ok] = (1.0 - u - v) * tri[:, 0] + u * tri[:, 1] + v * tri[:, 2]
    return out


# ----------------------------------------------------------------------------- Embree


_EMBREE_CACHE: dict[str, object] = {}
_EMBREE_LOCK = threading.Lock()


class EmbreeCaster:
    """Embree back end (engine/embree.py). Builds its Embree scene on first use in each process."""

    def __init__(self, scene: RuntimeScene):
        self.scene = scene
        self._key = scene.geometry_hash() if scene.n_triangles else ""
        self._embree: embree.Scene | None = None
        self.embree_seconds = 0.0  # wall time inside Embree calls (benchmarks read it)
        self.embree_rays = 0

    def __getstate__(self) -> dict:  # never pickle native Embree handles
        return {"scene": self.scene, "_key": self._key, "_embree": None, "embree_seconds": 0.0,
                "embree_rays": 0}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)

    def _get(self) -> embree.Scene | None:
        if self._embree is None and self.scene.n_triangles:
            with _EMBREE_LOCK:
                es = _EMBREE_CACHE.get(self._key)
                if es is None:
                    es = embree.build_scene(self.scene.tri_local32)
                    if len(_EMBREE_CACHE) >= 8:  # small per-process bound; callers keep their own refs
                        _EMBREE_CACHE.pop(next(iter(_EMBREE_CACHE)))
                    _EMBREE_CACHE[self._key] = es
                self._embree = es
        return self._embree

    # Fast path for engine kernels that already hold float32 rays relative to scene.center.
    # No validation: callers are engine code that produced finite rays themselves.
    def intersect_local(self, o32: np.ndarray, d32: np.ndarray, serial: bool | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(prim int32, u float32, v float32) for local float32 rays (n, 3); ``serial`` as in
        ``embree.intersect``."""
        n = o32.shape[0]
        es = self._get()
        if es is None or n == 0:
            return np.full(n, -1, np.int32), np.zeros(n, np.float32), np.zeros(n, np.float32)
        t0 = time.perf_counter()
        prim, u, v, _ = embree.intersect(es, o32, d32, serial)
        self.embree_seconds += time.perf_counter() - t0
        self.embree_rays += n
        return prim, u, v

    def occluded_local(self, o32: np.ndarray, d32: np.ndarray, tmax32: np.ndarray, serial: bool | None = None
                       ) -> np.ndarray:
        """(n,) bool: something lies strictly between the origin and tmax32."""
        n = o32.shape[0]
        es = self._get()
        if es is None or n == 0:
            return np.zeros(n, dtype=np.bool_)
        t0 = time.perf_counter()
        occ = embree.occluded(es, o32, d32, tmax32, serial)
        self.embree_seconds += time.perf_counter() - t0
        self.embree_rays += n
        return occ

    def _local(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (np.ascontiguousarray((o - self.scene.center).astype(np.float32)),
                np.ascontiguousarray(d.astype(np.float32)))

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        o, d = check_rays(origins, directions)
        n = o.shape[0]
        es = self._get()
        if es is None or n == 0:
            return Hits(np.full(n, np.inf), np.full(n, -1, np.int32), np.zeros(n), np.zeros(n))
        ol, dl = self._local(o, d)
        prim, u, v, t = embree.intersect(es, ol, dl)
        return Hits(t.astype(np.float64), prim, u.astype(np.float64), v.astype(np.float64))

    def occluded(self, origins: np.ndarray, directions: np.ndarray, tmax: np.ndarray) -> np.ndarray:
        o, d = check_rays(origins, directions)
        n = o.shape[0]
        es = self._get()
        if es is None or n == 0:
            return np.zeros(n, dtype=np.bool_)
        tm = np.asarray(tmax, dtype=np.float64)
        tm = np.minimum(tm, 3.0e38).astype(np.float32)
        ol, dl = self._local(o, d)
        return embree.occluded(es, ol, dl, tm)


# ----------------------------------------------------------------------------- reference


class ReferenceCaster:
    """Slow, obvious float64 brute force (Moller-Trumbore over every triangle).

    For tests only: O(rays x triangles). Same conventions as EmbreeCaster (tnear = 0).
    """

    def __init__(self, scene: RuntimeScene, chunk: int = 256):
        self.scene = scene
        self.chunk = chunk

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        o, d = check_rays(origins, directions)
        n = o.shape[0]
        t_best = np.full(n, np.inf)
        prim = np.full(n, -1, np.int32)
        u_best = np.zeros(n)
        v_best = np.zeros(n)
        p = self.scene.tri_p
        if p.shape[0] == 0:
            return Hits(t_best, prim, u_best, v_best)
        p0, e1, e2 = p[:, 0], p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
        for s in range(0, n, self.chunk):
            oo, dd = o[s:s + self.chunk, None, :], d[s:s + self.chunk, None, :]
            pvec = np.cross(dd, e2[None])
            det = np.einsum("ijk,jk->ij", pvec, e1)
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / det
                tvec = oo - p0[None]
                u = np.einsum("ijk,ijk->ij", tvec, pvec) * inv
                qvec = np.cross(tvec, e1[None])
                v = np.einsum("ijk,ijk->ij", np.broadcast_to(dd, qvec.shape), qvec) * inv
                t = np.einsum("ijk,jk->ij", qvec, e2) * inv
                ok = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & np.isfinite(t)
            t = np.where(ok, t, np.inf)
            j = np.argmin(t, axis=1)
            rows = np.arange(t.shape[0])
            tb = t[rows, j]
            hit = np.isfinite(tb)
            sl = slice(s, s + t.shape[0])
            t_best[sl] = tb
            prim[sl] = np.where(hit, j, -1)
            u_best[sl] = np.where(hit, u[rows, j], 0.0)
            v_best[sl] = np.where(hit, v[rows, j], 0.0)
        return Hits(t_best, prim, u_best, v_best)

    def occluded(self, origins: np.ndarray, directions: np.ndarray, tmax: np.ndarray) -> np.ndarray:
        h = self.intersect(origins, directions)
        return h.t < np.asarray(tmax, dtype=np.float64)

    def intersect_local(self, o32: np.ndarray, d32: np.ndarray, serial: bool | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        o = o32.astype(np.float64) + self.scene.center
        d = d32.astype(np.float64)
        h = self.intersect(o, d / np.linalg.norm(d, axis=1, keepdims=True))
        return h.prim, h.u.astype(np.float32), h.v.astype(np.float32)

    def occluded_local(self, o32: np.ndarray, d32: np.ndarray, tmax32: np.ndarray, serial: bool | None = None
                       ) -> np.ndarray:
        o = o32.astype(np.float64) + self.scene.center
        d = d32.astype(np.float64)
        return self.occluded(o, d / np.linalg.norm(d, axis=1, keepdims=True), tmax32.astype(np.float64))


def make_caster(scene: RuntimeScene, backend: str = "embree") -> RayCaster:
    """``backend``: 'embree' (production) or 'reference' (tests)."""
    if backend == "embree":
        return EmbreeCaster(scene)
    if backend == "reference":
        return ReferenceCaster(scene)
    raise InvalidInputError(f"unknown ray casting backend {backend!r} (expected 'embree' or 'reference')")


# ----------------------------------------------------------------------------- all hits


def all_hits(caster: RayCaster, origins: np.ndarray, directions: np.ndarray,
             max_hits: int = MAX_LAYERS_DEFAULT) -> AllHits:
    """Every surface crossing along each ray (for layered depth images).

    Re-casts past each hit from a spawn offset across the hit triangle's plane;
    ``t`` is measured from the ORIGINAL origin in float64 so it doesn't drift. A
    re-hit of the same surface within a few offsets (a ray through a shared edge
    of a concave fold) is not recorded twice. Rays with more than ``max_hits``
    crossings are cut off and flagged in ``truncated`` (bounded memory).
    """
    o0, d = check_rays(origins, directions)
    if max_hits < 1:
        raise InvalidInputError("max_hits must be >= 1")
    scene = caster.scene
    n = o0.shape[0]
    idx_all, t_all, prim_all, u_all, v_all = [], [], [], [], []
    active = np.arange(n)
    cur_o = o0.copy()
    last_t = np.full(n, -np.inf)
    count = np.zeros(n, dtype=np.int64)
    truncated = np.zeros(n, dtype=np.bool_)
    guard = 0
    while active.size:
        guard += 1
        h = caster.intersect(cur_o[active], d[active])
        ok = h.prim >= 0
        active, prim, u, v = active[ok], h.prim[ok], h.u[ok], h.v[ok]
        if not active.size:
            break
        hp = hit_points(scene, Hits(h.t[ok], prim, u, v))
        t_tot = np.einsum("ij,ij->i", hp - o0[active], d[active])
        mag = offset_magnitudes(scene, hp)
        fresh = t_tot > last_t[active] + 4.0 * mag
        rec = active[fresh]
        idx_all.append(rec)
        t_all.append(t_tot[fresh])
        prim_all.append(prim[fresh])
        u_all.append(u[fresh])
        v_all.append(v[fresh])
        last_t[rec] = t_tot[fresh]
        count[rec] += 1
        full = count[active] >= max_hits
        truncated[active[full]] = True
        keep = ~full
        active = active[keep]
        ng = scene.tri_ng[prim[keep]]
        cur_o[active] = spawn_origins(scene, hp[keep], ng, d[active])
        if guard > 4 * max_hits + 16:  # cannot happen unless offsets fail to advance; never spin
            truncated[active] = True
            break
    if idx_all:
        idx = np.concatenate(idx_all)
        order = np.lexsort((np.concatenate(t_all), idx))
        idx = idx[order]
        t = np.concatenate(t_all)[order]
        prim_c = np.concatenate(prim_all)[order].astype(np.int32)
        u_c = np.concatenate(u_all)[order]
        v_c = np.concatenate(v_all)[order]
    else:
        idx = np.zeros(0, np.int64)
        t, prim_c, u_c, v_c = np.zeros(0), np.zeros(0, np.int32), np.zeros(0), np.zeros(0)
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(idx, minlength=n), out=offsets[1:])
    return AllHits(offsets, t, prim_c, u_c, v_c, truncated)
