"""Error against sample count of the reference renderer's sampler, against an older revision's.

The Cornell box sample scene (``samples/scenes/cornell_box.json``) at ``--res`` pixels, direct
light (one rect-light sample per camera sample) and path tracing (one path of ``BOUNCES``
bounces per camera sample), ``n`` camera samples per pixel: the LRMS against a high-spp render
of the current renderer, RMS over ``--seeds`` seeds, for the current sampler and the one of
``--ab REV`` (loaded with ``bench.ab_module.module_at``). The ground truth is the mean of two
renders of different seeds; its own noise (``lrms(a, b) / 2``) is printed and taken out of the
errors in quadrature (``e^2 = e_measured^2 - e_truth^2``: the two are independent). Then, for each
``n``, how many samples the older sampler needs for the newer one's error (log-log
interpolation of its error curve; "~" marks extrapolation past its last point).

Pixels compared: covered, minus every pixel whose 3 x 3 neighbourhood sees the luminaire (as in
``bench/mitsuba_crosscheck.py``).

    flock /tmp/bench.lock python -m bench.reference_sampling --ab 6b5b1a0
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from engine import ENGINE_VERSION
from engine.metrics import lrms
from engine.reference import ReferenceParams, ReferenceRenderer

BOUNCES = 4  # as bench/mitsuba_crosscheck.py (Mitsuba path max_depth 6)


def _params(mod, kind: str, n: int, seed: int):
    if kind == "direct":
        return mod.ReferenceParams(spp=n, max_depth=0, area_light_samples=1, indirect_samples=0, seed=seed,
                                   chunk_pixels=1024)
    return mod.ReferenceParams(spp=n, max_depth=0, area_light_samples=1, indirect_samples=n,
                               indirect_bounces=BOUNCES, seed=seed, chunk_pixels=1024)


def _mask(runtime, out) -> np.ndarray:
    emissive = np.asarray(runtime.materials.emission).max(axis=1) > 0
    mid = out.material_id
    lum = np.zeros(mid.shape, bool)
    lum[mid >= 0] = emissive[mid[mid >= 0]]
    near = np.zeros_like(lum)
    p = np.pad(lum, 1)
    for dy in range(3):
        for dx in range(3):
            near |= p[dy:dy + mid.shape[0], dx:dx + mid.shape[1]]
    return (out.object_id >= 0) & ~near


def _old_samples_for(err: float, ns: list[int], errs: list[float]) -> tuple[float, bool]:
    """n at which the error curve (ns, errs) reaches ``err`` (log-log, piecewise linear)."""
    ln, le = np.log(ns), np.log(errs)
    for k in range(len(ns) - 1):
        if le[k + 1] <= math.log(err) <= le[k]:
            t = (math.log(err) - le[k]) / (le[k + 1] - le[k])
            return float(math.exp(ln[k] + t * (ln[k + 1] - ln[k]))), False
    k = 0 if math.log(err) > le[0] else len(ns) - 2
    slope = (le[k + 1] - le[k]) / (ln[k + 1] - ln[k])
    return float(math.exp(ln[k] + (math.log(err) - le[k]) / slope)), True


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ab", default="6b5b1a0", help="revision whose engine/reference.py is the old sampler")
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", default="4,16,64,256")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--truth-spp", default="direct:4096,path:1024", help="per render; two renders are averaged")
    ap.add_argument("--kinds", default="direct,path")
    ap.add_argument("--cache", default="/tmp/ibr_reference_sampling", help="ground truths are kept here")
    a = ap.parse_args(argv)

    import samples
    from api_schemas.scene import load_scene_file
    from bench.ab_module import module_at
    from workers.scene_loader import directory_resolver, load_scene

    ls = load_scene(load_scene_file(samples.sample_path("cornell_box")), directory_resolver(samples.SAMPLES_DIR))
    cam = replace(ls.camera, width=a.res, height=a.res)
    old, rev = module_at(a.ab, "engine/reference.py", "reference_sampling_ab_old")
    new_mod = __import__("engine.reference", fromlist=["ReferenceParams"])
    ren_new = ReferenceRenderer(ls.runtime)
    ren_old = old.ReferenceRenderer(ls.runtime)
    ns = [int(x) for x in a.spp.split(",")]
    truth_spp = dict(kv.split(":") for kv in a.truth_spp.split(","))
    Path(a.cache).mkdir(parents=True, exist_ok=True)
    print(f"Cornell box {a.res}x{a.res}, new = working tree (ENGINE_VERSION {ENGINE_VERSION}), old = {rev}; "
          f"LRMS RMS over {a.seeds} seeds")
    for kind in a.kinds.split(","):
        g = int(truth_spp[kind])
        f = Path(a.cache) / f"truth_{kind}_{a.res}_{g}_{BOUNCES}_{ENGINE_VERSION}.npz"
        if f.exists():
            z = np.load(f)
            ta, tb = z["a"], z["b"]
        else:
            t0 = time.perf_counter()
            ta = ren_new.render(cam, _params(new_mod, kind, g, 1000)).radiance
            tb = ren_new.render(cam, _params(new_mod, kind, g, 1001)).radiance
            np.savez(f, a=ta, b=tb)
            print(f"  {kind}: ground truth 2 x {g} spp in {time.perf_counter() - t0:.0f} s")
        out0 = ren_new.render(cam, ReferenceParams(spp=1, max_depth=0, pixel_jitter=False))
        mask = _mask(ls.runtime, out0)
        truth = 0.5 * (ta.astype(np.float64) + tb.astype(np.float64))
        e_truth = lrms(ta, tb, mask) / 2.0
        print(f"\n{kind}: ground truth 2 x {g} spp, its own LRMS ~{100 * e_truth:.3f} %; {int(mask.sum())} pixels")
        errs: dict[str, list[float]] = {"old": [], "new": []}
        secs: dict[str, float] = {"old": 0.0, "new": 0.0}
        for n in ns:
            for name, mod, ren in (("old", old, ren_old), ("new", new_mod, ren_new)):
                e2 = []
                for s in range(a.seeds):
                    t0 = time.perf_counter()
                    img = ren.render(cam, _params(mod, kind, n, s)).radiance
                    secs[name] += time.perf_counter() - t0
                    e2.append(lrms(img, truth, mask) ** 2)
                errs[name].append(math.sqrt(max(float(np.mean(e2)) - e_truth ** 2, 1e-30)))
        print("| spp | old LRMS | new LRMS | old samples for the new error | ratio |")
        print("|---:|---:|---:|---:|---:|")
        for k, n in enumerate(ns):
            eq, extra = _old_samples_for(errs["new"][k], ns, errs["old"])
            mark = "~" if extra else ""
            print(f"| {n} | {100 * errs['old'][k]:.2f} % | {100 * errs['new'][k]:.2f} % | {mark}{eq:.0f} | "
                  f"{mark}{eq / n:.1f}x |")
        print(f"render seconds (all seeds and spp): old {secs['old']:.1f}, new {secs['new']:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
