"""Walkthrough accuracy versus time.

Run: ``python -m bench.walkthrough_accuracy [--quick]`` from the repository root. Writes
``docs/accuracy/walkthrough.md`` (block ``walkthrough_accuracy``), ``docs/data/walkthrough_accuracy.json``
and ``docs/img/walkthrough/*.png``.

For two sample scenes (``cornell_animated``: a moving ball, a turning / stretching cube and a
moving, colour-changing point light plus the ceiling area light, with path-traced indirect light;
``static_room``: a 12 x 9 m room with a partition, tables, columns and two ceiling panels, static)
a camera path with times is reconstructed from low / medium / high quality bakes with every fill
mode, and each frame is compared (LRMS, docs/algorithms.md) with a full reference render of the same
frame (same renderer, same light model, path-traced indirect light). The time to render the
walkthrough frame by frame with the reference renderer is reported next to the bake and
reconstruction times. A speed section measures a 512 x 512 frame from two base images.

Times are wall-clock seconds on this machine (2 cores shared with other jobs): compare them as
ratios within one run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numba as nb
import numpy as np

from api_schemas.scene import load_scene_file
from bench.docs_writer import replace_block
from engine.imageio import write_image
from engine.metrics import lrms
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.scene import CameraParams
from engine.walkthrough.animation import AnimatedScene
from engine.walkthrough.bake import WalkthroughRenderer, bake_walkthrough, render_bases, walkthrough_preset
from engine.walkthrough.reconstruct import FILL_MODES
from engine.walkthrough.viewspace import PathSpace, PolygonSpace, ViewSpace
from workers.scene_loader import directory_resolver, load_animated_scene

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "accuracy" / "walkthrough.md"
DATA = ROOT / "docs" / "data" / "walkthrough_accuracy.json"
IMG = ROOT / "docs" / "img" / "walkthrough"
SAMPLES = ROOT / "samples"
QUALITIES = ("low", "medium", "high")


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


def run_scene(name: str, args: argparse.Namespace, ref_params: ReferenceParams) -> dict:
    an, space = load(name)
    cams, times = walkthrough_cameras(name, args.frames, args.width, args.height)
    for c in cams:  # the path must stay inside the view space
        if not space.contains(np.asarray(c.eye), 1e-6):
            raise SystemExit(f"{name}: camera {c.eye} leaves the view space")
    print(f"[{name}] reference: {len(cams)} frames", flush=True)
    refs, ref_times = [], []
    renderers: dict[float, ReferenceRenderer] = {}
    for cam, t in zip(cams, times, strict=True):
        rr = renderers.setdefault(float(t), ReferenceRenderer(an.scene_at(float(t))))
        t0 = time.perf_counter()
        out = rr.render(cam, ref_params)
        ref_times.append(time.perf_counter() - t0)
        refs.append(out)
    # noise floor: the same frames rendered with another seed
    floor = []
    for k in (0, len(cams) // 2, len(cams) - 1):
        other = ReferenceParams(**{**ref_params.to_dict(), "seed": 1})
        out = renderers[float(times[k])].render(cams[k], other)
        floor.append(lrms(out.radiance, refs[k].radiance, refs[k].object_id >= 0))
    result: dict = {"frames": len(cams), "width": args.width, "height": args.height,
                    "reference_seconds_per_frame": float(np.mean(ref_times)),
                    "reference_seconds_total": float(np.sum(ref_times)),
                    "reference_params": ref_params.to_dict(), "noise_floor_lrms": [float(x) for x in floor],
                    "static": an.is_static, "qualities": {}}
    for q in QUALITIES:
        params = walkthrough_preset(q, **args.overrides[q])
        print(f"[{name}] bake {q}: {params}", flush=True)
        t0 = time.perf_counter()
        bake = bake_walkthrough(an, space, params)
        bake_s = time.perf_counter() - t0
        wr = WalkthroughRenderer(bake, an)
        entry: dict = {"params": bake.params, "views": bake.n_views, "direct_times": bake.direct_times.tolist(),
                       "indirect_times": bake.indirect_times.tolist(), "bake_seconds": bake_s,
                       "bake_timings": bake.timings, "bake_mbytes": bake.nbytes / 2**20, "fills": {}}
        print(f"[{name}] {q}: {bake.n_views} views, {len(bake.direct_times)} direct / "
              f"{len(bake.indirect_times)} indirect times, bake {bake_s:.1f} s", flush=True)
        for fill in FILL_MODES:
            wr.render(cams[0], float(times[0]), fill=fill)  # warm-up (JIT, buffers)
            errs, secs, holes = [], [], []
            frames = []
            for cam, t, ref in zip(cams, times, refs, strict=True):
                t1 = time.perf_counter()
                fr = wr.render(cam, float(t), fill=fill)
                secs.append(time.perf_counter() - t1)
                errs.append(lrms(fr.radiance, ref.radiance, ref.object_id >= 0))
                holes.append(fr.counts.get("hole", 0) / (cam.width * cam.height))
                frames.append(fr.radiance)
            entry["fills"][fill] = {"lrms": [float(e) for e in errs], "mean_lrms": float(np.mean(errs)),
                                    "max_lrms": float(np.max(errs)), "seconds_per_frame": float(np.median(secs)),
                                    "hole_fraction": float(np.mean(holes))}
            if fill == "both":
                k = len(cams) // 2
                write_image(IMG / f"{name}_{q}_frame{k}.png", frames[k])
            print(f"[{name}] {q} {fill}: mean LRMS {np.mean(errs):.4f}, {np.median(secs) * 1e3:.1f} ms/frame",
                  flush=True)
        result["qualities"][q] = entry
    k = len(cams) // 2
    write_image(IMG / f"{name}_reference_frame{k}.png", refs[k].radiance)
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
        fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
        for q in QUALITIES:
            e = res["qualities"][q]["fills"]["both"]["lrms"]
            axes[0].plot(range(len(e)), e, marker="o", ms=3, label=f"{q} ({res['qualities'][q]['views']} views)")
        axes[0].set_title(f"{name}: per-frame LRMS, fill 'both'")
        for fill in FILL_MODES:
            e = res["qualities"]["high"]["fills"][fill]["lrms"]
            axes[1].plot(range(len(e)), e, marker=".", ms=3, label=fill)
        axes[1].set_title(f"{name}: high quality, every fill mode")
        for ax in axes:
            ax.set_xlabel("frame")
            ax.set_ylabel("LRMS")
            ax.axhline(float(np.mean(res["noise_floor_lrms"])), color="grey", ls=":", lw=1)
            ax.legend(fontsize=8)
            ax.grid(alpha=0.3)
        axes[1].set_yscale("log")
        fig.tight_layout()
        fig.savefig(IMG / f"{name}_lrms.png", dpi=90)
        plt.close(fig)


def _doc(data: dict) -> str:
    lines = [f"Run: `python -m bench.walkthrough_accuracy{' --quick' if data['quick'] else ''}` "
             f"({data['machine']}, numba threads {data['threads']}). "
             + ("**Reduced run**: " if data["reduced"] else "")
             + f"{data['frames']} frames of {data['width']} x {data['height']} per scene; preset resolutions "
             f"overridden as listed under 'Params per quality' (the shipped presets are larger, see "
             f"docs/walkthrough.md).",
             ""]
    for name, res in data["scenes"].items():
        lines += [f"### {name}", "",
                  f"Reference (frame by frame, {res['reference_params']['spp']} spp, "
                  f"{res['reference_params']['indirect_samples']} indirect paths / pixel, "
                  f"{res['reference_params']['indirect_bounces']} bounces): "
                  f"**{res['reference_seconds_per_frame']:.2f} s / frame, {res['reference_seconds_total']:.1f} s "
                  f"for the walkthrough**. Reference noise floor (same frames, another seed): LRMS "
                  f"{np.mean(res['noise_floor_lrms']):.4f}. Scene static: {res['static']}.", "",
                  "| quality | base views | time samples (direct / indirect) | bake (s) | bake MiB | "
                  "per-frame (ms), fill both | mean LRMS none | foreground | background | both | trace | "
                  "max LRMS both | bake + frames vs reference | break-even frames |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for q in QUALITIES:
            e = res["qualities"][q]
            f = e["fills"]
            total = e["bake_seconds"] + res["frames"] * f["both"]["seconds_per_frame"]
            lines.append(
                f"| {q} | {e['views']} | {len(e['direct_times'])} / {len(e['indirect_times'])} | "
                f"{e['bake_seconds']:.1f} | {e['bake_mbytes']:.0f} | {1e3 * f['both']['seconds_per_frame']:.1f} | "
                + " | ".join(f"{f[m]['mean_lrms']:.4f}" for m in FILL_MODES)
                + f" | {f['both']['max_lrms']:.4f} | {total / res['reference_seconds_total']:.2f}x | "
                f"{e['bake_seconds'] / (res['reference_seconds_per_frame'] - f['both']['seconds_per_frame']):.1f} |")
        lines += ["", "| quality | fill | mean LRMS | max LRMS | holes left (mean fraction) | ms / frame |",
                  "|---|---|---|---|---|---|"]
        for q in QUALITIES:
            for m in FILL_MODES:
                f = res["qualities"][q]["fills"][m]
                lines.append(f"| {q} | {m} | {f['mean_lrms']:.4f} | {f['max_lrms']:.4f} | "
                             f"{f['hole_fraction']:.4f} | {1e3 * f['seconds_per_frame']:.1f} |")
        lines += ["", "Params per quality: " + "; ".join(
            f"{q}: q={res['qualities'][q]['params']['q']}, q_indirect={res['qualities'][q]['params']['q_indirect']}, "
            f"face_res={res['qualities'][q]['params']['face_res']}, spp={res['qualities'][q]['params']['spp']}, "
            f"indirect_samples={res['qualities'][q]['params']['indirect_samples']}" for q in QUALITIES), "",
                  f"![per-frame LRMS](../img/walkthrough/{name}_lrms.png)", "",
                  "Middle frame: reference, low, medium, high (fill both):", "",
                  " ".join(f"![{k}](../img/walkthrough/{name}_{k}_frame{res['frames'] // 2}.png)"
                           for k in ("reference",) + QUALITIES), ""]
    sp = data["speed"]
    lines += ["### Speed: a 512 x 512 frame from two base images", "",
              f"Two bases of face_res {sp['face_res']} (6 x {sp['face_res']}^2 samples each), Cornell box. "
              f"Plain reference render of the same frame (ReferenceParams defaults: "
              f"{sp['reference_params']['spp']} spp, direct light only): **{sp['reference_ms']:.0f} ms**. "
              f"Machine load average (1 min) before / after: {sp['load_before'][0]:.1f} / "
              f"{sp['load_after'][0]:.1f} on 2 cores: with a load above 2 the wall times are inflated by other "
              f"jobs; the CPU column is the work of both threads (on an idle machine the wall time is about half "
              f"of it plus the serial parts).", "",
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
    if args.quick:
        args.frames, args.width, args.height, args.speed_reps = 6, 64, 48, 3
        args.overrides = {q: dict(face_res=32, probe_res=8, indirect_samples=2, max_views=3, max_time_samples=3)
                          for q in QUALITIES}
        ref = ReferenceParams(spp=1, indirect_samples=4, area_light_samples=4)
    else:
        args.frames, args.width, args.height, args.speed_reps = 16, 128, 96, 5
        args.overrides = {
            "low": dict(face_res=48, probe_res=12, max_views=3, max_time_samples=3, indirect_samples=4,
                        area_light_samples=4),
            "medium": dict(face_res=64, probe_res=16, max_views=5, max_time_samples=5, indirect_samples=8,
                           area_light_samples=4),
            "high": dict(face_res=96, probe_res=24, max_views=8, max_time_samples=9, indirect_samples=16,
                         area_light_samples=4),
        }
        ref = ReferenceParams(spp=2, indirect_samples=16, indirect_bounces=2, area_light_samples=4)
    IMG.mkdir(parents=True, exist_ok=True)
    data: dict = {"quick": args.quick, "reduced": True, "frames": args.frames, "width": args.width,
                  "height": args.height, "machine": f"{platform.machine()}, {platform.python_version()}",
                  "threads": nb.get_num_threads(), "scenes": {}}
    t0 = time.perf_counter()
    for name in ("cornell_animated", "static_room"):
        data["scenes"][name] = run_scene(name, args, ref)
    data["speed"] = speed(args)
    data["seconds"] = time.perf_counter() - t0
    print(json.dumps(data["speed"], indent=1))
    if args.no_doc:
        return
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(data, indent=1))
    _plots(data)
    replace_block(DOC, "walkthrough_accuracy", _doc(data), title="Walkthrough accuracy")


if __name__ == "__main__":
    main()
