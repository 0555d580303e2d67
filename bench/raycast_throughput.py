"""Ray casting throughput: raw embreex vs the reference renderer, on every sample scene.

Reports, from one run on one machine:
- raw embreex throughput for the scene camera's primary rays (one ``EmbreeScene.run``
  over pre-built float32 arrays: the ceiling for any renderer built on embreex);
- the reference renderer's effective throughput: every ray it traced (camera, shadow,
  reflection, indirect) per second of render time, shading included;
- their ratio, and the fraction of render time spent inside Embree calls.

The foundation issue's target: the renderer spends no more than half its time
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
from engine.camera import camera_rays, pixel_centers
from engine.raycast import EmbreeCaster
from engine.reference import ReferenceParams, ReferenceRenderer
from samples import SAMPLES_DIR, sample_names, sample_path
from workers.scene_loader import directory_resolver, load_scene

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "performance.md"
DATA = ROOT / "docs" / "data" / "raycast_throughput.json"

PAPER_SCENES = ["mirror_box", "teapot_glossy", "teapot_spheres", "cornell_box"]


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
    raw = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        es.run(o32, d32, output=1)
        raw.append(time.perf_counter() - t0)
    raw_rate = o32.shape[0] / min(raw)

    renderer = ReferenceRenderer(rt, caster)
    params = ReferenceParams(spp=spp)
    renderer.render(replace(cam, width=16, height=16), params)  # compile / load kernels
    best = None
    for _ in range(repeat):
        caster.embree_seconds = 0.0
        caster.embree_rays = 0
        t0 = time.perf_counter()
        out = renderer.render(cam, params)
        wall = time.perf_counter() - t0
        rays = sum(out.counts.values())
        rec = {"wall_s": wall, "rays": rays, "embree_s": caster.embree_seconds, "timings": out.timings,
               "counts": out.counts}
        if best is None or wall < best["wall_s"]:
            best = rec
    eff = best["rays"] / best["wall_s"]
    return {
        "scene": name, "triangles": rt.n_triangles, "lights": rt.lights.count, "size": size, "spp": spp,
        "raw_primary_rays_per_s": raw_rate, "renderer_rays_per_s": eff, "ratio": eff / raw_rate,
        "embree_time_fraction": best["embree_s"] / best["wall_s"],
        "embree_rays_per_s_in_render": best["rays"] / best["embree_s"] if best["embree_s"] else float("nan"),
        "render_wall_s": best["wall_s"], "rays": best["counts"],
        "timings_s": {k: round(v, 4) for k, v in best["timings"].items()},
    }


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
        print(json.dumps({k: r[k] for k in ("scene", "raw_primary_rays_per_s", "renderer_rays_per_s", "ratio",
                                            "embree_time_fraction")}))
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps({"machine": platform.platform(), "cpus": os.cpu_count(), "rows": rows},
                               indent=2) + "\n")
    lines = [
        f"Measured with `python -m bench.raycast_throughput --size {args.size} --spp {args.spp} "
        f"--repeat {args.repeat}` ({date_str()}, {os.cpu_count()} cores, best of {args.repeat}; "
        "raw data in `docs/data/raycast_throughput.json`). Default reference settings: direct light, "
        "mirror depth 4, 16 glossy samples, 16 area-light samples, no indirect.",
        "",
        "| scene | triangles | lights | raw embreex primary (Mrays/s) | renderer, all rays incl. shading "
        "(Mrays/s) | ratio | time inside Embree | rays traced (camera / shadow / reflection) |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        c = r["rays"]
        lines.append(
            f"| {r['scene']} | {r['triangles']:,} | {r['lights']} | {r['raw_primary_rays_per_s'] / 1e6:.2f} | "
            f"{r['renderer_rays_per_s'] / 1e6:.2f} | **{r['ratio']:.2f}** | {r['embree_time_fraction']:.0%} | "
            f"{c['camera']:,} / {c['shadow']:,} / {c['reflection']:,} |")
    lines += [
        "",
        "Ratio = renderer rays per second / raw primary-ray rate (target >= 0.5). 'Time inside Embree' "
        "is the share of the render's wall time spent in `EmbreeScene.run` (the other reading of the "
        "target: at most half the time outside Embree). Speeds are only compared within this one run.",
    ]
    replace_block(DOC, "raycast_throughput", "\n".join(lines), title="Performance")
    print(f"wrote {DOC}")


def date_str() -> str:
    return time.strftime("%Y-%m-%d")


if __name__ == "__main__":
    main()
