"""Time and samples of the progressive, adaptive reference render to reach an error, against uniform sampling.

The Cornell box sample scene (``samples/scenes/cornell_box.json``) at ``--res`` pixels with path
tracing (one path of ``BOUNCES`` bounces and one rect-light sample per camera sample), LRMS over
the error region (``ReferenceRenderer.error_region``: the pixels the progressive render estimates its
error over, and every contract and benchmark measures on) against the mean of two
``--truth-spp`` renders of other seeds; the ground truth's own noise (``lrms(a, b) / 2``) is taken
out of every measured error in quadrature (the errors are independent).

- uniform: plain renders at each of ``--spp``, error, wall and CPU time; the samples and time a target
  needs are interpolated in log-log between the two spp that bracket it;
- adaptive: ``max_error`` = each target (``spp`` cap ``--cap``), over ``--seeds`` seeds: the
  estimated error, the true error, mean samples per pixel, passes, wall and CPU time (medians);
- time budgets: ``max_ms`` alone, the estimated and true error of what it returns.

All renders run after a warm-up, one at a time, on a renderer whose BVH is built. ``--write``
puts the tables into docs/reference-renderer.md.

    flock /tmp/bench.lock python -m bench.progressive_reference --write
"""

from __future__ import annotations

import argparse
import math
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from engine import REFERENCE_VERSION
from engine.memory import keep_freed_memory
from engine.metrics import lrms
from engine.reference import ReferenceParams, ReferenceRenderer

BOUNCES = 4  # as bench/reference_sampling.py and bench/mitsuba_crosscheck.py (Mitsuba path max_depth 6)
DOC = Path(__file__).resolve().parent.parent / "docs" / "reference-renderer.md"


def _params(n: int, seed: int, **kw: float) -> ReferenceParams:
    return ReferenceParams(spp=n, max_depth=0, area_light_samples=1, indirect_samples=n, indirect_bounces=BOUNCES,
                           seed=seed, **kw)  # type: ignore[arg-type]


def _interp(target: float, xs: list[float], errs: list[float]) -> tuple[float, bool]:
    """x at which the error curve (xs, errs) reaches ``target`` (log-log, piecewise linear); True
    when extrapolated past the curve's ends."""
    lx, le, lt = np.log(xs), np.log(errs), math.log(target)
    for k in range(len(xs) - 1):
        if le[k + 1] <= lt <= le[k]:
            t = (lt - le[k]) / (le[k + 1] - le[k])
            return float(math.exp(lx[k] + t * (lx[k + 1] - lx[k]))), False
    k = 0 if lt > le[0] else len(xs) - 2
    slope = (le[k + 1] - le[k]) / (lx[k + 1] - lx[k])
    return float(math.exp(lx[k] + (lt - le[k]) / slope)), True


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", default="8,16,32,64,128,256,512,1024")
    ap.add_argument("--targets", default="0.05,0.02,0.01")
    ap.add_argument("--budgets", default="500,2000,8000", help="max_ms of the time-budget renders")
    ap.add_argument("--cap", type=int, default=4096)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--truth-spp", type=int, default=2048, help="per render; two renders are averaged")
    ap.add_argument("--cache", default="/tmp/ibr_progressive_reference", help="ground truths are kept here")
    ap.add_argument("--write", action="store_true", help="write the tables into docs/reference-renderer.md")
    a = ap.parse_args(argv)
    keep_freed_memory()  # renders are timed as a render worker runs them (its malloc policy, engine.memory)

    import samples
    from api_schemas.scene import load_scene_file
    from bench.docs_writer import replace_block
    from workers.scene_loader import directory_resolver, load_scene

    ls = load_scene(load_scene_file(samples.sample_path("cornell_box")), directory_resolver(samples.SAMPLES_DIR))
    cam = replace(ls.camera, width=a.res, height=a.res)
    ren = ReferenceRenderer(ls.runtime)
    load0 = os.getloadavg()[0]
    Path(a.cache).mkdir(parents=True, exist_ok=True)
    f = Path(a.cache) / f"truth_{a.res}_{a.truth_spp}_{BOUNCES}_{REFERENCE_VERSION}.npz"
    if f.exists():
        z = np.load(f)
        ta, tb = z["a"], z["b"]
    else:
        t0 = time.perf_counter()
        ta = ren.render(cam, _params(a.truth_spp, 1000)).radiance
        tb = ren.render(cam, _params(a.truth_spp, 1001)).radiance
        np.savez(f, a=ta, b=tb)
        print(f"ground truth 2 x {a.truth_spp} spp in {time.perf_counter() - t0:.0f} s")
    truth = 0.5 * (ta.astype(np.float64) + tb.astype(np.float64))
    aov = ren.render(cam, _params(1, 0))
    region = ren.error_region(cam, aov.object_id, aov.depth, 0)
    e_truth = lrms(ta, tb, region) / 2.0

    def true_err(img: np.ndarray) -> float:
        return math.sqrt(max(lrms(img, truth, region) ** 2 - e_truth ** 2, 1e-30))

    ren.render(cam, _params(8, 0))  # warm-up: kernels loaded, BVH built
    ren.render(cam, _params(8, 0, max_error=0.2))

    spps = [int(x) for x in a.spp.split(",")]
    u_err, u_sec, u_cpu = [], [], []
    for n in spps:
        t0, c0 = time.perf_counter(), time.process_time()
        img = ren.render(cam, _params(n, 7)).radiance
        u_sec.append(time.perf_counter() - t0)
        u_cpu.append(time.process_time() - c0)
        u_err.append(true_err(img))
        print(f"uniform {n:5d} spp: {100 * u_err[-1]:.2f} % in {u_sec[-1]:.2f} s ({u_cpu[-1]:.2f} CPU s)",
              flush=True)

    rows = []
    for x in (float(t) for t in a.targets.split(",")):
        runs = []
        for s in range(a.seeds):
            t0, c0 = time.perf_counter(), time.process_time()
            out = ren.render(cam, _params(a.cap, s, max_error=x))
            sec, cpu = time.perf_counter() - t0, time.process_time() - c0
            rep = out.adaptive
            assert rep is not None
            runs.append((rep["estimated_error"], true_err(out.radiance), rep["spp_mean"], rep["passes"], sec, cpu,
                         rep["stop_reason"]))
            print(f"adaptive {x:.3f} seed {s}: est {100 * runs[-1][0]:.2f} % true {100 * runs[-1][1]:.2f} % "
                  f"spp {runs[-1][2]:.1f} passes {runs[-1][3]} {sec:.2f} s ({cpu:.2f} CPU s) ({runs[-1][6]})",
                  flush=True)
        med = np.median(np.array([r[:6] for r in runs]), axis=0)
        u_spp, ex1 = _interp(x, spps, u_err)
        u_s, ex2 = _interp(x, u_sec, u_err)
        u_c, _ = _interp(x, u_cpu, u_err)
        rows.append((x, u_spp, u_s, u_c, ex1 or ex2, *med))

    budget_rows = []
    for ms in (float(b) for b in a.budgets.split(",")):
        t0 = time.perf_counter()
        out = ren.render(cam, _params(a.cap, 0, max_ms=ms))
        sec = time.perf_counter() - t0
        rep = out.adaptive
        assert rep is not None
        budget_rows.append((ms, rep["elapsed_ms"], 1000 * sec, rep["estimated_error"], true_err(out.radiance),
                            rep["spp_mean"], rep["passes"], rep["stop_reason"]))
    load1 = os.getloadavg()[0]

    head = (f"Cornell box sample scene, {a.res} x {a.res}, path tracing ({BOUNCES} bounces, one path and one "
            f"rect-light sample per camera sample), LRMS over the error region ({int(region.sum())} of "
            f"{region.size} pixels) against 2 x {a.truth_spp} spp "
            f"(its own noise, {100 * e_truth:.2f} %, taken out in quadrature); adaptive: medians of {a.seeds} "
            f"seeds, cap {a.cap} spp; wall-clock seconds on 2 cores, load {load0:.1f} at the start and "
            f"{load1:.1f} at the end; `~`: uniform extrapolated past {spps[-1]} spp.")
    lines = [head, "",
             "| target | uniform spp | uniform s (CPU s) | adaptive spp (mean) | adaptive s (CPU s) | passes | "
             "estimated | true | samples uniform / adaptive | time uniform / adaptive (CPU) |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for x, u_spp, u_s, u_c, extra, est, tru, spp_m, passes, sec, cpu in rows:
        m = "~" if extra else ""
        lines.append(f"| {100 * x:g} % | {m}{u_spp:.0f} | {m}{u_s:.2f} ({m}{u_c:.1f}) | {spp_m:.0f} | {sec:.2f} "
                     f"({cpu:.1f}) | {passes:.0f} | {100 * est:.2f} % | {100 * tru:.2f} % | {m}{u_spp / spp_m:.2f}x | "
                     f"{m}{u_s / sec:.2f}x ({m}{u_c / cpu:.2f}x) |")
    lines += ["", "Time budgets (`max_ms` alone, seed 0):", "",
              "| max_ms | render ms (reported) | wall ms | estimated | true | spp (mean) | passes | stopped by |",
              "|---:|---:|---:|---:|---:|---:|---:|---|"]
    for ms, rep_ms, wall, est, tru, spp_m, passes, why in budget_rows:
        lines.append(f"| {ms:.0f} | {rep_ms:.0f} | {wall:.0f} | {100 * est:.2f} % | {100 * tru:.2f} % | "
                     f"{spp_m:.0f} | {passes} | {why} |")
    lines += ["", "Reproduce with", "", "    flock /tmp/bench.lock python -m bench.progressive_reference --write"]
    text = "\n".join(lines)
    print()
    print(text)
    if a.write:
        replace_block(DOC, "progressive", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
