"""Precision of the relight kernel against the float64 per-pixel reference (``tests/engine/relight_naive.py``).

Run: ``python -m bench.relight_precision [--res 512] [--rows 1500] [--rev REV] --dataset-cache DIR`` (the
speed bench's generated dataset: ball on a floor, 224 lights). For one point light and for 4 directional
lights, on a random sample of store rows: the largest and the mean absolute difference between the
kernel's image and the float64 reference (eq. 1 per pixel, linear search, ``np.linalg.solve``), relative
to the image maximum and in 8-bit grey levels of the image scaled to its maximum, and the largest
relative difference over pixels above 1 % of the maximum; with ``--rev``, the same for
the relight kernel at that git revision
(``bench.relight_speed.old_relight_module``; e.g. the float64 kernel before the float32 points).
Prints a table; nothing is written.
"""

from __future__ import annotations

import argparse
import types

import numpy as np

from bench.relight_speed import _dataset, old_relight_module
from engine.relighting.bake import BakedDataset, bake_dataset
from engine.relighting.lights import DirectionalLight, PointLight
from engine.relighting.relight import relight
from engine.scene import CameraParams
from tests.engine.relight_naive import naive_relight


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=512)
    ap.add_argument("--spacing", type=float, default=10.0)
    ap.add_argument("--rows", type=int, default=1500)
    ap.add_argument("--rev", default=None)
    ap.add_argument("--dataset-cache", default=None)
    args = ap.parse_args(argv)
    cam = CameraParams("perspective", (0, 2.2, 2.2), (0, 0.3, 0), (0, 1, 0), args.res, args.res, fov_y_deg=40)
    ds, _ = _dataset(cam, args.spacing, args.dataset_cache)
    baked = bake_dataset(ds)
    del ds
    c = baked.sphere_center
    point = [(tuple(c + [1.0, 2.5, 1.2]), (20.0, 20.0, 20.0))]
    toward = [((0.3, 0.8, 0.5), (0.7, 0.6, 0.5)), ((-0.5, 0.6, 0.6), (0.4, 0.4, 0.4)),
              ((0.1, 0.95, -0.3), (0.5, 0.5, 0.6)), ((0.7, 0.3, 0.65), (0.3, 0.3, 0.3))]
    rows = np.sort(np.random.default_rng(0).choice(baked.pixel_index.size, args.rows, replace=False))
    sel = baked.pixel_index[rows]
    new = types.SimpleNamespace(relight=relight, BakedDataset=BakedDataset, PointLight=PointLight,
                                DirectionalLight=DirectionalLight)
    mods = {"working tree": (new, baked)}
    if args.rev:
        old = old_relight_module(args.rev)
        fields = set(old.BakedDataset.__dataclass_fields__)
        mods[args.rev] = (old, old.BakedDataset(**{f: getattr(baked, f) for f in baked.__dataclass_fields__
                                                  if f in fields}))
    print(f"{args.res}x{args.res}, {args.rows} random store rows of {baked.pixel_index.size}")
    print("| case | kernel | max abs diff / max | max, 8-bit levels | mean, 8-bit levels | max rel (> 1 % of max) |")
    print("|---|---|---|---|---|---|")
    for cname, pl, tl in (("1 point light", point, []), ("4 directional lights", [], toward)):
        want, _ = naive_relight(baked, pl, tl, rows=rows)
        want = want.reshape(-1, 3)[sel]
        for name, (mod, bk) in mods.items():
            lights = [mod.PointLight(p, i) for p, i in pl] + [mod.DirectionalLight(-np.asarray(d), e) for d, e in tl]
            got = mod.relight(bk, lights).image.reshape(-1, 3)[sel].astype(np.float64)
            full_max = float(np.max(want))
            err = np.abs(got - want)
            big = want > 0.01 * full_max
            print(f"| {cname} | {name} | {err.max() / full_max:.2g} | {255 * err.max() / full_max:.2g} | "
                  f"{255 * err.mean() / full_max:.2g} | {np.max(err[big] / want[big]):.2g} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
