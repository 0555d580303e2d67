"""A/B of the LDC renderer: the engine at a git revision against the working tree, in one process.

Run from the repository root::

    python -m bench.ldc_ab HEAD --ldc 128 --method ldc+ibrt:2 --rounds 6 [--scene mirror_box] [--size 512]
        [--supersample 4 --antialias edges]

The old ``engine/newviews/renderer.py``, ``warp.py``, ``ibrt.py`` and ``view_pass.py`` are loaded from
``REV`` next to the current ones (``bench.ab_module.module_at``; the old renderer uses the old
siblings), both renderers get the same bake, and every view of ``bench.ldc_accuracy`` is rendered
by both: first compared (``same`` / ``DIFF max|radiance difference| provenance-pixels``), then
timed on 2 and on 1 numba threads, old and new alternating per view (the order flips every
round) so both see the same machine load. Printed per stage: the sum over the views of each
view's minimum and the mean of each view's median, old -> new, and the ratio. Nothing is written:
a quick, noisy-machine-proof check of an engine change (this machine's speed drifts 20 % within
minutes; compare only within one run). The harness has a bias of its own: an A/A run (``HEAD``
against a clean tree; cornell_box, LDC 128, ``ldc``) put the unchanged stages at 0.88-1.0x, fill
and diffuse lowest, so read a stage's ratio against that, or run the A/A beside the A/B.

numba's disk cache is keyed by the whole engine source (engine/_numba_setup.py), so the working
tree's kernels are always the current code; the old modules are cached under the temp directory.
"""

from __future__ import annotations

import argparse
import time

import numba as nb
import numpy as np

from bench.ab_module import module_at
from bench.ldc_accuracy import LLF_PARAMS, LLF_RES, scene_setup
from engine.newviews.ldc import bake_ldc
from engine.newviews.llf import bake_llf
from engine.newviews.renderer import LDCViewRenderer


def old_renderer_module(rev: str):
    """engine/newviews/renderer.py at ``rev`` using ``rev``'s warp, ibrt and view_pass."""
    names = {}
    for mod in ("ibrt", "warp", "view_pass"):
        module_at(rev, f"engine/newviews/{mod}.py", f"{mod}_ab_old")
        names[f"engine.newviews.{mod}"] = f"{mod}_ab_old"
    return module_at(rev, "engine/newviews/renderer.py", "ldc_render_ab_old", imports=names)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rev", help="git revision of the old engine (e.g. HEAD)")
    ap.add_argument("--scene", default="mirror_box")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--ldc", type=int, default=256, help="LDC resolution")
    ap.add_argument("--llf-f", type=int, default=8, help="LLF frequency (4 f^2 + 2 directions)")
    ap.add_argument("--method", default="ldc+ibrt:1")
    ap.add_argument("--supersample", type=int, default=1, help="render(..., supersample=S)")
    ap.add_argument("--antialias", default="uniform", help="render(..., antialias=...) with --supersample > 1")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--threads", default="2,1", help="numba thread counts to time, in order")
    args = ap.parse_args(argv)
    old, sha = old_renderer_module(args.rev)
    sc, caster, plan, cams, _ = scene_setup(args.scene, args.size, args.views)
    llf = bake_llf(sc, caster, args.llf_f, LLF_RES, params=LLF_PARAMS) if plan.needs_llf else None
    ldc = bake_ldc(sc, caster, args.ldc, plan=plan)
    a_r = old.LDCViewRenderer(sc, ldc, llf, plan)
    b_r = LDCViewRenderer(sc, ldc, llf, plan)
    view = {"supersample": args.supersample, "antialias": args.antialias}
    for i, cam in enumerate(cams):
        a, b = a_r.render(cam, args.method, **view), b_r.render(cam, args.method, **view)
        same = np.array_equal(a.radiance, b.radiance) and np.array_equal(a.provenance, b.provenance)
        print(f"view {i}: {'same' if same else 'DIFF'} max|diff| {float(np.abs(a.radiance - b.radiance).max()):.3g}, "
              f"provenance differs in {int((a.provenance != b.provenance).sum())} pixels", flush=True)
    before = nb.get_num_threads()
    try:
        for th in (int(t) for t in args.threads.split(",")):
            nb.set_num_threads(th)
            times: dict[str, dict[str, dict[int, list[float]]]] = {"old": {}, "new": {}}
            for rnd in range(args.rounds):
                order = (("old", a_r), ("new", b_r)) if rnd % 2 == 0 else (("new", b_r), ("old", a_r))
                for i, cam in enumerate(cams):
                    for lab, ren in order:
                        t0 = time.perf_counter()
                        o = ren.render(cam, args.method, **view)
                        dt = time.perf_counter() - t0
                        times[lab].setdefault("TOTAL", {}).setdefault(i, []).append(dt)
                        for k, v in o.timings.items():
                            times[lab].setdefault(k, {}).setdefault(i, []).append(v)
            print(f"threads {th}: {sha} -> working tree, {args.scene} {args.size}x{args.size} LDC {args.ldc} "
                  f"{args.method} supersample {args.supersample} {args.antialias}; ms, per-view min summed / "
                  "per-view median averaged", flush=True)
            for k, per_view in times["old"].items():
                new = times["new"][k]
                mn_a = 1000 * sum(min(v) for v in per_view.values()) / len(cams)
                mn_b = 1000 * sum(min(v) for v in new.values()) / len(cams)
                md_a = 1000 * float(np.mean([np.median(v) for v in per_view.values()]))
                md_b = 1000 * float(np.mean([np.median(v) for v in new.values()]))
                if mn_a > 0 and mn_b > 0:
                    print(f"  {k:10s} min {mn_a:7.2f} -> {mn_b:7.2f} ({mn_a / mn_b:5.3f}x)   "
                          f"median {md_a:7.2f} -> {md_b:7.2f} ({md_a / md_b:5.3f}x)")
    finally:
        nb.set_num_threads(before)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
