"""Edge antialiasing of the LDC views: error floor and render time of ``supersample`` s with
``antialias="uniform"`` (s x s samples in every pixel) and ``antialias="edges"`` (only in the
pixels at an edge of the one-sample image), at the interactive size.

``python -m bench.ldc_antialias`` (512x512; cornell_box with method ``ldc``, mirror_box with
``ldc+ibrt:1``; ``--scene NAME`` for one scene, ``--quick`` for an iteration run). Writes the
``ldc_antialias`` block of ``docs/accuracy/ldc.md`` and ``docs/data/ldc_antialias.json`` (a run
of one scene merges into the stored results of the others). ``--direct-convergence LABEL``
measures instead how the bake's direct light converges with its rect-light samples per LDC sample
(``direct_convergence``; the ``ldc_direct_convergence`` block and
``docs/data/ldc_direct_convergence.json``, one entry per sampler label).

Direct light only (the bake without indirect light, the reference with ``indirect_samples=0``),
so the error left is the views' own: ground truth = the reference renderer at 64 jittered
samples per pixel, box filter. Views: cornell_box orbits its box centre (278, 273, 280) at 1080
units (azimuth / elevation 12 / 7, -20 / -5, -6 / 2 degrees; all see the box's inside only);
the other scenes take views 1, 4 and 6 of ``bench.ldc_accuracy.views`` (none aligned with an LDC axis). LRMS over
``bench.mitsuba_crosscheck.comparison_mask`` of the ground truth's ids (covered pixels, less the
3 x 3 neighbourhoods of emissive surfaces), mean over the views.

Where the error goes: the one-sample render's pixels split into *geometric edges* (a pixel of
the 3 x 3 neighbourhood shows another object, nothing, or a depth more than the renderer's
``silhouette_rel_depth`` away), *shading edges* (only a luminance step of more than
``EDGE_CONTRAST``: shadow and highlight borders, the light's rim) and the *interior* (the rest);
per setting the share of the squared error in each and the LRMS of the interior alone (its
squared error over all compared pixels: what the image's LRMS would be with perfect edges).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numba as nb
import numpy as np

from api_schemas import load_scene_file
from bench.docs_writer import replace_block
from bench.ldc_accuracy import LLF_PARAMS, LLF_RES, scene_setup, views
from bench.ldc_equal_error import _timed
from bench.mitsuba_crosscheck import comparison_mask
from engine.metrics import luminance
from engine.newviews.ldc import bake_ldc
from engine.newviews.llf import bake_llf
from engine.newviews.renderer import EDGE_CONTRAST, LDCViewRenderer, _edge_pixels, _mean_luminance
from engine.reference import ReferenceParams
from engine.scene import CameraParams
from samples import SAMPLES_DIR, sample_path
from workers.scene_loader import directory_resolver, load_scene

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "accuracy" / "ldc.md"
DATA = ROOT / "docs" / "data" / "ldc_antialias.json"

GT = ReferenceParams(spp=64, max_depth=4, glossy_samples=8, indirect_samples=0, seed=7)
# scene -> (LDC resolution, LLF f or None, method)
SCENES = {"cornell_box": (256, None, "ldc"), "mirror_box": (256, 4, "ldc+ibrt:1")}
SETTINGS = [(1, "uniform"), (2, "uniform"), (4, "uniform"), (2, "edges"), (3, "edges"), (4, "edges")]
CORNELL_CENTRE = (278.0, 273.0, 280.0)
CORNELL_ORBITS = ((12.0, 7.0), (-20.0, -5.0), (-6.0, 2.0))


def orbit(centre, dist: float, az: float, el: float, size: int, fov: float) -> CameraParams:
    """A camera at ``dist`` from ``centre``, azimuth ``az`` about +y from -z, elevation ``el``."""
    a, e = math.radians(az), math.radians(el)
    off = np.array([math.sin(a) * math.cos(e), math.sin(e), -math.cos(a) * math.cos(e)]) * dist
    return CameraParams("perspective", tuple(np.asarray(centre) + off), tuple(centre), (0.0, 1.0, 0.0), size, size,
                        fov)


def scene_views(name: str, cam: CameraParams, size: int, n: int) -> list[CameraParams]:
    if name == "cornell_box":
        return [orbit(CORNELL_CENTRE, 1080.0, az, el, size, cam.fov_y_deg) for az, el in CORNELL_ORBITS[:n]]
    return [views(cam, size, 8)[i] for i in (1, 4, 6)[:n]]


def edge_classes(r, rel_depth: float, bg) -> tuple[np.ndarray, np.ndarray]:
    """(geometric, shading) edge masks (h, w) of a one-sample render (module docstring)."""
    y_mean = _mean_luminance(r.radiance, r.object_id, np.asarray(bg, np.float64))
    geo = _edge_pixels(r.object_id, r.depth, r.radiance, rel_depth, math.inf, y_mean).reshape(r.object_id.shape)
    every = _edge_pixels(r.object_id, r.depth, r.radiance, rel_depth, EDGE_CONTRAST, y_mean)
    return geo, every.reshape(r.object_id.shape) & ~geo


def ground_truth(ren, name: str, vi: int, cam: CameraParams, cache: Path | None):
    """The reference's ground truth of view ``vi`` (radiance, object_id), kept in ``cache`` if given."""
    key = hashlib.sha256(repr((cam, GT)).encode()).hexdigest()[:12]
    f = None if cache is None else cache / f"{name}_{cam.width}x{cam.height}_v{vi}_{key}.npz"
    if f is not None and f.exists():
        d = np.load(f)
        return d["radiance"], d["object_id"]
    g = ren.render(cam, GT)
    if f is not None:
        f.parent.mkdir(parents=True, exist_ok=True)
        np.savez(f, radiance=g.radiance, object_id=g.object_id)
    return g.radiance, g.object_id


def run_scene(name: str, size: int, n_views: int, settings, log, cache: Path | None = None) -> dict:
    ldc_res, f, method = SCENES[name]
    sc, caster, plan, _, ren = scene_setup(name, size, 8)
    cam0 = load_scene(load_scene_file(sample_path(name)), directory_resolver(SAMPLES_DIR)).camera
    cams = scene_views(name, cam0, size, n_views)
    t0 = time.perf_counter()
    gts = [ground_truth(ren, name, i, cam, cache) for i, cam in enumerate(cams)]
    log(f"{name}: ground truth {(time.perf_counter() - t0) / len(cams):.1f} s/view")
    masks = [comparison_mask(sc, g[1])[0] for g in gts]
    ldc = bake_ldc(sc, caster, ldc_res, plan=plan)
    llf = bake_llf(sc, caster, f, LLF_RES, params=LLF_PARAMS, max_bytes=16 << 30) if f is not None else None
    r = LDCViewRenderer(sc, ldc, llf, plan)
    r.render(cams[0], method)  # warm: IBRT accel, numba dispatch
    one = [r.render(cam, method) for cam in cams]
    classes = [edge_classes(o, r.silhouette_rel_depth, ldc.background) for o in one]
    out: dict = {"scene": name, "ldc_res": ldc_res, "llf_f": f, "method": method, "views": len(cams),
                 "gt": {"spp": GT.spp, "glossy_samples": GT.glossy_samples}, "settings": []}
    for ss, aa in settings:
        r.render(cams[0], method, supersample=ss, antialias=aa)  # warm
        errs, interior, ts, share_geo, share_shade, edge_frac = [], [], [], [], [], []
        for cam, g, m, (geo, shade) in zip(cams, gts, masks, classes, strict=True):
            dt, o = _timed(lambda cam=cam, ss=ss, aa=aa: r.render(cam, method, supersample=ss, antialias=aa))
            ts.append(dt)
            yt, yr = luminance(o.radiance)[m], luminance(g[0])[m]
            mean = float(yr.mean())
            se = np.square(yt - yr)
            tot = float(se.sum())
            errs.append(math.sqrt(tot / se.size) / mean)
            inner = ~(geo | shade)[m]
            interior.append(math.sqrt(float(se[inner].sum()) / se.size) / mean)
            share_geo.append(float(se[geo[m]].sum()) / tot)
            share_shade.append(float(se[shade[m]].sum()) / tot)
            edge_frac.append(o.counts.get("edge_pixels", 0) / (cam.width * cam.height))
        row = {"supersample": ss, "antialias": aa, "lrms_mean": float(np.mean(errs)), "lrms_max": float(np.max(errs)),
               "lrms_interior": float(np.mean(interior)), "share_geometric_edges": float(np.mean(share_geo)),
               "share_shading_edges": float(np.mean(share_shade)), "render_ms": 1000 * float(np.median(ts)),
               "edge_pixel_fraction": float(np.mean(edge_frac)),
               "geometric_edge_fraction": float(np.mean([c[0].mean() for c in classes])),
               "shading_edge_fraction": float(np.mean([c[1].mean() for c in classes]))}
        out["settings"].append(row)
        log(f"{name}: ss{ss} {aa}: LRMS {row['lrms_mean']:.4f} (interior {row['lrms_interior']:.4f}, "
            f"edges geo {row['share_geometric_edges']:.2f} shading {row['share_shading_edges']:.2f}) "
            f"{row['render_ms']:.0f} ms, edge pixels {row['edge_pixel_fraction']:.3f}")
    return out


def write_doc(results: dict) -> None:
    cfg = results["config"]
    lines = [f"Generated by `python -m bench.ldc_antialias` on {cfg['date']} ({cfg['machine']}; load average "
             f"{cfg['load_start']:.1f} at start, {cfg['load_end']:.1f} at the end). {cfg['size']}x{cfg['size']}, "
             "direct light only, ground truth = the reference at 64 jittered spp (box filter). Times: per view the "
             "faster of two renders, median over the views, warm renderer, wall clock on a shared 2-core machine.",
             ""]
    for s in results["scenes"]:
        geo, shade = s["settings"][0]["geometric_edge_fraction"], s["settings"][0]["shading_edge_fraction"]
        lines += [f"**{s['scene']}** (LDC {s['ldc_res']}{'' if s['llf_f'] is None else ', LLF f=' + str(s['llf_f'])}, "
                  f"`{s['method']}`, {s['views']} views; edge pixels of the one-sample image: geometric "
                  f"{100 * geo:.1f} %, shading {100 * shade:.1f} %)", "",
                  "| supersample | antialias | LRMS mean (max) | LRMS interior only | error share: geometric edges | "
                  "shading edges | pixels supersampled | render ms | x ss1 |",
                  "|---|---|---|---|---|---|---|---|---|"]
        t1 = s["settings"][0]["render_ms"]
        for row in s["settings"]:
            frac = 1.0 if row["antialias"] == "uniform" and row["supersample"] > 1 else row["edge_pixel_fraction"]
            lines.append(f"| {row['supersample']} | {row['antialias'] if row['supersample'] > 1 else '-'} | "
                         f"{100 * row['lrms_mean']:.2f} % ({100 * row['lrms_max']:.2f} %) | "
                         f"{100 * row['lrms_interior']:.2f} % | {100 * row['share_geometric_edges']:.0f} % | "
                         f"{100 * row['share_shading_edges']:.0f} % | {100 * frac:.1f} % | {row['render_ms']:.0f} | "
                         f"{row['render_ms'] / t1:.2f} |")
        lines.append("")
    replace_block(DOC, "ldc_antialias", "\n".join(lines))


# ----------------------------------------------------------------------------- direct-light convergence

CONV_DATA = ROOT / "docs" / "data" / "ldc_direct_convergence.json"
CONV_LADDER = (4, 16, 64, 256)
CONV_TRUTH = 4096  # 64 x 64 rect-light samples per LDC sample
CONV_SEEDS = (1, 2, 3)


def direct_convergence(name: str, ldc_res: int, n_points: int, log) -> dict:
    """How the LDC's direct light converges with its rect-light samples per LDC sample: on
    ``n_points`` LDC samples (a seeded random subset of the z axis at ``ldc_res``), the relative RMS
    error of the direct light (luminance, both sides, rows lit in the converged value) at each count
    of ``CONV_LADDER`` against ``CONV_TRUTH`` samples, mean over ``CONV_SEEDS``, the seconds of
    shading (shadow rays included), and the error split between penumbra rows (the converged value
    strictly between unoccluded and black) and the rest."""
    from engine.newviews.ldc import bake_ldc_axis, shade_samples, surface_attributes

    sc, caster, plan, _, _ = scene_setup(name, 64, 1)
    ax = bake_ldc_axis(sc, caster, 2, ldc_res, plan=plan, area_light_samples=1)
    pick = np.sort(np.random.default_rng(0).choice(ax.n_samples, min(n_points, ax.n_samples), replace=False))
    p, ng, ns = surface_attributes(sc, ax.ldi.prim[pick], ax.ldi.u[pick], ax.ldi.v[pick])
    mat = ax.material[pick]
    occl = np.asarray(plan.occludable_lights, dtype=np.bool_)

    def shade(n: int, seed: int, occludable=occl) -> tuple[np.ndarray, float]:
        t0 = time.perf_counter()
        d, _, _ = shade_samples(sc, caster, p, ng, ns, mat, occludable, store_bits=False, area_light_samples=n,
                                seed=seed)
        return luminance(d.astype(np.float64)), time.perf_counter() - t0

    shade(4, 0)  # compile / warm
    truth, t_truth = shade(CONV_TRUTH, 99)
    free, _ = shade(CONV_TRUTH, 99, np.zeros_like(occl))
    lit = truth > 0
    frac = np.where(free > 0, truth / np.where(free > 0, free, 1.0), 0.0)
    pen = lit & (frac < 0.999)
    mean = float(truth[lit].mean())
    log(f"{name}: {pick.size} samples, converged value {t_truth:.1f} s; penumbra rows {pen.sum() / lit.sum():.3f}")
    rows = []
    for n in CONV_LADDER:
        se, se_pen, ts = [], [], []
        for seed in CONV_SEEDS:
            y, dt = shade(n, seed)
            d2 = np.square(y - truth)
            se.append(float(d2[lit].mean()))
            se_pen.append(float(d2[pen].sum() / lit.sum()))
            ts.append(dt)
        row = {"samples": n, "rel_rms": math.sqrt(np.mean(se)) / mean,
               "rel_rms_penumbra": math.sqrt(np.mean(se_pen)) / mean,
               "rel_rms_rest": math.sqrt(max(np.mean(se) - np.mean(se_pen), 0.0)) / mean,
               "seconds": float(np.median(ts))}
        rows.append(row)
        log(f"  {n} samples: rel RMS {row['rel_rms']:.5f} (penumbra {row['rel_rms_penumbra']:.5f}, "
            f"rest {row['rel_rms_rest']:.5f}) {row['seconds']:.2f} s")
    return {"scene": name, "ldc_res": ldc_res, "points": int(pick.size), "lit_rows": int(lit.sum()),
            "penumbra_share": float(pen.sum() / lit.sum()), "truth_samples": CONV_TRUTH, "seeds": list(CONV_SEEDS),
            "ladder": rows}


def write_convergence_doc(results: dict) -> None:
    lines = ["Relative RMS error of the LDC's direct light per LDC sample (luminance, every lit sample side) "
             f"against {CONV_TRUTH} rect-light samples per LDC sample, mean square over seeds "
             f"{', '.join(str(s) for s in CONV_SEEDS)}; seconds = shading with shadow rays of the subset, median "
             "over the seeds. Penumbra: sample sides whose converged light is strictly between black and "
             "unoccluded; the two split columns add in quadrature to the total.", ""]
    for label, r in results.items():
        lines += [f"**{label}** ({r['scene']}, LDC {r['ldc_res']}, z axis, {r['points']} samples, "
                  f"{100 * r['penumbra_share']:.1f} % of the lit sides in penumbra; {r['date']}, load "
                  f"{r['load']:.1f})", "",
                  "| rect samples per LDC sample | rel. RMS | penumbra part | rest | s |", "|---|---|---|---|---|"]
        for row in r["ladder"]:
            lines.append(f"| {row['samples']} | {100 * row['rel_rms']:.3f} % | "
                         f"{100 * row['rel_rms_penumbra']:.3f} % | {100 * row['rel_rms_rest']:.3f} % | "
                         f"{row['seconds']:.2f} |")
        lines.append("")
    for label, r in results.items():  # what an allocation by class would give (from the rows above)
        share, by_n = r["penumbra_share"], {row["samples"]: row for row in r["ladder"]}
        lines += [f"Allocations by class, **{label}** (a model from the split columns above: the error of an "
                  "allocation that gives the penumbra sides more samples than the rest, were they known in "
                  "advance; an adaptive bake would also pay for finding them):", "",
                  "| rest | penumbra | mean samples per side | rel. RMS |", "|---|---|---|---|"]
        for n_rest in sorted(by_n):
            for n_pen in sorted(by_n):
                if n_pen > n_rest:
                    err = math.hypot(by_n[n_rest]["rel_rms_rest"], by_n[n_pen]["rel_rms_penumbra"])
                    lines.append(f"| {n_rest} | {n_pen} | {n_rest * (1 - share) + n_pen * share:.0f} | "
                                 f"{100 * err:.3f} % |")
        lines.append("")
    replace_block(DOC, "ldc_direct_convergence", "\n".join(lines).rstrip())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", action="append", choices=sorted(SCENES), help="scene (repeatable; default all)")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="iteration run: 128x128, 1 view, no docs")
    ap.add_argument("--no-docs", action="store_true")
    ap.add_argument("--gt-cache", type=Path, help="keep the ground truths in this directory (reruns reuse them)")
    ap.add_argument("--direct-convergence", metavar="LABEL",
                    help="measure instead how the LDC's direct light converges with its rect-light samples "
                         "(cornell_box, LDC 256) and file the result under LABEL (the sampler's name)")
    args = ap.parse_args(argv)
    if args.direct_convergence:
        res = direct_convergence("cornell_box", 256, 20000, lambda m: print(m, flush=True))
        res.update(date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), load=os.getloadavg()[0])
        stored = json.loads(CONV_DATA.read_text()) if CONV_DATA.exists() else {}
        stored[args.direct_convergence] = res
        CONV_DATA.parent.mkdir(parents=True, exist_ok=True)
        CONV_DATA.write_text(json.dumps(stored, indent=1) + "\n")
        write_convergence_doc(stored)
        return 0
    size, n_views = (128, 1) if args.quick else (args.size, args.views)
    names = args.scene or list(SCENES)

    def log(msg):
        print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)

    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    scenes = [run_scene(n, size, n_views, SETTINGS, log, args.gt_cache) for n in names]
    cfg = {"argv": " ".join(sys.argv[1:] if argv is None else argv), "size": size, "n_views": n_views,
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "machine": f"{platform.machine()}, {os.cpu_count()} cores, {nb.get_num_threads()} numba threads",
           "load_start": load0, "load_end": os.getloadavg()[0], "run_s": time.perf_counter() - t0}
    if args.quick or args.no_docs:
        return 0
    old = json.loads(DATA.read_text()) if DATA.exists() else {"scenes": []}
    if old.get("config", {}).get("size") == size:
        keep = [s for s in old["scenes"] if s["scene"] not in names]
        scenes = sorted(keep + scenes, key=lambda s: list(SCENES).index(s["scene"]))
    results = {"config": cfg, "scenes": scenes}
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(results, indent=1) + "\n")
    write_doc(results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
