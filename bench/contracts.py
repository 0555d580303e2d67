"""Quality contracts, measured: does the planner's choice meet its target on views it was not
calibrated on, and what does it cost against the cheapest setting that would have met it?

Per sample scene (in process, the engine directly; the service adds queueing and encoding, not
error): bake the LDC (indirect light when the scene has any; a light field when its materials need
one), calibrate it with the service's defaults (``workers.jobs.calibrate.calibrate_scene``: four
probe views of 64 px, ground truth at 256 spp), then on held-out views (turned by angles the probes
do not use, at another size) render a converged ground truth (two halves of different seeds: their
spread is its noise, removed in quadrature from every measured error) and an exhaustive grid of
settings: the reference at every spp the planner offers up to 256 (1, 2, 3, 4, 6, ...) and every
LDC method of the bake, each timed alike (the median of three renders when one takes under a second).
Requests: error targets from 1 % to 20 % and time budgets from 20 ms to 5 s (log-spaced), and
pairs of both, on each held-out view. Each is planned (``engine.quality.plan``) and checked against
the grid's measurements (a reference above 256 spp is rendered and measured when planned):

- **met**: the chosen setting's measured error is at most the target and its measured time at most
  the budget (a request that no setting of the grid meets either, and that the planner refuses, is
  counted as answered correctly: "refused, nothing meets it");
- **cost ratio**: the chosen setting's measured time over the cheapest grid setting's that met the
  same target on that view.

Plans use the service's safety margins: each fit's calibrated error margin
(``engine.quality.calibrated_margin``; ``--flat-margin`` plans every setting with the flat
``producer.settings.Settings.contract_error_margin`` instead, ``--error-margin`` to change it) and
the time margin ``contract_time_margin`` (``--time-margin``); they include the adaptive reference
for error targets (rendered and measured when chosen; its estimated error, times the calibrated
scale at its aim, is reported against the measured one).

Served renders refine the model as in the service: the requests of a scene are planned in order
(view by view; on a view: the error targets, the time budgets, the pairs) from the calibration with
the corrections folded so far (``engine.quality.apply_corrections`` of
``producer.calibrations.read_served``, in a store of the run's own), and each request that renders a
setting not yet rendered for its view folds that render's measured time into them
(``producer.calibrations.record_served``, as the render job does; a repeated request is the
service's cached artifact and renders nothing, an adaptive render stopped by its time budget is not
folded). No request verifies, so no error is folded. ``--no-served`` plans from the calibration
alone.

``python -m bench.contracts`` (writes docs/accuracy/contracts.md and docs/img/contracts.png;
``--json PATH`` also keeps every request, each view's grid and the calibrated models);
``--quick`` for a smoke run; ``--replay-unserved PATH`` plans a kept run's requests again without
the served renders' corrections, from that run's measurements (:func:`replay_unserved`).
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from api_schemas import load_scene_file
from api_schemas.service import CalibrationParams
from bench.docs_writer import replace_block
from engine.memory import keep_freed_memory
from engine.metrics import lrms
from engine.newviews.effects import analyze
from engine.newviews.indirect import IndirectParams
from engine.newviews.ldc import bake_ldc
from engine.newviews.llf import bake_llf
from engine.newviews.renderer import LDCViewRenderer
from engine.quality import (
    REFERENCE_SPP_LADDER,
    SceneModel,
    Setting,
    adaptive_scale,
    apply_corrections,
    correction_factor,
    correction_key,
    plan,
)
from engine.raycast import EmbreeCaster
from engine.reference import ReferenceParams, ReferenceRenderer
from producer.calibrations import read_served, record_served
from producer.settings import Settings
from producer.store.local import LocalStore
from samples import SAMPLES_DIR, sample_path
from workers.jobs.calibrate import calibrate_scene, turned_camera, view_pivot
from workers.scene_loader import directory_resolver, load_scene

DOC = Path(__file__).resolve().parents[1] / "docs" / "accuracy" / "contracts.md"
PLOT = Path(__file__).resolve().parents[1] / "docs" / "img" / "contracts.png"
HELD_OUT_DEG = (4.0, -4.0, 12.0, -12.0, 20.0, -20.0)
"""Held-out views: angles the probes (+-8, +-16) never use."""
GRID_SPP = tuple(s for s in REFERENCE_SPP_LADDER if s <= 256)
"""The grid's reference settings: every spp the planner offers up to 256."""
ERRORS = tuple(float(x) for x in np.geomspace(0.01, 0.2, 10))
BUDGETS_MS = tuple(float(x) for x in np.geomspace(20.0, 5000.0, 8))


def _setup(name: str, ldc_res: int, log: Any) -> tuple[Any, Any, LDCViewRenderer, ReferenceRenderer, float]:
    path = sample_path(name)
    loaded = load_scene(load_scene_file(path), directory_resolver(SAMPLES_DIR))
    sc = loaded.runtime
    caster = EmbreeCaster(sc)
    effects = analyze(sc)
    t0 = time.perf_counter()
    gi = IndirectParams(noise=0.05, bounces=3) if effects.indirect_skip == "" else None
    ldc = bake_ldc(sc, caster, ldc_res, plan=effects, indirect=gi)
    llf = bake_llf(sc, caster, 4, 32, params=ReferenceParams(spp=1, max_depth=4, glossy_samples=8,
                                                             area_light_samples=4)) if effects.needs_llf else None
    bake_s = time.perf_counter() - t0
    log(f"{name}: bake LDC {ldc_res}{' + indirect' if gi else ''}{' + LLF' if llf is not None else ''} {bake_s:.1f} s")
    return sc, loaded.camera, LDCViewRenderer(sc, ldc, llf, effects), ReferenceRenderer(sc, caster), bake_s


REPEAT_BELOW_MS = 1000.0
"""A grid setting whose first render takes less than this is rendered :data:`REPEATS` times and timed
by the median: at 64 px a reference render at a few spp or an LDC view takes 5-20 ms, where one
timing is noise. Every setting is timed the same way, since the cost ratio divides two of them."""
REPEATS = 3


def _typical_ms(fn: Any, *args: Any) -> tuple[Any, float]:
    """``fn(*args)`` and its typical time: the median of :data:`REPEATS` runs when the first is under
    :data:`REPEAT_BELOW_MS`, else the one run's (the output is the first run's)."""
    t0 = time.perf_counter()
    out = fn(*args)
    times = [1000.0 * (time.perf_counter() - t0)]
    while times[0] < REPEAT_BELOW_MS and len(times) < REPEATS:
        t0 = time.perf_counter()
        fn(*args)
        times.append(1000.0 * (time.perf_counter() - t0))
    return out, float(np.median(times))


MARGINS = (float(Settings.model_fields["contract_error_margin"].default),
           float(Settings.model_fields["contract_time_margin"].default))
"""The service's default safety margins (error, time)."""


def run_scene(name: str, ldc_res: int, views: int, size: int, truth_spp: int, cal: CalibrationParams,
              log: Any, margins: tuple[float, float] = MARGINS, calibrated: bool = True,
              fold_served: bool = True) -> dict[str, Any]:
    sc, cam0, ren, ref, bake_s = _setup(name, ldc_res, log)
    model: SceneModel = calibrate_scene(sc, cam0, ren, params=cal, bake_plan={}, indirect_bounces=3, reference=ref,
                                        bake_cost_s=bake_s)
    log(f"{name}: calibration {model.cost_s:.1f} s, reference a={model.reference.error:.3f} "
        f"p={model.reference.exponent:.2f}, methods {[(m, round(f.error, 4)) for m, f in model.methods.items()]}, "
        f"excluded {list(model.excluded)}")
    pivot = view_pivot(cam0, *sc.bounds)
    gi = bool(model.reference_params.get("indirect_per_spp"))

    def rp(spp: int, seed: int = 0) -> ReferenceParams:
        p = model.reference_request_params(spp)
        return ReferenceParams(spp=p["spp"], max_depth=p["max_depth"], glossy_samples=p["glossy_samples"],
                               area_light_samples=p["area_light_samples"],
                               indirect_samples=p.get("indirect_samples", 0),
                               indirect_bounces=p["indirect_bounces"], seed=seed)

    requests: list[dict[str, Any]] = []
    grids: dict[str, dict[str, dict[str, float]]] = {}
    with tempfile.TemporaryDirectory(prefix="bench-contracts-") as root:
        served = _Served(model, root, fold_served)
        for deg in HELD_OUT_DEG[:views]:
            rows, grid = _view(name, served, ref, ren, turned_camera(cam0, deg, size, pivot), deg, truth_spp, rp,
                               log, margins, calibrated)
            requests += rows
            grids[f"{deg:+g}"] = {k: {"error": e, "ms": ms} for k, (e, ms) in grid.items()}
        corrections = served.corrections()
        log(f"{name}: {served.folded} served renders folded; corrections {corrections}")
    return {"scene": name, "ldc_resolution": ldc_res, "bake_s": bake_s, "calibration_s": model.cost_s,
            "calibration_breakdown_s": model.probe.get("cost_breakdown_s"),
            "model_reference_a": model.reference.error, "model_reference_p": model.reference.exponent,
            "model_methods": {m: f.error for m, f in model.methods.items()}, "excluded": model.excluded,
            "adaptive": None if model.adaptive is None else {"error_scale": model.adaptive.error_scale,
                                                             "time_ratio": model.adaptive.time_ratio,
                                                             "levels": model.adaptive.levels,
                                                             "margin": model.adaptive.margin},
            "margins": {"reference": model.reference.margin,
                        **{m: f.margin for m, f in model.methods.items() if m not in model.excluded}},
            "requests": requests, "indirect": gi, "served_folded": served.folded,
            "corrections": {kind: {k: correction_factor(corrections, kind, k) for k in table}
                            for kind, table in corrections.items()},
            "reference_tail_exponent": model.reference.tail_exponent,
            "model": model.to_json(), "grids": grids}


class _Served:
    """The corrections served renders fold into a scene's calibration, kept as the service keeps them
    (``producer.calibrations``, in a temporary store of this run): :meth:`model` is what the API plans
    from, :meth:`fold` what the render job records after a render."""

    KEY = "bench-calibration"

    def __init__(self, model: SceneModel, root: str, enabled: bool = True):
        self.base, self.store, self.enabled = model, LocalStore(root), enabled
        self.folded = 0

    def corrections(self) -> dict[str, Any]:
        if not self.enabled:
            return {}
        return read_served(self.store, self.base.scene_id, self.base.bake_key, self.KEY)

    def model(self) -> SceneModel:
        return apply_corrections(self.base, self.corrections())

    def fold(self, planned_from: dict[str, Any], model: SceneModel, s: Setting, predicted_ms: float,
             achieved_ms: float) -> None:
        """Fold one render of ``s`` (planned from the corrections ``planned_from`` with the corrected
        ``model``, predicted ``predicted_ms``) that took ``achieved_ms``."""
        if not self.enabled:
            return
        params = model.setting_params(s)
        key = correction_key(s.method, params, s.view)
        contract = {"method": s.method, "params": params, "view": s.view, "predicted_ms": predicted_ms,
                    "calibration": {"key": self.KEY, "bake_key": self.base.bake_key,
                                    "corrections": {k: correction_factor(planned_from, k, key)
                                                    for k in ("time", "error")}}}
        if record_served(self.store, self.base.scene_id, contract, achieved_ms=achieved_ms) is not None:
            self.folded += 1


class _Grid:
    """One held-out view's measurements: error (ground truth noise removed) and time per setting."""

    def __init__(self, ref: ReferenceRenderer, cam: Any, truth: Any, mask: Any, noise: float, rp: Any):
        self.ref, self.cam, self.truth, self.mask, self.noise, self.rp = ref, cam, truth, mask, noise, rp
        self.m: dict[str, tuple[float, float]] = {}
        self.estimated: dict[str, float] = {}
        self.stopped_by_time: set[str] = set()

    def measure(self, key: str, img: Any, ms: float) -> None:
        e = lrms(img, self.truth, self.mask)
        self.m[key] = (math.sqrt(max(e * e - self.noise * self.noise, 0.0)), ms)

    def reference(self, spp: int) -> tuple[float, float]:
        key = f"reference@{spp}spp"
        if key not in self.m:
            out, ms = _typical_ms(self.ref.render, self.cam, self.rp(spp))
            self.measure(key, out.radiance, ms)
        return self.m[key]

    def adaptive(self, model: SceneModel, s: Setting, aim: float) -> tuple[float, float]:
        """The adaptive reference of setting ``s`` (aiming at the contract error ``aim``), measured;
        ``estimated[name]``: its own estimate times the calibrated scale at that aim;
        ``stopped_by_time``: the names of those its time budget stopped."""
        if s.name not in self.m:
            p = model.setting_params(s)
            assert p is not None and model.adaptive is not None
            t0 = time.perf_counter()
            out = self.ref.render(self.cam, ReferenceParams(**p))
            self.measure(s.name, out.radiance, 1000.0 * (time.perf_counter() - t0))
            rep = out.adaptive or {}
            self.estimated[s.name] = adaptive_scale(model, aim) * float(rep["estimated_error"])
            if rep.get("stop_reason") == "time":
                self.stopped_by_time.add(s.name)
        return self.m[s.name]


def _view(name: str, served: _Served, ref: ReferenceRenderer, ren: LDCViewRenderer, cam: Any, deg: float,
          truth_spp: int, rp: Any, log: Any, margins: tuple[float, float] = MARGINS,
          calibrated: bool = True) -> tuple[list[dict[str, Any]], dict[str, tuple[float, float]]]:
    """The requests on one held-out view (planned and measured), and the view's grid: error and time
    of every setting measured on it."""
    px = cam.width * cam.height
    t0 = time.perf_counter()
    h1 = ref.render(cam, rp(truth_spp // 2, 1001)).radiance
    h2 = ref.render(cam, rp(truth_spp // 2, 2002)).radiance
    aov = ref.render(cam, ReferenceParams(spp=1, max_depth=0))
    mask = ref.error_region(cam, aov.object_id, aov.depth, rp(1).max_depth)
    noise = lrms(h1, h2, mask) / 2.0  # the mean of two halves: half their difference's spread
    log(f"{name} view {deg:+.0f} deg {cam.width}x{cam.height}: truth {time.perf_counter() - t0:.1f} s, "
        f"its noise {noise:.4f}")
    grid = _Grid(ref, cam, 0.5 * (h1 + h2), mask, noise, rp)
    for spp in GRID_SPP:
        grid.reference(spp)
    for setting, fit in served.base.methods.items():
        out, ms = _typical_ms(lambda c, f=fit: ren.render(c, f.method, supersample=f.supersample, antialias="edges"),
                              cam)
        grid.measure(setting, out.radiance, ms)
    names = _grid_names(served.base)
    rendered: set[str] = set()  # the settings this view has served (an identical request is a cache hit)
    rows: list[dict[str, Any]] = []
    targets: list[tuple[float | None, float | None]] = [(e, None) for e in ERRORS] + \
        [(None, t) for t in BUDGETS_MS] + [(e, t) for e in ERRORS[::3] for t in BUDGETS_MS[2::2]]
    for max_error, max_ms in targets:
        corrections = served.corrections()
        model = apply_corrections(served.base, corrections)
        p = plan(model, px, max_error=max_error, max_ms=max_ms, error_margin=margins[0], time_margin=margins[1],
                 calibrated_margins=calibrated)
        ok_grid = [ms for k, (e, ms) in grid.m.items() if k in names
                   and (max_error is None or e <= max_error) and (max_ms is None or ms <= max_ms)]
        cheapest = min(ok_grid) if ok_grid else None
        row: dict[str, Any] = {"scene": name, "view": deg, "max_error": max_error, "max_ms": max_ms,
                               "planned": p.met, "grid_can": cheapest is not None}
        if p.choice is not None:
            s = p.choice.setting
            if s.adaptive:
                err, ms = grid.adaptive(model, s, p.choice.error)
                row["estimated_error"] = grid.estimated[s.name]
            else:
                err, ms = grid.reference(s.spp) if s.spp is not None else grid.m[s.name]
            met = (max_error is None or err <= max_error) and (max_ms is None or ms <= max_ms)
            row |= {"choice": "reference@adaptive" if s.adaptive else s.name, "adaptive": s.adaptive,
                    "margin": p.choice.margin,
                    "predicted_error": p.choice.error, "predicted_ms": p.choice.ms, "error": err,
                    "ms": ms, "met": met,
                    "cost_ratio": ms / cheapest if cheapest and max_error is not None else None,
                    "time_correction": correction_factor(corrections, "time", correction_key(
                        s.method, model.setting_params(s), s.view))}
            if s.name not in rendered and s.name not in grid.stopped_by_time:
                served.fold(corrections, model, s, p.choice.render_ms, ms)
            rendered.add(s.name)
        else:
            row |= {"choice": None, "met": cheapest is None, "reason": p.reason}
        rows.append(row)
    return rows, grid.m


def replay_unserved(results: list[dict[str, Any]], margins: tuple[float, float] = MARGINS) -> dict[str, Any]:
    """The requests of a run (``--json`` output) planned again from the calibration alone (no served
    render folded), each outcome taken from that run's own measurements of the view: its grid, or the
    settings its requests chose (a setting measured neither way is counted as unknown). Separates what
    the served-render corrections did from what the machine's load did between runs."""
    out: dict[str, Any] = {}
    for res in results:
        model = SceneModel.from_json(res["model"])
        px = int(model.probe["width"]) * int(model.probe["height"])  # the held-out views' size here
        measured: dict[tuple[float, str], tuple[float, float]] = {
            (r["view"], r["choice"]): (r["error"], r["ms"]) for r in res["requests"] if r.get("choice")}
        for deg, grid in (res.get("grids") or {}).items():
            measured |= {(float(deg), k): (v["error"], v["ms"]) for k, v in grid.items()}
        met = unknown = changed = 0
        for r in res["requests"]:
            p = plan(model, px, max_error=r["max_error"], max_ms=r["max_ms"], error_margin=margins[0],
                     time_margin=margins[1])
            name = None if p.choice is None else p.choice.setting.name
            if name is None:
                ok = not r["grid_can"]
            elif (r["view"], name) in measured:
                e, ms = measured[(r["view"], name)]
                ok = (r["max_error"] is None or e <= r["max_error"]) and (r["max_ms"] is None or ms <= r["max_ms"])
            else:
                unknown += 1
                continue
            met += ok
            changed += name != r.get("choice")
        out[res["scene"]] = {"requests": len(res["requests"]), "met": met, "unknown": unknown, "changed": changed,
                             "met_served": sum(1 for r in res["requests"] if r["met"])}
    return out


def _grid_names(model: SceneModel) -> set[str]:
    return {f"reference@{s}spp" for s in GRID_SPP} | set(model.methods)


def doc_block(results: list[dict[str, Any]], cmd: str, size: int, truth_spp: int, views: int,
              margins: tuple[float, float] = MARGINS, calibrated: bool = True, plot: str | None = None,
              served: bool = True) -> str:
    reqs = [r for res in results for r in res["requests"]]
    n = len(reqs)
    met = sum(1 for r in reqs if r["met"])
    ratios = sorted(r["cost_ratio"] for r in reqs if r.get("cost_ratio") is not None and r.get("met"))
    refused = [r for r in reqs if r["choice"] is None]
    missed = [r for r in reqs if not r["met"]]
    lines = [f"Machine: {platform.machine()}, Python {sys.version.split()[0]}. Command: `{cmd}`. Held-out views of "
             f"{size} px (longest side) turned by {', '.join(f'{d:+g}' for d in HELD_OUT_DEG[:views])} degrees (the "
             f"probes: +-8, +-16); converged ground truth {truth_spp} spp in two halves (its noise removed in "
             f"quadrature). Safety margins: error x "
             f"{'each fit' + chr(39) + 's calibrated margin (below)' if calibrated else format(margins[0], 'g')}, "
             f"time x {margins[1]:g}. "
             + ("Served renders' measured times folded into the model in request order, as the service folds "
                "them (" + ", ".join(f"{res['scene']}: {res.get('served_folded', 0)} renders, final time factors "
                                     + (", ".join(f"{k} {v:.2f}" for k, v in (res.get('corrections') or {})
                                                  .get('time', {}).items()) or "none")
                                     for res in results) + ")."
                if served else "Planned from the calibration alone (no served render folded)."),
             "",
             f"**{met} of {n} requests ({100.0 * met / max(n, 1):.1f} %) met their contract** (measured error and time "
             f"of the chosen setting on the held-out view; {len(refused)} refused with a reason, of which "
             f"{sum(1 for r in refused if r['met'])} correctly: no grid setting met them either).",
             ""]
    if ratios:
        med = ratios[len(ratios) // 2]
        p90 = ratios[min(len(ratios) - 1, int(0.9 * len(ratios)))]
        lines += [f"Cost of the chosen setting over the cheapest grid setting that met the same error target on the "
                  f"same view ({len(ratios)} error requests that met theirs): median {med:.2f}x, 90th percentile "
                  f"{p90:.2f}x.", ""]
    adaptive = [r for r in reqs if r.get("adaptive")]
    if adaptive:
        a_met = sum(1 for r in adaptive if r["met"])
        est = sorted(r["error"] / r["estimated_error"] for r in adaptive if r.get("estimated_error"))
        lines += [f"The adaptive reference was chosen for {len(adaptive)} requests, {a_met} of them met; its measured "
                  f"error over its estimated one (the render's estimate times the calibrated scale): median "
                  f"{est[len(est) // 2]:.2f}, range {est[0]:.2f}-{est[-1]:.2f}." if est else
                  f"The adaptive reference was chosen for {len(adaptive)} requests, {a_met} of them met.", ""]
    if plot:
        lines += [f"![measured over target error per contract, and the cost ratios]({plot})", ""]
    lines += ["| scene | bake | calibration | reference a, p (past 16 spp) | LDC methods' error | adaptive scale (at "
              "error), time ratio | error margins | excluded |",
              "|---|---|---|---|---|---|---|---|"]
    for res in results:
        br = res["calibration_breakdown_s"] or {}
        cal = (f"{res['calibration_s']:.1f} s (truth {br.get('truth', 0):.1f}, reference {br.get('reference', 0):.1f}, "
               f"LDC {br.get('ldc', 0):.1f}, adaptive {br.get('adaptive', 0):.1f}, warm-up {br.get('warmup', 0):.1f})")
        ad = res.get("adaptive")
        if not ad:
            ad_s = "-"
        elif ad.get("levels"):
            ad_s = "; ".join(f"{lv['scale']:.2f} ({100 * lv['error']:.1f} %), {lv['time_ratio']:.2f}"
                             for lv in ad["levels"])
        else:
            ad_s = f"{ad['error_scale']:.2f}, {ad['time_ratio']:.2f}"
        mg = dict(res.get("margins") or {})
        if ad and ad.get("margin") is not None:
            mg["adaptive"] = ad["margin"]
        by_spp = ((res.get("model") or {}).get("reference") or {}).get("margins_by_spp") or []
        mg_s = ", ".join(f"{k} {v:.2f}" if k != "reference" or not by_spp else
                         "reference " + " / ".join(f"{m:.2f}" for _, m in by_spp) + " at "
                         + " / ".join(f"{int(s)}" for s, _ in by_spp) + " spp"
                         for k, v in mg.items() if v is not None) or "-"
        methods = ", ".join(f"{m} {e:.3f}" for m, e in res["model_methods"].items())
        lines.append(f"| {res['scene']} | LDC {res['ldc_resolution']}, {res['bake_s']:.1f} s | {cal} | "
                     f"{res['model_reference_a']:.3f}, {res['model_reference_p']:.2f} "
                     f"({res.get('reference_tail_exponent', 0.5):.2f}) | {methods} | {ad_s} | {mg_s} | "
                     f"{'; '.join(res['excluded']) or 'none'} |")
    lines += ["", f"Requests that missed ({len(missed)}{', the first 30' if len(missed) > 30 else ''}):", "",
              "| scene | view | max_error | max_ms | chosen | predicted error, ms | measured error, ms |",
              "|---|---|---|---|---|---|---|"]
    for r in missed[:30]:
        pe = f"{r['predicted_error']:.4f}, {r['predicted_ms']:.0f}" if r.get("choice") else "-"
        me = f"{r['error']:.4f}, {r['ms']:.0f}" if r.get("choice") else r.get("reason", "")[:60]
        e = "-" if r["max_error"] is None else f"{r['max_error']:.3f}"
        t = "-" if r["max_ms"] is None else f"{r['max_ms']:.0f}"
        lines.append(f"| {r['scene']} | {r['view']:+g} | {e} | {t} | {r.get('choice')} | {pe} | {me} |")
    return "\n".join(lines)


def write_plot(results: list[dict[str, Any]], path: Path) -> None:
    """Two panels: each error contract's measured error over its target (per kind of setting chosen;
    above 1: missed), and the cumulative distribution of the cost ratios (the goals marked)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    reqs = [r for res in results for r in res["requests"]]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.3))
    kinds = {"ladder": lambda r: str(r["choice"]).startswith("reference@") and not r.get("adaptive"),
             "adaptive reference": lambda r: bool(r.get("adaptive")),
             "LDC method": lambda r: not str(r["choice"]).startswith("reference")}
    for (label, pick), marker in zip(kinds.items(), ("o", "s", "^"), strict=True):
        rows = [r for r in reqs if r.get("choice") and r["max_error"] is not None and pick(r)]
        for scene, colour in zip(sorted({r["scene"] for r in reqs}), ("tab:blue", "tab:orange", "tab:green"),
                                 strict=False):
            xs = [r["max_error"] for r in rows if r["scene"] == scene]
            ys = [r["error"] / r["max_error"] for r in rows if r["scene"] == scene]
            if xs:
                ax1.scatter(xs, ys, marker=marker, s=22, color=colour, alpha=0.7, label=f"{scene}, {label}")
    ax1.axhline(1.0, color="red", lw=1, ls="--", label="target")
    ax1.set_xscale("log")
    ax1.set_xlabel("error target (LRMS)")
    ax1.set_ylabel("measured error / target")
    ax1.set_title("Error contracts on held-out views (above the line: missed)")
    ax1.legend(fontsize=6.5, loc="upper left")
    ratios = sorted(r["cost_ratio"] for r in reqs if r.get("cost_ratio") is not None and r.get("met"))
    if ratios:
        ax2.step(ratios, [(i + 1) / len(ratios) for i in range(len(ratios))], where="post")
        for x, txt in ((1.3, "goal: median 1.3x"), (2.0, "goal: 90th percentile 2x")):
            ax2.axvline(x, color="grey", ls=":", lw=1)
            ax2.text(x, 0.03, txt, rotation=90, fontsize=7, ha="right", va="bottom")
        ax2.axhline(0.5, color="grey", lw=0.5)
        ax2.axhline(0.9, color="grey", lw=0.5)
        ax2.set_xscale("log")
    ax2.set_xlabel("chosen setting's time / cheapest grid setting that met the target")
    ax2.set_ylabel("fraction of met error contracts")
    ax2.set_title(f"Cost ratio ({len(ratios)} met error contracts)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="cornell_box,mirror_box")
    ap.add_argument("--ldc", type=int, default=64)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--truth-spp", type=int, default=1024)
    ap.add_argument("--quick", action="store_true", help="smoke run: one scene, two small views")
    ap.add_argument("--no-doc", action="store_true")
    ap.add_argument("--error-margin", type=float, default=MARGINS[0])
    ap.add_argument("--time-margin", type=float, default=MARGINS[1])
    ap.add_argument("--flat-margin", action="store_true",
                    help="plan every setting with --error-margin instead of its fit's calibrated margin")
    ap.add_argument("--no-served", action="store_true",
                    help="plan from the calibration alone (no served render's time folded into it)")
    ap.add_argument("--json", type=Path, default=None, help="also write every request and model here")
    ap.add_argument("--replay-unserved", type=Path, default=None, metavar="JSON",
                    help="render nothing: plan a run's requests (its --json output) again from the calibration "
                         "alone and count the met ones from that run's measurements")
    a = ap.parse_args(argv)
    keep_freed_memory()  # renders are timed as a render worker runs them (its malloc policy, engine.memory)
    if a.replay_unserved is not None:
        print(json.dumps(replay_unserved(json.loads(a.replay_unserved.read_text()),
                                         (a.error_margin, a.time_margin)), indent=1))
        return 0
    margins = (a.error_margin, a.time_margin)
    cal = CalibrationParams()
    if a.quick:
        a.scenes, a.views, a.size, a.truth_spp, a.ldc = "mirror_box", 2, 32, 64, 24
        cal = CalibrationParams(probes=1, size=32, truth_spp=64, ibrt_ks=[1])

    def log(msg: str) -> None:
        print(msg, flush=True)

    results = [run_scene(s, a.ldc, a.views, a.size, a.truth_spp, cal, log, margins, not a.flat_margin,
                         not a.no_served) for s in a.scenes.split(",")]
    if a.json is not None:
        a.json.write_text(json.dumps(results, indent=1, default=str))
    cmd = "python -m bench.contracts" + (" " + " ".join(argv if argv is not None else sys.argv[1:])).rstrip()
    write_doc = not a.no_doc and not a.quick
    if write_doc:
        write_plot(results, PLOT)
    block = doc_block(results, cmd, a.size, a.truth_spp, a.views, margins, not a.flat_margin,
                      plot=f"../img/{PLOT.name}" if write_doc else None, served=not a.no_served)
    print(block)
    if write_doc:
        replace_block(DOC, "contracts", block, title="Quality contracts: met targets and their cost")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
