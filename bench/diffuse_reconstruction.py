"""Diffuse reconstruction of LDC views: nearest sample against bilinear between a surface's samples
(``LDCViewRenderer(diffuse_filter=...)``), one LDC read both ways.

The Cornell box at 512 x 512, ``bench.gi_equal_error``'s 6 orbit views and its ground truths (taken
from ``--gt-cache``, rendered there when missing: ~3 min per view), an LDC of 256 with indirect
light (by default noise 0.02 and 64 rect-light points per sample, as the ``gi_equal_error`` rows); one sample per
pixel and 4 x 4 edge supersampling. Prints one JSON row per setting: mean LRMS, the ground truth's
floor taken out, the error's parts by region (``gi_equal_error.error_breakdown``) and the median
view time. Run under ``flock /tmp/bench.lock``; the numbers are in docs/ldc.md, *Diffuse
reconstruction*.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from api_schemas import load_scene_file
from bench import gi_equal_error as gi
from bench.ibrt_throughput import sample_path
from bench.ldc_accuracy import scene_setup
from bench.ldc_antialias import edge_classes
from bench.mitsuba_crosscheck import comparison_mask, sees_rect_light
from engine.metrics import lrms
from engine.newviews.indirect import IndirectParams
from engine.newviews.ldc import bake_ldc
from engine.newviews.renderer import DIFFUSE_FILTERS, LDCViewRenderer


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gt-cache", required=True, help="gi_equal_error's ground-truth directory")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--noise", type=float, default=0.02, help="the indirect pass's noise target")
    ap.add_argument("--area-light-samples", type=int, default=gi.LDC_AREA_SAMPLES, help="rect-light points per sample")
    a = ap.parse_args(argv)
    name, size = "cornell_box", 512
    gi.GT_BUDGET_SCALE[0] = 1.5  # the ground truths of gi_equal_error --gt-budget-scale 1.5
    spec = gi.SCENES[name]
    sc, caster, plan, _, ren = scene_setup(name, size, 1)
    lo, hi = sc.bounds
    cam0 = load_scene_file(sample_path(name)).camera
    cams = gi.orbit_views(0.5 * (np.asarray(lo) + np.asarray(hi)), cam0.eye, cam0.fov_y_deg, size, a.views)
    cache = Path(a.gt_cache)
    gts = []
    for cam in cams:
        g = gi.converged_view(ren, name, cam, gi.gt_params(spec, gi.GT_SEED), cache)
        g["mask"], _ = comparison_mask(sc, g["object_id"], sees_rect_light(sc, cam, g["depth"]))
        gts.append(g)
    g2 = gi.converged_view(ren, name, cams[0], gi.gt_params(spec, gi.GT_SEED + 1), cache)
    floor = lrms(gts[0]["radiance"], g2["radiance"], gts[0]["mask"]) / math.sqrt(2)
    t0 = time.perf_counter()
    ldc = bake_ldc(sc, caster, 256, plan=plan, area_light_samples=a.area_light_samples,
                   indirect=IndirectParams(noise=a.noise, bounces=spec.bounces))
    print(json.dumps({"ground_truth_floor": floor, "bake_s": time.perf_counter() - t0}), flush=True)
    for filt in DIFFUSE_FILTERS:
        r = LDCViewRenderer(sc, ldc, None, plan, diffuse_filter=filt)
        for ss, aa in ((1, "uniform"), (gi.EDGES_SS, "edges")):
            r.render(cams[0], spec.method, supersample=ss, antialias=aa)  # warm
            errs, parts, ts = [], [], []
            for cam, g in zip(cams, gts, strict=True):
                cls = edge_classes(r.render(cam, spec.method), r.silhouette_rel_depth, ldc.background)
                dts = []
                for _ in range(3):
                    t1 = time.perf_counter()
                    v = r.render(cam, spec.method, supersample=ss, antialias=aa)
                    dts.append(time.perf_counter() - t1)
                ts.append(min(dts))
                errs.append(lrms(v.radiance, g["radiance"], g["mask"]))
                parts.append(gi.error_breakdown(v.radiance, g["radiance"], g["mask"], cls)["regions"])
            m = float(np.mean(errs))
            print(json.dumps({"diffuse_filter": filt, "supersample": ss, "antialias": aa, "lrms": m,
                              "corrected": gi.corrected(m, floor), "view_ms": 1000 * float(np.median(ts)),
                              **{k: float(np.mean([p[k] for p in parts])) for k in parts[0] if k.endswith("lrms")}}),
                  flush=True)


if __name__ == "__main__":
    main()
