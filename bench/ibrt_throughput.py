"""Image-based ray tracing through the LDC: speed against Embree, quadtree savings, accuracy.

For each of the first paper's three scenes and each LDC resolution, on three ray sets
(the scene camera's primary rays; mirror reflections of them from their Embree hit
points, with no spawn offset and the surface normal passed as ``origin_normals``; random
rays with origins in the scene bounds), measured in one run on one machine:

- rays/s of ``engine.newviews.ibrt.trace`` with 1 and 2 threads, and of Embree (engine/embree.py: the
  engine's kernels calling ``rtcIntersect4`` on the same number of threads) on the SAME rays;
  the ratio IBRT / Embree is the number to quote (the machine is shared and noisy);
- the quadtree's savings against ``trace_linear`` (same hits, no quadtree): cells visited,
  patch tests, time;
- agreement with Embree: same object hit (all rays, and rays away from silhouettes: four
  parallel rays 2 h to the sides see the same object within 8 h), |t - t_embree| <= h;
- accel build time and size next to the LDC's.

    python -m bench.ibrt_throughput [--resolutions 256 512] [--size 256] [--repeat 3]

Writes the block ``ibrt`` of docs/ldc.md and docs/data/ibrt_throughput.json.

``--ab REV`` instead times ``engine/newviews/ibrt.py`` at git revision REV against the working tree's in
one process, interleaved (old, new, old, new, ...; the machine is shared, so only the ratio
is quoted), on the rays the LDC view renderer traces (``LDCViewRenderer._trace`` captured
while rendering ``--ab-scenes`` at 512x512 from an LDC of resolution 256, 6 views: hole /
silhouette eye rays and mirror reflection rays) and on random rays; it checks that both
return the same axis, sample, t, n_steps and n_tests for every ray and writes the result
under the heading "Traversal A/B" at the end of the ``ibrt`` block:

    python -m bench.ibrt_throughput --ab HEAD~1 [--ab-rounds 15]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from api_schemas import load_scene_file
from bench.docs_writer import replace_block
from engine import embree
from engine.camera import camera_rays, pixel_centers
from engine.newviews.ibrt import build_accel, trace, trace_linear
from engine.newviews.ldc import bake_ldc
from engine.raycast import EmbreeCaster, hit_points
from samples import SAMPLES_DIR, sample_path
from workers.scene_loader import directory_resolver, load_scene

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "ldc.md"
DATA = ROOT / "docs" / "data" / "ibrt_throughput.json"
SCENES = ["mirror_box", "teapot_glossy", "teapot_spheres"]
THREADS = 2


def _embree_once(caster: EmbreeCaster, o32: np.ndarray, d32: np.ndarray, threads: int) -> tuple[float, float]:
    """(wall, process CPU) seconds of one Embree pass (engine/embree.py) on 1 or all threads."""
    es = caster._get()
    assert es is not None
    t0, c0 = time.perf_counter(), time.process_time()
    embree.intersect(es, o32, d32, serial=threads == 1)
    return time.perf_counter() - t0, time.process_time() - c0


def ldc_objects(ldc, hits) -> np.ndarray:
    """Object id of each image-based hit (-1: miss)."""
    out = np.full(hits.hit.shape[0], -1, dtype=np.int64)
    for a in range(3):
        s = hits.axis == a
        out[s] = ldc.axes[a].object[hits.sample[s]]
    return out


def embree_objects(sc, e) -> np.ndarray:
    """Object id of each Embree hit (-1: miss)."""
    return np.where(e.prim >= 0, sc.tri_object[np.maximum(e.prim, 0)], -1)


def _stable(sc, caster, o, d, h, eobj, et):
    """Rays away from silhouettes: four parallel rays 2 h to the sides, starting halfway to the
    hit (4 h along a missing ray, so rays leaving a surface don't start inside it), see the
    same object (or all miss) within 8 h."""
    a = np.cross(d, [0.577, 0.577, 0.577])
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(d, a)
    s = np.where(np.isfinite(et), 0.5 * np.where(np.isfinite(et), et, 0.0), 4 * h)
    mid = o + s[:, None] * d
    ok = np.ones(o.shape[0], dtype=bool)
    for off in (2 * h * a, -2 * h * a, 2 * h * b, -2 * h * b):
        e2 = caster.intersect(mid + off, d)
        with np.errstate(invalid="ignore"):
            ok &= (embree_objects(sc, e2) == eobj) & ((e2.prim < 0) | (np.abs(e2.t + s - et) < 8 * h))
    return ok


def random_rays(lo, hi, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` rays from uniform points of the box ``lo``..``hi`` in uniform directions."""
    rng = np.random.default_rng(seed)
    o = lo + rng.random((n, 3)) * (hi - lo)
    d = rng.normal(size=(n, 3))
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def camera_and_reflection_rays(ls, caster, size: int) -> tuple[np.ndarray, ...]:
    """The scene camera's primary rays at ``size`` x ``size`` (o, d) and, where they hit, mirror
    rays from the hit points with no offset (p, r) and the faces' normals there (ng)."""
    sc = ls.runtime
    cam = replace(ls.camera, width=size, height=size)
    px, py = pixel_centers(cam)
    o, d = camera_rays(cam, px, py)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    e = caster.intersect(o, d)
    ok = e.prim >= 0
    p = hit_points(sc, e)[ok]
    ng = sc.tri_ng[e.prim[ok]]
    r = d[ok] - 2 * np.einsum("ij,ij->i", d[ok], ng)[:, None] * ng
    return o, d, p, r, ng


def ray_sets(ls, caster, size: int, seed: int = 1) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
    o, d, p, r, ng = camera_and_reflection_rays(ls, caster, size)
    ro, rd = random_rays(*ls.runtime.bounds, size * size, seed)
    return {"primary": (o, d, None), "reflection": (p, r, ng), "random": (ro, rd, None)}


def measure(name: str, res: int, size: int, repeat: int) -> dict:
    ls = load_scene(load_scene_file(sample_path(name)), directory_resolver(SAMPLES_DIR))
    sc = ls.runtime
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, res)
    t0 = time.perf_counter()
    acc = build_accel(ldc)
    t_build = time.perf_counter() - t0
    out = {"scene": name, "resolution": res, "samples": ldc.n_samples, "ldc_bytes": ldc.nbytes,
           "accel_bytes": acc.nbytes, "accel_nodes": acc.n_nodes, "build_s": t_build,
           "max_layers": max(int(ax.ldi.counts().max()) for ax in ldc.axes), "sets": {}}
    for label, (o, d, nrm) in ray_sets(ls, caster, size).items():
        n = o.shape[0]
        kw = {"origin_normals": nrm}
        trace(ldc, acc, o[:64], d[:64], **{k: (v[:64] if v is not None else None) for k, v in kw.items()})
        rec: dict = {"rays": n}
        o32 = np.ascontiguousarray((o - sc.center).astype(np.float32))
        d32 = np.ascontiguousarray(d.astype(np.float32))
        for th in (1, THREADS):
            best_i = best_e = cpu_i = cpu_e = float("inf")
            for _ in range(repeat):  # interleaved, best of each: both see the same machine load
                t0, c0 = time.perf_counter(), time.process_time()
                hits = trace(ldc, acc, o, d, threads=th, **kw)
                best_i = min(best_i, time.perf_counter() - t0)
                cpu_i = min(cpu_i, time.process_time() - c0)
                w, c = _embree_once(caster, o32, d32, th)
                best_e, cpu_e = min(best_e, w), min(cpu_e, c)
            rec[f"ibrt_rays_per_s_{th}"] = n / best_i
            rec[f"embree_rays_per_s_{th}"] = n / best_e
            rec[f"ratio_{th}"] = best_e / best_i
            # CPU time: what each costs per ray regardless of how busy the machine is
            rec[f"ibrt_rays_per_cpu_s_{th}"] = n / cpu_i
            rec[f"embree_rays_per_cpu_s_{th}"] = n / cpu_e
            rec[f"cpu_ratio_{th}"] = cpu_e / cpu_i
        c0 = time.process_time()
        lin = trace_linear(ldc, acc, o, d, threads=1, **kw)
        t_lin = time.process_time() - c0
        rec.update(steps_per_ray=hits.n_steps / n, tests_per_ray=hits.n_tests / n,
                   linear_steps_per_ray=lin.n_steps / n, linear_tests_per_ray=lin.n_tests / n,
                   linear_speedup=t_lin * rec["ibrt_rays_per_cpu_s_1"] / n,
                   linear_same_hits=bool(np.array_equal(lin.hit, hits.hit)
                                         and np.allclose(lin.t[lin.hit], hits.t[hits.hit], rtol=1e-9)))
        # accuracy against Embree (reflection rays: Embree from a spawn offset off the true surface)
        eo = o
        if nrm is not None:
            eo = o + 1e-5 * sc.extent * np.sign(np.einsum("ij,ij->i", nrm, d))[:, None] * nrm
        e = caster.intersect(eo, d)
        eobj = embree_objects(sc, e)
        obj = ldc_objects(ldc, hits)
        stable = _stable(sc, caster, eo, d, ldc.h, eobj, e.t)
        hit_st = stable & (e.prim >= 0)
        rec.update(same_object_all=float((obj == eobj).mean()),
                   same_object_stable=float((obj == eobj)[stable].mean()),
                   stable_fraction=float(stable.mean()),
                   t_within_h_stable_hits=float((np.abs(hits.t[hit_st] - e.t[hit_st]) <= ldc.h).mean()),
                   embree_hit_fraction=float((e.prim >= 0).mean()))
        out["sets"][label] = rec
        print(json.dumps({"scene": name, "res": res, "set": label, "cpu_ratio_1": round(rec["cpu_ratio_1"], 4),
                          "ratio_2": round(rec["ratio_2"], 4),
                          "same_all": round(rec["same_object_all"], 4)}), flush=True)
    return out

# ----------------------------------------------------------------------------- A/B against a revision

AB_SCENES = ["mirror_box", "teapot_glossy"]
AB_HEADING = "Traversal A/B"


def render_rays(name: str, size: int = 512, ldc_res: int = 256, n_views: int = 6):
    """(ldc, [(o, d, origin_normals or None), ...]): every batch ``LDCViewRenderer._trace``
    gets while rendering the scene's ``n_views`` benchmark views with ``ldc+ibrt:1``."""
    from bench.ldc_accuracy import LLF_PARAMS, LLF_RES, scene_setup
    from engine.newviews.llf import bake_llf
    from engine.newviews.renderer import LDCViewRenderer

    sc, caster, plan, cams, _ = scene_setup(name, size, n_views)
    ldc = bake_ldc(sc, caster, ldc_res, plan=plan)
    llf = bake_llf(sc, caster, 8, LLF_RES, params=LLF_PARAMS) if plan.needs_llf else None
    r = LDCViewRenderer(sc, ldc, llf, plan)
    batches: list = []
    inner = r._trace

    def spy(o, d, origin_normals=None):
        batches.append((np.array(o, np.float64, order="C"), np.array(d, np.float64, order="C"),
                        None if origin_normals is None else np.array(origin_normals, np.float64)))
        return inner(o, d, origin_normals)

    r._trace = spy
    for cam in cams:
        r.render(cam, "ldc+ibrt:1")
    return sc, ldc, batches


def _trace_all(mod, ldc, args, acc, batches):
    return [mod.trace_prepared(ldc, args, acc, o, d, origin_normals=nrm) for o, d, nrm in batches]


def _same(ra, rb) -> dict:
    """Per field: identical over every ray of every batch (np.array_equal; t compared bit for bit)."""
    out = {}
    for k, name in enumerate(("axis", "sample", "t")):
        out[name] = all(np.array_equal(a[k], b[k]) and np.array_equal(np.asarray(a[k]).view(np.uint8),
                                                                       np.asarray(b[k]).view(np.uint8))
                        for a, b in zip(ra, rb, strict=True))
    out["n_steps"] = all(a[3] == b[3] for a, b in zip(ra, rb, strict=True))
    out["n_tests"] = all(a[4] == b[4] for a, b in zip(ra, rb, strict=True))
    return out


def ab(rev: str, scenes: list[str], rounds: int, log=print) -> dict:
    """Interleaved timing of ``trace_prepared`` (REV's module against the working tree's) on the
    renderer's captured rays and on random rays, 2 threads and 1 thread; hits compared."""
    import numba as nb

    import engine.newviews.ibrt as new
    from bench.ab_module import module_at

    old, sha = module_at(rev, "engine/newviews/ibrt.py", "ibrt_ab_old")
    new_sha = subprocess.run(["git", "-C", str(ROOT), "log", "-1", "--format=%h", "--", "engine/newviews/ibrt.py"],
                             capture_output=True, text=True, check=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", str(ROOT), "diff", "--quiet", "HEAD", "--",
                            "engine/newviews/ibrt.py"]).returncode != 0
    res: dict = {"rev": rev, "sha": sha, "new": new_sha + (" with uncommitted changes" if dirty else ""),
                 "rounds": rounds, "scenes": {}}
    threads_all = sorted({1, max(1, nb.config.NUMBA_NUM_THREADS)}, reverse=True)
    for name in scenes:
        sc, ldc, batches = render_rays(name)
        lo, hi = sc.bounds
        rng = np.random.default_rng(7)
        n_rand = 20000
        ro = lo + rng.random((n_rand, 3)) * (hi - lo)
        rd = rng.normal(size=(n_rand, 3))
        rd = np.ascontiguousarray(rd / np.linalg.norm(rd, axis=1, keepdims=True))
        sets = {"render": batches, "random": [(np.ascontiguousarray(ro), rd, None)]}
        acc_old, acc_new = old.build_accel(ldc), new.build_accel(ldc)
        args_old, args_new = old.trace_args(ldc), new.trace_args(ldc)
        rec: dict = {"ldc_res": 256, "size": 512, "views": 6}
        for label, bs in sets.items():
            n = sum(b[0].shape[0] for b in bs)
            ra = _trace_all(old, ldc, args_old, acc_old, bs)
            rb = _trace_all(new, ldc, args_new, acc_new, bs)
            same = _same(ra, rb)
            r = {"rays": n, "batches": len(bs), "identical": same,
                 "steps_per_ray": sum(x[3] for x in rb) / max(n, 1), "tests_per_ray": sum(x[4] for x in rb) / max(n, 1)}
            prev = nb.get_num_threads()
            for th in threads_all:
                nb.set_num_threads(th)
                try:
                    ts: dict = {"old": [], "new": []}
                    for _ in range(rounds):
                        for side, mod, args, acc in (("old", old, args_old, acc_old), ("new", new, args_new, acc_new)):
                            t0 = time.perf_counter()
                            _trace_all(mod, ldc, args, acc, bs)
                            ts[side].append(time.perf_counter() - t0)
                finally:
                    nb.set_num_threads(prev)
                r[f"threads_{th}"] = {
                    "old_min_s": min(ts["old"]), "new_min_s": min(ts["new"]),
                    "old_median_s": float(np.median(ts["old"])), "new_median_s": float(np.median(ts["new"])),
                    "speedup_min": min(ts["old"]) / min(ts["new"]),
                    "speedup_median": float(np.median(ts["old"]) / np.median(ts["new"])),
                    # each round's old / new (run back to back, so under about the same load)
                    "speedup_paired": float(np.median(np.array(ts["old"]) / np.array(ts["new"])))}
            rec[label] = r
            log(json.dumps({"scene": name, "set": label, "rays": n, "identical": same,
                            **{k: {kk: round(vv, 5) for kk, vv in v.items()} for k, v in r.items()
                               if k.startswith("threads_")}}))
        res["scenes"][name] = rec
    return res


def _ab_lines(res: dict, rounds: int) -> list[str]:
    th = sorted({int(k.split("_")[1]) for rec in res["scenes"].values() for s in ("render", "random")
                 for k in rec[s] if k.startswith("threads_")}, reverse=True)
    la = os.getloadavg()
    lines = [f"### {AB_HEADING}", "",
             f"Measured with `python -m bench.ibrt_throughput --ab {res['rev']} --ab-rounds {rounds}` "
             f"({time.strftime('%Y-%m-%d')}, load average {la[0]:.1f}): "
             f"`engine/newviews/ibrt.py` at {res['sha']} (old) "
             f"against {res['new']} (new), `trace_prepared` on the same rays in one process, interleaved, "
             f"{rounds} rounds; `render` = every batch `LDCViewRenderer._trace` gets while rendering the 6 "
             "benchmark views at 512x512 from an LDC of resolution 256 with `ldc+ibrt:1` (hole / silhouette eye "
             "rays and mirror reflection rays), `random` = 20000 rays, origins uniform in the scene bounds.", "",
             "| scene | rays | identical axis / sample / t / steps / tests | steps + tests per ray | "
             + " | ".join(f"old / new ms, {t} thread{'s' if t > 1 else ''} (min; median) | speed-up: min; median; "
                          "**median of the rounds' ratios**" for t in th) + " |",
             "|---|---|---|---:|" + "---|---:|" * len(th)]
    for name, rec in res["scenes"].items():
        for s in ("render", "random"):
            r = rec[s]
            ident = " / ".join("yes" if r["identical"][k] else "**NO**"
                               for k in ("axis", "sample", "t", "n_steps", "n_tests"))
            row = f"| {name} | {s}: {r['rays']:,} | {ident} | {r['steps_per_ray']:.0f} + {r['tests_per_ray']:.0f} |"
            for t in th:
                q = r[f"threads_{t}"]
                row += (f" {q['old_min_s'] * 1e3:.1f} / {q['new_min_s'] * 1e3:.1f}; {q['old_median_s'] * 1e3:.1f} / "
                        f"{q['new_median_s'] * 1e3:.1f} | {q['speedup_min']:.2f}x; {q['speedup_median']:.2f}x; "
                        f"**{q['speedup_paired']:.2f}x** |")
            lines.append(row)
    return lines


def write_ab(res: dict, rounds: int) -> None:
    """Replace the A/B part at the end of the ``ibrt`` block (the rest of the block is kept)."""
    text = DOC.read_text()
    start, end = "<!-- bench:ibrt:start -->", "<!-- bench:ibrt:end -->"
    body = text[text.index(start) + len(start):text.index(end)].strip("\n") if start in text else ""
    cut = body.find(f"### {AB_HEADING}")
    if cut >= 0:
        body = body[:cut].rstrip()
    replace_block(DOC, "ibrt", body + "\n\n" + "\n".join(_ab_lines(res, rounds)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolutions", type=int, nargs="*", default=[256, 512])
    ap.add_argument("--size", type=int, default=256, help="camera image side: size^2 primary / random rays")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--scenes", nargs="*", default=SCENES)
    ap.add_argument("--ab", metavar="REV", default=None,
                    help="only time engine/newviews/ibrt.py at REV against the working tree on the renderer's rays")
    ap.add_argument("--ab-scenes", nargs="*", default=AB_SCENES)
    ap.add_argument("--ab-rounds", type=int, default=15)
    ap.add_argument("--no-write", action="store_true", help="--ab: print only, don't touch docs/ldc.md")
    args = ap.parse_args()
    if args.ab:
        res = ab(args.ab, args.ab_scenes, args.ab_rounds)
        if not args.no_write:
            write_ab(res, args.ab_rounds)
            print(f"wrote {DOC}")
        return
    rows = [measure(n, r, args.size, args.repeat) for n in args.scenes for r in args.resolutions]
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps({"machine": platform.platform(), "cpus": os.cpu_count(),
                                "load_avg": os.getloadavg(), "rows": rows}, indent=2) + "\n")
    la = os.getloadavg()
    lines = [
        f"Measured with `python -m bench.ibrt_throughput --resolutions {' '.join(map(str, args.resolutions))} "
        f"--size {args.size} --repeat {args.repeat}` ({time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores, load "
        f"average {la[0]:.1f} at the end: the machine is shared, so only ratios within one run are meaningful, "
        "and the 1-thread columns use process CPU time, which a busy machine disturbs far less than wall "
        "time; "
        "raw data in `docs/data/ibrt_throughput.json`). Rays: `primary` = the scene camera's "
        f"{args.size}x{args.size} pixel-centre rays; `reflection` = their mirror reflections from the Embree hit "
        "points (no offset, `origin_normals` given); `random` = origins uniform in the scene bounds, uniform "
        "directions.",
        "",
        "| scene | LDC res | rays | IBRT / Embree Mrays per CPU s (1 thread) | **IBRT / Embree, 1 thread, CPU** | "
        "IBRT / Embree Mrays/s wall, 2 threads | IBRT / Embree, 2 threads, wall | "
        "cells + tests per ray: quadtree / linear | quadtree speed-up (CPU, 1 thread) | "
        "same object: all / away from silhouettes | abs(dt) <= h |",
        "|---|---:|---|---|---:|---|---:|---|---:|---|---:|",
    ]
    for r in rows:
        for label, s in r["sets"].items():
            lines.append(
                f"| {r['scene']} | {r['resolution']} | {label} | {s['ibrt_rays_per_cpu_s_1'] / 1e6:.2f} / "
                f"{s['embree_rays_per_cpu_s_1'] / 1e6:.2f} | **{s['cpu_ratio_1']:.3f}** | "
                f"{s['ibrt_rays_per_s_2'] / 1e6:.2f} / {s['embree_rays_per_s_2'] / 1e6:.2f} | {s['ratio_2']:.3f} | "
                f"{s['steps_per_ray']:.0f} + {s['tests_per_ray']:.0f} / {s['linear_steps_per_ray']:.0f} + "
                f"{s['linear_tests_per_ray']:.0f} | {s['linear_speedup']:.1f}x | "
                f"{100 * s['same_object_all']:.2f} % / {100 * s['same_object_stable']:.2f} % | "
                f"{100 * s['t_within_h_stable_hits']:.2f} % |")
    lines += ["", "| scene | LDC res | samples | max layers | LDC size | accel size | accel nodes | build |",
              "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['resolution']} | {r['samples']:,} | {r['max_layers']} | "
                     f"{r['ldc_bytes'] / 2**20:.1f} MiB | {r['accel_bytes'] / 2**20:.2f} MiB | {r['accel_nodes']:,} | "
                     f"{r['build_s'] * 1e3:.0f} ms |")
    same = all(s["linear_same_hits"] for r in rows for s in r["sets"].values())
    lines += ["", f"The linear march returned the same hits as the quadtree on every ray set: {same}."]
    replace_block(DOC, "ibrt", "\n".join(lines))
    print(f"wrote {DOC}")


if __name__ == "__main__":
    main()
