"""Progressive, adaptive reference rendering: passes of samples until an estimated error or a
time budget is reached, with more samples where the image is noisy.

``ReferenceRenderer.render`` (engine/reference.py) comes here when ``ReferenceParams.max_error``
or ``max_ms`` is set; ``spp`` is then the cap on any pixel's samples. This module plans and
estimates; the renderer traces the samples of each pass (``run_progressive``'s ``render_rows``).
docs/reference-renderer.md describes the mode and its measured costs.

Two half buffers. Every pixel q owns two independent sample sequences of the engine's sampler
(engine/sampler.py): half A is the pixel's own sequence (the samples a plain render takes, in the
same order), half B the sequence of the virtual pixel q + w h, whose scrambles are independent of
A's. A pass gives a pixel the same number of new samples in both halves, continuing each sequence
where it stopped (sample indices keep counting). The pixel's value is the mean of all its
samples, ``(S_A + S_B) / n`` with ``n`` samples in all, and since A and B are independent
estimates of the same integral with ``n/2`` samples each,

    v_q = (Y_A - Y_B)^2 / 4        (Y_A, Y_B: the halves' mean luminance)

is an unbiased estimate of the variance of the pixel's mean luminance, whatever its samples'
distribution and however well stratified each half is (the estimate of a stratified sequence's
variance from its own samples would not be). Independent halves cost a little against one
sequence of ``n``: the two halves are not stratified against each other.

Image error. The estimated LRMS against the converged image (the metric of engine/metrics.py,
RMS of the luminance difference over the mean luminance) over the pixels R an error is measured
on (``ReferenceRenderer.error_region``: covered, not next to an emitter, directly or in a mirror; the
whole image when R is empty) is

    E = sqrt(mean_{q in R} v_q) / mean_{q in R} Y_q.

Its square's numerator is unbiased for the expected squared error; on images of a few thousand
pixels and more E is within a few per cent of the truth (tests/engine/test_progressive.py
measures it against high-spp renders). Measured over the whole image instead, a Cornell box view
asked for 1 % came out at 2.6 % on R: the luminaire's 2 % of the pixels nearly tripled the mean,
and its outline's noise drew pixels up to the cap while the walls kept 8 samples.

Allocation (Cycles-style adaptive sampling, planned for the image's error rather than a
per-pixel threshold). With per-sample standard deviations sigma_q, the allocation minimising
the image's error for a given total is ``n_q`` proportional to ``sigma_q``, and the total that
meets an error ``x`` is ``(sum sigma)^2 / (P (x Y)^2)`` for the P pixels of R, of mean luminance
Y. Each pass plans for ``AIM`` x ``max_error`` (the plan is made from noisy estimates), gives
every pixel at most ``GROWTH`` times its samples (so estimates refresh before much is spent), at
least ``MIN_PASS`` of the samples taken so far in all, and never more than ``spp``. Without an
error target, each pass doubles the total, distributed the same way. Pixels outside R (an
emitter and its outline, the background) are sampled by the same rule from their own noise, but
never aimed past the mean count R's pixels are aimed at: a noise-free sky takes no samples, and a
luminaire's outline as many as an average pixel of R, not the budget.

No bias from the allocation. A pixel's samples are never used to decide how many samples the
pixel gets: ``sigma_q^2`` is the mean of ``v_r n_r`` over the 8 neighbours r of q (the pixel
itself and pixels outside R left out), so a pixel's sample count is independent of its own sample values, and the mean
of a prefix of a scrambled Sobol sequence whose length does not depend on its values is unbiased.
What remains is second order: the stopping rule reads the image error, to which one pixel
contributes 1/P of the sum, and a neighbour's sample count (which depends on this pixel's values)
changes only the precision of that neighbour's estimate, not its expectation.
(One exception: when no neighbour of any unfinished pixel is noisy but the image's error is still
above the target, the pixels with their own non-zero variance are doubled; isolated noise is
rare.) tests/engine/test_progressive.py checks that means over seeds converge to closed forms.

Stopping, after every pass: ``error`` when E <= max_error; ``spp_cap`` when no pixel that could
still improve has room below the cap; ``time`` when the budget is spent, or when the next pass,
cut to the time left (``TIME_SHARE`` of what the budget leaves after the estimate that follows the
pass, at the last pass's measured seconds per sample), would add fewer than ``MIN_PASS`` of the
samples taken so far. The first
pass always runs (``FIRST_PASS`` samples per half), so a budget shorter than it is overrun, and
reported. A render that cannot reach its error within its limits returns its best image with
``target_met`` False and the estimated error it has.

Determinism: a render stopped by its error or by the cap is bit-for-bit deterministic for its
seed (any number of pipelines and chunks). A time budget is not: where the budget cuts the render
depends on the machine's speed and load, so with ``max_ms`` set the image is deterministic only
when the budget never cut a pass short.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from engine.errors import NonFiniteOutputError
from engine.metrics import REC709_WEIGHTS

__all__ = ["AIM", "FIRST_PASS", "GROWTH", "MIN_PASS", "STOP_REASONS", "TIME_SHARE", "AdaptiveReport", "LightPass",
           "RenderRows", "estimate_error", "pass_pieces", "run_progressive"]

FIRST_PASS = 4
"""Samples per half buffer in the first pass (8 per pixel; fewer when the cap is lower)."""
AIM = 0.9
"""Each pass is planned for AIM x max_error."""
GROWTH = 2.0
"""A pass at most multiplies a pixel's samples by this."""
MIN_PASS = 0.125
"""A pass adds at least this fraction of the samples taken so far (no long tail of tiny passes)."""
TIME_SHARE = 0.8
"""Under a time budget a pass is planned to take at most this share of the time left, at the pass
before's cost per sample: later passes sample the noisier pixels, whose samples cost up to 18 %
more than the pass before's (the Cornell box at 64 px, ``bench.contracts``' held-out views, where
passes planned to end within the budget at that cost ended up to 3.6 % past it)."""
STOP_REASONS = ("error", "time", "spp_cap")
_LUM = np.asarray(REC709_WEIGHTS, np.float64)


@dataclass(frozen=True)
class AdaptiveReport:
    """How a progressive render ended.

    estimated_error: estimated LRMS of the image against the converged one;
    target_met: ``estimated_error <= max_error`` (None without an error target);
    stop_reason: ``error`` (the target is met), ``time`` (the budget is spent) or ``spp_cap``
        (every pixel that could still improve has ``spp`` samples);
    passes: rounds of samples taken; spp_mean / spp_min / spp_max: samples per pixel (both halves);
    spp_cap: the cap (the request's ``spp``, rounded down to even); samples: camera samples in all;
    elapsed_ms: render time, from the start of the render to the image; region_pixels: the pixels
    the error is estimated over (``ReferenceRenderer.error_region``)."""

    estimated_error: float
    target_met: bool | None
    stop_reason: str
    passes: int
    spp_mean: float
    spp_min: int
    spp_max: int
    spp_cap: int
    samples: int
    max_error: float | None
    max_ms: float | None
    elapsed_ms: float
    region_pixels: int

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def estimate_error(sum_a: np.ndarray, sum_b: np.ndarray, n_half: np.ndarray,
                   region: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """(E, v): the estimated LRMS against the converged image over the pixels ``region`` (P,) bool
    (None or none set: every pixel) and the estimated variance of each pixel's mean luminance,
    from the half buffers' sums ``sum_a``, ``sum_b`` (P, 3) of ``n_half`` (P,) samples each (>= 1)."""
    nh = n_half.astype(np.float64)
    ya = (sum_a @ _LUM) / nh
    yb = (sum_b @ _LUM) / nh
    v = 0.25 * (ya - yb) ** 2
    sel = slice(None) if region is None or not np.any(region) else region
    y = float(np.mean(0.5 * (ya + yb)[sel]))
    num = math.sqrt(float(np.mean(v[sel])))
    if y <= 0.0:
        return (0.0 if num == 0.0 else math.inf), v
    return num / y, v


def _ring_mean(x: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Mean of each pixel's (up to 8) neighbours in the (h, w) image x that are ``inside`` (h, w)
    bool, the pixel itself left out; where none is, the mean of x over the pixels inside (over
    every pixel when none is)."""
    h, w = x.shape
    wgt = inside.astype(np.float64)
    fallback = float(np.mean(x[inside])) if np.any(inside) else float(np.mean(x))
    p = np.pad(x * wgt, 1)
    c = np.pad(wgt, 1)
    s = np.zeros_like(x)
    k = np.zeros_like(x)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            if dy == 1 and dx == 1:
                continue
            s += p[dy:dy + h, dx:dx + w]
            k += c[dy:dy + h, dx:dx + w]
    return np.where(k > 0, s / np.maximum(k, 1.0), fallback)


def _plan(n_half: np.ndarray, v: np.ndarray, shape: tuple[int, int], cap_half: int, max_error: float | None,
          y_mean: float, region: np.ndarray) -> np.ndarray:
    """New samples per half buffer for every pixel in the next pass (all zero: nothing left to do);
    planned for the error over ``region`` (P,) bool (the module docstring, *Allocation*)."""
    n = 2.0 * n_half
    room = cap_half - n_half
    vn = (v * n).reshape(shape)
    inside = region.reshape(shape)
    partial = not bool(region.all())
    # a pixel's noise is read from its neighbours of its own kind (in or out of the region)
    sigma2 = _ring_mean(vn, inside).ravel()
    if partial:
        sigma2 = np.where(region, sigma2, _ring_mean(vn, ~inside).ravel())
    sigma = np.sqrt(sigma2)
    total_sigma = float(sigma[region].sum())
    add = np.zeros_like(n_half)
    if total_sigma > 0.0:
        if max_error is not None and y_mean > 0.0:
            want = sigma * total_sigma / (int(region.sum()) * (AIM * max_error * y_mean) ** 2)
        else:
            want = sigma * 2.0 * float(n[region].sum()) / total_sigma
        target = np.minimum(np.maximum(want, n), GROWTH * n)
        if partial:
            cap_out = np.maximum(float(np.mean(target[region])), n)
            target = np.where(region, target, np.minimum(target, cap_out))
        add = np.minimum(np.ceil((target - n) / 2.0).astype(np.int64), room)
    if add.sum() == 0:
        # no neighbour of an unfinished pixel is noisy: double the pixels that are
        add = np.where((v > 0.0) & (room > 0) & region, np.minimum(n_half, room), 0)
    low = int(math.ceil(MIN_PASS * float(n_half.sum())))
    if 0 < add.sum() < low:
        add = np.minimum(np.ceil(add * (low / add.sum())).astype(np.int64), room)
    return add


def pass_pieces(cnt: np.ndarray, npix: int, chunk_pixels: int, spp: int, pipelines: int) -> list[tuple[int, int]]:
    """Split a pass's rows (``cnt`` samples each) into pieces of about the plain render's rays per
    chunk (``chunk_pixels`` pixels, ``spp`` samples) and at most a quarter of the pass per
    pipeline: ``[(first row, end row), ...]``. A row is never split, so every accumulator row is
    written by one piece, in ray order: the image does not depend on the split or the threads."""
    total = int(cnt.sum())
    chunk_px = max(1, min(chunk_pixels, max(1024, -(-npix // 8))))
    budget = max(1, min(chunk_px * spp, -(-total // (4 * pipelines))))
    offset = np.cumsum(cnt) - cnt
    cuts = np.flatnonzero(np.diff(offset // budget)) + 1
    return [(int(a), int(b)) for a, b in zip(np.r_[0, cuts], np.r_[cuts, cnt.size], strict=True) if b > a]


LightPass = Callable[[int], tuple[np.ndarray, np.ndarray]]
"""``light_pass(samples)``: light paths for a pass of ``samples`` camera samples traced; returns the
light-traced part of every pixel (P, 3) as half A's and half B's independent estimates."""

RenderRows = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, Callable[[], None]], None]
"""``render_rows(rid, start, cnt, acc, tick)``: samples ``start[a] .. start[a] + cnt[a] - 1`` of
each virtual pixel ``rid[a]`` added to ``acc[rid]``; ``tick()`` between pieces (it may raise to
cancel)."""


def run_progressive(render_rows: RenderRows, width: int, height: int, spp: int, max_error: float | None,
                    max_ms: float | None, t_start: float, add_time: Callable[[str, float], None],
                    progress: Callable[[float, str], None] | None = None,
                    region: np.ndarray | None = None,
                    light_pass: LightPass | None = None) -> tuple[np.ndarray, AdaptiveReport]:
    """The passes of a progressive render (see the module docstring) of a ``width`` x ``height``
    image with at most ``spp`` samples per pixel, until ``max_error`` (estimated LRMS over
    ``region`` (h, w) bool, ``ReferenceRenderer.error_region``; None or empty: the whole image) or
    ``max_ms`` after ``t_start`` (``time.perf_counter()``) is reached, or every pixel that could
    improve is at the cap. Returns the radiance (h, w, 3) float64 and the report;
    ``add_time(stage, seconds)`` collects the estimate's time. The renderer
    (``engine.reference.ReferenceRenderer``) supplies ``render_rows``, and ``light_pass`` where part
    of the image is light-traced (engine/light_tracing.py): called after each pass's rows with the
    pass's camera samples, it traces light paths in proportion and returns the light-traced part of
    each pixel as two independent estimates, (half A, half B), each added to its half buffer's mean."""
    h, w = height, width
    npix = w * h
    if region is None or not np.any(region):
        region = np.ones(npix, np.bool_)
    region = np.asarray(region, np.bool_).reshape(-1)
    if region.size != npix:
        raise ValueError(f"region has {region.size} pixels, the image {npix}")
    cap_half = spp // 2
    deadline = None if max_ms is None else t_start + max_ms / 1000.0
    acc = np.zeros((2 * npix, 3))  # rows 0..P-1: half A's sums, P..2P-1: half B's
    n_half = np.zeros(npix, np.int64)
    add = np.full(npix, min(FIRST_PASS, cap_half), np.int64)
    passes = 0
    err = math.inf
    first_err: float | None = None
    per_sample = 0.0
    shown = [0.0]

    def report(frac: float) -> None:
        shown[0] = max(shown[0], min(0.99, frac))
        if progress is not None:
            progress(shown[0], "render")

    def fraction() -> float:
        f = 0.0
        if max_error is not None and first_err is not None and math.isfinite(err) and first_err > max_error:
            f = math.log(first_err / max(err, 1e-300)) / math.log(first_err / max_error)
        if max_ms is not None:
            f = max(f, (time.perf_counter() - t_start) / (max_ms / 1000.0))
        f = max(f, float(n_half.sum()) / (cap_half * npix))
        return min(max(f, 0.0), 0.99)

    while True:
        rows = np.flatnonzero(add)
        rid = np.concatenate([rows, rows + npix])
        start = np.concatenate([n_half[rows], n_half[rows]])
        cnt = np.concatenate([add[rows], add[rows]])
        t0 = time.perf_counter()
        render_rows(rid, start, cnt, acc, lambda: report(shown[0]))
        if light_pass is not None:
            light_a, light_b = light_pass(int(cnt.sum()))
        # seconds per sample of the last pass: later passes sample the noisy (costlier) pixels
        t_pass_end = time.perf_counter()
        per_sample = (t_pass_end - t0) / max(1, int(cnt.sum()))
        n_half += add
        passes += 1
        t0 = t_pass_end
        bad = ~np.isfinite(acc)
        if np.any(bad):  # before any estimate or plan reads it
            raise NonFiniteOutputError(f"reference render produced {int(bad.sum())} non-finite values")
        sums = acc
        if light_pass is not None:  # each half's light-traced estimate, as sums of its samples
            sums = acc + np.concatenate([light_a, light_b]) * np.tile(n_half, 2)[:, None]
            if not np.all(np.isfinite(sums)):
                raise NonFiniteOutputError("light tracing produced non-finite values")
        err, v = estimate_error(sums[:npix], sums[npix:], n_half, region)
        if first_err is None:
            first_err = err
        add_time("estimate", time.perf_counter() - t0)
        report(fraction())
        if max_error is not None and err <= max_error:
            reason = "error"
            break
        if deadline is not None and time.perf_counter() >= deadline:
            reason = "time"
            break
        y_mean = float(np.mean(((sums[:npix] + sums[npix:]) @ _LUM / (2.0 * n_half))[region]))
        add = _plan(n_half, v, (h, w), cap_half, max_error, y_mean, region)
        if add.sum() == 0:
            reason = "spp_cap"
            break
        if deadline is not None:
            now = time.perf_counter()
            # the estimate and the plan follow the next pass too, so its time is what is left after them
            left = TIME_SHARE * (deadline - now - (now - t_pass_end))
            need = per_sample * 2.0 * float(add.sum())
            if need > left:
                add = np.floor(add * max(0.0, left / need)).astype(np.int64)
                if add.sum() < MIN_PASS * float(n_half.sum()):  # a tail of tiny passes, each with its fixed cost
                    reason = "time"
                    break

    radiance = ((sums[:npix] + sums[npix:]) / (2.0 * n_half)[:, None]).reshape(h, w, 3)
    spp_px = 2 * n_half
    rep = AdaptiveReport(
        estimated_error=float(err), target_met=None if max_error is None else bool(err <= max_error),
        stop_reason=reason, passes=passes, spp_mean=float(spp_px.mean()), spp_min=int(spp_px.min()),
        spp_max=int(spp_px.max()), spp_cap=2 * cap_half, samples=int(spp_px.sum()), max_error=max_error,
        max_ms=max_ms, elapsed_ms=1000.0 * (time.perf_counter() - t_start), region_pixels=int(region.sum()))
    return radiance, rep
