"""The LDC's indirect pass: the fixed path count against the adaptive sampler, and caustics from a
photon map against caustics from paths alone, at equal view error.

``flock /tmp/bench.lock python -m bench.indirect_sampling --gt-cache DIR`` bakes each scene's LDC
with each sampler setting (``IndirectParams.sampling``, ``engine/newviews/indirect_sampling.py``)
and caustic setting (``IndirectParams.caustics``, ``engine/caustics.py``) one after the other in
one process, renders the same views of each as ``bench.gi_equal_error`` does (6 views of 512 x 512
orbiting the scene, the scene's view method with its glossy lobes gathered from the light field, one
sample per pixel and 4 x 4 edge supersampling)
and compares them with that benchmark's ground truths (``--gt-cache`` shares them; missing ones
are rendered first, ~2 min per view). Per setting: the bake's wall and CPU time, its mean paths
per traced side, each view's LRMS (mean over the views), the one-sample LRMS without its worst
2 % of pixels (where the speckles of rare bright paths sit) and outside the surfaces with a glossy
lobe (kg > 0: the light field renders them, not the LDC's diffuse light this pass bakes). Writes
the ``indirect_sampling`` block of ``docs/accuracy/gi.md`` and ``docs/data/indirect_sampling.json``.

Settings: the Cornell box at LDC 128 (the API's default resolution), the mirror / glossy Cornell
box at LDC 256 with its light field (the resolution ``bench.gi_equal_error`` bakes it at).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench import gi_equal_error as gi
from bench.docs_writer import replace_block
from bench.ldc_antialias import edge_classes
from engine.metrics import lrms
from engine.newviews.indirect import IndirectParams
from engine.newviews.ldc import bake_ldc
from engine.newviews.llf import bake_llf
from engine.newviews.renderer import LDCViewRenderer
from engine.scene import RuntimeScene

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "accuracy" / "gi.md"
DATA = ROOT / "docs" / "data" / "indirect_sampling.json"

DEFAULT = IndirectParams()

PHOTONS_4M = {"caustic_photons": 1 << 22, "caustic_radius": 0.005}
"""Four times the default photons at half its radius: the same photons per kernel disk, half the blur."""

SETTINGS: dict[str, tuple[int, list[tuple[str, float, str, dict[str, Any]]]]] = {
    # scene: (LDC resolution, [(sampling, noise, caustics, other IndirectParams), ...]) -- the fixed
    # counts bracket the adaptive row; the Cornell box has no caustics (no mirror / glossy surface),
    # so its photon setting would be its path setting
    "cornell_box": (128, [("adaptive", 0.02, "paths", {}), ("fixed", 0.02, "paths", {}),
                          ("fixed", 0.014, "paths", {})]),
    "cornell_mirror_glossy": (256, [("adaptive", 0.05, "paths", {}), ("fixed", 0.05, "paths", {}),
                                    ("fixed", 0.03, "paths", {}), ("fixed", 0.05, "photons", {}),
                                    ("fixed", 0.05, "photons", PHOTONS_4M), ("fixed", 0.03, "photons", {})]),
}


def glossy_objects(sc: RuntimeScene) -> np.ndarray:
    """Per object id: does any of its triangles have a glossy lobe (kg > 0)?"""
    out = np.zeros(int(sc.tri_object.max(initial=-1)) + 1, np.bool_)
    out[sc.tri_object[np.any(sc.materials.kg[sc.tri_material] > 0.0, axis=1)]] = True
    return out


def run_scene(name: str, n_views: int, cache: Path | None, log) -> dict[str, Any]:
    spec = gi.SCENES[name]
    res, rows = SETTINGS[name]
    sc, caster, plan, _, ren = gi.scene_setup(name, 512, 1)
    cams = gi.scene_views(name, sc, 512, n_views)
    gts = []
    for cam in cams:
        g = gi.converged_view(ren, name, cam, gi.gt_params(spec, gi.GT_SEED), cache)
        g["mask"] = gi.compared_pixels(sc, spec, cam, g["depth"], g["object_id"])
        gts.append(g)
    log(f"{name}: {n_views} ground truths ready")
    llf = None
    if spec.llf is not None:
        llf = bake_llf(sc, caster, spec.llf[0], spec.llf[1], params=gi.llf_params(spec), max_bytes=16 << 30)
    out_rows = []
    outside = [g["mask"] & ~glossy_objects(sc)[np.maximum(g["object_id"], 0)] for g in gts]
    for sampling, noise, caustics, extra in rows:
        ip = IndirectParams(noise=noise, sampling=sampling, bounces=spec.bounces, caustics=caustics, **extra)
        c0, t0 = time.process_time(), time.perf_counter()
        ldc = bake_ldc(sc, caster, res, plan=plan, area_light_samples=gi.LDC_AREA_SAMPLES, indirect=ip,
                       max_bytes=gi.LDC_MAX_BYTES)
        bake_s, bake_cpu = time.perf_counter() - t0, time.process_time() - c0
        axes = ldc.plan["indirect"]["axes"]
        sides = sum(a["sides"] for a in axes)
        paths_mean = sum(a["paths_total"] for a in axes) / max(sides, 1)
        r = LDCViewRenderer(sc, ldc, llf, plan)
        # the light field's gather of the glossy lobes, as when these rows were measured: this benchmark
        # compares bakes (traced lobes, the views' default on that box, are in bench.gi_equal_error)
        one = [r.render(cam, spec.method, glossy_rays=0) for cam in cams]
        e1 = [lrms(v.radiance, g["radiance"], g["mask"]) for v, g in zip(one, gts, strict=True)]
        e_out = [lrms(v.radiance, g["radiance"], m) for v, g, m in zip(one, gts, outside, strict=True)]
        rest = [gi.error_breakdown(v.radiance, g["radiance"], g["mask"],
                                   edge_classes(v, r.silhouette_rel_depth, ldc.background))["lrms_without_top2pct"]
                for v, g in zip(one, gts, strict=True)]
        e4 = [lrms(r.render(cam, spec.method, supersample=gi.EDGES_SS, antialias="edges", glossy_rays=0).radiance,
                   g["radiance"], g["mask"]) for cam, g in zip(cams, gts, strict=True)]
        row = {"sampling": sampling, "noise": noise, "caustics": caustics, **extra,
               "lrms_1_outside_glossy": float(np.mean(e_out)), "glossy_pixels": float(np.mean(
                   [1.0 - m.sum() / max(g["mask"].sum(), 1) for m, g in zip(outside, gts, strict=True)])),
               "paths": ip.paths_per_side if sampling == "fixed" else None,
               "bake_s": bake_s, "bake_cpu_s": bake_cpu, "paths_mean": paths_mean,
               "lrms_1": float(np.mean(e1)), "lrms_1_without_top2pct": float(np.mean(rest)),
               "lrms_edges": float(np.mean(e4)), "lrms_edges_max": float(np.max(e4))}
        out_rows.append(row)
        log(f"{name} {sampling} {noise} {caustics}: bake {bake_s:.1f} s ({bake_cpu:.1f} CPU s), "
            f"{paths_mean:.0f} paths/side, "
            f"LRMS {row['lrms_1']:.4f} / 4x4 edges {row['lrms_edges']:.4f}, "
            f"w/o top 2 % {row['lrms_1_without_top2pct']:.4f}")
    return {"scene": name, "ldc_resolution": res, "method": spec.method, "views": n_views, "rows": out_rows}


def doc_block(res: dict[str, Any]) -> str:
    lines = [f"Machine: {res['machine']}. Command: `{res['command']}` (total {res['total_s'] / 60:.0f} min), "
             f"load average {res['load_start']:.1f} at the start, {res['load_end']:.1f} at the end. Bakes in one "
             "process, one after the other; each view's LRMS against `bench.gi_equal_error`'s ground truth of it "
             "(mean over the views); bake time relative to the adaptive row of the same scene.", ""]
    for s in res["scenes"]:
        lines += [f"**`{s['scene']}`**, LDC {s['ldc_resolution']}, view method `{s['method']}`, {s['views']} views "
                  "of 512x512:", "",
                  "| sampling | caustics | noise | paths per side | bake s (CPU s) | bake time vs adaptive | LRMS, one "
                  "sample | without its worst 2 % | outside glossy surfaces | LRMS, 4x4 edges (max) |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        base = next(r["bake_s"] for r in s["rows"] if r["sampling"] == "adaptive")
        for r in s["rows"]:
            paths = f"{r['paths']}" if r["paths"] else f"{r['paths_mean']:.0f} (mean)"
            caustics = r["caustics"]
            if caustics == "photons":
                caustics += f" ({r.get('caustic_photons', DEFAULT.caustic_photons) / 2 ** 20:g} M, radius " \
                            f"{r.get('caustic_radius', DEFAULT.caustic_radius):g})"
            lines.append(f"| {r['sampling']} | {caustics} | {r['noise']:g} | {paths} | "
                         f"{r['bake_s']:.1f} ({r['bake_cpu_s']:.1f}) | "
                         f"{r['bake_s'] / base:.2f}x | {100 * r['lrms_1']:.2f} % | "
                         f"{100 * r['lrms_1_without_top2pct']:.2f} % | {100 * r['lrms_1_outside_glossy']:.2f} % | "
                         f"{100 * r['lrms_edges']:.2f} % "
                         f"({100 * r['lrms_edges_max']:.2f} %) |")
        glossy = s["rows"][0]["glossy_pixels"]
        if glossy > 0:
            lines.append(f"\nGlossy surfaces cover {100 * glossy:.0f} % of the compared pixels.")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", action="append", choices=sorted(SETTINGS), help="scene (repeatable; default all)")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--gt-cache", type=Path, help="bench.gi_equal_error's ground-truth cache (shared)")
    ap.add_argument("--gt-budget-scale", type=float, default=1.0, help="as bench.gi_equal_error's (its cache key)")
    ap.add_argument("--no-doc", action="store_true", help="print the block instead of writing docs/")
    args = ap.parse_args(argv)
    gi.GT_BUDGET_SCALE[0] = args.gt_budget_scale
    t0 = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.strftime('%H:%M:%S')} {time.perf_counter() - t0:7.1f} s] {msg}", flush=True)

    load_start = os.getloadavg()[0]
    scenes = [run_scene(name, args.views, args.gt_cache, log) for name in (args.scene or list(SETTINGS))]
    machine = f"{platform.machine()}, {os.cpu_count()} cores, Python {sys.version.split()[0]}"
    res = {"scenes": scenes, "machine": machine,
           "command": "python -m bench.indirect_sampling" + (" --gt-cache DIR" if args.gt_cache else "")
           + (f" --gt-budget-scale {args.gt_budget_scale:g}" if args.gt_budget_scale != 1.0 else ""),
           "total_s": time.perf_counter() - t0, "load_start": load_start, "load_end": os.getloadavg()[0]}
    block = doc_block(res)
    if args.no_doc:
        print(block)
        return 0
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(res, indent=1, default=float))
    replace_block(DOC, "indirect_sampling", block)
    log(f"wrote {DOC.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
