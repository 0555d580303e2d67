"""What global illumination costs: image-based views with baked indirect light against path tracers.

``python -m bench.gi_equal_error`` (cornell_box and cornell_mirror_glossy, 6 views each at 512x512;
``--quick`` for an iteration run at 128x128 with 2 views; ``--scene NAME`` for one scene;
``--gt-cache DIR`` keeps the ground truths on disk, so a rerun reuses them). Writes the
``gi_equal_error`` block of ``docs/accuracy/gi.md``, a plot per scene
``docs/img/gi_equal_error_SCENE.png`` and ``docs/data/gi_equal_error.json``.

Ground truth (the converged image of each view): the reference renderer itself, full path tracing
(chain-aware: mirror / glossy chains, indirect light, caustics through MIS-weighted emitter hits),
progressive and adaptive (``ReferenceParams.max_error``, engine/progressive.py) to an estimated
LRMS of ``GT_ERROR`` or the scene's ``gt_ms`` of render time, whichever comes first, at most ``GT_CAP``
samples per pixel, box filter. Its noise floor is measured seed to seed (a second ground truth of
view 0 with another seed, ``LRMS(a, b) / sqrt 2``), and every LRMS is also given corrected for it,
``sqrt(LRMS^2 - floor^2)`` (noise adds in quadrature). The ground truth is checked against Mitsuba
3's ``path`` (llvm_ad_rgb, both cores, multijitter) on view 0 in the same run: two renders of
``MI_CHECK_SPP / 2`` spp with different seeds, whose difference gives Mitsuba's own noise, and
whose mean is compared (LRMS raw and with both noise floors taken out, mean brightness ratio).
The Cornell box's Mitsuba twin is its own ``cbox-rgb.xml``; the mirror / glossy box is converted
by ``bench/mitsuba_bridge.py``.

Bounces: the Cornell box at ``BOUNCES`` diffuse bounces (Mitsuba ``max_depth`` = bounces + 2),
the mirror / glossy box at the Mitsuba cross-check's ``MIRROR_BOUNCES`` / ``MIRROR_DEPTH``
(bench/mitsuba_crosscheck.py), so ground truth and Mitsuba count path lengths alike; the LDC bake
traces the same bounce count.

Equal error: for each image-based setting (LDC resolution, indirect noise level, method,
supersampling and ``antialias``, the glossy lobe gathered or traced with ``glossy_rays`` per
pixel (the scene's ``glossy_rays``, at one sample and at 4 x 4 edges); direct light at
``LDC_AREA_SAMPLES`` rect-light points per LDC sample), its LRMS against the ground truth over the
views (``comparison_mask``: covered pixels not next to an emitter, nor showing a rect light directly
or through mirrors), its render time; and the time our
reference (``spp`` = indirect paths per pixel raised along ``REF_LADDER``) and Mitsuba 3
(multijitter, ``MI_LADDER``) each need to reach that LRMS, interpolated log-log on their ladders
(measured on 2 of the views; beyond a ladder's end extrapolated with error ~ time^-1/2, marked).
Break-even: the number of views after which bake + views cost less than rendering every view
with the reference at the same error.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import resource
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench.docs_writer import replace_block
from bench.ldc_accuracy import scene_setup
from bench.ldc_antialias import edge_classes
from bench.mitsuba_crosscheck import (
    MIRROR_BOUNCES,
    MIRROR_DEPTH,
    comparison_mask,
    mirrored_emitters,
    sees_rect_light,
)
from engine import REFERENCE_VERSION
from engine.metrics import REC709_WEIGHTS, lrms
from engine.newviews.indirect import IndirectParams
from engine.newviews.ldc import bake_ldc
from engine.newviews.llf import bake_llf
from engine.newviews.renderer import LDCViewRenderer
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.scene import CameraParams, RuntimeScene

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "accuracy" / "gi.md"
PLOT_DIR = ROOT / "docs" / "img"
DATA = ROOT / "docs" / "data" / "gi_equal_error.json"
LUMA = np.asarray(REC709_WEIGHTS)
LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"

BOUNCES = 3
GT_ERROR = 0.01  # the adaptive ground truth's target (estimated LRMS over ReferenceRenderer.error_region)
GT_CAP = 4096  # spp cap of any pixel
GT_SEED = 101
REF_LADDER = [1, 4, 16, 64]  # spp, one indirect path per camera sample
MI_LADDER = [1, 4, 16, 64]
MI_CHECK_SPP = 256
LDC_MAX_BYTES = 8 << 30  # the worst-case bound of an LDC 512 (32 layers) is 2.2 GiB; it holds ~160 MiB
EDGES_SS = 4  # supersampling of the ``antialias="edges"`` rows
LDC_AREA_SAMPLES = 64  # rect-light points per LDC sample (docs/accuracy/ldc.md, "Direct light: convergence")


@dataclass(frozen=True)
class SceneSpec:
    """How one scene is measured: bounce counts, mirror / glossy depth, the LDC settings (resolution,
    indirect noise level, indirect stride; the pass's default fixed sampler, so the noise level sets
    the paths per side: 0.02 -> 256, 0.014 -> 512, 0.03 -> 128), the view method and an LLF for it
    (f, resolution, or None)."""

    bounces: int
    max_depth: int
    ldc: tuple[tuple[int, float, int], ...]
    gt_ms: float  # the ground truth's time budget per view
    method: str = "ldc"
    llf: tuple[int, int] | None = None
    glossy_rays: tuple[int, ...] = ()  # traced glossy lobes rendered besides the gathered one (``view.glossy_rays``)


SCENES = {
    "cornell_box": SceneSpec(bounces=BOUNCES, max_depth=0, ldc=((256, 0.02, 1), (256, 0.014, 1),
                                                                             (512, 0.014, 2)), gt_ms=140_000.0),
    "cornell_mirror_glossy": SceneSpec(bounces=MIRROR_BOUNCES, max_depth=MIRROR_DEPTH,
                                       ldc=((256, 0.03, 1), (256, 0.014, 1)),
                                       gt_ms=90_000.0, method="ldc+ibrt:1", llf=(4, 48), glossy_rays=(16, 64)),
}
QUICK_LDC = ((64, 0.05, 1), (128, 0.05, 2))


GT_BUDGET_SCALE = [1.0]  # ``--gt-budget-scale``: multiplies every scene's ``gt_ms``


def gt_params(spec: SceneSpec, seed: int, quick: bool = False) -> ReferenceParams:
    """The ground truth's reference parameters (module docstring): one indirect path and one
    rect-light sample per camera sample, as Mitsuba's ``path``."""
    return ReferenceParams(spp=GT_CAP, max_depth=spec.max_depth, area_light_samples=1, glossy_samples=1,
                           indirect_samples=GT_CAP, indirect_bounces=spec.bounces, seed=seed,
                           chunk_pixels=max(256, (1 << 20) // GT_CAP), max_error=0.03 if quick else GT_ERROR,
                           max_ms=10_000.0 if quick else spec.gt_ms * GT_BUDGET_SCALE[0])


def ladder_params(spec: SceneSpec, spp: int) -> ReferenceParams:
    return ReferenceParams(spp=spp, indirect_samples=spp, indirect_bounces=spec.bounces, area_light_samples=1,
                           glossy_samples=1, max_depth=spec.max_depth, seed=3,
                           chunk_pixels=max(256, (1 << 20) // spp))


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


def scene_views(name: str, sc: RuntimeScene, size: int, n: int) -> list[CameraParams]:
    """The benchmark's ``n`` views of sample scene ``name``: ``orbit_views`` around the centre of
    its bounds through its own camera's eye, ``size`` x ``size``."""
    from api_schemas import load_scene_file
    from bench.ibrt_throughput import sample_path

    cam0 = load_scene_file(sample_path(name)).camera
    lo, hi = sc.bounds
    return orbit_views(0.5 * (np.asarray(lo) + np.asarray(hi)), cam0.eye, cam0.fov_y_deg, size, n)


def compared_pixels(sc: RuntimeScene, spec: SceneSpec, cam: CameraParams, depth: np.ndarray,
                    object_id: np.ndarray) -> np.ndarray:
    """The pixels every LRMS of a view is taken over (``comparison_mask``): covered, not next to an
    emitter seen directly or, in a scene with mirrors, through them."""
    light_px = sees_rect_light(sc, cam, depth)
    if spec.max_depth > 0:
        light_px |= mirrored_emitters(sc, cam, spec.max_depth)
    return comparison_mask(sc, object_id, light_px)[0]


def converged_view(ren: ReferenceRenderer, name: str, cam: CameraParams, params: ReferenceParams,
                   cache: Path | None) -> dict:
    """The ground truth of one view (module docstring), from ``cache`` when it holds it (a reference
    renderer of another version, ``engine.REFERENCE_VERSION``, renders it again)."""
    key = hashlib.sha256(repr((name, cam, params.to_dict(), REFERENCE_VERSION)).encode()).hexdigest()[:16]
    f = None if cache is None else cache / f"gi_{name}_{cam.width}_{key}.npz"
    if f is not None and f.exists():
        d = np.load(f)
        return {"radiance": d["radiance"], "object_id": d["object_id"], "depth": d["depth"],
                "adaptive": json.loads(str(d["adaptive"])), "seconds": float(d["seconds"]), "cached": True}
    c0, t0 = time.process_time(), time.perf_counter()
    r = ren.render(cam, params)
    out = {"radiance": r.radiance, "object_id": r.object_id, "depth": r.depth, "adaptive": r.adaptive or {},
           "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0, "cached": False}
    if f is not None:
        f.parent.mkdir(parents=True, exist_ok=True)
        np.savez(f, radiance=r.radiance, object_id=r.object_id, depth=r.depth,
                 adaptive=np.array(json.dumps(out["adaptive"])), seconds=np.float64(out["seconds"]))
    return out


def _paths_label(row: dict) -> str:
    """The indirect pass's paths per traced side: the fixed count, or the adaptive sampler's mean."""
    axes = (row.get("indirect") or {}).get("axes") or []
    sides = sum(a.get("sides", 0) for a in axes)
    if not sides:
        return "-"
    mean = sum(a.get("paths_total", 0) for a in axes) / sides
    fixed = all(a.get("sampling") == "fixed" for a in axes)
    return f"{mean:.0f}" if fixed else f"{mean:.0f} mean, adaptive"


def _ldc_label(row: dict) -> str:
    """The LDC column: its resolution, and the indirect pass's stride when it is not 1."""
    stride = row.get("stride", 1)
    return f"{row['ldc_resolution']}" + (f", indirect every {stride}" if stride > 1 else "")


def _glossy_label(row: dict) -> str:
    """How a setting's view renders the glossy lobe: the light field's gather, or traced rays."""
    return f"traced, {row['glossy_rays']} rays" if row.get("glossy_rays") else "gathered"


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


def run(scene_name: str, size: int, n_views: int, log, cache: Path | None, quick: bool = False) -> dict:
    spec = SCENES[scene_name]
    sc, caster, plan, _, ren = scene_setup(scene_name, size, 1)
    cams = scene_views(scene_name, sc, size, n_views)
    out: dict[str, Any] = {"scene": scene_name, "size": size, "views": n_views, "bounces": spec.bounces,
                           "max_depth": spec.max_depth, "method": spec.method, "plan": plan.to_dict(),
                           "load_start": os.getloadavg()[0]}

    # ---- ground truth
    gts = []
    for i, cam in enumerate(cams):
        g = converged_view(ren, scene_name, cam, gt_params(spec, GT_SEED, quick), cache)
        g["mask"] = compared_pixels(sc, spec, cam, g["depth"], g["object_id"])
        gts.append(g)
        a = g["adaptive"]
        log(f"gt view {i}: {g['seconds']:.1f} s{' (cached)' if g['cached'] else ''}, estimated "
            f"{a.get('estimated_error', float('nan')):.4f}, spp mean {a.get('spp_mean', 0):.0f}, "
            f"stopped by {a.get('stop_reason')}")
    g2 = converged_view(ren, scene_name, cams[0], gt_params(spec, GT_SEED + 1, quick), cache)
    m0 = gts[0]["mask"]
    seed_noise = lrms(gts[0]["radiance"], g2["radiance"], m0) / math.sqrt(2)
    gp = gt_params(spec, GT_SEED, quick)
    out["ground_truth"] = {
        "noise_lrms_seed_to_seed": seed_noise, "target": gp.max_error, "budget_s": (gp.max_ms or 0.0) / 1000.0,
        "cap_spp": GT_CAP,
        "estimated_error_mean": float(np.mean([g["adaptive"].get("estimated_error", np.nan) for g in gts])),
        "spp_mean": float(np.mean([g["adaptive"].get("spp_mean", np.nan) for g in gts])),
        "stop_reasons": sorted({str(g["adaptive"].get("stop_reason")) for g in gts}),
        "seconds_per_view": float(np.median([g["seconds"] for g in [*gts, g2]])),
        "cached_views": sum(int(g["cached"]) for g in [*gts, g2])}
    log(f"gt noise: seed-to-seed {seed_noise:.4f}")

    ladder_views = [0, n_views // 2]
    # ---- our reference, raising spp (one indirect path per camera sample)
    ref_ladder = []
    ren.render(cams[ladder_views[0]], ladder_params(spec, 1))  # warm: a fresh numba cache compiles here
    for spp in REF_LADDER:
        errs, ts, cpus = [], [], []
        for vi in ladder_views:
            c0, t0 = time.process_time(), time.perf_counter()
            r = ren.render(cams[vi], ladder_params(spec, spp))
            ts.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
            errs.append(lrms(r.radiance, gts[vi]["radiance"], gts[vi]["mask"]))
        ref_ladder.append({"spp": spp, "lrms": float(np.mean(errs)), "seconds": float(np.median(ts)),
                           "cpu_seconds": float(np.median(cpus))})
        log(f"reference spp {spp}: lrms {np.mean(errs):.4f} {np.median(ts):.2f} s")
    out["reference_ladder"] = ref_ladder

    # ---- Mitsuba 3
    out["mitsuba"] = mitsuba_part(scene_name, spec, sc, cams, gts, ladder_views, seed_noise, log, quick=quick)

    # ---- image-based settings
    llf = None
    if spec.llf is not None:
        c0, t0 = time.process_time(), time.perf_counter()
        llf = bake_llf(sc, caster, spec.llf[0], spec.llf[1], params=llf_params(spec), max_bytes=16 << 30)
        out["llf"] = {"f": spec.llf[0], "resolution": spec.llf[1], "params": llf_params(spec).to_dict(),
                      "bake_s": time.perf_counter() - t0, "bake_cpu_s": time.process_time() - c0,
                      "mib": llf.nbytes / 2**20}
        log(f"bake LLF f={spec.llf[0]} res {spec.llf[1]}: {out['llf']['bake_s']:.1f} s")
    settings = []
    for res, noise, stride in (QUICK_LDC if quick else spec.ldc):
        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        c0, t0 = time.process_time(), time.perf_counter()
        ldc = bake_ldc(sc, caster, res, plan=plan, area_light_samples=LDC_AREA_SAMPLES,
                       indirect=IndirectParams(noise=noise, bounces=spec.bounces, stride=stride),
                       max_bytes=LDC_MAX_BYTES)
        t_bake, c_bake = time.perf_counter() - t0, time.process_time() - c0
        rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        state = ldc.plan["indirect"]
        log(f"bake LDC {res} noise {noise} stride {stride}: {t_bake:.1f} s, {ldc.n_samples} samples, "
            f"{ldc.nbytes / 2**20:.1f} MiB")
        r = LDCViewRenderer(sc, ldc, llf, plan)
        classes = [edge_classes(r.render(cam, spec.method), r.silhouette_rel_depth, ldc.background) for cam in cams]
        rows = [(1, "uniform", 0), (2, "uniform", 0), (EDGES_SS, "edges", 0)]
        rows += [(ss, aa, m) for m in spec.glossy_rays for ss, aa in ((1, "uniform"), (EDGES_SS, "edges"))]
        for ss, aa, gr in rows:
            r.render(cams[0], spec.method, supersample=ss, antialias=aa, glossy_rays=gr)  # warm
            errs, ts, cpus, breakdown, ratios = [], [], [], [], []
            for cam, g, cls in zip(cams, gts, classes, strict=True):
                dts, dcs = [], []
                for _ in range(3):
                    c1, t1 = time.process_time(), time.perf_counter()
                    v = r.render(cam, spec.method, supersample=ss, antialias=aa, glossy_rays=gr)
                    dts.append(time.perf_counter() - t1)
                    dcs.append(time.process_time() - c1)
                ts.append(min(dts))
                cpus.append(min(dcs))
                errs.append(lrms(v.radiance, g["radiance"], g["mask"]))
                breakdown.append(error_breakdown(v.radiance, g["radiance"], g["mask"], cls))
                ratios.append(_mean_y(v.radiance, g["mask"]) / _mean_y(g["radiance"], g["mask"]))
            row = {"ldc_resolution": res, "noise": noise, "stride": stride, "supersample": ss, "antialias": aa,
                   "glossy_rays": gr, "lrms": float(np.mean(errs)),
                   "lrms_max": float(np.max(errs)), "render_ms": 1000 * float(np.median(ts)),
                   "render_cpu_ms": 1000 * float(np.median(cpus)), "bake_s": t_bake, "bake_cpu_s": c_bake,
                   "bake_peak_rss_growth_mib": max(0, rss1 - rss0) / 1024.0, "ldc_mib": ldc.nbytes / 2**20,
                   "samples": ldc.n_samples, "indirect": state,
                   "error_top1pct_share": float(np.mean([b["top1pct_share"] for b in breakdown])),
                   "lrms_without_top2pct": float(np.mean([b["lrms_without_top2pct"] for b in breakdown])),
                   "regions": {k: float(np.mean([b["regions"][k] for b in breakdown]))
                               for k in breakdown[0]["regions"]},
                   "mean_ratio": float(np.mean(ratios))}
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
            log(f"  ss{ss} {aa} glossy_rays {gr}: lrms {row['lrms']:.4f} (corrected {row['lrms_corrected']:.4f}) "
                f"{row['render_ms']:.1f} ms; reference {t_ref} s, mitsuba {t_mi} s")
    # the smallest bake without indirect light, for the record of what indirect light adds
    res0 = (QUICK_LDC if quick else spec.ldc)[0][0]
    ldc0 = bake_ldc(sc, caster, res0, plan=plan, area_light_samples=LDC_AREA_SAMPLES)
    r0 = LDCViewRenderer(sc, ldc0, llf, plan)
    v0 = [r0.render(c, spec.method) for c in cams[:2]]
    out["direct_only"] = [{
        "ldc_resolution": res0, "lrms": float(np.mean([lrms(v.radiance, g["radiance"], g["mask"])
                                                       for v, g in zip(v0, gts, strict=False)])),
        "mean_ratio": float(np.mean([_mean_y(v.radiance, g["mask"]) / _mean_y(g["radiance"], g["mask"])
                                     for v, g in zip(v0, gts, strict=False)]))}]
    out["settings"] = settings
    if scene_name == "cornell_box":
        out["bounce_costs"] = bounce_costs(sc, caster, 32 if quick else 64)
    out["load_end"] = os.getloadavg()[0]
    return out


def llf_params(spec: SceneSpec) -> ReferenceParams:
    """The LLF's shading: the reference's full radiance toward each direction, indirect light
    included (a few paths per sample: the gathered reflections average many samples)."""
    return ReferenceParams(spp=1, max_depth=spec.max_depth, glossy_samples=8, area_light_samples=4,
                           indirect_samples=8, indirect_bounces=spec.bounces, seed=5)


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


def error_breakdown(test: np.ndarray, ref: np.ndarray, mask: np.ndarray,
                    classes: tuple[np.ndarray, np.ndarray]) -> dict:
    """Where the squared error is: the share carried by the worst 1 % of pixels and the LRMS of the
    rest; and by region of the view's one-sample render (``bench.ldc_antialias.edge_classes``):
    geometric edges (silhouettes, creases between objects, depth steps), shading edges (shadow and
    light borders: a luminance step only) and the interior, each region's share of the squared error,
    its pixel fraction and its part of the LRMS (its squared error over all compared pixels)."""
    y_t, y_r = test[mask].astype(np.float64) @ LUMA, ref[mask].astype(np.float64) @ LUMA
    e2 = np.square(y_t - y_r)
    d2 = np.sort(e2)[::-1]
    mean = y_r.mean()
    k1, k2 = max(1, d2.size // 100), max(1, d2.size // 50)
    tot = max(float(e2.sum()), 1e-300)
    geo, shade = classes[0][mask], classes[1][mask]
    regions = {}
    for name, sel in (("geometric", geo), ("shading", shade), ("interior", ~(geo | shade))):
        regions[f"{name}_share"] = float(e2[sel].sum()) / tot
        regions[f"{name}_pixels"] = float(sel.mean())
        regions[f"{name}_lrms"] = math.sqrt(float(e2[sel].sum()) / e2.size) / mean
    return {"top1pct_share": float(d2[:k1].sum() / tot),
            "lrms_without_top2pct": float(math.sqrt(d2[k2:].sum() / d2.size) / mean), "regions": regions}


def mitsuba_part(scene_name: str, spec: SceneSpec, sc: RuntimeScene, cams, gts, ladder_views, gt_noise: float,
                 log, quick: bool = False) -> dict:
    """Mitsuba 3 ``path`` on the scene: its ladder on ``ladder_views`` and the check of the ground
    truth on view 0 (module docstring)."""
    import tempfile

    os.environ.setdefault("DRJIT_LIBLLVM_PATH", LLVM)
    from bench import mitsuba_bridge as mb

    variant = mb.LLVM_VARIANT
    mi = mb.mitsuba(variant)
    workdir = tempfile.mkdtemp(prefix="gi_mitsuba_")
    if scene_name == "cornell_box":
        scene = mi.load_file(str(mb.require_shared(mb.CBOX_XML)), res=int(cams[0].width), spp=16)
    else:
        scene = mb.runtime_to_mitsuba(sc, cams[0], workdir, sampler="multijitter", variant=variant)

    def sensor(cam, spp):
        return mi.load_dict(mb.sensor_dict(cam, spp, "multijitter", variant=variant))

    mb.render(scene, "path", spec.bounces, spp=1, sensor=sensor(cams[0], 1), variant=variant)  # JIT warm-up
    ladder = []
    for spp in MI_LADDER:
        errs, ts = [], []
        for vi in ladder_views:
            r = mb.render(scene, "path", spec.bounces, spp=spp, seed=5, sensor=sensor(cams[vi], spp), variant=variant)
            ts.append(r.seconds)
            errs.append(lrms(r.radiance, gts[vi]["radiance"], gts[vi]["mask"]))
        ladder.append({"spp": spp, "lrms": float(np.mean(errs)), "seconds": float(np.median(ts))})
        log(f"mitsuba spp {spp}: lrms {np.mean(errs):.4f} {np.median(ts):.2f} s")
    half = (16 if quick else MI_CHECK_SPP) // 2
    a, b = (mb.render(scene, "path", spec.bounces, spp=half, seed=s, sensor=sensor(cams[0], half), variant=variant)
            for s in (9, 10))
    m = gts[0]["mask"]
    mean_img = 0.5 * (a.radiance + b.radiance)
    mi_noise = lrms(a.radiance, b.radiance, m) / 2.0  # of the mean of the two
    raw = lrms(mean_img, gts[0]["radiance"], m)
    check = {"spp": 2 * half, "size": cams[0].width, "lrms_vs_gt": raw, "mitsuba_noise_lrms": mi_noise,
             "gt_noise_lrms": gt_noise,
             "lrms_vs_gt_corrected": math.sqrt(max(raw * raw - mi_noise * mi_noise - gt_noise * gt_noise, 0.0)),
             "mean_ratio_gt_over_mitsuba": _mean_y(gts[0]["radiance"], m) / _mean_y(mean_img, m),
             "seconds": a.seconds + b.seconds}
    log(f"mitsuba {2 * half} spp vs gt: {check}")
    return {"variant": variant, "sampler": "multijitter", "max_depth": spec.bounces + 2, "ladder": ladder,
            "check": check}


# ---------------------------------------------------------------------------- report


def _s(x: float | None, ext: bool = False) -> str:
    if x is None:
        return "-"
    v = f"{x:.2f}" if x < 10 else f"{x:.0f}"
    return f"~{v}*" if ext else v


def scene_block(res: dict) -> list[str]:
    gt = res["ground_truth"]
    mi = res["mitsuba"]
    lines = [
        f"### `{res['scene']}`", "",
        f"{res['views']} views of {res['size']}x{res['size']} orbiting the box (none along an LDC axis), "
        f"{res['bounces']} diffuse bounces"
        + (f", mirror / glossy depth {res['max_depth']}" if res["max_depth"] else "")
        + f"; view method `{res['method']}`. Load average {res['load_start']:.1f} at the start of the scene, "
        f"{res['load_end']:.1f} at its end.",
        "",
        f"**Ground truth**: the reference, adaptive to an estimated {100 * gt['target']:.1f} % or "
        f"{gt['budget_s']:.0f} s per view (cap {gt['cap_spp']} spp): {gt['seconds_per_view']:.0f} s per view, "
        f"{gt['spp_mean']:.0f} spp mean, estimated error {100 * gt['estimated_error_mean']:.2f} %, stopped by "
        f"{', '.join(gt['stop_reasons'])}. Noise floor seed to seed (view 0): LRMS "
        f"{100 * gt['noise_lrms_seed_to_seed']:.2f} %.",
    ]
    if "llf" in res:
        lf = res["llf"]
        lines.append(f"LLF for the view method: f = {lf['f']}, {lf['resolution']}x{lf['resolution']} per direction, "
                     f"the reference's radiance with {lf['params']['indirect_samples']} indirect paths per sample; "
                     f"bake {lf['bake_s']:.0f} s, {lf['mib']:.0f} MiB.")
    if "check" in mi:
        c = mi["check"]
        lines.append(f"Against Mitsuba 3 `path` ({mi['variant']}, max_depth {mi['max_depth']}, {c['spp']} spp "
                     f"multijitter as two seeds of {c['spp'] // 2}, view 0 at {c['size']}x{c['size']}): LRMS "
                     f"{100 * c['lrms_vs_gt']:.2f} % raw; Mitsuba's own noise {100 * c['mitsuba_noise_lrms']:.2f} %, "
                     f"the ground truth's {100 * c['gt_noise_lrms']:.2f} %; both taken out in quadrature "
                     f"{100 * c['lrms_vs_gt_corrected']:.2f} %. Mean brightness ratio ours / Mitsuba "
                     f"{c['mean_ratio_gt_over_mitsuba']:.4f}.")
    lines += ["", "| LDC | indirect noise (paths per side) | ss | antialias | glossy lobe | LRMS mean (max) | "
                  "corrected | view ms (CPU ms) | our reference s at that LRMS | Mitsuba s at that LRMS | "
                  "x vs reference | x vs Mitsuba | bake s (CPU s) | LDC MiB | break-even views | "
                  "worst 1 % of pixels' share of error | "
                  "LRMS without worst 2 % | mean brightness ratio |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["settings"]:
        t_view = r["render_ms"] / 1000
        xr = r["ref_s_at_error"] / t_view if r["ref_s_at_error"] else None
        xm = r["mitsuba_s_at_error"] / t_view if r["mitsuba_s_at_error"] else None
        lines.append(
            f"| {_ldc_label(r)} | {r['noise']:.3f} ({_paths_label(r)}) | {r['supersample']} | "
            f"{r['antialias'] if r['supersample'] > 1 else '-'} | {_glossy_label(r)} | {100 * r['lrms']:.2f} % "
            f"({100 * r['lrms_max']:.2f} %) | {100 * r['lrms_corrected']:.2f} % | "
            f"{r['render_ms']:.1f} ({r['render_cpu_ms']:.1f}) | "
            f"{_s(r['ref_s_at_error'], r['ref_extrapolated'])} | "
            f"{_s(r['mitsuba_s_at_error'], r['mitsuba_extrapolated'])} "
            f"| {_s(xr, r['ref_extrapolated'])} | {_s(xm, r['mitsuba_extrapolated'])} | {r['bake_s']:.0f} "
            f"({r['bake_cpu_s']:.0f}) | {r['ldc_mib']:.0f} | {r.get('break_even_views') or '-'} | "
            f"{100 * r['error_top1pct_share']:.0f} % | {100 * r['lrms_without_top2pct']:.2f} % | "
            f"{r['mean_ratio']:.4f} |")
    lines += ["", "Where each setting's error is, by region of the view's one-sample render (geometric edges: "
                  "another object, nothing or a depth step in the 3 x 3 neighbourhood; shading edges: a luminance "
                  "step only, i.e. shadow and light borders; interior: the rest): share of the squared error / "
                  "part of the LRMS (the region's squared error over all compared pixels; the parts add in "
                  "quadrature to the LRMS). The interior part includes the ground truth's noise "
                  f"({100 * gt['noise_lrms_seed_to_seed']:.2f} % over the whole image).", "",
              "| LDC | noise | ss | antialias | glossy lobe | geometric edges (pixels) | shading edges (pixels) | "
              "interior |",
              "|---|---|---|---|---|---|---|---|"]
    for r in res["settings"]:
        g = r["regions"]
        lines.append(f"| {_ldc_label(r)} | {r['noise']:.3f} | {r['supersample']} | "
                     f"{r['antialias'] if r['supersample'] > 1 else '-'} | {_glossy_label(r)} | "
                     f"{100 * g['geometric_share']:.0f} % / {100 * g['geometric_lrms']:.2f} % "
                     f"({100 * g['geometric_pixels']:.1f} %) | {100 * g['shading_share']:.0f} % / "
                     f"{100 * g['shading_lrms']:.2f} % ({100 * g['shading_pixels']:.1f} %) | "
                     f"{100 * g['interior_share']:.0f} % / {100 * g['interior_lrms']:.2f} % |")
    lines += ["", f"Ladders (mean LRMS over views 0 and {res['views'] // 2}; seconds per view):",
              "", "| renderer | spp | LRMS | s |", "|---|---|---|---|"]
    for r in res["reference_ladder"]:
        lines.append(f"| ours (reference) | {r['spp']} | {100 * r['lrms']:.2f} % | {r['seconds']:.2f} |")
    for r in mi.get("ladder", []):
        lines.append(f"| Mitsuba 3 path | {r['spp']} | {100 * r['lrms']:.2f} % | {r['seconds']:.2f} |")
    for d in res.get("direct_only", []):
        lines += ["", f"Without indirect light (LDC {d['ldc_resolution']}, views 0-1): LRMS {100 * d['lrms']:.1f} %, "
                      f"mean brightness ratio {d['mean_ratio']:.3f}."]
    if res.get("bounce_costs"):
        lines += ["", "What the bounce limit costs and brings (indirect pass of one axis, LDC 64, noise 0.02):", "",
                  "| bounces | s (CPU s) | paths per side | indirect light, share of 5 bounces |", "|---|---|---|---|"]
        for b in res["bounce_costs"]:
            lines.append(f"| {b['bounces']} | {b['seconds']:.1f} ({b['cpu_seconds']:.1f}) | {b['paths_mean']:.0f} | "
                         f"{100 * b['share_of_5_bounces']:.1f} % |")
    lines += ["", f"![LRMS against time](../img/gi_equal_error_{res['scene']}.png)", ""]
    return lines


def doc_block(results: dict) -> str:
    lines = [f"Machine: {results['machine']}. Command: `{results['command']}` (total {results['total_s'] / 60:.0f} "
             "min). Equal error is taken on the raw LRMS (every renderer against the same ground truth); the "
             "corrected column removes the ground truth's own noise. `*`: extrapolated past the ladder's most "
             "accurate point with error ~ time^-1/2.", ""]
    for res in results["scenes"]:
        lines += scene_block(res)
    return "\n".join(lines).rstrip()


def plot(res: dict) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4.8))
    rl = res["reference_ladder"]
    ax.loglog([r["seconds"] for r in rl], [r["lrms"] for r in rl], "o-", label="our reference (spp raised)")
    ml = res["mitsuba"].get("ladder", [])
    if ml:
        ax.loglog([r["seconds"] for r in ml], [r["lrms"] for r in ml], "s-", label="Mitsuba 3 path (spp raised)")
    bakes: list[tuple] = []  # one marker shape per bake, one colour per setting
    colours = plt.get_cmap("tab20")
    for i, r in enumerate(res["settings"]):
        aa = f" {r['antialias']}" if r["supersample"] > 1 else ""
        bake = (r["ldc_resolution"], r["noise"], r["stride"])
        if bake not in bakes:
            bakes.append(bake)
        ax.loglog([r["render_ms"] / 1000], [r["lrms"]], "*DP^v"[bakes.index(bake) % 5], color=colours(i % 20),
                  markersize=11 if bakes.index(bake) == 0 else 8,
                  label=f"LDC {_ldc_label(r)} noise {r['noise']} ss{r['supersample']}{aa}"
                        f"{' glossy ' + str(r['glossy_rays']) if r.get('glossy_rays') else ''} "
                        f"(bake {r['bake_s']:.0f} s)")
    ax.axhline(res["ground_truth"]["noise_lrms_seed_to_seed"], color="grey", ls=":", label="ground truth noise")
    ax.set_xlabel("seconds per view")
    ax.set_ylabel("LRMS against the converged image")
    ax.set_title(f"{res['scene']} {res['size']}x{res['size']}, {res['bounces']} bounces")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    path = PLOT_DIR / f"gi_equal_error_{res['scene']}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="128x128, 2 views, LDC 64 (an iteration run; no docs)")
    ap.add_argument("--scene", action="append", choices=sorted(SCENES), help="scene (repeatable; default all)")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--gt-cache", type=Path, help="keep the ground truths in this directory (reruns reuse them)")
    ap.add_argument("--gt-budget-scale", type=float, default=1.0,
                    help="multiply the ground truths' time budgets (a shorter run, a noisier ground truth)")
    args = ap.parse_args(argv)
    GT_BUDGET_SCALE[0] = args.gt_budget_scale
    t0 = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.strftime('%H:%M:%S')} {time.perf_counter() - t0:7.1f} s] {msg}", flush=True)

    size, n_views = (128, 2) if args.quick else (512, args.views)
    names = args.scene or list(SCENES)
    scenes = [run(name, size, n_views, log, args.gt_cache, quick=args.quick) for name in names]
    if not args.quick and DATA.exists():  # a run of some scenes keeps the stored results of the others
        kept = [s for s in json.loads(DATA.read_text()).get("scenes", []) if s["scene"] not in names]
        scenes = sorted(kept + scenes, key=lambda s: list(SCENES).index(s["scene"]))
    res: dict[str, Any] = {"scenes": scenes}
    res["machine"] = f"{platform.machine()}, {os.cpu_count()} cores, Python {sys.version.split()[0]}"
    res["command"] = "python -m bench.gi_equal_error" + (" --quick" if args.quick else "") + \
        (" --gt-cache DIR" if args.gt_cache else "") + \
        (f" --gt-budget-scale {args.gt_budget_scale:g}" if args.gt_budget_scale != 1.0 else "")
    res["total_s"] = time.perf_counter() - t0
    if args.quick:
        print(doc_block(res))
        return 0
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(res, indent=1, default=float))
    for sc_res in scenes:
        plot(sc_res)
    replace_block(DOC, "gi_equal_error", doc_block(res), title="Global illumination: accuracy and cost")
    log(f"wrote {DOC.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
