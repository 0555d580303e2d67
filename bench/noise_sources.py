"""Where a path-traced view's noise comes from: the mirror / glossy Cornell box against itself with
the mirror or the glossy lobe switched off, and against the plain Cornell box.

``flock /tmp/bench.lock python -m bench.noise_sources`` renders view 0 of ``bench.gi_equal_error``
(256 x 256) with that benchmark's ladder settings (one indirect path and one rect-light sample per
camera sample, 256 spp) twice, with two seeds, for each scene variant: the sample scene as it is,
its mirror material's ``kr`` set to 0 (a black sphere: no light reaches anything through it), its
glossy material's ``kg`` set to 0, both, and the plain Cornell box. Half the squared difference of
the two renders is each pixel's variance of one render; the LRMS of one render is its root over the
compared pixels (``comparison_mask``) against the mean image, and the variance is split by the
object each pixel shows. Variances add: the part a lobe brings is the variance with it minus the
variance without it. The renders light-trace the caustics seen on diffuse surfaces
(``ReferenceParams.light_paths``, its default, engine/light_tracing.py); the mirror / glossy box is
rendered once more with ``light_paths`` 0 (the camera's paths alone), the renderer before it.
Writes the ``noise_sources`` block of ``docs/accuracy/gi.md`` (``--no-doc``: print it).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from bench import gi_equal_error as gi
from bench.docs_writer import replace_block
from engine.metrics import REC709_WEIGHTS

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "accuracy" / "gi.md"
SPP = 256
SIZE = 256

VARIANTS: dict[str, tuple[str, dict[str, dict[str, list[float]]]] | tuple[str, dict, float]] = {
    # label: (sample scene, {material: fields replaced}[, light_paths])
    "mirror / glossy box": ("cornell_mirror_glossy", {}),
    "  camera paths alone (light_paths 0)": ("cornell_mirror_glossy", {}, 0.0),
    "  without the mirror (kr = 0)": ("cornell_mirror_glossy", {"mirror": {"kr": [0.0, 0.0, 0.0]}}),
    "  without the gloss (kg = 0)": ("cornell_mirror_glossy", {"glossy_box": {"kg": [0.0, 0.0, 0.0]}}),
    "  without either": ("cornell_mirror_glossy", {"mirror": {"kr": [0.0, 0.0, 0.0]},
                                                   "glossy_box": {"kg": [0.0, 0.0, 0.0]}}),
    "Cornell box": ("cornell_box", {}),
}


def _variant(scene: str, changes: dict[str, dict[str, list[float]]]):
    """The sample scene with ``changes`` applied to its materials, loaded (its runtime scene)."""
    from api_schemas.scene import load_scene_json
    from bench.ibrt_throughput import sample_path
    from samples import SAMPLES_DIR
    from workers.scene_loader import directory_resolver, load_scene

    doc = json.loads(Path(sample_path(scene)).read_text())
    for m in doc["materials"]:
        m.update(changes.get(m["name"], {}))
    return load_scene(load_scene_json(json.dumps(doc).encode()), directory_resolver(SAMPLES_DIR)).runtime


def measure(scene: str, changes: dict[str, dict[str, list[float]]], light_paths: float | None = None) -> dict:
    from engine.raycast import EmbreeCaster
    from engine.reference import ReferenceRenderer

    sc = _variant(scene, changes)
    spec = gi.SCENES["cornell_mirror_glossy"]  # the same bounces and depth for every variant
    ren = ReferenceRenderer(sc, EmbreeCaster(sc))
    cam = gi.scene_views(scene, sc, SIZE, 6)[0]
    ys, t0, c0 = [], time.perf_counter(), time.process_time()
    for seed in (1, 2):
        params = dataclasses.replace(gi.ladder_params(spec, SPP), seed=seed)
        if light_paths is not None:
            params = dataclasses.replace(params, light_paths=light_paths)
        r = ren.render(cam, params)
        ys.append(r.radiance.reshape(-1, 3).astype(np.float64) @ np.asarray(REC709_WEIGHTS))
    m = gi.compared_pixels(sc, spec, cam, r.depth, r.object_id).reshape(-1)
    var = (ys[0] - ys[1]) ** 2 / 2.0
    mean = (ys[0] + ys[1]) / 2.0
    oid = r.object_id.reshape(-1)
    total = float(var[m].sum())
    by_object = {sc.object_names[o]: float(var[m & (oid == o)].sum() / total) for o in np.unique(oid[m]) if o >= 0}
    return {"lrms": float(np.sqrt(total / (mean[m] ** 2).sum())), "variance": total / float((mean[m] ** 2).sum()),
            "by_object": by_object, "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0}


def doc_block(res: dict) -> str:
    base = res["rows"]["mirror / glossy box"]["variance"]
    lines = [f"Command: `{res['command']}` (view 0 of the benchmark above at {SIZE}x{SIZE}, {SPP} spp with one "
             "indirect path (6 diffuse bounces, mirror / glossy depth 8) and one rect-light sample each, two seeds "
             f"per variant; {res['total_s']:.0f} s).", "",
             "| scene | LRMS of one render | variance, share of the mirror / glossy box's | one render, s (CPU s) | "
             "where the variance is (share by object) |", "|---|---|---|---|---|"]
    for label, r in res["rows"].items():
        top = sorted(r["by_object"].items(), key=lambda kv: -kv[1])[:3]
        lines.append(f"| {label.strip()} | {100 * r['lrms']:.2f} % | {r['variance'] / base:.2f} | "
                     f"{r['seconds'] / 2:.1f} ({r['cpu_seconds'] / 2:.1f}) | "
                     + ", ".join(f"{k} {100 * v:.0f} %" for k, v in top) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--no-doc", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = {}
    for label, variant in VARIANTS.items():
        rows[label] = measure(*variant)
        print(f"{label.strip()}: LRMS {rows[label]['lrms']:.4f}", flush=True)
    res = {"rows": rows, "command": "python -m bench.noise_sources", "total_s": time.perf_counter() - t0}
    block = doc_block(res)
    if args.no_doc:
        print(block)
    else:
        replace_block(DOC, "noise_sources", block)
    return 0


if __name__ == "__main__":
    sys.exit(main())
