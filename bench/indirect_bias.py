"""Is the LDC's indirect pass unbiased? Its indirect light against the reference renderer's at the same points.

``python -m bench.indirect_bias [--write]``: per scene (cornell_box, cornell_mirror_glossy), the z
axis of an LDC of ``--res`` (default 32) px; for its samples on materials with a diffuse and no
mirror or glossy lobe, the indirect radiance of the front side (a) as the indirect pass
(``engine.newviews.ldc.indirect_chunk``, noise 0.02, 3 bounces) estimates it with each
``(min_paths, max_paths, caustics)`` of ``--paths`` (caustics: ``paths`` or ``photons``, the
caustic photon map of engine/caustics.py) and (b) as the reference renderer's ``shade_hits``
estimates it with ``--ref-paths`` paths per point (full radiance minus its direct-only radiance;
``shade_hits`` traces a fixed number of paths, so it has no stopping rule that could bias it).
The ratio of the means (a) / (b) shows a bias of the pass's stopping rule beyond the noise of both
(the noise of a ratio of means over ~1000 points is a fraction of a percent).

Writes the ``indirect_bias`` block of ``docs/accuracy/gi.md`` with ``--write``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bench.docs_writer import replace_block
from bench.image_digest import load_sample
from engine.metrics import REC709_WEIGHTS
from engine.newviews.effects import analyze
from engine.newviews.indirect import IndirectParams
from engine.newviews.ldc import bake_ldc_axis, indirect_chunk, surface_attributes
from engine.raycast import EmbreeCaster
from engine.reference import ReferenceParams, ReferenceRenderer

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "accuracy" / "gi.md"
LUMA = np.asarray(REC709_WEIGHTS)


def diffuse_samples(sc, ax) -> np.ndarray:
    """Indices of ``ax``'s samples on materials with a diffuse and no mirror or glossy lobe (where
    the reference's radiance toward any direction is the same diffuse light the pass bakes)."""
    mt = sc.materials
    local = ~np.any((mt.kr > 0) | (mt.kg > 0), axis=1) & np.any(mt.kd > 0, axis=1)
    return np.flatnonzero(local[ax.material])


def reference_indirect(ren: ReferenceRenderer, sc, ax, sel: np.ndarray, paths: int, seed: int = 0) -> float:
    """Mean luminance of the indirect light leaving the front sides (side 0) of samples ``sel`` of
    ``ax``, as the reference renderer's ``shade_hits`` estimates it with ``paths`` paths per point
    (3 bounces): its full radiance minus its direct-only radiance, both from one fixed count."""
    _, ng, _ = surface_attributes(sc, ax.ldi.prim[sel], ax.ldi.u[sel], ax.ldi.v[sel])
    base = dict(spp=1, max_depth=4, glossy_samples=8, area_light_samples=4, seed=seed, indirect_bounces=3)
    hits = (ax.ldi.prim[sel], ax.ldi.u[sel], ax.ldi.v[sel], -ng)  # rays arriving on the front side
    full = ren.shade_hits(*hits, ReferenceParams(indirect_samples=paths, **base))
    direct = ren.shade_hits(*hits, ReferenceParams(indirect_samples=0, **base))
    return float(((full - direct) @ LUMA).mean())


def run_scene(name: str, res: int, paths: list[tuple[int, int, str]], ref_paths: int, log) -> list[dict]:
    sc, _cam = load_sample(name)
    caster = EmbreeCaster(sc)
    ren = ReferenceRenderer(sc, caster)
    ax = bake_ldc_axis(sc, caster, 2, res, plan=analyze(sc))
    sel = diffuse_samples(sc, ax)
    ref = reference_indirect(ren, sc, ax, sel, ref_paths)
    rows = []
    for lo, hi, caustics in paths:
        t0 = time.perf_counter()
        # lo < hi: the adaptive sampler (a pilot of lo paths sizes each side); lo = hi: that fixed count
        ip = IndirectParams(noise=0.02, bounces=3, min_paths=lo, max_paths=hi, sampling="adaptive", caustics=caustics)
        ch = indirect_chunk(sc, caster, ax, 0, ax.n_samples, ip, renderer=ren)
        ours = float((ch.radiance[sel, 0] @ LUMA).mean())
        rows.append({"scene": name, "min_paths": lo, "max_paths": hi, "caustics": caustics, "points": int(sel.size),
                     "ratio": ours / ref, "paths_mean": ch.stats["paths_mean"], "met_target": ch.stats["met_target"],
                     "rel_stderr_median": ch.stats["rel_stderr_median"], "seconds": time.perf_counter() - t0})
        log(f"{name} paths {lo}..{hi}, caustics by {caustics}: ratio {ours / ref:.4f}, "
            f"{ch.stats['paths_mean']:.0f} paths per side")
    return rows


def _table(rows: list[dict], ref_paths: int) -> str:
    lines = ["| scene | min_paths .. max_paths | caustics | mean paths per side | sides at the 2 % target | "
             "median side's rel. error | indirect light, pass / reference |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['min_paths']} .. {r['max_paths']} | {r['caustics']} | {r['paths_mean']:.0f} "
                     f"| {100 * r['met_target']:.0f} % | {100 * r['rel_stderr_median']:.2f} % | {r['ratio']:.4f} |")
    lines += ["", f"Reference: ``shade_hits`` with {ref_paths} paths per point; {rows[0]['points']} points of "
                  "the z axis on the first scene. min = max: a fixed count, nothing stops early."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["cornell_box", "cornell_mirror_glossy"])
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--ref-paths", type=int, default=256)
    ap.add_argument("--paths", nargs="+",
                    default=["64:1024:paths", "256:1024:paths", "1024:1024:paths", "256:256:photons",
                             "1024:1024:photons"],
                    help="min_paths:max_paths:caustics settings of the pass (caustics: paths or photons)")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args(argv)
    paths = [(int(lo), int(hi), caustics) for lo, hi, caustics in (s.split(":") for s in args.paths)]
    rows = [r for s in args.scenes for r in run_scene(s, args.res, paths, args.ref_paths,  # type: ignore[arg-type]
                                                      lambda m: print(m, flush=True))]
    table = _table(rows, args.ref_paths)
    print(table)
    if args.write:
        replace_block(DOC, "indirect_bias", table)


if __name__ == "__main__":
    main()
