"""How much the reference's error at a few spp varies from seed to seed, on the calibration's probe
views and on the contracts benchmark's held-out views: the evidence behind the per-spp, seeded
error margins of quality contracts (``docs/quality-contracts.md``, *Safety margins*).

Per view (64 px, the probes turned +-8 and +-16 degrees, the held-out views +-4 and +-12, as in
``bench/contracts.py``): a ground truth of two 1024-spp halves (their spread is its noise, removed in
quadrature), then the reference at each of ``--spp`` with ``--seeds`` seeds, each rendered as the
calibration renders it (``workers.jobs.calibrate``: the scene's indirect light traced when it has
any). The model is ``engine.quality.fit_reference`` over the probes' renders of every seed; each
render's error over the model's is a ratio, and per view and spp the table gives seed 0's ratio (the
service's default seed), the median, the 90th percentile, the largest and the standard deviation
of the log ratio over seeds; per spp, the margin the calibration would get from the probes' ratios
with the first one and the first four seeds (``engine.quality.calibrated_margin``).

``python -m bench.seed_spread --scene mirror_box`` (prints; writes nothing).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from api_schemas import load_scene_file
from engine.metrics import lrms
from engine.newviews.effects import analyze
from engine.quality import calibrated_margin, fit_reference
from engine.reference import ReferenceParams, ReferenceRenderer
from samples import SAMPLES_DIR, sample_path
from workers.jobs.calibrate import turned_camera, view_pivot
from workers.scene_loader import directory_resolver, load_scene

PROBES_DEG = (8.0, -8.0, 16.0, -16.0)
HELD_OUT_DEG = (4.0, -4.0, 12.0, -12.0)
TRUTH_SPP = 1024


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="mirror_box")
    ap.add_argument("--seeds", type=int, default=24)
    ap.add_argument("--spp", default="1,2,4,8,16")
    ap.add_argument("--size", type=int, default=64)
    a = ap.parse_args(argv)
    spps = [int(s) for s in a.spp.split(",")]
    loaded = load_scene(load_scene_file(sample_path(a.scene)), directory_resolver(SAMPLES_DIR))
    sc = loaded.runtime
    ref = ReferenceRenderer(sc)
    gi = analyze(sc).indirect_skip == ""
    base = ReferenceParams()

    def params(spp: int, seed: int) -> ReferenceParams:
        return ReferenceParams(spp=spp, max_depth=base.max_depth, glossy_samples=base.glossy_samples,
                               area_light_samples=base.area_light_samples, indirect_samples=spp if gi else 0,
                               indirect_bounces=3 if gi else base.indirect_bounces, seed=seed)

    pivot = view_pivot(loaded.camera, *sc.bounds)
    errors: dict[float, dict[int, list[float]]] = {}
    t0 = time.perf_counter()
    for deg in PROBES_DEG + HELD_OUT_DEG:
        cam = turned_camera(loaded.camera, deg, a.size, pivot)
        h1, h2 = ref.render(cam, params(TRUTH_SPP // 2, 1001)), ref.render(cam, params(TRUTH_SPP // 2, 2002))
        truth = 0.5 * (h1.radiance + h2.radiance)
        mask = ref.error_region(cam, h1.object_id, h1.depth, base.max_depth)
        noise = lrms(h1.radiance, h2.radiance, mask) / 2.0
        errors[deg] = {}
        for spp in spps:
            errs = []
            for seed in range(a.seeds):
                e = lrms(ref.render(cam, params(spp, seed)).radiance, truth, mask)
                errs.append(math.sqrt(max(e * e - noise * noise, 0.0)))
            errors[deg][spp] = errs
        print(f"view {deg:+g} deg: {time.perf_counter() - t0:.0f} s", flush=True)
    points = [{"spp": s, "error": e, "pixels": 1, "ms": 1.0, "probe": i}
              for i, deg in enumerate(PROBES_DEG) for s in spps for e in errors[deg][s]]
    fit = fit_reference(points, 1 << 30)
    print(f"\n{a.scene}, {a.size} px, {a.seeds} seeds; model over the probes' renders: "
          f"{fit.error:.3f} s^-{fit.exponent:.2f}\n")
    print("| view | spp | seed 0 | median | p90 | max | sd log |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for deg, by in errors.items():
        kind = "probe" if deg in PROBES_DEG else "held out"
        for s, errs in by.items():
            r = np.asarray(errs) / fit.error_at(s)
            print(f"| {deg:+g} ({kind}) | {s} | {r[0]:.2f} | {np.median(r):.2f} | {np.quantile(r, 0.9):.2f} | "
                  f"{r.max():.2f} | {np.std(np.log(r)):.3f} |")
    print("\n| spp | margin, 1 seed per probe | margin, 4 seeds per probe |")
    print("|---:|---:|---:|")
    for s in spps:
        ratios = [[e / fit.error_at(s) for e in errors[deg][s]] for deg in PROBES_DEG]
        print(f"| {s} | {calibrated_margin([r[0] for r in ratios], len(PROBES_DEG)):.2f} | "
              f"{calibrated_margin([x for r in ratios for x in r[:4]], len(PROBES_DEG)):.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
