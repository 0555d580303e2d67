"""Time for the reference renderer and for Mitsuba 3 to reach a given error against one Mitsuba ground truth.

Scenes: the Cornell box (Mitsuba's own ``cbox-rgb.xml`` from ``../shared/data/cornell-box-mitsuba``
against ``samples/scenes/cornell_box.json``), the spheres box and the mirror / glossy Cornell box
(``samples/scenes/cornell_mirror_glossy.json``; both converted by ``bench/mitsuba_bridge.py``),
at ``--res`` pixels; ``direct`` and ``path`` (the glossy box: path only, as in
``bench/mitsuba_crosscheck.py``). Mitsuba runs ``llvm_ad_rgb`` on every core; ours its default
two pipelines.

Ground truth: Mitsuba ``multijitter``, two renders of ``--truth-spp`` samples with other seeds,
averaged (cached in ``--cache`` between runs); its own noise, ``lrms(a, b) / 2``, is taken out of
every measured error in quadrature. Pixels compared: ``bench/mitsuba_crosscheck.comparison_mask``
(covered, minus the emitters' neighbourhoods).

Contestants, interleaved at each step of the ladder ``--spp`` (and ``--errors``):

- ours, uniform: ``spp`` camera samples, one rect-light sample and (path) one path per sample;
- ours, adaptive: ``max_error`` = each of ``--errors`` (progressive render, cap ``--cap`` spp);
- Mitsuba ``direct`` / ``path`` (``max_depth`` = bounces + 2) with the ``multijitter`` and the
  ``independent`` sampler at ``spp`` samples.

Time to reach a target error: uniform renders take the samples per pixel the target needs
(log-log interpolation of the error against spp) over their best speed among the renders of 64
spp or more (samples per second: JIT compilation and start-up amortised, the machine's other work
least in the way); adaptive renders interpolate their measured wall time against their error.
A target the cheapest render already beats shows that render's time as an upper bound ("<=").
Wall and CPU seconds (``time.process_time``: every thread of the
process). Load average at the start and at the end. Results per scene go to ``--cache`` as JSON;
``--write`` builds ``docs/accuracy/reference-vs-mitsuba.md`` and its plot from every scene
measured so far at this resolution and engine version.

    flock /tmp/bench.lock python -m bench.reference_vs_mitsuba --scenes cornell_box --write
    flock /tmp/bench.lock python -m bench.reference_vs_mitsuba --scenes spheres_box --write
    flock /tmp/bench.lock python -m bench.reference_vs_mitsuba --scenes cornell_mirror_glossy --write
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench import mitsuba_bridge as mb
from bench import mitsuba_crosscheck as cc
from bench.progressive_reference import _interp
from engine import ENGINE_VERSION
from engine.memory import keep_freed_memory
from engine.metrics import lrms
from engine.reference import ReferenceParams, ReferenceRenderer

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "accuracy" / "reference-vs-mitsuba.md"
PLOT = ROOT / "docs" / "img" / "reference_vs_mitsuba.png"
TARGETS = (0.10, 0.05, 0.03, 0.02, 0.01)
SCENES = ("cornell_box", "spheres_box", "cornell_mirror_glossy")
MIN_SPEED_SPP = 64
NOT_REACHED = "n/r"  # the adaptive renders all stopped above the target (at the spp cap)
CONTESTANTS = ("ours", "ours_adaptive", "mi_multijitter", "mi_independent")
LABEL = {"ours": "ours, uniform", "ours_adaptive": "ours, adaptive (max_error)",
         "mi_multijitter": "Mitsuba multijitter", "mi_independent": "Mitsuba independent"}


def _prepare(name: str, res: int, workdir: str):
    """(our runtime, camera, Mitsuba scene, {sampler: sensor}, kinds, our max_depth, bounces), all in
    ``llvm_ad_rgb``."""
    v = mb.LLVM_VARIANT
    mi = mb.mitsuba(v)
    if name == "cornell_box":
        ls = cc._sample("cornell_box")
        cam = replace(ls.camera, width=res, height=res)
        scene = mi.load_file(str(mb.require_shared(mb.CBOX_XML)), res=int(res), spp=16)
        sensors = {s: mb.resampled_sensor(scene, s, variant=v) for s in ("multijitter", "independent")}
        return ls.runtime, cam, scene, sensors, cc.KINDS, 0, cc.BOUNCES
    if name == "spheres_box":
        from api_schemas.scene import load_scene_json
        from workers.scene_loader import load_scene

        ls = load_scene(load_scene_json(json.dumps(cc.SPHERES_BOX)))
        kinds, depth, bounces = cc.KINDS, 0, cc.BOUNCES
    elif name == "cornell_mirror_glossy":
        ls = cc._sample(name)
        kinds, depth, bounces = cc.KINDS_OF[name], cc.MIRROR_DEPTH, cc.MIRROR_BOUNCES
    else:
        raise KeyError(name)
    cam = replace(ls.camera, width=res, height=res)
    scene = mb.runtime_to_mitsuba(ls.runtime, cam, workdir, sampler="multijitter", variant=v)
    sensors = {s: mi.load_dict(mb.sensor_dict(cam, 16, s, variant=v)) for s in ("multijitter", "independent")}
    return ls.runtime, cam, scene, sensors, kinds, depth, bounces


def _ours_params(kind: str, spp: int, seed: int, depth: int, bounces: int, **kw) -> ReferenceParams:
    paths = spp if kind == "path" else 0
    chunk = max(256, (1 << 20) // spp)
    return ReferenceParams(spp=spp, max_depth=depth, area_light_samples=1, glossy_samples=1,
                           indirect_samples=paths, indirect_bounces=bounces, seed=seed, chunk_pixels=chunk, **kw)


def _mi_render(scene, sensor, kind: str, bounces: int, spp: int, seed: int) -> np.ndarray:
    mi = mb.mitsuba(mb.LLVM_VARIANT)
    integ = mi.load_dict(mb.integrator_dict(kind, bounces))  # Mitsuba splits large spp into passes itself
    img = mi.render(scene, sensor=sensor, integrator=integ, spp=int(spp), seed=int(seed))
    return np.ascontiguousarray(np.array(img, dtype=np.float32)[..., :3])


def _timed(fn):
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t0, time.process_time() - c0


def measure(name: str, a) -> dict:
    workdir = tempfile.mkdtemp(prefix="ibr_rvm_")
    runtime, cam, scene, sensors, kinds, depth, bounces = _prepare(name, a.res, workdir)
    ren = ReferenceRenderer(runtime)
    aov = ren.render(cam, ReferenceParams(spp=1, max_depth=depth))
    light_px = cc.sees_rect_light(runtime, cam, aov.depth)
    if depth:
        light_px |= cc.mirrored_emitters(runtime, cam, depth)
    mask, _ = cc.comparison_mask(runtime, aov.object_id, light_px)
    spps = [int(x) for x in a.spp.split(",")]
    errors = [float(x) for x in a.errors.split(",")]
    res: dict = {"scene": name, "res": a.res, "engine": ENGINE_VERSION, "truth_spp": a.truth_spp,
                 "pixels": int(mask.sum()), "load_start": os.getloadavg()[0], "kinds": {}}
    for kind in kinds:
        cache = Path(a.cache) / f"truth_{name}_{kind}_{a.res}_{a.truth_spp}.npz"
        if cache.exists():
            z = np.load(cache)
            ta, tb = z["a"], z["b"]
        else:
            t0 = time.perf_counter()
            ta = _mi_render(scene, sensors["multijitter"], kind, bounces, a.truth_spp, 1000)
            tb = _mi_render(scene, sensors["multijitter"], kind, bounces, a.truth_spp, 1001)
            np.savez(cache, a=ta, b=tb)
            print(f"{name} {kind}: ground truth 2 x {a.truth_spp} spp in {time.perf_counter() - t0:.0f} s", flush=True)
        truth = 0.5 * (ta.astype(np.float64) + tb.astype(np.float64))
        e_truth = lrms(ta, tb, mask) / 2.0

        def err(img, truth=truth, e_truth=e_truth) -> float:
            return math.sqrt(max(lrms(img, truth, mask) ** 2 - e_truth ** 2, 1e-12))

        # warm-ups: kernels compiled / loaded, BVH built, Dr.Jit kernels traced
        ren.render(cam, _ours_params(kind, 4, 0, depth, bounces))
        ren.render(cam, _ours_params(kind, 64, 0, depth, bounces, max_error=0.2))
        for s in sensors.values():
            _mi_render(scene, s, kind, bounces, 4, 0)
            _mi_render(scene, s, kind, bounces, 64, 0)
        rows: dict[str, list] = {c: [] for c in CONTESTANTS}
        for k in range(max(len(spps), len(errors))):
            if k < len(spps):
                n = spps[k]
                img, w, c = _timed(lambda n=n, kind=kind: ren.render(cam, _ours_params(kind, n, 7, depth,
                                                                                        bounces)).radiance)
                rows["ours"].append((n, err(img), w, c))
                for s, sensor in sensors.items():
                    img, w, c = _timed(lambda sensor=sensor, n=n, kind=kind: _mi_render(scene, sensor, kind,
                                                                                        bounces, n, 7))
                    rows[f"mi_{s}"].append((n, err(img), w, c))
            if k < len(errors):
                x = errors[k]
                out, w, c = _timed(lambda x=x, kind=kind: ren.render(cam, _ours_params(kind, a.cap, 7, depth, bounces,
                                                                             max_error=x)))
                rep = out.adaptive or {}
                rows["ours_adaptive"].append((float(rep.get("spp_mean", 0.0)), err(out.radiance), w, c))
            print(f"{name} {kind} step {k}: " + ", ".join(
                f"{c} {100 * rows[c][-1][1]:.2f} % {rows[c][-1][2]:.2f} s" for c in CONTESTANTS
                if len(rows[c]) > k), flush=True)
        res["kinds"][kind] = {"truth_noise": e_truth, "rows": rows,
                              "mitsuba_max_depth": mb.integrator_dict(kind, bounces).get("max_depth")}
    res["load_end"] = os.getloadavg()[0]
    res["bounces"] = bounces
    res["max_depth"] = depth
    return res


def seconds_for(rows: list, target: float, uniform: bool, cpu: bool = False) -> tuple[float, str]:
    """Seconds (CPU seconds) a contestant needs for ``target`` LRMS (see the module docstring) and
    a mark: "~" extrapolated below its lowest error, "<=" reached already by its cheapest render
    (the time of the cheapest render that reaches it: an upper bound), NOT_REACHED (nan seconds)
    when the adaptive renders all stopped at one error above the target."""
    col = 3 if cpu else 2
    es = [max(r[1], 1e-9) for r in rows]
    if target >= max(es):
        return min(r[col] for r, e in zip(rows, es, strict=True) if e <= target), "<="
    if uniform:
        spp, extra = _interp(target, [r[0] for r in rows], es)
        # each renderer's best speed over its renders of >= MIN_SPEED_SPP samples: JIT compilation
        # and start-up amortised, the least disturbed by the machine's other work
        speed = max(r[0] / r[col] for r in rows if r[0] >= MIN_SPEED_SPP)
        return spp / speed, "~" if extra else ""
    order = sorted(range(len(rows)), key=lambda i: -es[i])
    xs, ys = [rows[i][col] for i in order], [es[i] for i in order]
    same = [k for k in range(1, len(ys)) if ys[k] >= ys[k - 1] * (1.0 - 1e-6)]  # the same image again
    if target < ys[-1] and len(ys) - 1 in same:
        # renders asked for different errors stopped at the same image: the spp cap, not a target
        return math.nan, NOT_REACHED
    keep = [k for k in range(len(ys)) if k not in same]  # equal errors: keep the first
    t, extra = _interp(target, [xs[k] for k in keep], [ys[k] for k in keep])
    return t, "~" if extra else ""


def _ratio(a: tuple[float, str], b: tuple[float, str]) -> str:
    """a / b, "-" when either is only a bound (both reached the target with their cheapest render)
    or was not reached."""
    return "-" if {"<=", NOT_REACHED} & {a[1], b[1]} else f"{a[0] / b[0]:.2f}x"


def _fmt(v: tuple[float, str]) -> str:
    s, mark = v
    if mark == NOT_REACHED:
        return "not reached"
    return f"{mark}{s:.2f}" if s < 100 else f"{mark}{s:.0f}"


def write(a) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bench.docs_writer import replace_block

    found = []
    for name in SCENES:  # the latest result of each scene at this engine version, whatever its size
        fs = sorted(Path(a.cache).glob(f"result_{name}_*_{ENGINE_VERSION}.json"), key=lambda f: f.stat().st_mtime)
        if fs:
            found.append(json.loads(fs[-1].read_text()))
    if not found:
        raise SystemExit("nothing measured yet")
    panels = [(r, kind) for r in found for kind in r["kinds"]]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.8), squeeze=False)
    lines = [f"Measured by `bench/reference_vs_mitsuba.py` (engine {ENGINE_VERSION}, "
             f"Mitsuba {_mi_version()} `llvm_ad_rgb` on every core, ours with two pipelines on a 2-core machine "
             "shared with other work). Seconds to reach each LRMS against a Mitsuba multijitter ground truth "
             "(its own noise taken out in quadrature); uniform renders: samples needed / best measured speed "
             "(renders of 64 spp or more), adaptive: interpolated wall time of `max_error` renders; `~`: "
             "extrapolated past the measured range; `<=`: the cheapest render already reaches it. "
             "Ratios above 1: ours faster.", ""]
    for ax, (r, kind) in zip(axes[0], panels, strict=True):
        d = r["kinds"][kind]
        rows = d["rows"]
        title = f"{r['scene']} {kind}, {r['res']} x {r['res']}"
        for c in CONTESTANTS:
            pts = sorted((row[2], 100 * row[1]) for row in rows[c])
            ax.loglog([x for x, _ in pts], [e for _, e in pts], "o-", label=LABEL[c], ms=3)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("wall seconds")
        ax.set_ylabel("LRMS %")
        ax.grid(True, which="both", alpha=0.3)
        lines += [f"### {title}", "",
                  f"{r['pixels']} pixels compared; ground truth 2 x {r['truth_spp']} spp, its noise "
                  f"{100 * d['truth_noise']:.2f} %; ours {r['bounces']} bounces"
                  + (f", max_depth {r['max_depth']}" if r["max_depth"] else "")
                  + f", Mitsuba max_depth {d['mitsuba_max_depth'] or '-'}; load {r['load_start']:.1f} at the start, "
                  f"{r['load_end']:.1f} at the end.", "",
                  "| target | ours uniform s (CPU) | ours adaptive s (CPU) | Mitsuba multijitter s (CPU) | "
                  "Mitsuba independent s (CPU) | multijitter / ours | multijitter / adaptive |",
                  "|---:|---:|---:|---:|---:|---:|---:|"]
        for t in TARGETS:
            ou, oa = seconds_for(rows["ours"], t, True), seconds_for(rows["ours_adaptive"], t, False)
            mj, mi_ = seconds_for(rows["mi_multijitter"], t, True), seconds_for(rows["mi_independent"], t, True)
            cu, ca = seconds_for(rows["ours"], t, True, True), seconds_for(rows["ours_adaptive"], t, False, True)
            cmj, cmi = seconds_for(rows["mi_multijitter"], t, True, True), seconds_for(rows["mi_independent"], t,
                                                                                        True, True)
            lines.append(f"| {100 * t:g} % | {_fmt(ou)} ({_fmt(cu)}) | {_fmt(oa)} ({_fmt(ca)}) | {_fmt(mj)} "
                         f"({_fmt(cmj)}) | {_fmt(mi_)} ({_fmt(cmi)}) | {_ratio(mj, ou)} | {_ratio(mj, oa)} |")
        lines += ["", "Raw measurements (spp or mean spp, LRMS, wall s, CPU s):", ""]
        for c in CONTESTANTS:
            lines.append(f"- {LABEL[c]}: " + "; ".join(f"{row[0]:.0f} / {100 * row[1]:.2f} % / {row[2]:.2f} / "
                                                          f"{row[3]:.2f}" for row in rows[c]))
        lines.append("")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    PLOT.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(PLOT, dpi=110)
    lines += [f"![LRMS against wall time](../img/{PLOT.name})", "", "Reproduce (each under 15 minutes once the "
              "ground truths are cached):", ""]
    lines += [f"    flock /tmp/bench.lock python -m bench.reference_vs_mitsuba --res {r['res']} "
              f"--truth-spp {r['truth_spp']} --scenes {r['scene']} --write" for r in found]
    replace_block(DOC, "reference-vs-mitsuba", "\n".join(lines), title="The reference renderer against Mitsuba 3")


def _mi_version() -> str:
    import mitsuba

    return str(mitsuba.__version__)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="cornell_box", help="comma-separated; empty: only --write")
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", default="4,16,64,256,1024")
    ap.add_argument("--errors", default="0.1,0.05,0.03,0.02,0.01")
    ap.add_argument("--cap", type=int, default=4096)
    ap.add_argument("--truth-spp", type=int, default=4096)
    ap.add_argument("--cache", default="/tmp/ibr_reference_vs_mitsuba")
    ap.add_argument("--write", action="store_true")
    a = ap.parse_args(argv)
    # our renders are timed as a render worker runs them: with its malloc policy (engine.memory),
    # which spares the wavefront's buffers some of their page faults (128x128 path, 256 spp:
    # 208,000 -> 178,000 minor faults, system time 0.58-0.74 -> 0.46-0.63 s of ~8 s CPU)
    keep_freed_memory()
    Path(a.cache).mkdir(parents=True, exist_ok=True)
    for name in [s for s in a.scenes.split(",") if s]:
        r = measure(name, a)
        (Path(a.cache) / f"result_{name}_{a.res}_{ENGINE_VERSION}.json").write_text(json.dumps(r))
    if a.write:
        write(a)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
