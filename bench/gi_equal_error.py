"""What global illumination costs: image-based views with baked indirect light against path tracers.

``python -m bench.gi_equal_error`` (cornell_box, 6 views at 512x512; ``--quick`` for an iteration
run at 128x128 with 2 views). Writes the ``gi_equal_error`` block of ``docs/accuracy/gi.md``, its
plot ``docs/img/gi_equal_error.png`` and ``docs/data/gi_equal_error.json``.

Ground truth (the converged image of each view): the reference renderer's direct light at 64
jittered samples per pixel (box filter) plus its indirect light at each pixel centre's first hit,
path-traced per pixel to a relative standard error of 2 % of the pixel's brightness
(``trace_indirect_points``, the estimator the reference uses at camera hits, 3 bounces). Its noise
floor is measured seed to seed (a second ground truth of view 0) and every LRMS is also given
corrected for it, ``sqrt(LRMS^2 - floor^2)`` (noise adds in quadrature): a ground truth below 1 %
at 512x512 needs ~4,000 paths per pixel, about 20 minutes per view on this machine (1.2 % took
1,400 paths per pixel, 27 s per 128x128 view). The indirect part is
point-sampled at the pixel centre: at edge pixels (a few % of the image) the box filter would
mix the indirect light of both sides; that approximation is in the floor too and is stated
beside the results. It is exact only for diffuse scenes (indirect light seen through a mirror
is not added), which the Cornell box is. The ground truth is checked against Mitsuba 3's
``path`` (llvm_ad_rgb, both cores, the scene's own ``cbox-rgb.xml``) at high spp on one view.

Equal error: for each image-based setting (LDC resolution, indirect noise target,
supersampling), its LRMS against the ground truth over the views (``comparison_mask``: covered
pixels not next to an emitter), its render time; and the time our reference (``spp`` = indirect
paths per pixel raised 1 .. 64) and Mitsuba 3 (multijitter, spp raised 1 .. 256) each need to reach
that LRMS, interpolated log-log on their ladders (measured on 2 of the views; beyond a ladder's
end extrapolated with error ~ time^-1/2, marked). Break-even: the number of views after which
bake + views cost less than rendering every view with the reference at the same error.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.docs_writer import replace_block
from bench.ldc_accuracy import scene_setup
from bench.mitsuba_crosscheck import comparison_mask
from engine.camera import camera_rays, pixel_centers
from engine.metrics import REC709_WEIGHTS, lrms
from engine.newviews.indirect import IndirectParams, side_frames, trace_indirect_points
from engine.newviews.ldc import bake_ldc, surface_attributes
from engine.newviews.renderer import LDCViewRenderer
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.sampler import sample_key
from engine.scene import CameraParams, RuntimeScene

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "accuracy" / "gi.md"
PLOT = ROOT / "docs" / "img" / "gi_equal_error.png"
DATA = ROOT / "docs" / "data" / "gi_equal_error.json"
LUMA = np.asarray(REC709_WEIGHTS)
LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"

BOUNCES = 3
GT_DIRECT = ReferenceParams(spp=64, indirect_samples=0, area_light_samples=16, max_depth=4, seed=101)
GT_INDIRECT = IndirectParams(noise=0.02, min_paths=64, max_paths=8192, bounces=BOUNCES, seed=101)
REF_LADDER = [1, 4, 16, 64]  # spp, one indirect path per camera sample
MI_LADDER = [1, 4, 16, 64]
MI_CHECK_SPP = 256


def orbit_views(target, eye, fov: float, size: int, n: int) -> list[CameraParams]:
    """n views on a sphere around ``target`` through ``eye``: azimuth -20 .. 20 deg, elevation
    alternating +-7 deg; none looks along an axis of the LDC (5 deg or more off each)."""
    target = np.asarray(target, float)
    off = np.asarray(eye, float) - target
    r = float(np.linalg.norm(off))
    az0 = math.atan2(off[0], -off[2])
    el0 = math.asin(off[1] / r)
    out = []
    for i, az in enumerate(np.linspace(-20.0, 20.0, n)):
        if abs(az) < 5.0:
            az = 5.0 if az >= 0 else -5.0
        a = az0 + math.radians(az)
        e = el0 + math.radians(7.0 if i % 2 else -7.0)
        d = np.array([math.sin(a) * math.cos(e), math.sin(e), -math.cos(a) * math.cos(e)]) * r
        out.append(CameraParams("perspective", tuple(target + d), tuple(target), (0.0, 1.0, 0.0), size, size, fov))
    return out


def converged_view(ren: ReferenceRenderer, sc: RuntimeScene, cam: CameraParams, seed_offset: int = 0) -> dict:
    """The ground truth of one view (see the module docstring) and its noise estimate."""
    t0 = time.perf_counter()
    direct = ren.render(cam, ReferenceParams(**{**GT_DIRECT.to_dict(), "seed": GT_DIRECT.seed + seed_offset}))
    t_direct = time.perf_counter() - t0
    px, py = pixel_centers(cam)
    o, d = camera_rays(cam, px, py)
    hits = ren.caster.intersect(o, d)
    hit = np.flatnonzero(hits.prim >= 0)
    p, ng, ns = surface_attributes(sc, hits.prim[hit], hits.u[hit], hits.v[hit])
    g2, s2 = side_frames(ng, ns)
    side = (np.einsum("ij,ij->i", ng, d[hit]) > 0).astype(np.int64)
    rows = np.arange(hit.size)
    flat = direct.radiance.reshape(-1, 3).astype(np.float64)
    t0 = time.perf_counter()
    mat = sc.tri_material[hits.prim[hit]].astype(np.int32)
    ind = trace_indirect_points(ren, p, g2[rows, side], s2[rows, side], mat, flat[hit], GT_INDIRECT,
                                key=sample_key(GT_INDIRECT.seed + seed_offset, 9),
                                brightness=float((flat[hit] @ LUMA).mean()))
    t_ind = time.perf_counter() - t0
    img = flat.copy()
    img[hit] += ind.radiance
    se = np.zeros(flat.shape[0])
    se[hit] = ind.stderr
    return {"radiance": img.reshape(direct.radiance.shape).astype(np.float32), "direct": direct.radiance,
            "object_id": direct.object_id, "indirect_se": se.reshape(direct.radiance.shape[:2]),
            "seconds": {"direct": t_direct, "indirect": t_ind}, "paths": int(ind.paths.sum())}


def corrected(err: float, floor: float) -> float:
    """LRMS against the truth from LRMS against a ground truth with noise ``floor`` (quadrature)."""
    return math.sqrt(max(err * err - floor * floor, 0.0))


def _mean_y(img: np.ndarray, mask: np.ndarray) -> float:
    return float((img[mask].astype(np.float64) @ LUMA).mean())


def time_at(err: float, ladder: list[dict]) -> tuple[float | None, bool]:
    """Seconds a ladder needs for LRMS ``err`` (log-log interpolation on the monotone ladder;
    beyond its most accurate point extrapolated with error ~ time^-1/2: flag True)."""
    pts = sorted((r["seconds"], r["lrms"]) for r in ladder)
    best = []
    for t, e in pts:  # monotone: each point is the fastest to reach at most its error
        if not best or e < best[-1][1]:
            best.append((t, e))
    if not best or err > best[0][1]:
        return (best[0][0] if best else None), False  # already less accurate than the cheapest point
    for (t0, e0), (t1, e1) in zip(best, best[1:], strict=False):
        if e1 <= err <= e0:
            f = (math.log(err) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return math.exp(math.log(t0) + f * (math.log(t1) - math.log(t0))), False
    t_last, e_last = best[-1]
    return t_last * (e_last / err) ** 2, True


def run(scene_name: str, size: int, n_views: int, ldc_settings: list[tuple[int, float]], log) -> dict:
    sc, caster, plan, _, ren = scene_setup(scene_name, size, 1)
    lo, hi = sc.bounds
    target = 0.5 * (np.asarray(lo) + np.asarray(hi))
    from api_schemas import load_scene_file
    from bench.ibrt_throughput import sample_path

    cam0 = load_scene_file(sample_path(scene_name)).camera
    cams = orbit_views(target, cam0.eye, cam0.fov_y_deg, size, n_views)
    out: dict[str, Any] = {"scene": scene_name, "size": size, "views": n_views, "bounces": BOUNCES,
                           "plan": plan.to_dict()}

    # ---- ground truth
    gts = []
    for i, cam in enumerate(cams):
        g = converged_view(ren, sc, cam)
        g["mask"], _ = comparison_mask(sc, g["object_id"])
        gts.append(g)
        log(f"gt view {i}: direct {g['seconds']['direct']:.1f} s, indirect {g['seconds']['indirect']:.1f} s "
            f"({g['paths'] / max(1, int((g['object_id'] >= 0).sum())):.0f} paths/px)")
    g2 = converged_view(ren, sc, cams[0], seed_offset=1)
    m0 = gts[0]["mask"]
    mean0 = _mean_y(gts[0]["radiance"], m0)
    direct_noise = lrms(gts[0]["direct"], g2["direct"], m0) / math.sqrt(2)
    ind_noise = float(np.sqrt(np.mean(np.square(gts[0]["indirect_se"][m0])))) / mean0
    seed_noise = lrms(gts[0]["radiance"], g2["radiance"], m0) / math.sqrt(2)
    out["ground_truth"] = {
        "direct_noise_lrms": direct_noise, "indirect_noise_lrms_estimated": ind_noise,
        "noise_lrms_seed_to_seed": seed_noise,
        "seconds_per_view": float(np.median([sum(g["seconds"].values()) for g in gts])),
        "indirect_share": float(np.mean([1 - _mean_y(g["direct"], g["mask"]) / _mean_y(g["radiance"], g["mask"])
                                         for g in gts]))}
    log(f"gt noise: seed-to-seed {seed_noise:.4f} (direct {direct_noise:.4f}, indirect est {ind_noise:.4f})")

    ladder_views = [0, n_views // 2]
    # ---- our reference, raising spp (one indirect path per camera sample)
    ref_ladder = []
    for spp in REF_LADDER:
        params = ReferenceParams(spp=spp, indirect_samples=spp, indirect_bounces=BOUNCES, area_light_samples=1,
                                 max_depth=4, seed=3)
        errs, ts, cpus = [], [], []
        for vi in ladder_views:
            c0, t0 = time.process_time(), time.perf_counter()
            r = ren.render(cams[vi], params)
            ts.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
            errs.append(lrms(r.radiance, gts[vi]["radiance"], gts[vi]["mask"]))
        ref_ladder.append({"spp": spp, "lrms": float(np.mean(errs)), "seconds": float(np.median(ts)),
                           "cpu_seconds": float(np.median(cpus))})
        log(f"reference spp {spp}: lrms {np.mean(errs):.4f} {np.median(ts):.2f} s")
    out["reference_ladder"] = ref_ladder

    # ---- Mitsuba 3
    out["mitsuba"] = mitsuba_part(scene_name, cams, gts, ladder_views, log)

    # ---- image-based settings
    settings = []
    for res, noise in ldc_settings:
        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        c0, t0 = time.process_time(), time.perf_counter()
        ldc = bake_ldc(sc, caster, res, indirect=IndirectParams(noise=noise, bounces=BOUNCES))
        t_bake, c_bake = time.perf_counter() - t0, time.process_time() - c0
        rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        state = ldc.plan["indirect"]
        log(f"bake LDC {res} noise {noise}: {t_bake:.1f} s, {ldc.n_samples} samples, {ldc.nbytes / 2**20:.1f} MiB")
        r = LDCViewRenderer(sc, ldc, None)
        for ss in (1, 2):
            r.render(cams[0], "ldc", supersample=ss)  # warm
            errs, ts, cpus, breakdown = [], [], [], []
            for cam, g in zip(cams, gts, strict=True):
                dts, dcs = [], []
                for _ in range(3):
                    c1, t1 = time.process_time(), time.perf_counter()
                    v = r.render(cam, "ldc", supersample=ss)
                    dts.append(time.perf_counter() - t1)
                    dcs.append(time.process_time() - c1)
                ts.append(min(dts))
                cpus.append(min(dcs))
                errs.append(lrms(v.radiance, g["radiance"], g["mask"]))
                breakdown.append(error_breakdown(v.radiance, g["radiance"], g["mask"]))
            row = {"ldc_resolution": res, "noise": noise, "supersample": ss, "lrms": float(np.mean(errs)),
                   "lrms_max": float(np.max(errs)), "render_ms": 1000 * float(np.median(ts)),
                   "render_cpu_ms": 1000 * float(np.median(cpus)), "bake_s": t_bake, "bake_cpu_s": c_bake,
                   "bake_peak_rss_growth_mib": max(0, rss1 - rss0) / 1024.0, "ldc_mib": ldc.nbytes / 2**20,
                   "samples": ldc.n_samples, "indirect": state,
                   "error_top1pct_share": float(np.mean([b["top1pct_share"] for b in breakdown])),
                   "lrms_without_top2pct": float(np.mean([b["lrms_without_top2pct"] for b in breakdown])),
                   "mean_ratio": float(np.mean([_mean_y(v.radiance, g["mask"]) / _mean_y(g["radiance"], g["mask"])
                                                for g in gts[-1:]]))}
            row["lrms_corrected"] = corrected(row["lrms"], seed_noise)
            t_ref, ext_r = time_at(row["lrms"], ref_ladder)
            t_mi, ext_m = time_at(row["lrms"], out["mitsuba"]["ladder"]) if out["mitsuba"].get("ladder") else \
                (None, False)
            row.update(ref_s_at_error=t_ref, ref_extrapolated=ext_r, mitsuba_s_at_error=t_mi,
                       mitsuba_extrapolated=ext_m)
            if t_ref:
                per_view_gain = t_ref - row["render_ms"] / 1000
                row["break_even_views"] = math.ceil(t_bake / per_view_gain) if per_view_gain > 0 else None
            settings.append(row)
            log(f"  ss{ss}: lrms {row['lrms']:.4f} {row['render_ms']:.1f} ms; reference {t_ref} s, mitsuba {t_mi} s")
        # the same bake without indirect light, for the record of what it adds
        ldc0 = bake_ldc(sc, caster, res)
        v0 = [LDCViewRenderer(sc, ldc0, None).render(c, "ldc") for c in cams[:2]]
        out.setdefault("direct_only", []).append({
            "ldc_resolution": res, "lrms": float(np.mean([lrms(v.radiance, g["radiance"], g["mask"])
                                                          for v, g in zip(v0, gts, strict=False)])),
            "mean_ratio": float(np.mean([_mean_y(v.radiance, g["mask"]) / _mean_y(g["radiance"], g["mask"])
                                         for v, g in zip(v0, gts, strict=False)]))})
    out["settings"] = settings
    out["bounce_costs"] = bounce_costs(sc, caster)
    return out


def bounce_costs(sc: RuntimeScene, caster, res: int = 64) -> list[dict]:
    """What each bounce limit costs and brings, on the z axis of an LDC of ``res`` (noise 0.02):
    seconds, CPU seconds, mean paths per side, mean indirect luminance (relative to 5 bounces)."""
    from engine.newviews.ldc import bake_ldc_axis, indirect_chunk

    ax = bake_ldc_axis(sc, caster, 2, res)
    rows = []
    for b in (1, 2, 3, 5):
        c0, t0 = time.process_time(), time.perf_counter()
        r = indirect_chunk(sc, caster, ax, 0, ax.n_samples, IndirectParams(noise=0.02, bounces=b))
        rows.append({"bounces": b, "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0,
                     "paths_mean": r.stats["paths_mean"],
                     "mean_indirect": float((r.radiance.reshape(-1, 3).astype(np.float64) @ LUMA).mean())})
    for row in rows:
        row["share_of_5_bounces"] = row["mean_indirect"] / max(rows[-1]["mean_indirect"], 1e-300)
    return rows


def error_breakdown(test: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> dict:
    """Where the squared error is: the share carried by the worst 1 % of pixels (edges: silhouettes,
    shadow and light borders) and the LRMS of the rest."""
    y_t, y_r = test[mask].astype(np.float64) @ LUMA, ref[mask].astype(np.float64) @ LUMA
    d2 = np.sort(np.square(y_t - y_r))[::-1]
    mean = y_r.mean()
    k1, k2 = max(1, d2.size // 100), max(1, d2.size // 50)
    return {"top1pct_share": float(d2[:k1].sum() / max(d2.sum(), 1e-300)),
            "lrms_without_top2pct": float(math.sqrt(d2[k2:].sum() / d2.size) / mean)}


def mitsuba_part(scene_name: str, cams, gts, ladder_views, log) -> dict:
    """Mitsuba 3 on the scene's own Mitsuba file (only the Cornell box has one here)."""
    if scene_name != "cornell_box":
        return {"skipped": "no Mitsuba twin of this scene"}
    os.environ.setdefault("DRJIT_LIBLLVM_PATH", LLVM)
    from bench import mitsuba_bridge as mb

    try:
        mi = mb.mitsuba("llvm_ad_rgb")
        variant = "llvm_ad_rgb"
    except Exception:  # noqa: BLE001 - fall back to the variant that needs no LLVM
        mi = mb.mitsuba("scalar_rgb")
        variant = "scalar_rgb"
    scene = mb.load_cornell_box(cams[0].width, 16)

    def sensor(cam, spp):
        return mi.load_dict(mb.sensor_dict(cam, spp, "multijitter"))

    mb.render(scene, "path", BOUNCES, spp=1, sensor=sensor(cams[0], 1))  # JIT warm-up
    ladder = []
    for spp in MI_LADDER:
        errs, ts = [], []
        for vi in ladder_views:
            r = mb.render(scene, "path", BOUNCES, spp=spp, seed=5, sensor=sensor(cams[vi], spp))
            ts.append(r.seconds)
            errs.append(lrms(r.radiance, gts[vi]["radiance"], gts[vi]["mask"]))
        ladder.append({"spp": spp, "lrms": float(np.mean(errs)), "seconds": float(np.median(ts))})
        log(f"mitsuba spp {spp}: lrms {np.mean(errs):.4f} {np.median(ts):.2f} s")
    r = mb.render(scene, "path", BOUNCES, spp=MI_CHECK_SPP, seed=9, sensor=sensor(cams[0], MI_CHECK_SPP))
    m = gts[0]["mask"]
    check = {"spp": MI_CHECK_SPP, "lrms_vs_gt": lrms(r.radiance, gts[0]["radiance"], m),
             "mean_ratio_gt_over_mitsuba": _mean_y(gts[0]["radiance"], m) / _mean_y(r.radiance, m),
             "seconds": r.seconds}
    log(f"mitsuba {MI_CHECK_SPP} spp vs gt: {check}")
    return {"variant": variant, "sampler": "multijitter", "ladder": ladder, "check": check}


# ---------------------------------------------------------------------------- report


def _s(x: float | None, ext: bool = False) -> str:
    if x is None:
        return "-"
    v = f"{x:.2f}" if x < 10 else f"{x:.0f}"
    return f"~{v}*" if ext else v


def doc_block(res: dict) -> str:
    gt = res["ground_truth"]
    mi = res["mitsuba"]
    lines = [
        f"Scene `{res['scene']}`, {res['views']} views of {res['size']}x{res['size']} orbiting the box (none along an "
        f"LDC axis), {res['bounces']} bounces. Machine: {res['machine']}. Command: `{res['command']}`.",
        "",
        f"**Ground truth** ({gt['seconds_per_view']:.0f} s per view): noise floor seed to seed LRMS "
        f"{100 * gt['noise_lrms_seed_to_seed']:.2f} % (direct part {100 * gt['direct_noise_lrms']:.2f} %, indirect "
        f"part estimated {100 * gt['indirect_noise_lrms_estimated']:.2f} %). Indirect light is "
        f"{100 * gt['indirect_share']:.0f} % of the image's mean brightness.",
    ]
    if "check" in mi:
        c = mi["check"]
        lines.append(f"Against Mitsuba 3 `path` ({mi['variant']}, {c['spp']} spp multijitter, view 0): LRMS "
                     f"{100 * c['lrms_vs_gt']:.2f} % (including Mitsuba's own noise at that spp), mean brightness "
                     f"ratio ours / Mitsuba {c['mean_ratio_gt_over_mitsuba']:.4f}.")
    lines += ["", "Equal error is taken on the raw LRMS (every renderer against the same ground truth); the "
                  "corrected column removes the ground truth's own noise.",
              "", "| LDC | indirect noise target | ss | LRMS mean (max) | corrected | view ms (CPU ms) | "
                  "our reference s at that LRMS | Mitsuba s at that LRMS | x vs reference | x vs Mitsuba | "
                  "bake s (CPU s) | LDC MiB | "
                  "break-even views | worst 1 % of pixels' share of error | LRMS without worst 2 % |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["settings"]:
        t_view = r["render_ms"] / 1000
        xr = r["ref_s_at_error"] / t_view if r["ref_s_at_error"] else None
        xm = r["mitsuba_s_at_error"] / t_view if r["mitsuba_s_at_error"] else None
        lines.append(
            f"| {r['ldc_resolution']} | {r['noise']:.3f} | {r['supersample']} | {100 * r['lrms']:.2f} % "
            f"({100 * r['lrms_max']:.2f} %) | {100 * r['lrms_corrected']:.2f} % | "
            f"{r['render_ms']:.1f} ({r['render_cpu_ms']:.1f}) | "
            f"{_s(r['ref_s_at_error'], r['ref_extrapolated'])} | "
            f"{_s(r['mitsuba_s_at_error'], r['mitsuba_extrapolated'])} "
            f"| {_s(xr, r['ref_extrapolated'])} | {_s(xm, r['mitsuba_extrapolated'])} | {r['bake_s']:.0f} "
            f"({r['bake_cpu_s']:.0f}) | {r['ldc_mib']:.0f} | {r.get('break_even_views') or '-'} | "
            f"{100 * r['error_top1pct_share']:.0f} % | {100 * r['lrms_without_top2pct']:.2f} % |")
    lines += ["", "`*` extrapolated past the ladder's most accurate point with error ~ time^-1/2.", "",
              f"Ladders (mean LRMS over views 0 and {res['views'] // 2}; seconds per view):",
              "", "| renderer | spp | LRMS | s |", "|---|---|---|---|"]
    for r in res["reference_ladder"]:
        lines.append(f"| ours (reference) | {r['spp']} | {100 * r['lrms']:.2f} % | {r['seconds']:.2f} |")
    for r in mi.get("ladder", []):
        lines.append(f"| Mitsuba 3 path | {r['spp']} | {100 * r['lrms']:.2f} % | {r['seconds']:.2f} |")
    for d in res.get("direct_only", []):
        lines.append("")
        lines.append(f"Without indirect light (LDC {d['ldc_resolution']}, views 0-1): LRMS {100 * d['lrms']:.1f} %, "
                     f"mean brightness ratio {d['mean_ratio']:.3f}.")
    lines += ["", "What the bounce limit costs and brings (indirect pass of one axis, LDC 64, noise 0.02):", "",
              "| bounces | s (CPU s) | paths per side | indirect light, share of 5 bounces |", "|---|---|---|---|"]
    for b in res.get("bounce_costs", []):
        lines.append(f"| {b['bounces']} | {b['seconds']:.1f} ({b['cpu_seconds']:.1f}) | {b['paths_mean']:.0f} | "
                     f"{100 * b['share_of_5_bounces']:.1f} % |")
    lines += ["", "![LRMS against time](../img/gi_equal_error.png)"]
    return "\n".join(lines)


def plot(res: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    rl = res["reference_ladder"]
    ax.loglog([r["seconds"] for r in rl], [r["lrms"] for r in rl], "o-", label="our reference (spp raised)")
    ml = res["mitsuba"].get("ladder", [])
    if ml:
        ax.loglog([r["seconds"] for r in ml], [r["lrms"] for r in ml], "s-", label="Mitsuba 3 path (spp raised)")
    for r in res["settings"]:
        ax.loglog([r["render_ms"] / 1000], [r["lrms"]], "*", markersize=12,
                  label=f"LDC {r['ldc_resolution']} noise {r['noise']} ss{r['supersample']} (bake {r['bake_s']:.0f} s)")
    ax.axhline(res["ground_truth"]["noise_lrms_seed_to_seed"], color="grey", ls=":", label="ground truth noise")
    ax.set_xlabel("seconds per view")
    ax.set_ylabel("LRMS against the converged image")
    ax.set_title(f"{res['scene']} {res['size']}x{res['size']}, {res['bounces']} bounces")
    ax.legend(fontsize=7)
    fig.tight_layout()
    PLOT.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(PLOT, dpi=110)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="128x128, 2 views, LDC 64 (an iteration run; no docs)")
    ap.add_argument("--scene", default="cornell_box")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:7.1f} s] {msg}", flush=True)

    if args.quick:
        res = run(args.scene, 128, 2, [(64, 0.05)], log)
    else:
        res = run(args.scene, 512, 6, [(128, 0.02), (256, 0.05), (256, 0.02)], log)
    res["machine"] = f"{platform.machine()}, {os.cpu_count()} cores, Python {sys.version.split()[0]}"
    res["command"] = "python -m bench.gi_equal_error" + (" --quick" if args.quick else "")
    res["total_s"] = time.perf_counter() - t0
    if args.quick:
        print(doc_block(res))
        return 0
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(res, indent=1, default=float))
    plot(res)
    replace_block(DOC, "gi_equal_error", doc_block(res), title="Global illumination: accuracy and cost")
    log(f"wrote {DOC.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
