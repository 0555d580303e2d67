"""Indirect diffuse light of LDC samples: per-sample path tracing to a requested noise level.

The LDC's ``diffuse`` holds the view-independent radiance of each sample side. Direct light,
ambient and emission are computed in closed form or on a fixed light-sample grid
(``engine/newviews/ldc.py``); this module adds the indirect part, the light that reaches the
sample after one or more bounces (interreflection, colour bleeding), the part that makes
rendering expensive and that a bake pays for once:

    L_ind(x, side) = kd/pi * integral over the side's hemisphere of L(x, w) cos(theta) dw

where L(x, w) is the radiance arriving from direction w after at least one bounce. It is
estimated exactly as the reference renderer estimates it at a camera hit
(``ReferenceRenderer.trace_diffuse_paths``): cosine-distributed paths with next-event estimation
at every vertex, mirror and glossy lobes followed where paths meet them, up to ``bounces``
diffuse vertices. A view rendered from the LDC thus shows the light of the reference renderer
with ``indirect_bounces = bounces``, without paying for it per view.

Sampling (per sample side, deterministic, unbiased; ``sampling``, the rule and why fixed is the
default in ``engine/newviews/indirect_sampling.py``):

- paths come in rounds of ``round_paths``; path j of a sample side is sample j of its own
  pixel of an Owen-scrambled Sobol sequence (``engine/sampler.py``), so every round, and every
  union of rounds, is a stratified set of directions; the spread of the round means (batch means)
  gives the standard error of the side's mean luminance;
- ``fixed``: every side that receives light traces the same count, sized from ``noise``;
- ``adaptive``: a pilot of ``min_paths`` paths (8 rounds by default: with fewer, the spread of the
  round means is itself so noisy that sizing on it picks the sides whose error it underestimates;
  measured on a two-wall room, two seeds differ by more than 3 estimated standard errors on 5.2 % of
  the sides with 2 rounds of 16 paths and on none with 8 rounds of 8) sizes the estimate:
  ``SIZE_MARGIN`` times the rounds that bring the pilot's standard error to ``noise`` times the
  side's brightness (direct + indirect, never less than ``floor`` times the axis's mean direct
  brightness, so that dark samples do not take ``max_paths`` for light nobody sees), at least as
  many as the pilot's (or what ``max_paths`` leaves), pilot and estimate together at most
  ``max_paths``. The estimate is a fresh set of paths from an independent sequence, and the pilot's
  paths are not part of it. A side that stopped on its own paths would be biased wherever the
  integrand is heavy-tailed: paths that reach the light through a mirror or glossy surface are rare
  and bright, and a side whose first paths missed them looks converged and stops low. Measured on
  the mirror / glossy Cornell box (the back wall's indirect light against the reference's
  ``shade_hits`` with 256 paths per point): 6.4 % low with stopping on the same paths at
  ``min_paths`` 64, 4.0 % low at 256, 0.8 % high (noise) at a fixed 1024; on the plain Cornell box
  0.3 % low. With ``min_paths`` = ``max_paths`` nothing is sized, and those paths are the estimate;
- every decision depends only on the side's own paths and on the axis's mean, so the result
  is the same whatever the batching or the split of an axis into chunks.

Each sample side's estimated standard error and path count are returned (and summarised as
the achieved noise level), so a bake reports what it reached, not only what it was asked.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from engine.caustics import caustic_map
from engine.errors import InvalidInputError
from engine.metrics import REC709_WEIGHTS
from engine.newviews.indirect_sampling import SAMPLINGS, fixed_paths
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.sampler import derive_key, sample_key

_LUMA = np.asarray(REC709_WEIGHTS, dtype=np.float64)

MAX_RAYS_PER_BATCH = 1 << 20
"""Paths traced in one wavefront batch (bounds the bake's working memory to a few hundred MiB)."""

SIZE_MARGIN = 1.25
"""The estimate traces this many times the rounds the pilot's spread asks for: the pilot's standard
error (from 8 round means) is itself uncertain by ~27 %, and sized without a margin about half
the sides would end above their target; with it most end below (test_indirect.py checks 80 % at
1 % noise), for 25 % more paths."""

_ESTIMATE_DIM = 0x5EED
"""The estimate's paths draw from ``derive_key(key, _ESTIMATE_DIM, 0)``, a sequence independent of
the pilot's (``key``), so the number of rounds the pilot sets says nothing about their values."""

CAUSTICS = ("photons", "paths")
"""How the indirect pass finds caustic light (``IndirectParams.caustics``)."""

_STREAM = 3
"""The sampler stream of indirect paths (the reference renderer's camera paths use 0, its
``shade_hits`` 1): sample_key(seed, _STREAM, axis)."""


@dataclass(frozen=True)
class IndirectParams:
    """Settings of the indirect-light bake.

    sampling: ``fixed`` (every side the count ``fixed_paths`` sizes from ``noise``) or
        ``adaptive`` (a pilot per side sizes its own estimate); ``engine/newviews/indirect_sampling.py``.
    noise: the noise level asked for, e.g. 0.02. ``fixed``: sizes the count,
        ``(FIXED_PATHS_SCALE / noise)^2`` paths; ``adaptive``: the target relative standard error of
        each sample side's radiance (luminance), 0.02 = 2 % of its brightness.
    min_paths: the fewest paths a side traces (a multiple of ``round_paths``, at least two rounds,
        since the error is estimated from the spread of round means); ``adaptive``: the pilot's
        paths per side, which size its estimate, and the estimate traces at least as many again.
    max_paths: the most paths any side traces (the bake's cost bound; ``adaptive``: pilot and
        estimate together); equal to ``min_paths``: that count, no pilot, in either sampler.
    bounces: diffuse vertices per path (1 = one bounce of light, the colour bleeding; more =
        interreflection of higher order). Mirror and glossy lobes met on the way do not count.
    round_paths: paths per side per round, a power of two (a stratified block of the sequence).
    floor: the brightness the noise is measured against is never less than this fraction of
        the axis's mean direct brightness.
    seed: sampler seed; equal seeds give identical bakes.
    area_light_samples / max_depth: light sampling and mirror / glossy depth at path vertices,
        as in ``engine.reference.ReferenceParams``.
    stride: trace every ``stride``-th LDI pixel in each direction and interpolate the samples in
        between on the same surface (``engine.newviews.sparse_indirect``); 1 traces every sample.
    caustics: how light that reaches a diffuse surface through mirror / glossy lobes (a caustic)
        is found: ``photons`` (a caustic photon map, engine/caustics.py; only in scenes that have
        caustics, rect lights and mirror / glossy surfaces) or ``paths`` (by the paths alone).
    caustic_photons: photons aimed at the scene's mirror / glossy surfaces.
    caustic_radius: the photon kernel's radius, a fraction of the scene's diagonal.
    """

    noise: float = 0.02
    sampling: str = "fixed"
    min_paths: int = 64
    max_paths: int = 1024
    bounces: int = 3
    round_paths: int = 8
    floor: float = 0.25
    seed: int = 0
    area_light_samples: int = 4
    max_depth: int = 4
    stride: int = 1
    caustics: str = "photons"
    caustic_photons: int = 1 << 20
    caustic_radius: float = 0.01

    RANGES = {"noise": (0.001, 0.5), "min_paths": (2, 65536), "max_paths": (2, 65536), "bounces": (1, 16),
              "round_paths": (1, 256), "floor": (0.0, 1.0), "area_light_samples": (1, 1024), "max_depth": (0, 16),
              "stride": (1, 8), "caustic_photons": (1024, 1 << 26), "caustic_radius": (0.0005, 0.1)}

    def __post_init__(self) -> None:
        for name, (lo, hi) in self.RANGES.items():
            v = getattr(self, name)
            is_int = isinstance(lo, int)
            ok = (isinstance(v, (int, np.integer)) and not isinstance(v, bool)) if is_int else \
                (isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v))
            if not ok or not lo <= v <= hi:
                kind = "an integer" if is_int else "a number"
                raise InvalidInputError(f"indirect {name} must be {kind} in [{lo}, {hi}], got {v!r}")
        r = self.round_paths
        if r & (r - 1):
            raise InvalidInputError(f"indirect round_paths must be a power of two, got {r}")
        if self.min_paths % r or self.min_paths < 2 * r:
            raise InvalidInputError(f"indirect min_paths must be a multiple of round_paths ({r}) and at least "
                                    f"{2 * r}, got {self.min_paths}")
        if self.max_paths < self.min_paths:
            raise InvalidInputError(f"indirect max_paths ({self.max_paths}) must be at least min_paths "
                                    f"({self.min_paths})")
        if self.caustics not in CAUSTICS:
            raise InvalidInputError(f"indirect caustics must be one of {', '.join(CAUSTICS)}, got {self.caustics!r}")
        if self.sampling not in SAMPLINGS:
            raise InvalidInputError(f"indirect sampling must be one of {', '.join(SAMPLINGS)}, got {self.sampling!r}")

    @property
    def adaptive(self) -> bool:
        """Does a pilot size each side's estimate? (``adaptive`` with room above the pilot.)"""
        return self.sampling == "adaptive" and self.max_paths > self.min_paths

    @property
    def paths_per_side(self) -> int:
        """Paths every traced side takes when nothing is sized (``min_paths`` for the adaptive
        sampler's pilot)."""
        if self.sampling == "fixed":
            return fixed_paths(self.noise, self.min_paths, self.max_paths, self.round_paths)
        return self.min_paths

    def to_dict(self) -> dict:
        return asdict(self)

    def reference_params(self) -> ReferenceParams:
        return ReferenceParams(area_light_samples=self.area_light_samples, max_depth=self.max_depth,
                               indirect_bounces=self.bounces, seed=self.seed)


@dataclass(frozen=True)
class IndirectResult:
    """Indirect diffuse radiance of a run of LDC samples (``first`` .. ``first + n - 1`` of an axis).

    radiance (n, 2, 3) float32 per side; stderr (n, 2) float32 estimated standard error of each
    side's luminance (0 where no path was traced); paths (n, 2) int32 paths traced per side;
    stats: timings and a summary of the achieved noise level (``summarize``)."""

    first: int
    radiance: np.ndarray
    stderr: np.ndarray
    paths: np.ndarray
    stats: dict = field(default_factory=dict)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays for storage; ``stats`` without its wall-clock times (``content_stats``), so
        the same chunk computed twice stores the same bytes."""
        return {"first": np.int64(self.first), "radiance": self.radiance, "stderr": self.stderr,
                "paths": self.paths, "stats": np.array(json.dumps(content_stats(self.stats), sort_keys=True))}

    @classmethod
    def from_arrays(cls, d) -> IndirectResult:
        try:
            r = cls(first=int(np.asarray(d["first"])), radiance=np.ascontiguousarray(d["radiance"], np.float32),
                    stderr=np.ascontiguousarray(d["stderr"], np.float32),
                    paths=np.ascontiguousarray(d["paths"], np.int32),
                    stats=json.loads(str(np.asarray(d["stats"]))))
        except KeyError as e:
            raise InvalidInputError(f"stored indirect chunk lacks array {e.args[0]!r}") from None
        n = r.radiance.shape[0]
        if r.radiance.shape != (n, 2, 3) or r.stderr.shape != (n, 2) or r.paths.shape != (n, 2) or r.first < 0:
            raise InvalidInputError("stored indirect chunk arrays don't match each other")
        return r


def side_frames(ng: np.ndarray, ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Geometric and shading normals of both sides, (n, 2, 3) each: side 0 is the side the
    geometric normal points to, side 1 the other; a shading normal on the wrong side of its
    geometric one falls back to it (the reference renderer's convention)."""
    g = np.stack([ng, -ng], axis=1).astype(np.float64)
    s = np.stack([ns, -ns], axis=1).astype(np.float64)
    bad = np.einsum("nsk,nsk->ns", s, g) <= 0.0
    s[bad] = g[bad]
    return np.ascontiguousarray(g), np.ascontiguousarray(s)


def axis_brightness(base: np.ndarray, receives: np.ndarray) -> float:
    """Mean luminance of the direct (base) radiance over the sample sides that receive indirect
    light: the yardstick of the noise floor, computed once per LDC axis."""
    y = base.reshape(-1, 3).astype(np.float64) @ _LUMA
    sel = np.repeat(receives, 2)
    return float(y[sel].mean()) if sel.any() else 0.0


def trace_indirect(renderer: ReferenceRenderer, p: np.ndarray, ng: np.ndarray, ns: np.ndarray, mat: np.ndarray,
                   base: np.ndarray, params: IndirectParams, *, stream_id: int, first: int = 0,
                   brightness: float | None = None,
                   progress: Callable[[float], None] | None = None) -> IndirectResult:
    """Indirect diffuse radiance of both sides of samples ``first .. first + n - 1`` of one LDC axis.

    ``p`` (n, 3) float64 points, ``ng`` / ``ns`` (n, 3) geometric / shading normals as baked
    (unflipped), ``mat`` (n,) material ids, ``base`` (n, 2, 3) the direct + ambient + emission
    radiance of each side (the noise test's brightness). ``stream_id`` names the axis (its own
    sampler stream); ``brightness`` the axis's ``axis_brightness`` (computed from ``base`` when
    None, which is only right when the samples are the whole axis). ``progress(fraction)`` after
    every round; it may raise to cancel."""
    n = int(p.shape[0])
    if base.shape != (n, 2, 3) or ng.shape != (n, 3) or ns.shape != (n, 3) or mat.shape != (n,):
        raise InvalidInputError("trace_indirect: p, ng, ns, mat and base must describe the same samples")
    if brightness is None:
        brightness = axis_brightness(base, np.any(renderer.scene.materials.kd[mat] > 0.0, axis=1))
    g2, s2 = side_frames(ng, ns)
    # sample side i, s is point 2 i + s, pixel 2 (first + i) + s of the axis's sampler stream
    res = trace_indirect_points(renderer, np.repeat(np.ascontiguousarray(p, np.float64), 2, axis=0),
                                g2.reshape(-1, 3), s2.reshape(-1, 3), np.repeat(mat, 2), base.reshape(-1, 3),
                                params, key=sample_key(params.seed, _STREAM, int(stream_id)), pixel_base=2 * first,
                                brightness=brightness, progress=progress)
    return IndirectResult(first=int(first), radiance=res.radiance.reshape(n, 2, 3),
                          stderr=res.stderr.reshape(n, 2), paths=res.paths.reshape(n, 2), stats=res.stats)


@dataclass(frozen=True)
class PointsIndirect:
    """``trace_indirect_points``' result: radiance (m, 3) float32, stderr (m,) float32, paths (m,)
    int32, stats (``summarize`` plus time, rounds, ray counts, stage times)."""

    radiance: np.ndarray
    stderr: np.ndarray
    paths: np.ndarray
    stats: dict


def trace_indirect_points(renderer: ReferenceRenderer, p: np.ndarray, g: np.ndarray, s: np.ndarray,
                          mat: np.ndarray, base: np.ndarray, params: IndirectParams, *, key: np.uint64,
                          pixel_base: int = 0, brightness: float,
                          progress: Callable[[float], None] | None = None) -> PointsIndirect:
    """Indirect diffuse radiance leaving m surface points, each on one given side, to the noise target.

    ``p`` (m, 3) points; ``g`` / ``s`` (m, 3) geometric / shading normal of the side to shade (unit,
    ``s`` on ``g``'s side); ``mat`` (m,); ``base`` (m, 3) the point's other radiance (its share of
    the brightness the noise is measured against); ``brightness`` the mean brightness the floor is a
    fraction of. Point j draws its paths as pixel ``pixel_base + j`` of the sampler stream ``key``,
    so a point's result depends only on (key, its pixel, its own data, brightness): split the
    points over calls or jobs with matching ``pixel_base`` and the results are identical.
    Points whose material has kd = 0 receive nothing and trace nothing. With ``caustics`` =
    ``photons`` in a scene with caustics, the caustic light comes from the renderer's photon map
    (``engine.caustics.caustic_map``): at the points themselves by its kernel estimate, added to
    the paths' mean (its noise is not in ``stderr``), and at the paths' vertices by its cells."""
    t_start = time.perf_counter()
    m_pts = int(p.shape[0])
    if g.shape != (m_pts, 3) or s.shape != (m_pts, 3) or mat.shape != (m_pts,) or base.shape != (m_pts, 3):
        raise InvalidInputError("trace_indirect_points: p, g, s, mat and base must describe the same points")
    p64 = np.ascontiguousarray(p, dtype=np.float64)
    g64 = np.ascontiguousarray(g, dtype=np.float64)
    s64 = np.ascontiguousarray(s, dtype=np.float64)
    mat = np.ascontiguousarray(mat, dtype=np.int32)
    y_base = base.astype(np.float64) @ _LUMA
    receives = np.any(renderer.scene.materials.kd[mat] > 0.0, axis=1) if m_pts else np.zeros(0, np.bool_)
    r_paths = params.round_paths
    max_rounds = params.max_paths // r_paths
    first_rounds = params.paths_per_side // r_paths  # the fixed count (the estimate) or the adaptive pilot
    rparams = params.reference_params()
    timings: dict[str, float] = {}
    counts: dict[str, int] = {}
    floor = params.floor * brightness
    per_batch = max(1, MAX_RAYS_PER_BATCH // r_paths)
    cmap = None
    if params.caustics == "photons" and np.any(receives):
        t_map = time.perf_counter()
        cmap = caustic_map(renderer, params.caustic_photons, params.caustic_radius, params.max_depth, params.seed)
        timings["caustic_map"] = time.perf_counter() - t_map
    adaptive = params.adaptive
    first_pass = np.where(receives, first_rounds, 0).astype(np.int64)
    expected = int(first_pass.sum()) * (2 if adaptive else 1)  # for progress; refined after the pilot
    done_rounds = 0

    def trace_rounds(k: np.uint64, want: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``want[j]`` rounds of point j under key ``k``: (sum of round means RGB, of their
        luminance, of its square, rounds traced)."""
        nonlocal done_rounds
        total = np.zeros((m_pts, 3))
        s1 = np.zeros(m_pts)
        s2sq = np.zeros(m_pts)
        rounds = np.zeros(m_pts, np.int64)
        acc = np.zeros((m_pts, 3))
        active = np.flatnonzero(want > 0)
        while active.size:
            for b in range(0, active.size, per_batch):
                ids = active[b:b + per_batch]
                rows = np.repeat(ids, r_paths)
                sidx = rounds[rows] * r_paths + np.tile(np.arange(r_paths, dtype=np.int64), ids.size)
                renderer.trace_diffuse_paths(p64[rows], g64[rows], s64[rows], mat[rows], rows + pixel_base, sidx, k,
                                             params.bounces, acc, pix_base=pixel_base, params=rparams,
                                             timings=timings, counts=counts, caustics=cmap)
            m = acc[active] / r_paths
            acc[active] = 0.0
            total[active] += m
            y = m @ _LUMA
            s1[active] += y
            s2sq[active] += y * y
            rounds[active] += 1
            done_rounds += active.size
            active = active[rounds[active] < want[active]]
            if progress is not None:
                progress(min(1.0, done_rounds / max(1, expected)))
        return total, s1, s2sq, rounds

    n_rounds = first_rounds
    total, s1, s2sq, rounds = trace_rounds(key, first_pass)
    spent = rounds.copy()
    if adaptive:
        # The pilot only sizes the estimate (see the module docstring, "Sampling and stopping"): rounds
        # for the side's noise target at the pilot's spread, se ~ 1 / sqrt(rounds).
        k_p = np.maximum(rounds, 1)
        se = np.where(rounds > 1, _stderr(s1, s2sq, k_p), 0.0)
        tol = params.noise * np.maximum(y_base + s1 / k_p, floor)
        with np.errstate(divide="ignore", invalid="ignore"):
            need = np.ceil(SIZE_MARGIN * first_rounds * np.where(tol > 0, (se / np.where(tol > 0, tol, 1.0)) ** 2, 0.0))
        lo = min(first_rounds, max_rounds - first_rounds)
        fresh = np.where(receives, np.clip(need, lo, max_rounds - first_rounds), 0).astype(np.int64)
        expected = done_rounds + int(fresh.sum())
        total, s1, s2sq, rounds = trace_rounds(derive_key(key, _ESTIMATE_DIM, 0), fresh)
        spent += rounds
        n_rounds += int(fresh.max(initial=0))
    k_all = np.maximum(rounds, 1)
    radiance = total / k_all[:, None]
    if cmap is not None:
        t_c = time.perf_counter()
        lit = np.flatnonzero(receives)
        radiance[lit] += renderer.scene.materials.kd[mat[lit]] / np.pi * cmap.irradiance(p64[lit], g64[lit])
        timings["caustic_lookup"] = time.perf_counter() - t_c
    if not np.all(np.isfinite(radiance)):
        raise InvalidInputError("indirect bake produced non-finite radiance")
    stderr = np.where(rounds > 1, _stderr(s1, s2sq, k_all), 0.0)
    paths = (spent * r_paths).astype(np.int32)
    rel = stderr / np.maximum(y_base + s1 / k_all, max(floor, 1e-300))
    traced = spent > 0
    stats = summarize(rel[traced], paths[traced], params)
    stats.update(time=time.perf_counter() - t_start, rounds=n_rounds,
                 rays={k2: int(v) for k2, v in counts.items()},
                 stages={k2: float(v) for k2, v in timings.items()}, brightness=float(brightness),
                 caustics=_caustic_stats(cmap, params))
    return PointsIndirect(radiance=radiance.astype(np.float32), stderr=stderr.astype(np.float32), paths=paths,
                          stats=stats)


def _caustic_stats(cmap, params: IndirectParams) -> dict:
    """What found the caustic light: ``paths``, or the photon map's counts (no times: stored chunks
    keep this)."""
    if cmap is None:
        return {"method": "paths"}
    return {"method": "photons", "photons": cmap.stats["photons"], "stored": cmap.stats["stored"],
            "radius": params.caustic_radius}


def _stderr(s1: np.ndarray, s2sq: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Standard error of the mean of k round means from their sum and sum of squares (batch means)."""
    mean = s1 / k
    var = np.maximum(s2sq / k - mean * mean, 0.0) * k / np.maximum(k - 1, 1)
    return np.sqrt(var / k)


def summarize(rel: np.ndarray, paths: np.ndarray, params: IndirectParams) -> dict:
    """Achieved noise level of traced sample sides: relative standard error (median, p95, max),
    the fraction that met ``params.noise``, and path counts (total, mean, max)."""
    if rel.size == 0:
        return {"sides": 0, "sampling": params.sampling, "noise_target": params.noise,
                "rel_stderr_median": 0.0, "rel_stderr_p95": 0.0,
                "rel_stderr_max": 0.0, "met_target": 1.0, "paths_total": 0, "paths_mean": 0.0, "paths_max": 0}
    return {"sides": int(rel.size), "sampling": params.sampling, "noise_target": params.noise,
            "rel_stderr_median": float(np.median(rel)), "rel_stderr_p95": float(np.percentile(rel, 95)),
            "rel_stderr_max": float(rel.max()), "met_target": float(np.mean(rel <= params.noise * (1 + 1e-9))),
            "paths_total": int(paths.sum()), "paths_mean": float(paths.mean()), "paths_max": int(paths.max())}


WALL_CLOCK_STATS = ("time", "stages")
"""The entries of an indirect pass's ``stats`` that measure wall-clock time (seconds): they differ
from one run to the next, so stored bytes leave them out (they live in job results instead)."""


def content_stats(stats: dict) -> dict:
    """``stats`` without its wall-clock entries: what a stored chunk keeps."""
    return {k: v for k, v in stats.items() if k not in WALL_CLOCK_STATS}


def _time_of(parts: list[dict]) -> dict:
    """``{"time": total}`` when the parts carry times (freshly computed), else nothing (loaded)."""
    return {"time": float(sum(s["time"] for s in parts if "time" in s))} if any("time" in s for s in parts) else {}


def merge_summaries(parts: list[dict], params: IndirectParams) -> dict:
    """One summary for several chunks' ``stats`` (weighted by their sample sides; p95 and median
    are the sides-weighted means of the chunks', an approximation stated in the key name). The
    total ``time`` only when the chunks carry theirs (not when they were loaded from the store)."""
    live = [s for s in parts if s.get("sides", 0)]
    sides = sum(s["sides"] for s in live)
    if not sides:
        return summarize(np.zeros(0), np.zeros(0, np.int64), params) | _time_of(parts)
    w = [s["sides"] / sides for s in live]

    def weighted(name: str) -> float:
        return float(sum(wi * s[name] for wi, s in zip(w, live, strict=True)))

    return {"sides": sides, "sampling": params.sampling, "noise_target": params.noise,
            "rel_stderr_median_of_chunks": weighted("rel_stderr_median"),
            "rel_stderr_p95_of_chunks": weighted("rel_stderr_p95"),
            "rel_stderr_max": float(max(s["rel_stderr_max"] for s in live)),
            "met_target": weighted("met_target"),
            "paths_total": int(sum(s["paths_total"] for s in live)),
            "paths_mean": float(sum(s["paths_total"] for s in live) / sides),
            "paths_max": int(max(s["paths_max"] for s in live)),
            **_time_of(parts)}
