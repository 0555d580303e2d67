"""How an LDC view's error varies from view to view, and whether anything the renderer knows cheaply
predicts it: the evidence behind the per-scene (not per-view) LDC error model of quality contracts
(``docs/accuracy/contracts.md``, *Why the LDC error is planned per scene*).

Per scene: the LDC bake of ``bench/contracts.py`` (LDC 64, the scene's indirect light, a light field
when its materials need one), then views of 64 px turned from -20 to +20 degrees in 2-degree steps
around the calibration's pivot (the probes' +-8 and +-16 and the held-out views' +-4, +-12, +-20
among them). Per view: a ground truth of two 256-spp halves, rendered as the calibration renders it
(their spread is its noise, removed in quadrature), and each LDC method at one sample per pixel and
at 2 x 2 and 4 x 4 edge supersampling. Printed per view: the errors and the one-sample image's edge
pixels (the pixels edge antialiasing supersamples, ``counts["edge_pixels"]``); per setting: the
spread over views, the correlation of the squared error with the edge fraction, and, for error
targets from 5 % to 20 %, the fraction of views on which that setting meets the target (a planner
that must meet 95 % of contracts cannot promise a target that fewer than 95 % of views meet, unless
it can tell those views apart); and the correlation of one view's errors across the settings.

``python -m bench.ldc_view_spread --scene mirror_box --methods ldc+ibrt:1,ldc+llf`` (prints; writes
nothing; ``--json PATH`` keeps the rows).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bench.contracts import _setup
from engine.metrics import lrms
from engine.reference import ReferenceParams
from workers.jobs.calibrate import probe_reference_params, turned_camera, view_pivot

ANGLES = tuple(float(a) for a in range(-20, 21, 2))
SUPERSAMPLE = (1, 2, 4)
TARGETS = (0.05, 0.075, 0.10, 0.14, 0.20)
INDIRECT_BOUNCES = 3
"""The bake's and the calibration's bounces in ``bench/contracts.py``."""


def measure(scene: str, methods: list[str], truth_spp: int, log: Callable[[str], None]) -> list[dict[str, Any]]:
    sc, cam0, ren, ref, _bake_s = _setup(scene, 64, log)
    pivot = view_pivot(cam0, *sc.bounds)
    base = ReferenceParams()
    gi = ren.plan.indirect_skip == ""

    def rp(spp: int, seed: int) -> ReferenceParams:
        return probe_reference_params(spp, gi, INDIRECT_BOUNCES, seed)

    rows = []
    for deg in ANGLES:
        t0 = time.perf_counter()
        cam = turned_camera(cam0, deg, 64, pivot)
        h1 = ref.render(cam, rp(truth_spp // 2, 1001)).radiance
        h2 = ref.render(cam, rp(truth_spp // 2, 2002)).radiance
        aov = ref.render(cam, ReferenceParams(spp=1, max_depth=0))
        mask = ref.error_region(cam, aov.object_id, aov.depth, base.max_depth)
        noise = lrms(h1, h2, mask) / 2.0
        truth = 0.5 * (h1 + h2)
        row: dict[str, Any] = {"deg": deg, "truth_noise": noise}
        for m in methods:
            for s in SUPERSAMPLE:
                out = ren.render(cam, m, supersample=s, antialias="edges")
                e = lrms(out.radiance, truth, mask)
                row[f"{m}@{s}"] = math.sqrt(max(e * e - noise * noise, 0.0))
                if s > 1:
                    row["edge_fraction"] = out.counts["edge_pixels"] / (cam.width * cam.height)
        log(f"{deg:+5.0f} deg  edge fraction {row['edge_fraction']:.3f}  " + "  ".join(
            f"{m}@{s} {100 * row[f'{m}@{s}']:5.1f} %" for m in methods for s in SUPERSAMPLE)
            + f"  ({time.perf_counter() - t0:.1f} s)")
        rows.append(row)
    return rows


def summarize(rows: list[dict[str, Any]], methods: list[str], log: Callable[[str], None]) -> None:
    f = np.array([r["edge_fraction"] for r in rows])
    for m in methods:
        errs = {s: np.array([r[f"{m}@{s}"] for r in rows]) for s in SUPERSAMPLE}
        for s, e in errs.items():
            meets = "  ".join(f"{100 * t:g} %: {np.mean(e <= t):.0%}" for t in TARGETS)
            log(f"{m}@{s}: error {100 * e.min():.1f}-{100 * e.max():.1f} % (median {100 * np.median(e):.1f}), "
                f"corr(edge fraction, error^2) {np.corrcoef(f, e * e)[0, 1]:+.2f}; views meeting {meets}")
        c = {(a, b): np.corrcoef(errs[a], errs[b])[0, 1] for a, b in ((1, 2), (2, 4), (1, 4))}
        log(f"{m}: corr of a view's errors across settings: " +
            ", ".join(f"{a}x{a} vs {b}x{b} {v:+.2f}" for (a, b), v in c.items()))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="cornell_box")
    ap.add_argument("--methods", default="ldc", help="comma-separated LDC methods the bake serves")
    ap.add_argument("--truth-spp", type=int, default=512, help="the ground truth's spp (two halves)")
    ap.add_argument("--json", type=Path, help="keep the per-view rows here")
    args = ap.parse_args(argv)
    methods = args.methods.split(",")

    def log(msg: str) -> None:
        print(msg, flush=True)

    rows = measure(args.scene, methods, args.truth_spp, log)
    summarize(rows, methods, log)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
