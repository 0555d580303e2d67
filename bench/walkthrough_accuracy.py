"""Walkthrough accuracy versus time, against a converged ground truth.

Run: ``python -m bench.walkthrough_accuracy [--quick] [--scene NAME]`` from the repository root.
Writes ``docs/accuracy/walkthrough.md`` (block ``walkthrough_accuracy``),
``docs/data/walkthrough_accuracy.json`` and ``docs/img/walkthrough/*.png``. ``--scene`` runs one
scene and keeps the other scene's saved results (each scene fits in one ~15-minute run).

For two sample scenes (``cornell_animated``: a moving ball, a turning / stretching cube and a
moving, colour-changing point light plus the ceiling area light; ``static_room``: a 12 x 9 m room
with a partition, tables, columns and two ceiling panels, static) a camera path with times is
reconstructed from low / medium / high quality bakes (bases with indirect light traced to the
preset's noise target) with every fill mode, and each frame is compared (LRMS, docs/algorithms.md)
with a **converged ground truth** of the same frame: the reference renderer's image model of one
point sample per pixel centre (``pixel_jitter=False``, 1 spp) with 1024 area-light samples,
plus indirect light traced per pixel (``engine.newviews.indirect.trace_indirect_points``, the
reference renderer's own indirect paths) to a relative noise target. Its noise floor is
measured: the same frames with another seed.

Rendering every frame instead is priced at the same error: the reference renderer (same image
model) at a ladder of light / indirect sample counts, its LRMS against the ground truth and its
time per frame, interpolated (log-log) to the time it needs to reach each walkthrough setting's
error. A speed section measures a 512 x 512 frame from two base images.

Times are wall-clock seconds on this machine (2 cores shared with other jobs): compare them as
ratios within one run.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import platform
import time
from pathlib import Path

import numba as nb
import numpy as np

from api_schemas.scene import load_scene_file
from bench.docs_writer import replace_block
from engine.imageio import write_image
from engine.metrics import REC709_WEIGHTS, lrms
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.scene import CameraParams
from engine.walkthrough.animation import AnimatedScene
from engine.walkthrough.bake import (
    WalkthroughBake,
    WalkthroughParams,
    WalkthroughRenderer,
    bake_walkthrough,
    render_bases,
    walkthrough_preset,
)
from engine.walkthrough.ground_truth import AREA_LIGHT_SAMPLES, converged_frame
from engine.walkthrough.range_images import render_cube
from engine.walkthrough.reconstruct import FILL_MODES
from engine.walkthrough.viewspace import PathSpace, PolygonSpace, ViewSpace
from workers.scene_loader import directory_resolver, load_animated_scene

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "accuracy" / "walkthrough.md"
DATA = ROOT / "docs" / "data" / "walkthrough_accuracy.json"
IMG = ROOT / "docs" / "img" / "walkthrough"
SAMPLES = ROOT / "samples"
QUALITIES = ("low", "medium", "high")
SCENES = ("cornell_animated", "static_room")
PROV_NAMES = ("hole", "reprojected", "foreground_fill", "background_fill", "traced", "sky")
"""Provenance codes of a frame's pixels (engine.walkthrough.reconstruct), in code order."""
LUMA = np.asarray(REC709_WEIGHTS, np.float64)


def _path_points(points: np.ndarray, n: int) -> np.ndarray:
    space = PathSpace(points)
    return np.array([space.point_at(space.length * i / (n - 1)) for i in range(n)])


def walkthrough_cameras(name: str, n: int, w: int, h: int) -> tuple[list[CameraParams], np.ndarray]:
    """The camera path of a scene: eyes inside its view space, looking ahead / at the action."""
    cams = []
    if name == "cornell_animated":
        eyes = _path_points(np.array([[170.0, 273, 20], [278, 273, 70], [390, 273, 20]]), n)
        for e in eyes:
            cams.append(CameraParams("perspective", tuple(e), (278.0, 150.0, 420.0), (0, 1, 0), w, h,
                                     fov_y_deg=60))
        times = np.linspace(0.0, 4.0, n)
    else:
        way = np.array([[2.0, 1.6, 7.2], [2.2, 1.6, 1.4], [6.0, 1.6, 1.2], [10.4, 1.6, 1.6]])
        eyes = _path_points(way, n)
        fine = _path_points(way, 8 * n)
        tangent = np.array([0.0, 0.0, -1.0])
        for i, e in enumerate(eyes):
            j = min(8 * i + 4, 8 * n - 1)
            step = fine[j] - fine[max(j - 4, 0)]
            if np.linalg.norm(step) > 1e-6:  # look where the path goes (smoothed), a little down
                tangent = 0.5 * tangent + 0.5 * step / np.linalg.norm(step)
                tangent /= np.linalg.norm(tangent)
            target = e + 1.5 * tangent + np.array([0.0, -0.35, 0.0])
            cams.append(CameraParams("perspective", tuple(e), tuple(target), (0, 1, 0), w, h, fov_y_deg=65))
        times = np.zeros(n)
    return cams, times


def load(name: str) -> tuple[AnimatedScene, ViewSpace]:
    scene = load_scene_file(SAMPLES / "scenes" / f"{name}.json")
    an = load_animated_scene(scene, directory_resolver(SAMPLES))
    vs = scene.view_space
    assert vs is not None
    if vs.type == "path":
        space: ViewSpace = PathSpace(np.asarray(vs.points, np.float64), vs.radius)
    else:
        assert vs.type == "polygon"
        space = PolygonSpace(np.asarray(vs.vertices, np.float64), vs.eye_height)
    return an, space


GT_CACHE = Path(os.environ.get("IBR_BENCH_CACHE", "/tmp/ibr-bench-cache")) / "walkthrough_gt"
"""Ground truths are cached here between runs (they depend only on the scene, frames and settings)."""
GT_AREA_SAMPLES = AREA_LIGHT_SAMPLES
LADDER = ((1, 1), (4, 4), (4, 16), (9, 64), (16, 256), (64, 256))
"""(area_light_samples, indirect_samples) of the reference renders that price 'render every frame'."""


def time_at_error(ladder: list[dict], err: float) -> tuple[float, str]:
    """Reference seconds per frame to reach LRMS ``err``: log-log interpolation between ladder
    points; beyond the ladder's best error, the last point extrapolated with time ~ error^-2
    (Monte Carlo convergence); below its worst, its first point (the cheapest render)."""
    pts = sorted(((e["lrms"], e["seconds"]) for e in ladder), reverse=True)
    if err >= pts[0][0]:
        return pts[0][1], "cheapest"
    for (e0, t0), (e1, t1) in zip(pts, pts[1:], strict=False):
        if e1 <= err <= e0:
            a = (math.log(err) - math.log(e0)) / (math.log(e1) - math.log(e0)) if e1 < e0 else 0.0
            return math.exp(math.log(t0) + a * (math.log(t1) - math.log(t0))), "interpolated"
    e_last, t_last = pts[-1]
    return t_last * (e_last / err) ** 2, "extrapolated"


def fixed_sample_bake(an: AnimatedScene, bake: WalkthroughBake, params: WalkthroughParams) -> tuple[
        WalkthroughBake, float]:
    """The same bases with the indirect part of a fixed path count instead (``params.indirect_samples``
    per pixel, ``render_cube(..., indirect=True)``: full render - direct render), for comparison;
    and the seconds that indirect pass took."""
    rdiv = params.indirect_res_div
    ri = params.face_res // rdiv
    ind = np.zeros_like(bake.indirect)
    t0 = time.perf_counter()
    for k, t in enumerate(bake.indirect_times):
        rr = ReferenceRenderer(an.scene_at(float(t)))
        for v, eye in enumerate(bake.views):
            c = render_cube(rr, eye, ri, params.reference_params(True), time_value=float(t), indirect=True)
            ind[v, k] = np.repeat(np.repeat(c.indirect, rdiv, axis=1), rdiv, axis=2)
    return dataclasses.replace(bake, indirect=ind), time.perf_counter() - t0


def run_scene(name: str, args: argparse.Namespace) -> dict:
    an, space = load(name)
    cams, times = walkthrough_cameras(name, args.frames, args.width, args.height)
    for c in cams:  # the path must stay inside the view space
        if not space.contains(np.asarray(c.eye), 1e-6):
            raise SystemExit(f"{name}: camera {c.eye} leaves the view space")
    bounces = args.bounces
    print(f"[{name}] ground truth: {len(cams)} frames, indirect noise {args.gt_noise}", flush=True)
    renderers: dict[float, ReferenceRenderer] = {}
    for t in times:
        renderers.setdefault(float(t), ReferenceRenderer(an.scene_at(float(t))))
    # the ground truth is expensive and depends only on these settings: cached between runs
    tag = json.dumps([name, args.frames, args.width, args.height, args.gt_noise, bounces, GT_AREA_SAMPLES,
                      list(args.floor_frames)])
    cache = GT_CACHE / f"{name}_{hashlib.sha256(tag.encode()).hexdigest()[:16]}.npz"
    if cache.exists():
        with np.load(cache) as z:
            gts, masks, floor_imgs = list(z["gts"]), list(z["masks"]), list(z["floor"])
            gt_stats = json.loads(str(z["stats"]))
        print(f"[{name}] ground truth from {cache}", flush=True)
    else:
        gts, masks, gt_stats, floor_imgs = [], [], [], []
        for i, (cam, t) in enumerate(zip(cams, times, strict=True)):
            img, mask, _, st = converged_frame(renderers[float(t)], cam, i, 0, args.gt_noise, bounces)
            gts.append(img)
            masks.append(mask)
            gt_stats.append(st)
            print(f"[{name}] gt {i}: {st['seconds']:.1f} s, paths/pixel {st['paths_mean']:.0f}", flush=True)
        # noise floor of the ground truth: the same frames with another seed
        for k in args.floor_frames:
            floor_imgs.append(converged_frame(renderers[float(times[k])], cams[k], k, 1, args.gt_noise, bounces)[0])
        GT_CACHE.mkdir(parents=True, exist_ok=True)
        np.savez(cache, gts=np.stack(gts), masks=np.stack(masks), floor=np.stack(floor_imgs),
                 stats=np.array(json.dumps(gt_stats)))
    floor = [lrms(img, gts[k], masks[k]) for img, k in zip(floor_imgs, args.floor_frames, strict=True)]
    print(f"[{name}] ground-truth pairs (seeds 0 / 1) differ by LRMS {[round(x, 5) for x in floor]}", flush=True)
    if args.gt_only:
        return {}
    # rendering every frame: the reference (same image model) at a ladder of sample counts
    ladder = []
    warm = ReferenceParams(spp=1, pixel_jitter=False, area_light_samples=1, indirect_samples=1,
                           indirect_bounces=bounces)
    for k in args.floor_frames:  # warm-up: kernels compiled, BVHs built before anything is timed
        renderers[float(times[k])].render(cams[k], warm)
    for area, ind in args.ladder:
        rp = ReferenceParams(spp=1, pixel_jitter=False, area_light_samples=area, indirect_samples=ind,
                             indirect_bounces=bounces, seed=2)
        errs, secs = [], []
        for k in args.floor_frames:
            t0 = time.perf_counter()
            out = renderers[float(times[k])].render(cams[k], rp)
            secs.append(time.perf_counter() - t0)
            errs.append(lrms(out.radiance, gts[k], masks[k]))
        ladder.append({"area_light_samples": area, "indirect_samples": ind, "lrms": float(np.mean(errs)),
                       "seconds": float(np.mean(secs))})
        print(f"[{name}] reference {area} light / {ind} indirect samples: LRMS {np.mean(errs):.4f}, "
              f"{np.mean(secs):.2f} s / frame", flush=True)
    result: dict = {"frames": len(cams), "width": args.width, "height": args.height, "bounces": bounces,
                    "gt_noise_target": args.gt_noise, "gt_area_light_samples": GT_AREA_SAMPLES,
                    "gt_seconds_per_frame": float(np.mean([st["seconds"] for st in gt_stats])),
                    "gt_paths_per_pixel": float(np.mean([st["paths_mean"] for st in gt_stats])),
                    "gt_met_target": float(np.mean([st["met_target"] for st in gt_stats])),
                    "noise_floor_pair_lrms": [float(x) for x in floor],
                    "noise_floor_lrms": float(np.mean(floor) / math.sqrt(2.0)),
                    "ladder": ladder, "static": an.is_static, "qualities": {}}
    for q in QUALITIES:
        params = walkthrough_preset(q, **args.overrides[q])
        print(f"[{name}] bake {q}: {params}", flush=True)
        t0 = time.perf_counter()
        bake = bake_walkthrough(an, space, params)
        bake_s = time.perf_counter() - t0
        wr = WalkthroughRenderer(bake, an)
        ist = {k: v for k, v in bake.indirect_stats.items() if k != "cubes"}
        entry: dict = {"params": bake.params, "views": bake.n_views, "direct_times": bake.direct_times.tolist(),
                       "indirect_times": bake.indirect_times.tolist(), "bake_seconds": bake_s,
                       "bake_timings": bake.timings, "bake_mbytes": bake.nbytes / 2**20, "indirect": ist,
                       "fills": {}}
        print(f"[{name}] {q}: {bake.n_views} views, {len(bake.direct_times)} direct / "
              f"{len(bake.indirect_times)} indirect times, bake {bake_s:.1f} s, indirect {ist}", flush=True)
        for fill in FILL_MODES:
            wr.render(cams[0], float(times[0]), fill=fill)  # warm-up (JIT, buffers)
            errs, secs, holes = [], [], []
            frames = []
            sq = np.zeros(len(PROV_NAMES))
            npx = np.zeros(len(PROV_NAMES))
            for cam, t, gt, mask in zip(cams, times, gts, masks, strict=True):
                t1 = time.perf_counter()
                fr = wr.render(cam, float(t), fill=fill)
                secs.append(time.perf_counter() - t1)
                errs.append(lrms(fr.radiance, gt, mask))
                # where the error is: squared luminance error (relative to the frame's mean) per provenance
                y_t, y_r = fr.radiance.astype(np.float64) @ LUMA, gt.astype(np.float64) @ LUMA
                e2 = ((y_t - y_r) / max(float(y_r[mask].mean()), 1e-300)) ** 2
                prov = np.minimum(fr.provenance, len(PROV_NAMES) - 1)
                sq += np.bincount(prov[mask], weights=e2[mask], minlength=len(PROV_NAMES))
                npx += np.bincount(prov[mask], minlength=len(PROV_NAMES))
                holes.append(fr.counts.get("hole", 0) / (cam.width * cam.height))
                frames.append(fr.radiance)
            f_entry = {"lrms": [float(e) for e in errs], "mean_lrms": float(np.mean(errs)),
                       "max_lrms": float(np.max(errs)), "seconds_per_frame": float(np.median(secs)),
                       "hole_fraction": float(np.mean(holes)),
                       "error_share": dict(zip(PROV_NAMES, (sq / max(sq.sum(), 1e-300)).tolist(), strict=True)),
                       "pixel_share": dict(zip(PROV_NAMES, (npx / max(npx.sum(), 1)).tolist(), strict=True))}
            f_entry["reference_seconds_at_error"], f_entry["reference_at_error"] = time_at_error(
                ladder, f_entry["mean_lrms"])
            entry["fills"][fill] = f_entry
            if fill == "both":
                k = len(cams) // 2
                write_image(IMG / f"{name}_{q}_frame{k}.png", frames[k])
            print(f"[{name}] {q} {fill}: mean LRMS {np.mean(errs):.4f}, {np.median(secs) * 1e3:.1f} ms/frame, "
                  f"reference at that error {f_entry['reference_seconds_at_error']:.2f} s/frame", flush=True)
        # the previous method's bases (a fixed number of indirect paths per pixel) on the same views and times
        fixed, fixed_s = fixed_sample_bake(an, bake, params)
        wf = WalkthroughRenderer(fixed, an)
        errs = [lrms(wf.render(cam, float(t), fill="both").radiance, gt, mask)
                for cam, t, gt, mask in zip(cams, times, gts, masks, strict=True)]
        entry["fixed_samples"] = {"indirect_samples": params.indirect_samples, "indirect_seconds": fixed_s,
                                  "mean_lrms_both": float(np.mean(errs))}
        print(f"[{name}] {q} with fixed-sample bases ({params.indirect_samples} paths): mean LRMS (both) "
              f"{np.mean(errs):.4f}, indirect pass {fixed_s:.1f} s", flush=True)
        result["qualities"][q] = entry
    k = len(cams) // 2
    write_image(IMG / f"{name}_reference_frame{k}.png", gts[k])
    return result


def speed(args: argparse.Namespace) -> dict:
    """512 x 512 frame from two base images (face_res 256) vs a plain reference render."""
    an, _ = load("cornell_animated")
    params = walkthrough_preset("high", face_res=256, spp=1, indirect_samples=0)
    bake = render_bases(an, [[200.0, 273, 30], [300.0, 273, 60]], [0.0], [0.0], params)
    wr = WalkthroughRenderer(bake, an)
    cam = CameraParams("perspective", (250.0, 273, 45), (278.0, 150, 420), (0, 1, 0), 512, 512, fov_y_deg=60)
    out: dict = {"face_res": 256, "bases": 2, "fills": {}, "load_before": list(os.getloadavg())}
    for fill in ("none", "foreground", "background", "both"):
        wr.render(cam, 0.0, fill=fill, strict=False)
        ws, cs = [], []
        for _ in range(args.speed_reps):
            c0, w0 = time.process_time(), time.perf_counter()
            fr = wr.render(cam, 0.0, fill=fill, strict=False)
            ws.append(time.perf_counter() - w0)
            cs.append(time.process_time() - c0)
        out["fills"][fill] = {"wall_ms_median": 1e3 * float(np.median(ws)), "wall_ms_min": 1e3 * float(np.min(ws)),
                              "cpu_ms_median": 1e3 * float(np.median(cs)),
                              "phases_ms": {k: 1e3 * v for k, v in fr.timings.items()}}
    rr = ReferenceRenderer(an.scene_at(0.0))
    rr.render(CameraParams("perspective", cam.eye, cam.look_at, cam.up, 32, 32, fov_y_deg=60))  # warm-up
    refs = []
    for _ in range(1):
        w0 = time.perf_counter()
        rr.render(cam, ReferenceParams())
        refs.append(time.perf_counter() - w0)
    out["reference_ms"] = 1e3 * float(np.min(refs))
    out["load_after"] = list(os.getloadavg())
    out["reference_params"] = ReferenceParams().to_dict()
    return out


def _plots(data: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for name, res in data["scenes"].items():
        fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
        for q in QUALITIES:
            e = res["qualities"][q]["fills"]["both"]["lrms"]
            axes[0].plot(range(len(e)), e, marker="o", ms=3, label=f"{q} ({res['qualities'][q]['views']} views)")
        axes[0].axhline(res["noise_floor_lrms"], color="grey", ls=":", lw=1, label="ground-truth noise")
        axes[0].set_title(f"{name}: per-frame LRMS, fill 'both'")
        axes[0].set_xlabel("frame")
        axes[0].set_ylabel("LRMS vs ground truth")
        lad = res["ladder"]
        axes[1].plot([x["seconds"] for x in lad], [x["lrms"] for x in lad], marker="s", color="k",
                     label="reference, every frame")
        n = res["frames"]
        for q in QUALITIES:
            e = res["qualities"][q]
            f = e["fills"]["both"]
            axes[1].plot([e["bake_seconds"] / n + f["seconds_per_frame"]], [f["mean_lrms"]], marker="o", ls="",
                         label=f"{q}: (bake + {n} frames) / {n}")
        axes[1].set_xscale("log")
        axes[1].set_yscale("log")
        axes[1].set_xlabel("seconds per frame")
        axes[1].set_ylabel("mean LRMS vs ground truth")
        axes[1].set_title(f"{name}: error against time per frame")
        for ax in axes:
            ax.legend(fontsize=7)
            ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(IMG / f"{name}_lrms.png", dpi=90)
        plt.close(fig)


def _cmd(data: dict) -> str:
    return "python -m bench.walkthrough_accuracy" + (" --quick" if data["quick"] else "")


def _doc(data: dict) -> str:
    lines = [f"Run: `{_cmd(data)}` (or one scene at a time, `--scene NAME`; {data['machine']}, numba threads "
             f"{data['threads']}). " + ("**Reduced run**: " if data["reduced"] else "")
             + f"{data['frames']} frames of {data['width']} x {data['height']} per scene; preset resolutions "
             f"overridden as listed under 'Params per quality' (the shipped presets are larger, see "
             f"docs/walkthrough.md).", ""]
    for name, res in data["scenes"].items():
        n = res["frames"]
        pair = res["noise_floor_pair_lrms"]
        lines += [f"### {name}", "",
                  f"Ground truth: pixel centres, {res['gt_area_light_samples']} area-light samples, indirect light "
                  f"({res['bounces']} bounces) traced per pixel to a relative standard error of "
                  f"{res['gt_noise_target']:g} ({res['gt_paths_per_pixel']:.0f} paths / pixel on average, "
                  f"{100 * res['gt_met_target']:.1f} % of the pixels met it), {res['gt_seconds_per_frame']:.1f} s "
                  f"/ frame. **Noise floor: LRMS {res['noise_floor_lrms']:.4f}** per ground-truth frame "
                  f"(measured: two ground truths of frames {', '.join(str(k) for k in res.get('floor_frames', []))} "
                  f"with different seeds differ by LRMS {', '.join(f'{x:.4f}' for x in pair)}; "
                  f"one frame's noise is that / sqrt 2). Scene static: {res['static']}.", "",
                  "Reference renderer rendering every frame (same image model: pixel centres, 1 spp), against the "
                  "ground truth:", "",
                  "| area-light samples | indirect paths / pixel | LRMS vs ground truth | s / frame |",
                  "|---|---|---|---|"]
        for x in res["ladder"]:
            lines.append(f"| {x['area_light_samples']} | {x['indirect_samples']} | {x['lrms']:.4f} | "
                         f"{x['seconds']:.3f} |")
        lines += ["", "Walkthrough (fill `both`), and the reference at the same error:", "",
                  "| quality | base views | time samples (direct / indirect) | indirect noise target | achieved "
                  "(median / p95 of cubes, met) | bake (s) | of which indirect (s) | bake MiB | ms / frame | "
                  "mean LRMS | max LRMS | reference s / frame at that LRMS | bake + frames vs reference, "
                  f"{n} frames | break-even frames |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for q in QUALITIES:
            e = res["qualities"][q]
            f = e["fills"]["both"]
            ist = e["indirect"]
            t_ref = f["reference_seconds_at_error"]
            total = e["bake_seconds"] + n * f["seconds_per_frame"]
            gain = t_ref - f["seconds_per_frame"]
            be = f"{e['bake_seconds'] / gain:.1f}" if gain > 0 else "never"
            achieved = (f"{ist.get('rel_stderr_median_of_chunks', 0):.4f} / "
                        f"{ist.get('rel_stderr_p95_of_chunks', 0):.4f}, {100 * ist.get('met_target', 0):.1f} %"
                        if ist else "-")
            lines.append(
                f"| {q} | {e['views']} | {len(e['direct_times'])} / {len(e['indirect_times'])} | "
                f"{e['params']['indirect_noise']:g} | {achieved} | {e['bake_seconds']:.1f} | "
                f"{e['bake_timings'].get('indirect', 0.0):.1f} | {e['bake_mbytes']:.0f} | "
                f"{1e3 * f['seconds_per_frame']:.1f} | {f['mean_lrms']:.4f} | {f['max_lrms']:.4f} | "
                f"{t_ref:.3f} ({f['reference_at_error']}) | {total / (n * t_ref):.2f}x | {be} |")
        if all("fixed_samples" in res["qualities"][q] for q in QUALITIES):
            lines += ["", "The same views and times with the previous bases, indirect light of a fixed number of "
                      "paths per pixel (the preset's `indirect_samples`; full render - direct render):", "",
                      "| quality | indirect paths / pixel | indirect pass (s) | mean LRMS, fill both | "
                      "converged bases: indirect pass (s) | mean LRMS |", "|---|---|---|---|---|---|"]
            for q in QUALITIES:
                e = res["qualities"][q]
                fx = e["fixed_samples"]
                lines.append(f"| {q} | {fx['indirect_samples']} | {fx['indirect_seconds']:.1f} | "
                             f"{fx['mean_lrms_both']:.4f} | {e['bake_timings'].get('indirect', 0.0):.1f} | "
                             f"{e['fills']['both']['mean_lrms']:.4f} |")
        lines += ["", "Where the error of fill `both` is: share of the squared error (share of the pixels) by "
                  "provenance: reprojected base pixels, foreground-fill quads, background fill.", "",
                  "| quality | reprojected | foreground fill | background fill |", "|---|---|---|---|"]
        for q in QUALITIES:
            f = res["qualities"][q]["fills"]["both"]
            if "error_share" in f:
                lines.append(f"| {q} | " + " | ".join(
                    f"{100 * f['error_share'][k]:.0f} % ({100 * f['pixel_share'][k]:.0f} %)"
                    for k in ("reprojected", "foreground_fill", "background_fill")) + " |")
        lines += ["", "| quality | fill | mean LRMS | max LRMS | holes left (mean fraction) | ms / frame |",
                  "|---|---|---|---|---|---|"]
        for q in QUALITIES:
            for m in FILL_MODES:
                f = res["qualities"][q]["fills"][m]
                lines.append(f"| {q} | {m} | {f['mean_lrms']:.4f} | {f['max_lrms']:.4f} | "
                             f"{f['hole_fraction']:.4f} | {1e3 * f['seconds_per_frame']:.1f} |")
        lines += ["", "Params per quality: " + "; ".join(
            f"{q}: q={p['q']}, q_indirect={p['q_indirect']}, face_res={p['face_res']}, spp={p['spp']}, "
            f"indirect_res_div={p['indirect_res_div']}, indirect_noise={p['indirect_noise']}, "
            f"indirect_max_paths={p['indirect_max_paths']}, max_views={p['max_views']}, "
            f"max_time_samples={p['max_time_samples']}"
            for q in QUALITIES for p in [res["qualities"][q]["params"]]), "",
                  f"![per-frame LRMS](../img/walkthrough/{name}_lrms.png)", "",
                  "Middle frame: ground truth, low, medium, high (fill both):", "",
                  " ".join(f"![{k}](../img/walkthrough/{name}_{k}_frame{n // 2}.png)"
                           for k in ("reference",) + QUALITIES), ""]
    sp = data.get("speed")
    if sp:
        lines += ["### Speed: a 512 x 512 frame from two base images", "",
                  f"Two bases of face_res {sp['face_res']} (6 x {sp['face_res']}^2 samples each), Cornell box. "
                  f"Plain reference render of the same frame (ReferenceParams defaults: "
                  f"{sp['reference_params']['spp']} spp, direct light only): **{sp['reference_ms']:.0f} ms**. "
                  f"Machine load average (1 min) before / after: {sp['load_before'][0]:.1f} / "
                  f"{sp['load_after'][0]:.1f} on 2 cores: with a load above 2 the wall times are inflated by other "
                  f"jobs; the CPU column is the work of both threads (on an idle machine the wall time is about "
                  f"half of it plus the serial parts).", "",
                  "| fill | wall ms (median) | wall ms (best) | CPU ms (median, both threads) | reference / recon |",
                  "|---|---|---|---|---|"]
        for m, f in sp["fills"].items():
            lines.append(f"| {m} | {f['wall_ms_median']:.1f} | {f['wall_ms_min']:.1f} | {f['cpu_ms_median']:.1f} | "
                         f"{sp['reference_ms'] / f['wall_ms_median']:.0f}x |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny run (smoke test)")
    ap.add_argument("--no-doc", action="store_true")
    ap.add_argument("--scene", choices=SCENES, help="run one scene; the other's saved results are kept")
    ap.add_argument("--gt-only", action="store_true",
                    help="only compute (and cache) the ground truth of --scene, to split a long run in two")
    ap.add_argument("--gt-noise", type=float, help="the ground truth's indirect noise target (default 0.006)")
    ap.add_argument("--doc-only", action="store_true", help="rewrite the doc and plots from the saved JSON")
    ap.add_argument("--speed-only", action="store_true",
                    help="re-measure only the 512 x 512 speed section; the rest comes from the saved JSON")
    args = ap.parse_args()
    if args.doc_only:
        data = json.loads(DATA.read_text())
        _plots(data)
        replace_block(DOC, "walkthrough_accuracy", _doc(data), title="Walkthrough accuracy")
        return
    if args.speed_only:
        args.speed_reps = 9
        data = json.loads(DATA.read_text())
        data["speed"] = speed(args)
        print(json.dumps(data["speed"], indent=1))
        if not args.no_doc:
            DATA.write_text(json.dumps(data, indent=1))
            replace_block(DOC, "walkthrough_accuracy", _doc(data), title="Walkthrough accuracy")
        return
    args.bounces = 2
    if args.quick:
        args.frames, args.width, args.height, args.speed_reps = 4, 32, 24, 3
        args.overrides = {q: dict(face_res=16, probe_res=8, max_views=2, max_time_samples=2, area_light_samples=4,
                                  indirect_max_paths=512) for q in QUALITIES}
        args.gt_noise, args.floor_frames, args.ladder = 0.02, (0, 2), LADDER[:3]
    else:
        args.frames, args.width, args.height, args.speed_reps = 8, 80, 60, 5
        args.overrides = {
            "low": dict(face_res=48, probe_res=12, max_views=3, max_time_samples=3, area_light_samples=4),
            "medium": dict(face_res=64, probe_res=16, max_views=5, max_time_samples=5, area_light_samples=4),
            "high": dict(face_res=96, probe_res=24, max_views=8, max_time_samples=5, area_light_samples=4),
        }
        args.gt_noise, args.floor_frames, args.ladder = args.gt_noise or 0.006, (0, 4), LADDER
    for q in QUALITIES:
        args.overrides[q]["indirect_bounces"] = args.bounces
    IMG.mkdir(parents=True, exist_ok=True)
    data: dict = {"quick": args.quick, "reduced": True, "frames": args.frames, "width": args.width,
                  "height": args.height, "machine": f"{platform.machine()}, {platform.python_version()}",
                  "threads": nb.get_num_threads(), "scenes": {}}
    if args.scene and DATA.exists():
        old = json.loads(DATA.read_text())
        if old.get("quick") == args.quick and old.get("frames") == args.frames:
            data["scenes"] = {k: v for k, v in old.get("scenes", {}).items() if "ladder" in v}
        if "speed" in old:
            data["speed"] = old["speed"]
    t0 = time.perf_counter()
    for name in (args.scene,) if args.scene else SCENES:
        if args.gt_only:
            run_scene(name, args)
            return
        data["scenes"][name] = run_scene(name, args)
        data["scenes"][name]["floor_frames"] = list(args.floor_frames)
    data["scenes"] = {k: data["scenes"][k] for k in SCENES if k in data["scenes"]}
    if not args.scene:
        data["speed"] = speed(args)
        print(json.dumps(data["speed"], indent=1))
    data["seconds"] = time.perf_counter() - t0
    if args.no_doc:
        return
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(data, indent=1))
    _plots(data)
    replace_block(DOC, "walkthrough_accuracy", _doc(data), title="Walkthrough accuracy")


if __name__ == "__main__":
    main()
