"""Walkthrough quality contracts against converged frames: how often a planned walkthrough meets its
error target or time budget, and what the plan costs against the cheapest setting that met it.

Run: ``python -m bench.walkthrough_contracts [--scene NAME] [--presets low,medium] [--path-noises
0.02,0.05]`` (default: the calibration's) from the
repository root. Writes ``docs/accuracy/walkthrough_contracts.md`` (block ``walkthrough_contracts``),
``docs/data/walkthrough_contracts.json`` and ``docs/img/walkthrough_contracts.png``.

Per sample scene (``cornell_animated``, ``static_room``):

1. calibrate as the service does (``workers.jobs.calibrate_walkthrough.calibrate_walkthrough``,
   default parameters: 3 probe frames of 64 px looking the way the scene camera looks), with the
   shipped presets named by ``--presets`` baked in-process (the bakes' wall time is their cost) and
   path-traced frames at ``--path-noises``;
2. held-out frames: the accuracy benchmark's camera path (``bench.walkthrough_accuracy``, eyes along
   the view space looking ahead or at the action, so directions the probes never had) at
   ``--width`` x ``--height``, each with a converged frame (``engine.walkthrough.ground_truth``);
3. an exhaustive grid: every setting (preset x fill, and path-traced frames) rendered on every
   held-out frame, its LRMS against the converged frame and its render time (median of three; a
   path-traced frame, which takes tenths of a second or more, timed once, building its time's scene
   as the chunk job does);
4. contracts: error targets and per-frame time budgets over the range the settings span, each
   planned as the service plans (``engine.walkthrough.quality.plan_walkthrough``: every bake
   stored, the service's margins) and checked on every held-out frame from the grid: a frame meets
   its contract when its measured error is at most ``max_error`` and its render time at most
   ``max_ms``; a walkthrough meets it when every frame does. The cost of a plan, per frame: its
   frame time against the fastest setting that met the same target on that frame (an oracle that
   could switch settings from frame to frame); per walkthrough: its frames' time against the
   cheapest single setting that met the target on every frame (the best one setting a request
   could have named). Every contract is planned
   twice: with every bake in the store (``ready``, the cost above), and for a scene with no bake yet
   (``cold``: each preset priced with its bake, as the service prices it; path-traced frames need
   none), which shows where path-traced frames replace a bake.

Times are wall-clock on this machine (2 cores shared with other work): compare within one run.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from api_schemas.walkthrough import DEFAULT_PATH_NOISES, WalkthroughCalibrationParams
from bench.docs_writer import replace_block
from bench.walkthrough_accuracy import load, walkthrough_cameras
from engine import ENGINE_VERSION
from engine.metrics import lrms
from engine.reference import ReferenceRenderer
from engine.walkthrough.bake import WalkthroughBake, WalkthroughRenderer, bake_walkthrough, walkthrough_preset
from engine.walkthrough.ground_truth import converged_frame
from engine.walkthrough.quality import (
    PATH,
    WalkthroughModel,
    fit_path_setting,
    interpolated_path_fit,
    plan_walkthrough,
)
from producer.settings import Settings
from workers.jobs.calibrate_walkthrough import calibrate_walkthrough
from workers.jobs.walkthrough import PathTracedFrames
from workers.scene_loader import camera_params

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "accuracy" / "walkthrough_contracts.md"
DATA = ROOT / "docs" / "data" / "walkthrough_contracts.json"
PLOT = ROOT / "docs" / "img" / "walkthrough_contracts.png"
SCENES = ("cornell_animated", "static_room")
ERROR_TARGETS = (0.02, 0.03, 0.05, 0.08, 0.10, 0.12, 0.15, 0.18, 0.20, 0.25, 0.30, 0.40)
TIME_BUDGETS_MS = (1.0, 2.0, 3.0, 5.0, 8.0, 12.0, 20.0, 50.0, 200.0, 1000.0)
TRUTH_SEED = 31_337


def _scene_camera(name: str) -> Any:
    from api_schemas.scene import load_scene_file

    return camera_params(load_scene_file(ROOT / "samples" / "scenes" / f"{name}.json").camera)


def _grid(bakes: dict[str, WalkthroughBake], an: Any, fills: list[str], noises: list[float], cams: list[Any],
          times: np.ndarray, truths: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, list[dict[str, float]]]:
    out: dict[str, list[dict[str, float]]] = {}
    for preset, bake in bakes.items():
        for fill in fills:
            wr = WalkthroughRenderer(bake, an if fill == "trace" else None)
            wr.render(cams[0], float(times[0]), fill=fill, strict=False)  # warm-up, untimed
            rows = []
            for cam, t, (gt, mask) in zip(cams, times, truths, strict=True):
                ms = []
                for _ in range(3):
                    t0 = time.perf_counter()
                    img = wr.render(cam, float(t), fill=fill, strict=False).radiance
                    ms.append(1000.0 * (time.perf_counter() - t0))
                rows.append({"error": float(lrms(img, gt, mask)), "ms": float(np.median(ms))})
            out[f"{preset}/{fill}"] = rows
    for noise in noises:
        out[f"{PATH}/{noise:g}"] = _path_rows(an, noise, cams, times, truths)
    return out


def _path_rows(an: Any, noise: float, cams: list[Any], times: np.ndarray,
               truths: list[tuple[np.ndarray, np.ndarray]]) -> list[dict[str, float]]:
    """Path-traced frames at ``noise`` on the held-out frames: each one's LRMS and time (one timing,
    building its time's scene as the chunk job does), and what the frame estimated and traced."""
    PathTracedFrames(an, noise).render(cams[0], float(times[0]), 0)  # warm-up, untimed
    shared = PathTracedFrames(an, noise)
    rows = []
    for i, (cam, t, (gt, mask)) in enumerate(zip(cams, times, truths, strict=True)):
        frames = shared if an.is_static else PathTracedFrames(an, noise)  # as the chunk job renders
        t0 = time.perf_counter()
        img, _, st = frames.render(cam, float(t), i)
        rows.append({"error": float(lrms(img, gt, mask)), "ms": 1000.0 * (time.perf_counter() - t0),
                     "estimated_error": float(st.get("estimated_error", math.nan)),
                     "paths": float(st.get("paths_mean", math.nan))})
    return rows


def _contracts(model: WalkthroughModel, grid: dict[str, list[dict[str, float]]], pixels: int, frames: int,
               settings: Settings, ready: set[str] | None = None,
               measure: Callable[[str], list[dict[str, float]]] | None = None) -> list[dict[str, Any]]:
    """Every contract planned with the bakes ``ready`` (default: every calibrated preset's) and
    checked frame by frame: against the grid, or, for a path-traced noise target the planner chose
    between the calibrated ones, against ``measure(setting)`` (its frames rendered on the held-out
    frames). The cheapest setting that met a target is the grid's."""
    ready = set(model.bake_keys) if ready is None else ready
    asks: list[dict[str, float | None]] = [{"max_error": e, "max_ms": None} for e in ERROR_TARGETS]
    asks += [{"max_error": None, "max_ms": t} for t in TIME_BUDGETS_MS]
    asks += [{"max_error": e, "max_ms": t} for e in (0.12, 0.2, 0.3) for t in (3.0, 10.0)]
    out = []
    for ask in asks:
        p = plan_walkthrough(model, pixels, frames, max_error=ask["max_error"], max_ms=ask["max_ms"],
                             bakes_ready=ready, flat_margin=settings.contract_error_margin,
                             time_margin=settings.contract_time_margin)
        row: dict[str, Any] = {**ask, "planned": p.choice.name if p.choice else None, "rule": p.rule,
                               "predicted_error": p.choice.error if p.choice else None,
                               "predicted_ms": p.choice.frame_ms if p.choice else None,
                               "predicted_total_ms": p.choice.total_ms if p.choice else None, "frames": []}
        got_rows = None
        if p.choice is not None:
            if p.choice.name in grid:
                got_rows = grid[p.choice.name]
            elif measure is None:
                raise SystemExit(f"{p.choice.name} was planned and is not in the grid: rerun without --replan")
            else:
                got_rows = measure(p.choice.name)
        for i in range(frames):
            def meets(r: dict[str, float], ask: dict[str, float | None] = ask) -> bool:
                return ((ask["max_error"] is None or r["error"] <= ask["max_error"])
                        and (ask["max_ms"] is None or r["ms"] <= ask["max_ms"]))

            meeting = [(grid[k][i]["ms"], k) for k in grid if meets(grid[k][i])]
            cheapest = min(meeting) if meeting else None
            f: dict[str, Any] = {"feasible": cheapest is not None,
                                 "cheapest": cheapest[1] if cheapest else None}
            if got_rows is not None:
                got = got_rows[i]
                f.update(error=got["error"], ms=got["ms"], met=meets(got),
                         cost_ratio=got["ms"] / cheapest[0] if cheapest and ask["max_error"] is not None else None)
            row["frames"].append(f)
        out.append(row)
    return out


def cached_bake(name: str, preset: str, an: Any, space: Any, cache: str | Path | None,
                progress: Any = None) -> tuple[WalkthroughBake, float, bool]:
    """The shipped ``preset``'s bake of scene ``name``: from ``cache`` (``NAME_PRESET_ENGINE.npz``, with
    the wall time it took when it was made beside it) when it is there, else baked now (and kept there
    when ``cache`` is given). Returns (bake, its wall time in seconds, whether it came from the cache)."""
    path = None if cache is None else Path(cache) / f"{name}_{preset}_{ENGINE_VERSION}.npz"
    if path is not None and path.exists():
        return WalkthroughBake.load(path), float(json.loads(path.with_suffix(".json").read_text())["seconds"]), True
    t0 = time.perf_counter()
    bake = bake_walkthrough(an, space, walkthrough_preset(preset), progress=progress)
    seconds = time.perf_counter() - t0
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        bake.save(path)
        path.with_suffix(".json").write_text(json.dumps({"seconds": seconds}))
    return bake, seconds, False


def run_scene(name: str, presets: list[str], fills: list[str], noises: list[float],
              args: argparse.Namespace) -> dict[str, Any]:
    an, space = load(name)
    cam = _scene_camera(name)
    bakes: dict[str, WalkthroughBake] = {}
    bake_s: dict[str, float] = {}

    def bake_for(preset: str, progress: Any) -> tuple[WalkthroughBake, str, float]:
        bakes[preset], bake_s[preset], reused = cached_bake(name, preset, an, space, args.bake_cache, progress)
        print(f"[{name}] bake {preset}: {bake_s[preset]:.1f} s{' (from the bake cache)' if reused else ''}", flush=True)
        return bakes[preset], preset, bake_s[preset]

    params = WalkthroughCalibrationParams(presets=presets, fills=fills, path_noises=noises)  # type: ignore[arg-type]
    t0 = time.perf_counter()
    model = calibrate_walkthrough(an, space, cam, bake_for, params=params)
    calib_s = time.perf_counter() - t0
    print(f"[{name}] calibration {calib_s:.1f} s: "
          + ", ".join(f"{k} {f.error:.3f} (margin {f.margin:.2f})" for k, f in model.fits.items()), flush=True)
    cams, times = walkthrough_cameras(name, args.frames, args.width, args.height)
    truths, truth_s = [], []
    for i, (c, t) in enumerate(zip(cams, times, strict=True)):
        img, _, mask, st = converged_frame(ReferenceRenderer(an.scene_at(float(t))), c, i, TRUTH_SEED, args.truth_noise,
                                        walkthrough_preset(presets[0]).indirect_bounces)
        truths.append((img, mask))
        truth_s.append(st["seconds"])
    print(f"[{name}] {len(cams)} converged frames, {np.mean(truth_s):.1f} s each", flush=True)
    grid = _grid(bakes, an, fills, noises, cams, times, truths)
    between: dict[str, list[dict[str, float]]] = {}  # path-traced targets planned between the calibrated ones

    def measure(setting: str) -> list[dict[str, float]]:
        if setting not in between:
            between[setting] = _path_rows(an, float(setting.split("/", 1)[1]), cams, times, truths)
        return between[setting]

    contracts = _contracts(model, grid, args.width * args.height, len(cams), Settings(), measure=measure)
    cold = _contracts(model, grid, args.width * args.height, len(cams), Settings(), ready=set(), measure=measure)
    return {"model": model.to_json(), "calibration_s": calib_s, "bake_s": bake_s,
            "truth_s_per_frame": float(np.mean(truth_s)), "grid": grid, "between": between, "contracts": contracts,
            "cold": cold, "frames": len(cams), "width": args.width, "height": args.height}


def _refit_paths(model: WalkthroughModel) -> WalkthroughModel:
    """``model`` with its path-traced settings fitted again from their probe measurements by the
    current :func:`fit_path_setting` (a change of that rule, replanned without rendering)."""
    fits = dict(model.fits)
    for name, fit in model.fits.items():
        if name.startswith(f"{PATH}/"):
            fits[name] = fit_path_setting(float(name.split("/", 1)[1]), fit.points, model.probe["truth_noise"])
    return replace(model, fits=fits)


def _summary(res: dict[str, Any], which: str = "contracts") -> dict[str, Any]:
    """The contracts ``which`` (``contracts``: every bake stored; ``cold``: none) of one scene: how many
    were planned, met frame by frame and in full, and their cost."""
    frames = [f for c in res[which] if c["planned"] for f in c["frames"]]
    walks = [c for c in res[which] if c["planned"]]
    ratios = [f["cost_ratio"] for f in frames if f.get("cost_ratio") is not None and f["met"]]
    whole = [r for c in walks if (r := _walkthrough_cost_ratio(c, res["grid"])) is not None]
    path_grid = {k: v for k, v in res["grid"].items() if k.startswith(f"{PATH}/")}
    by_path = [r for c in walks if c["planned"].startswith(f"{PATH}/")
               and (r := _walkthrough_cost_ratio(c, path_grid)) is not None]
    return {"requests": len(res[which]), "planned": len(walks), "refused": len(res[which]) - len(walks),
            "path_traced": sum(1 for c in walks if c["planned"].startswith(f"{PATH}/")),
            "refused_feasible": sum(1 for c in res[which] if not c["planned"]
                                    and any(f["feasible"] for f in c["frames"])),
            "frames_met": sum(f["met"] for f in frames) / max(1, len(frames)),
            "walkthroughs_met": sum(all(f["met"] for f in c["frames"]) for c in walks) / max(1, len(walks)),
            "cost_median": float(np.median(ratios)) if ratios else math.nan,
            "cost_p90": float(np.percentile(ratios, 90)) if ratios else math.nan,
            "walk_cost_median": float(np.median(whole)) if whole else math.nan,
            "walk_cost_p90": float(np.percentile(whole, 90)) if whole else math.nan,
            "path_cost_median": float(np.median(by_path)) if by_path else math.nan,
            "path_cost_max": float(np.max(by_path)) if by_path else math.nan}


def _walkthrough_cost_ratio(c: dict[str, Any], grid: dict[str, list[dict[str, float]]]) -> float | None:
    """An error contract met on every frame: its setting's time over all frames over that of the
    cheapest single setting that met it on every frame (what a planner choosing one setting per
    walkthrough, as a request does, could at best have picked); None for a time budget alone or a
    missed walkthrough, or when no setting of ``grid`` met it on every frame."""
    if c["max_error"] is None or not all(f.get("met") for f in c["frames"]):
        return None

    def meets_all(rows: list[dict[str, float]]) -> bool:
        return all(r["error"] <= c["max_error"] and (c["max_ms"] is None or r["ms"] <= c["max_ms"]) for r in rows)

    costs = [sum(r["ms"] for r in rows) for rows in grid.values() if meets_all(rows)]
    return sum(f["ms"] for f in c["frames"]) / min(costs) if costs else None


def _doc(data: dict[str, Any]) -> str:
    replanned = (" Contracts planned again from these measurements with the current rules "
                 "(`--replan`).") if data.get("replanned") else ""
    noises = data.get("path_noises") or []
    lines = [f"Run: `python -m bench.walkthrough_contracts --presets {','.join(data['presets'])} --path-noises "
             f"{','.join(f'{n:g}' for n in noises) or 'none'}` ({data['machine']}; {data['seconds'] / 60:.0f} min)."
             f"{replanned} Presets {', '.join(data['presets'])} (shipped sizes), fills {', '.join(data['fills'])}, "
             f"path-traced frames at noise {', '.join(f'{n:g}' for n in noises) or '(none)'}; held-out frames "
             f"{data['width']} x {data['height']}, converged to a relative standard error of {data['truth_noise']}. "
             "Every bake stored, and, in the last columns, none stored (each preset priced with its bake). Cost "
             "per frame: the planned setting's frame time over the fastest setting that met the target on that "
             "frame; per walkthrough: its frames' time over that of the cheapest single setting that met the "
             "target on every frame; path-traced plans against path-traced frames alone: the same over the "
             "cheapest calibrated noise target that met it (how well the planner picks a noise target, "
             "apart from whether path tracing was the right choice). Bakes: the wall time of each preset's "
             "bake when it was made.", ""]
    lines += ["| scene | calibration without the bakes (s) | bakes (s) | requests | planned (path-traced) "
              "| refused (a setting met it) | frames met | walkthroughs met | cost per frame median / p90 "
              "| cost per walkthrough median / p90 | path-traced plans against path-traced frames median / max "
              "| no bake stored: planned (path-traced) | no bake stored: walkthroughs met |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, res in data["scenes"].items():
        s = _summary(res)
        cold = _summary(res, "cold") if "cold" in res else None
        cold_cells = (f"{cold['planned']} ({cold['path_traced']}) | {100 * cold['walkthroughs_met']:.0f} %"
                      if cold else "- | -")
        parts = res["model"]["probe"]["cost_breakdown_s"]
        rest = sum(v for k, v in parts.items() if k != "bakes")  # the bakes may come from --bake-cache
        lines.append(f"| {name} | {rest:.0f} | {sum(res['bake_s'].values()):.0f} | {s['requests']} "
                     f"| {s['planned']} ({s['path_traced']}) | {s['refused']} ({s['refused_feasible']}) "
                     f"| {100 * s['frames_met']:.1f} % | {100 * s['walkthroughs_met']:.0f} % "
                     f"| {s['cost_median']:.2f}x / {s['cost_p90']:.2f}x "
                     f"| {s['walk_cost_median']:.2f}x / {s['walk_cost_p90']:.2f}x "
                     f"| {s['path_cost_median']:.2f}x / {s['path_cost_max']:.2f}x | {cold_cells} |")
    for name, res in data["scenes"].items():
        lines += ["", f"### {name}", "", "| setting | predicted LRMS (margin) | held-out LRMS mean / max "
                  "| predicted ms / frame | held-out ms / frame (median) |", "|---|---|---|---|---|"]
        model = WalkthroughModel.from_json(res["model"])
        between = res.get("between") or {}
        for k, rows in sorted({**res["grid"], **between}.items(), key=lambda kv: _setting_order(kv[0])):
            f = model.fits[k] if k in model.fits else interpolated_path_fit(model, float(k.split("/", 1)[1]))
            pred_ms = f.b_ms + f.c_ms * res["width"] * res["height"]
            errs = [r["error"] for r in rows]
            name = k if k in res["grid"] else f"{k} (between the calibrated)"
            lines.append(f"| {name} | {f.error:.3f} ({f.margin:.2f}) | {np.mean(errs):.3f} / {max(errs):.3f} "
                         f"| {pred_ms:.1f} | {np.median([r['ms'] for r in rows]):.1f} |")
        lines += ["", "| max_error | max_ms | planned | frames met | reason it missed | planned, no bake stored |",
                  "|---|---|---|---|---|---|"]
        colds = res.get("cold") or [{"planned": "-"}] * len(res["contracts"])
        for c, cold_c in zip(res["contracts"], colds, strict=True):
            met = sum(f.get("met", False) for f in c["frames"])
            miss = sorted({("error" if c["max_error"] is not None and f["error"] > c["max_error"] else "time")
                           for f in c["frames"] if c["planned"] and not f["met"]})
            lines.append(f"| {c['max_error'] if c['max_error'] is not None else '-'} | "
                         f"{c['max_ms'] if c['max_ms'] is not None else '-'} | {c['planned'] or 'refused'} | "
                         f"{met}/{len(c['frames']) if c['planned'] else 0} | {', '.join(miss)} "
                         f"| {cold_c['planned'] or 'refused'} |")
    lines += ["", "![predicted against held-out error](../img/walkthrough_contracts.png)"]
    return "\n".join(lines)


def _setting_order(name: str) -> tuple[int, float, str]:
    """Bake presets first (as named), then path-traced targets from the finest."""
    preset, fill = name.split("/", 1)
    return (1, float(fill), "") if preset == PATH else (0, 0.0, name)


def _plot(data: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    for name, res in data["scenes"].items():
        for k, rows in res["grid"].items():
            pred = res["model"]["fits"][k]["error"]
            ax.scatter([pred] * len(rows), [r["error"] for r in rows], s=12, label=f"{name} {k}")
    lim = ax.get_xlim()[1]
    ax.plot([0, lim], [0, lim], color="grey", lw=1, ls=":")
    ax.set_xlabel("predicted LRMS (calibration's worst probe)")
    ax.set_ylabel("held-out frame LRMS")
    ax.legend(fontsize=6)
    fig.tight_layout()
    PLOT.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(PLOT, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", choices=SCENES)
    ap.add_argument("--presets", default="low,medium")
    ap.add_argument("--fills", default="both,trace")
    ap.add_argument("--path-noises", default=",".join(f"{n:g}" for n in DEFAULT_PATH_NOISES),
                    help="noise targets of the path-traced frames "
                                                                  "('none': no path-traced setting)")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--height", type=int, default=72)
    ap.add_argument("--truth-noise", type=float, default=0.01)
    ap.add_argument("--bake-cache", help="keep the bakes (and their measured bake time) in this directory between "
                                         "runs: a rerun then measures the calibration's rendering, not the bakes")
    ap.add_argument("--replan", action="store_true",
                    help="plan the contracts again from the saved models and grids (docs/data), rendering nothing: "
                         "for a change of the planner's rules")
    ap.add_argument("--no-doc", action="store_true")
    args = ap.parse_args()
    if args.replan:
        data = json.loads(DATA.read_text())
        for res in data["scenes"].values():
            model = _refit_paths(WalkthroughModel.from_json(res["model"]))
            res["model"] = model.to_json()
            res["contracts"] = _contracts(model, res["grid"], res["width"] * res["height"], res["frames"], Settings())
            res["cold"] = _contracts(model, res["grid"], res["width"] * res["height"], res["frames"], Settings(),
                                     ready=set())
        data["replanned"] = True
        DATA.write_text(json.dumps(data, indent=1))
        replace_block(DOC, "walkthrough_contracts", _doc(data), title="Walkthrough quality contracts")
        return
    presets, fills = args.presets.split(","), args.fills.split(",")
    noises = [] if args.path_noises == "none" else [float(x) for x in args.path_noises.split(",")]
    data: dict[str, Any] = {"presets": presets, "fills": fills, "path_noises": noises, "width": args.width,
                            "height": args.height,
                            "truth_noise": args.truth_noise, "machine": f"{platform.machine()}, "
                            f"{platform.python_version()}", "scenes": {}}
    if args.scene and DATA.exists():
        old = json.loads(DATA.read_text())
        if old.get("presets") == presets and old.get("fills") == fills and old.get("path_noises") == noises:
            data["scenes"] = old.get("scenes", {})
    t0 = time.perf_counter()
    for name in (args.scene,) if args.scene else SCENES:
        data["scenes"][name] = run_scene(name, presets, fills, noises, args)
        print(json.dumps({name: _summary(data["scenes"][name])}), flush=True)
    data["seconds"] = time.perf_counter() - t0
    if args.no_doc:
        return
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(data, indent=1))
    _plot(data)
    replace_block(DOC, "walkthrough_contracts", _doc(data), title="Walkthrough quality contracts")


if __name__ == "__main__":
    main()
