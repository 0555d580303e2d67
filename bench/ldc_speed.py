"""Interactive speed of the LDC renderer at 512x512 (goal: a view in <= 250 ms on 2 cores).

Run from the repository root: ``python -m bench.ldc_speed [--views N] [--size S]``. Writes the
block ``ldc_speed`` of ``docs/ldc.md``. Per sample scene: LDC at 256 and 512, LLF 258
directions (and 66 with the 256 LDC) at 48x48; one warm renderer; N views around the scene's
camera (those of ``bench.ldc_accuracy``); per method the median and 90th percentile of the
render time, the median process CPU time (all threads: on an idle 2-core machine the wall
time of a well-parallel render approaches half of it), and the median of each stage. Engine
only (no API, queue or image encoding).

A/B in the same run (``--ab REV``): every view is also rendered by the renderer as of git
revision REV (``bench.ldc_ab.old_renderer_module``), interleaved with the current one so both see
the same machine load; the table gives the ratio of the medians (before / now) and checks the
images are identical.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numba as nb
import numpy as np

from api_schemas import load_scene_file
from bench.docs_writer import replace_block
from bench.ldc_ab import old_renderer_module
from bench.ldc_accuracy import LLF_PARAMS, LLF_RES, ROOT, SCENES, views
from engine.newviews.effects import analyze
from engine.newviews.ldc import bake_ldc
from engine.newviews.llf import bake_llf
from engine.newviews.renderer import LDCViewRenderer
from engine.raycast import EmbreeCaster
from samples import SAMPLES_DIR, sample_path
from workers.scene_loader import directory_resolver, load_scene

DOC = ROOT / "docs" / "ldc.md"
METHODS = ("ldc", "ldc+llf", "ldc+ibrt:1")
CONFIGS = ((256, 8), (256, 4), (512, 8))  # (LDC resolution, LLF frequency f: 4 f^2 + 2 directions)


def _timed(renderer, cam, method):
    t0, c0 = time.perf_counter(), time.process_time()
    out = renderer.render(cam, method)
    return out, 1000 * (time.perf_counter() - t0), 1000 * (time.process_time() - c0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=10)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--ab", metavar="REV", default=None,
                    help="also render every view with the renderer as of this git revision (the 'before' columns)")
    args = ap.parse_args(argv)
    before, before_sha = old_renderer_module(args.ab) if args.ab else (None, None)
    load0 = os.getloadavg()
    rows = []
    for name in args.scenes.split(","):
        ls = load_scene(load_scene_file(sample_path(name)), directory_resolver(SAMPLES_DIR))
        sc = ls.runtime
        caster = EmbreeCaster(sc)
        plan = analyze(sc)
        llfs = {f: bake_llf(sc, caster, f, LLF_RES, params=LLF_PARAMS) if plan.needs_llf else None
                for f in sorted({f for _, f in CONFIGS})}
        ldcs = {res: bake_ldc(sc, caster, res, plan=plan) for res in sorted({r for r, _ in CONFIGS})}
        cams = views(ls.camera, args.size, args.views)
        for res, f in CONFIGS:
            llf = llfs[f]
            n_dirs = llf.n_directions if llf is not None else 0
            if llf is None and f != CONFIGS[0][1]:
                continue  # a diffuse scene has no LLF: one row set per LDC is enough
            r = LDCViewRenderer(sc, ldcs[res], llf, plan)
            old = None if before is None else before.LDCViewRenderer(sc, ldcs[res], llf, plan)
            for method in METHODS:
                r.render(cams[0], method)  # warm (numba compiled, IBRT accel built)
                if old is not None:
                    old.render(cams[0], method)
                tot, cpu, tot_old, st, worst = [], [], [], {}, 0.0
                for cam in cams:
                    o, ms, cms = _timed(r, cam, method)
                    tot.append(ms)
                    cpu.append(cms)
                    for k, v in o.timings.items():
                        st.setdefault(k, []).append(1000 * v)
                    if old is not None:
                        b, ms_old, _ = _timed(old, cam, method)
                        tot_old.append(ms_old)
                        worst = max(worst, float(np.abs(b.radiance - o.radiance).max()))
                        if not (np.array_equal(b.provenance, o.provenance) and np.array_equal(b.depth, o.depth)):
                            worst = max(worst, float("inf"))
                med = {k: float(np.median(v)) for k, v in st.items()}
                row = {"scene": name, "ldc": res, "dirs": n_dirs, "method": method, "med": float(np.median(tot)),
                       "p90": float(np.percentile(tot, 90)), "cpu": float(np.median(cpu)), "st": med,
                       "old": float(np.median(tot_old)) if tot_old else None, "diff": worst}
                rows.append(row)
                ab = (f", before {row['old']:.0f} ms ({row['old'] / row['med']:.2f}x), max |diff| {worst:.1e}"
                      if tot_old else "")
                print(f"{name} LDC{res} LLF{n_dirs} {method}: median {row['med']:.0f} ms, p90 {row['p90']:.0f}, "
                      f"cpu {row['cpu']:.0f}{ab}", flush=True)
    load1 = os.getloadavg()
    ab_cols = before is not None
    lines = [f"Generated by `python -m bench.ldc_speed` on {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} "
             f"({platform.machine()}, {os.cpu_count()} cores, numba threads {nb.get_num_threads()}, Python "
             f"{sys.version.split()[0]}); load average (1/5/15 min) {load0[0]:.1f}/{load0[1]:.1f}/{load0[2]:.1f} "
             f"at start, {load1[0]:.1f}/{load1[1]:.1f}/{load1[2]:.1f} at the end (other work shares the "
             f"machine: absolute times vary by 2x between runs, compare within the table). {args.size}x{args.size}, "
             f"{args.views} views per scene, warm renderer, engine only. `cpu`: median process CPU time of a render "
             "(both threads). `view pass`: the fused per-pixel kernels (surface records, refinement, highlights, "
             "gather; `surfaces` + `highlights` + `gather` in the result's timings). "
             + (f"`before`: the renderer as of revision {before_sha}, rendered "
                "interleaved with the current one in this run; `x` = before / now (medians); `diff`: max "
                "|difference| of the radiance over the views (0: identical images)." if ab_cols else ""), "",
             "| scene | LDC | LLF dirs | method | median ms | p90 ms | cpu ms | warp | holes+fill | view pass | ibrt |"
             + (" before ms | x | diff |" if ab_cols else ""),
             "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|" + ("---:|---:|---:|" if ab_cols else "")]
    for w in rows:
        st = w["st"]
        line = (f"| {w['scene']} | {w['ldc']} | {w['dirs']} | {w['method']} | {w['med']:.0f} | {w['p90']:.0f} | "
                f"{w['cpu']:.0f} | {st['warp']:.0f} | {st['holes'] + st['fill']:.0f} | "
                f"{st['surfaces'] + st['highlights'] + st['gather']:.0f} | {st['ibrt']:.0f} |")
        if ab_cols:
            line += f" {w['old']:.0f} | {w['old'] / w['med']:.2f} | {w['diff']:.1g} |"
        lines.append(line)
    replace_block(DOC, "ldc_speed", "\n".join(lines))
    print(f"wrote {DOC.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
