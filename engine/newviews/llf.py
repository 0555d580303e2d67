"""Layered light field (LLF): the view-dependent half of the first paper (docs/algorithms.md part A).

**Directions.** ``octahedron_directions(f)`` gives the ``4 f^2 + 2`` vertices of an octahedron
whose faces are subdivided with frequency ``f`` (66, 258, 1026 for f = 4, 8, 16): the integer
points ``(a, b, c)`` with ``|a| + |b| + |c| = f``. They are put on the sphere with the
*equal-area* octahedral map (Clarberg 2008) rather than by normalising ``(a, b, c)``: with
``r = (|a| + |b|) / f``, ``z = sign(c) (1 - r^2)``, ``sin(theta) = r sqrt(2 - r^2)`` and the
azimuth inside the quadrant ``(pi / 2) |b| / (|a| + |b|)``. Every lattice point then stands
for the same solid angle (up to the cells' shape), so the gather needs no per-direction area
weights; normalising instead would leave directions near the octahedron's face centres ~5x
sparser (in solid angle) than near its vertices. Order: a ascending, b ascending, then
``+c`` before ``-c``. The inverse map takes any direction to continuous lattice coordinates
(``direction_to_lattice``), so the directions near a given one are found in a small window
of the lattice (``candidate_directions``), without a search over all n.

**Views.** ``LLFView`` ``index`` = a parallel-projection LDI (``engine/newviews/ldi.py``) whose rays
travel along ``direction`` (= the frame's ``w``); its square frame (``resolution`` x
``resolution``) is perpendicular to the direction and covers the scene's bounding sphere
(centre and half-diagonal of the bounds) plus one pixel on every side. ``radiance`` (n, 3)
float32 is, per sample, the radiance leaving the sample toward ``-direction`` (back along
the view's rays, toward its reference plane), i.e. what a viewer looking along
``direction`` sees at that layer. So the radiance ARRIVING at a point p from direction d
(light travelling along -d) is read in the view whose direction is d, at the first sample
beyond p along its pixel rays (``engine/newviews/view_pass.py``).

**Radiance = the reference renderer.** Every sample is shaded by
``ReferenceRenderer.shade_hits`` as if it were the first hit of a camera ray travelling
along ``direction``: emission + kd ambient, direct light from every light with shadow rays
(diffuse + energy-normalised Phong highlight), rect lights on the g x g jittered grid of
``area_light_samples``, ideal-mirror recursion and glossy reflection (``glossy_samples``
lobe samples at the first glossy bounce, one after) up to ``max_depth``, and path-traced
indirect light when ``indirect_samples`` > 0. Surfaces are two-sided: the side the view's
ray arrives on. ``spp`` is ignored (one chain per sample, at the sample itself).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import InvalidInputError
from engine.newviews.ldi import DEFAULT_MAX_BYTES, LDI, LDIFrame, build_ldi, estimate_ldi_bytes
from engine.raycast import RayCaster
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.scene import RuntimeScene

MAX_FREQUENCY = 64  # 16,386 directions
MAX_LLF_RESOLUTION = 1024
LLF_SAMPLE_BYTES = 20 + 12  # LDI sample + float32 RGB radiance


def llf_direction_count(f: int) -> int:
    """Number of LLF directions for octahedron frequency ``f``: ``4 f^2 + 2``."""
    _check_f(f)
    return 4 * int(f) * int(f) + 2


def _check_f(f) -> None:
    if not isinstance(f, (int, np.integer)) or isinstance(f, bool) or not (1 <= f <= MAX_FREQUENCY):
        raise InvalidInputError(f"LLF frequency f must be an integer in [1, {MAX_FREQUENCY}], got {f!r}")


def _lattice(f: int) -> np.ndarray:
    """(4 f^2 + 2, 3) int64 lattice points |a| + |b| + |c| = f in the canonical order."""
    pts = []
    for a in range(-f, f + 1):
        for b in range(-(f - abs(a)), f - abs(a) + 1):
            c = f - abs(a) - abs(b)
            pts.append((a, b, c))
            if c > 0:
                pts.append((a, b, -c))
    return np.asarray(pts, dtype=np.int64)


def _lattice_to_dirs(lat: np.ndarray, f: int) -> np.ndarray:
    a = lat[:, 0].astype(np.float64)
    b = lat[:, 1].astype(np.float64)
    c = lat[:, 2]
    s = np.abs(a) + np.abs(b)
    r = s / f
    z = np.sign(c) * (1.0 - r * r)
    sin_t = r * np.sqrt(np.maximum(2.0 - r * r, 0.0))
    phi = 0.5 * np.pi * np.abs(b) / np.where(s > 0, s, 1.0)
    x = np.sign(a) * sin_t * np.cos(phi)
    y = np.sign(b) * sin_t * np.sin(phi)
    d = np.column_stack([x, y, z])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def octahedron_directions(f: int) -> np.ndarray:
    """(4 f^2 + 2, 3) float64 unit directions (equal-area subdivided octahedron, see module doc)."""
    _check_f(f)
    return _lattice_to_dirs(_lattice(int(f)), int(f))


def lattice_index_table(f: int) -> np.ndarray:
    """(2f + 1, 2f + 1, 2) int64: direction index of lattice point (a, b, +-c) at [a + f, b + f,
    0 for c >= 0 / 1 for c < 0]; -1 where |a| + |b| > f. Equator points (c = 0) fill both."""
    _check_f(f)
    lat = _lattice(int(f))
    tab = np.full((2 * f + 1, 2 * f + 1, 2), -1, np.int64)
    for i, (a, b, c) in enumerate(lat):
        if c >= 0:
            tab[a + f, b + f, 0] = i
        if c <= 0:
            tab[a + f, b + f, 1] = i
    return tab


@nb.njit(cache=True, nogil=True, error_model="numpy")
def direction_to_lattice(dx, dy, dz, f):
    """Continuous lattice coordinates (A, B) and hemisphere (0: z >= 0, 1: z < 0) of a unit direction."""
    az = abs(dz)
    if az > 1.0:
        az = 1.0
    r = math.sqrt(1.0 - az)
    phi = math.atan2(abs(dy), abs(dx))
    t = phi / (0.5 * math.pi)
    sa = 1.0 if dx >= 0.0 else -1.0
    sb = 1.0 if dy >= 0.0 else -1.0
    return sa * f * r * (1.0 - t), sb * f * r * t, 0 if dz >= 0.0 else 1


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def candidate_directions(dx, dy, dz, f, radius, table, out):
    """Write the indices of the directions in a (2 radius) x (2 radius) lattice window around
    direction (dx, dy, dz), both hemispheres, into ``out``; returns how many. Every direction
    within an angle of about ``(radius - 1) / f`` radians is in the window (the inverse map
    moves lattice coordinates by at most ~f per radian)."""
    A, B, _ = direction_to_lattice(dx, dy, dz, f)
    a0 = int(math.floor(A))
    b0 = int(math.floor(B))
    n = 0
    for a in range(max(a0 - radius + 1, -f), min(a0 + radius, f) + 1):
        rem = f - abs(a)
        for b in range(max(b0 - radius + 1, -rem), min(b0 + radius, rem) + 1):
            i0 = table[a + f, b + f, 0]
            out[n] = i0
            n += 1
            i1 = table[a + f, b + f, 1]
            if i1 != i0:
                out[n] = i1
                n += 1
    return n


def direction_spacing(f: int) -> float:
    """Typical angle (radians) between neighbouring directions: sqrt(4 pi / n)."""
    return math.sqrt(4.0 * math.pi / llf_direction_count(f))


# ----------------------------------------------------------------------------- views


def view_frame(scene: RuntimeScene, direction: np.ndarray, resolution: int) -> LDIFrame:
    """Square parallel-projection frame looking along ``direction`` that covers the scene's
    bounding sphere (centre and half-diagonal of the bounds) plus one pixel on every side."""
    w = np.asarray(direction, dtype=np.float64).reshape(3)
    w = w / np.linalg.norm(w)
    e = np.zeros(3)
    e[int(np.argmin(np.abs(w)))] = 1.0
    u = np.cross(w, e)
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    lo, hi = scene.bounds
    c = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    if not radius > 0:
        radius = max(scene.extent, 1e-6)
    h = 2.0 * radius / max(resolution - 2, 1)
    half = radius + h
    origin = c - half * (u + v) - half * w
    return LDIFrame(origin=origin, u=u, v=v, w=w, h=h, nu=int(resolution), nv=int(resolution))


@dataclass(frozen=True)
class LLFView:
    """One LLF direction: ``ldi`` along ``direction`` (its frame's w) and ``radiance`` (n, 3)
    float32 leaving each sample toward ``-direction`` (see module docstring)."""

    index: int
    direction: np.ndarray
    ldi: LDI
    radiance: np.ndarray
    timings: dict = field(default_factory=dict)

    @property
    def n_samples(self) -> int:
        return self.ldi.n_samples

    @property
    def nbytes(self) -> int:
        return int(self.ldi.nbytes + self.radiance.nbytes)

    def to_arrays(self) -> dict[str, np.ndarray]:
        out = self.ldi.to_arrays("ldi_")
        out.update(index=np.int64(self.index), direction=np.asarray(self.direction, np.float64),
                   radiance=self.radiance)
        return out

    @classmethod
    def from_arrays(cls, d) -> LLFView:
        ldi = LDI.from_arrays(d, "ldi_")
        try:
            view = cls(index=int(np.asarray(d["index"])), direction=np.asarray(d["direction"], np.float64).reshape(3),
                       ldi=ldi, radiance=np.ascontiguousarray(d["radiance"], dtype=np.float32))
        except KeyError as e:
            raise InvalidInputError(f"stored LLF view lacks array {e.args[0]!r}") from None
        if view.radiance.shape != (ldi.n_samples, 3):
            raise InvalidInputError("stored LLF view: radiance does not match its sample count")
        return view


@dataclass(frozen=True)
class LLF:
    """All views of a layered light field, with packed arrays for the gather kernels:
    ``pk_offsets`` ((n_views * res^2 + 1,) int64, global sample index per pixel, pixel
    ``j * res^2 + k`` for view j), ``pk_depth`` float64, ``pk_radiance`` (N, 3) float32 and
    the frames as arrays (``pk_origin``, ``pk_u``, ``pk_v``, ``pk_w`` (n, 3), ``pk_h`` (n,))."""

    f: int
    resolution: int
    directions: np.ndarray
    views: tuple[LLFView, ...]
    params: dict
    pk_offsets: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]
    pk_depth: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]
    pk_radiance: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]
    pk_origin: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]
    pk_u: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]
    pk_v: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]
    pk_w: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]
    pk_h: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]
    table: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]

    @property
    def n_directions(self) -> int:
        return len(self.views)

    @property
    def n_samples(self) -> int:
        return int(self.pk_depth.shape[0])

    @property
    def spacing(self) -> float:
        return direction_spacing(self.f)

    @property
    def nbytes(self) -> int:
        return int(sum(v.nbytes for v in self.views) + self.pk_offsets.nbytes)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Small metadata only (views are stored on their own with ``LLFView.to_arrays``)."""
        import json

        return {"f": np.int64(self.f), "resolution": np.int64(self.resolution),
                "params": np.array(json.dumps(self.params))}

    @classmethod
    def from_arrays(cls, meta, views: Sequence[LLFView]) -> LLF:
        import json

        try:
            f = int(np.asarray(meta["f"]))
            res = int(np.asarray(meta["resolution"]))
            params = json.loads(str(np.asarray(meta["params"])))
        except KeyError as e:
            raise InvalidInputError(f"stored LLF metadata lacks {e.args[0]!r}") from None
        return merge_llf(f, res, views, params)


def _check_resolution(resolution) -> None:
    if not isinstance(resolution, (int, np.integer)) or isinstance(resolution, bool) or \
            not (4 <= resolution <= MAX_LLF_RESOLUTION):
        raise InvalidInputError(f"LLF resolution must be an integer in [4, {MAX_LLF_RESOLUTION}], got {resolution!r}")


def estimate_llf_bytes(f: int, resolution: int, max_layers: int = 32, n_views: int | None = None) -> int:
    """Worst-case bytes of ``n_views`` (default: all) LLF views (every pixel full to max_layers)."""
    n = llf_direction_count(f) if n_views is None else int(n_views)
    _check_resolution(resolution)
    return n * estimate_ldi_bytes(resolution * resolution, max_layers, LLF_SAMPLE_BYTES)


def bake_llf_views(scene: RuntimeScene, caster: RayCaster, f: int, resolution: int, indices: Sequence[int], *,
                   params: ReferenceParams | None = None, progress: Callable[[float], None] | None = None,
                   max_layers: int = 32, max_bytes: int = DEFAULT_MAX_BYTES,
                   renderer: ReferenceRenderer | None = None) -> list[LLFView]:
    """Bake the LLF views ``indices`` (any subset of ``range(4 f^2 + 2)``, so a bake can be
    split into chunks): one LDI per direction, every sample shaded by the reference renderer
    (``params``; see module docstring for what is included). ``progress(fraction)`` after
    each view and inside long shading runs. Refuses (InvalidInputError) when the worst case
    of the requested views exceeds ``max_bytes``."""
    _check_f(f)
    _check_resolution(resolution)
    if scene.n_triangles == 0:
        raise InvalidInputError("cannot bake an LLF of an empty scene")
    n = llf_direction_count(f)
    idx = [int(i) for i in indices]
    if any(not (0 <= i < n) for i in idx) or len(set(idx)) != len(idx):
        raise InvalidInputError(f"LLF direction indices must be distinct integers in [0, {n - 1}]")
    est = estimate_llf_bytes(f, resolution, max_layers, len(idx))
    if est > max_bytes:
        raise InvalidInputError(f"{len(idx)} LLF views of {resolution}x{resolution} x {max_layers} layers need up to "
                                f"{est / 2**20:.1f} MiB, over the limit of {max_bytes / 2**20:.1f} MiB; "
                                "lower the resolution or bake fewer directions per chunk")
    params = params or ReferenceParams()
    dirs = octahedron_directions(f)
    ren = renderer if renderer is not None else ReferenceRenderer(scene, caster)
    out = []
    for k, i in enumerate(idx):
        t0 = time.perf_counter()
        frame = view_frame(scene, dirs[i], resolution)
        ldi = build_ldi(caster, frame, max_layers=max_layers, max_bytes=max_bytes)
        t1 = time.perf_counter()

        def sub(frac: float, k=k) -> None:
            if progress is not None:
                progress((k + frac) / len(idx))

        d = np.broadcast_to(frame.w, (ldi.n_samples, 3))
        rad = ren.shade_hits(ldi.prim, ldi.u, ldi.v, d, params, stream_id=i, progress=sub)
        out.append(LLFView(index=i, direction=dirs[i].copy(), ldi=ldi, radiance=rad.astype(np.float32),
                           timings={"ldi": t1 - t0, "shade": time.perf_counter() - t1}))
        if progress is not None:
            progress((k + 1) / len(idx))
    return out


def merge_llf(f: int, resolution: int, views: Sequence[LLFView], params: dict) -> LLF:
    """Assemble baked views (any order, e.g. from several chunks) into an LLF; checks that
    every direction index is present once and that the views belong together."""
    _check_f(f)
    _check_resolution(resolution)
    n = llf_direction_count(f)
    by = {v.index: v for v in views}
    if len(views) != n or sorted(by) != list(range(n)):
        missing = sorted(set(range(n)) - set(by))
        raise InvalidInputError(f"merge_llf needs each of the {n} directions exactly once; got {len(views)} views, "
                                f"missing {missing[:10]}{'...' if len(missing) > 10 else ''}")
    dirs = octahedron_directions(f)
    ordered = tuple(by[i] for i in range(n))
    for v in ordered:
        fr = v.ldi.frame
        if fr.nu != resolution or fr.nv != resolution:
            raise InvalidInputError(f"LLF view {v.index} has resolution {fr.nu}x{fr.nv}, expected {resolution}")
        if float(np.dot(fr.w, dirs[v.index])) < 1.0 - 1e-9:
            raise InvalidInputError(f"LLF view {v.index} does not look along direction {v.index} of f={f}")
    npx = resolution * resolution
    counts = np.concatenate([np.diff(v.ldi.offsets) for v in ordered])
    pk_off = np.zeros(n * npx + 1, np.int64)
    np.cumsum(counts, out=pk_off[1:])
    depth = np.concatenate([v.ldi.depth for v in ordered]) if n else np.zeros(0)
    rad = np.concatenate([v.radiance for v in ordered]) if n else np.zeros((0, 3), np.float32)
    return LLF(f=int(f), resolution=int(resolution), directions=dirs, views=ordered, params=dict(params),
               pk_offsets=pk_off, pk_depth=np.ascontiguousarray(depth, np.float64),
               pk_radiance=np.ascontiguousarray(rad, np.float32),
               pk_origin=np.ascontiguousarray([v.ldi.frame.origin for v in ordered], np.float64),
               pk_u=np.ascontiguousarray([v.ldi.frame.u for v in ordered], np.float64),
               pk_v=np.ascontiguousarray([v.ldi.frame.v for v in ordered], np.float64),
               pk_w=np.ascontiguousarray([v.ldi.frame.w for v in ordered], np.float64),
               pk_h=np.ascontiguousarray([v.ldi.frame.h for v in ordered], np.float64),
               table=lattice_index_table(f))


def bake_llf(scene: RuntimeScene, caster: RayCaster, f: int, resolution: int, *,
             params: ReferenceParams | None = None, progress: Callable[[float], None] | None = None,
             max_layers: int = 32, max_bytes: int = DEFAULT_MAX_BYTES) -> LLF:
    """Bake every direction and merge (convenience for tests and benchmarks)."""
    params = params or ReferenceParams()
    views = bake_llf_views(scene, caster, f, resolution, range(llf_direction_count(f)), params=params,
                           progress=progress, max_layers=max_layers, max_bytes=max_bytes)
    return merge_llf(f, resolution, views, llf_params_dict(params, max_layers))


def llf_params_dict(params: ReferenceParams, max_layers: int = 32) -> dict:
    """The bake parameters recorded with an LLF."""
    d = params.to_dict()
    d["max_layers"] = int(max_layers)
    return d
