"""Ray casting throughput: raw Embree vs the reference renderer, on every sample scene.

Reports, from one run on one machine:
- raw Embree throughput for the scene camera's primary rays (one ``engine.embree.intersect``
  over pre-built float32 arrays: the ceiling for any renderer built on it);
- the reference renderer's effective throughput: every ray it traced (camera, shadow,
  reflection, indirect) per second of render time, shading included;
- their ratio, and the fraction of render time spent inside Embree calls.

The target: the renderer spends no more than half its time
outside Embree (ratio >= 0.5). Shadow and secondary rays are less coherent than
primary rays, so the ratio against *primary* throughput is the stricter of the two
readings; both are recorded.

    python -m bench.raycast_throughput [--size 512] [--spp 4] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from api_schemas import load_scene_file
from bench.docs_writer import replace_block
from engine import embree
from engine.camera import camera_rays, pixel_centers
from engine.raycast import EmbreeCaster
from engine.reference import ReferenceParams, ReferenceRenderer
from samples import SAMPLES_DIR, sample_names, sample_path
from workers.scene_loader import directory_resolver, load_scene

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "performance.md"
DATA = ROOT / "docs" / "data" / "raycast_throughput.json"

PAPER_SCENES = ["mirror_box", "teapot_glossy", "teapot_spheres", "cornell_box"]
THREADS = 2  # this machine's cores; the renderer's default pipelines


def measure(name: str, size: int, spp: int, repeat: int) -> dict:
    loaded = load_scene(load_scene_file(sample_path(name)), directory_resolver(SAMPLES_DIR))
    rt = loaded.runtime
    cam = replace(loaded.camera, width=size, height=size)
    caster = EmbreeCaster(rt)
    es = caster._get()
    px, py = pixel_centers(cam)
    o, d = camera_rays(cam, px, py)
    o32 = np.ascontiguousarray((o - rt.center).astype(np.float32))
    d32 = np.ascontiguousarray(d.astype(np.float32))
    raw = {}
    for threads in (1, THREADS):
        best_t = float("inf")
        for _ in range(repeat):
            t0 = time.perf_counter()
            _run_threads(es, o32, d32, threads)
            best_t = min(best_t, time.perf_counter() - t0)
        raw[threads] = o32.shape[0] / best_t

    renderer = ReferenceRenderer(rt, caster)
    result = {"scene": name, "triangles": rt.n_triangles, "lights": rt.lights.count, "size": size, "spp": spp,
              "raw_primary_rays_per_s_1thread": raw[1],
              f"raw_primary_rays_per_s_{THREADS}threads": raw[THREADS]}
    for pipelines in (1, THREADS):
        params = ReferenceParams(spp=spp, pipelines=pipelines)
        renderer.render(replace(cam, width=64, height=64), params)  # compile / load kernels
        best = None
        for _ in range(repeat):
            caster.embree_seconds = 0.0
            t0 = time.perf_counter()
            out = renderer.render(cam, params)
            wall = time.perf_counter() - t0
            rec = {"wall_s": wall, "rays": sum(out.counts.values()), "embree_thread_s": caster.embree_seconds,
                   "timings": out.timings, "counts": out.counts}
            if best is None or wall < best["wall_s"]:
                best = rec
        eff = best["rays"] / best["wall_s"]
        result[f"pipelines_{pipelines}"] = {
            "renderer_rays_per_s": eff,
            "ratio_vs_raw_same_threads": eff / raw[pipelines],
            "embree_thread_seconds_per_wall_second": best["embree_thread_s"] / best["wall_s"],
            "render_wall_s": best["wall_s"], "rays": best["counts"],
            "timings_s": {k: round(v, 4) for k, v in best["timings"].items()},
        }
    return result


def _run_threads(es, o32, d32, threads: int) -> None:
    """The engine's Embree kernels (engine/embree.py) on one thread or on all."""
    embree.intersect(es, o32, d32, serial=threads == 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--scenes", nargs="*", default=None)
    args = ap.parse_args()
    names = args.scenes or [n for n in PAPER_SCENES if n in sample_names()]
    rows = []
    for n in names:
        r = measure(n, args.size, args.spp, args.repeat)
        rows.append(r)
        print(json.dumps({"scene": n,
                          "ratio_1": r["pipelines_1"]["ratio_vs_raw_same_threads"],
                          f"ratio_{THREADS}": r[f"pipelines_{THREADS}"]["ratio_vs_raw_same_threads"]}))
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps({"machine": platform.platform(), "cpus": os.cpu_count(), "rows": rows},
                               indent=2) + "\n")
    lines = [
        f"Measured with `python -m bench.raycast_throughput --size {args.size} --spp {args.spp} "
        f"--repeat {args.repeat}` ({date_str()}, {os.cpu_count()} cores, best of {args.repeat}; raw data in "
        "`docs/data/raycast_throughput.json`). Reference settings: direct light, mirror depth 4, 16 glossy "
        "samples, 16 area-light samples, no indirect. Both the raw rate (engine/embree.py's "
        f"kernels) and the renderer are measured with 1 thread and with {THREADS} (the renderer's "
        "`pipelines`: chunks in flight at once, each thread alternating Embree calls and serial numba "
        "kernels).",
        "",
        f"| scene | triangles | lights | raw Embree primary, 1 / {THREADS} threads (Mrays/s) | "
        f"renderer, all rays incl. shading, 1 / {THREADS} pipelines (Mrays/s) | ratio at 1 | **ratio at {THREADS}** | "
        "rays traced (camera / shadow / reflection) |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        p1, p2 = r["pipelines_1"], r[f"pipelines_{THREADS}"]
        c = p2["rays"]
        lines.append(
            f"| {r['scene']} | {r['triangles']:,} | {r['lights']} | "
            f"{r['raw_primary_rays_per_s_1thread'] / 1e6:.2f} / "
            f"{r[f'raw_primary_rays_per_s_{THREADS}threads'] / 1e6:.2f} | "
            f"{p1['renderer_rays_per_s'] / 1e6:.2f} / {p2['renderer_rays_per_s'] / 1e6:.2f} | "
            f"{p1['ratio_vs_raw_same_threads']:.2f} | **{p2['ratio_vs_raw_same_threads']:.2f}** | "
            f"{c['camera']:,} / {c['shadow']:,} / {c['reflection']:,} |")
    lines += [
        "",
        "Ratio = the renderer's rays per second (every camera, shadow and reflection ray, shading "
        "included) / raw Embree primary-ray rate with the same number of threads. Target >= 0.5: "
        "the renderer spends at most half its time outside Embree. Primary rays are the most coherent "
        "kind, so this is the strict reading. Speeds are only compared within one run.",
    ]
    replace_block(DOC, "raycast_throughput", "\n".join(lines), title="Performance")
    print(f"wrote {DOC}")


def date_str() -> str:
    return time.strftime("%Y-%m-%d")


if __name__ == "__main__":
    main()
