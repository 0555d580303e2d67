"""How a reconstructed walkthrough frame's error varies from frame to frame, and whether what the
frame reprojects and fills predicts it: the evidence behind the per-scene (not per-frame) error
model of walkthrough contracts (``docs/accuracy/walkthrough_contracts.md``, *Why a walkthrough's
error is planned per scene*).

Per scene: the shipped presets' bakes (``--bake-cache``: ``bench.walkthrough_contracts.cached_bake``, baked
there when missing), then frames along the accuracy benchmark's camera path
(``bench.walkthrough_accuracy.walkthrough_cameras``) with a converged frame each
(``engine.walkthrough.ground_truth.converged_frame``, another seed than the bases'). Per frame and
setting (preset x fill): the LRMS, the share of the error region's pixels of each provenance
(reprojected, foreground fill, background fill, traced) and the squared error of each, the distance
from the frame's eye to the nearest base eye and the animation time to the nearest indirect time
sample.

Two models are fitted on every third frame (the "probes") and judged on the others:

- **constant**: the largest probe error, as the calibration bounds a setting
  (``engine.walkthrough.quality.fit_setting``);
- **provenance**: each provenance's mean squared relative error over the probes' pixels of that
  provenance, weighted by the frame's own shares: what the frame's hole fills would predict, were
  they the source of the spread.

Printed per setting: the range of errors, the correlation of measured and predicted errors on the
held-out frames, and the spread (standard deviation of the log) of measured over predicted, which
sets the margin a planner needs; the correlation of a frame's error with each provenance share and
with the distances; and the correlation of one frame's errors across the settings.

``python -m bench.walkthrough_frame_spread --scene static_room --bake-cache DIR`` (prints; writes
nothing; ``--json PATH`` keeps the rows).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.walkthrough_accuracy import load, walkthrough_cameras
from bench.walkthrough_contracts import cached_bake
from engine.metrics import REC709_WEIGHTS
from engine.reference import ReferenceRenderer
from engine.walkthrough.bake import WalkthroughRenderer, walkthrough_preset
from engine.walkthrough.ground_truth import converged_frame
from engine.walkthrough.reconstruct import (
    PROV_BACKGROUND_FILL,
    PROV_FOREGROUND,
    PROV_HOLE,
    PROV_REPROJECTED,
    PROV_SKY,
    PROV_TRACED,
)

PROVENANCE = {PROV_HOLE: "hole", PROV_REPROJECTED: "reprojected", PROV_FOREGROUND: "foreground fill",
              PROV_BACKGROUND_FILL: "background fill", PROV_TRACED: "traced", PROV_SKY: "sky"}
TRUTH_SEED = 31_337
FILLS = ("both", "trace")


def measure(name: str, presets: list[str], frames: int, width: int, height: int, noise: float,
            cache: Path | None) -> list[dict[str, Any]]:
    """One row per frame: its time, and per setting its error, provenance shares and squared errors
    (relative to the converged frame's mean luminance squared), and the distances to the bases."""
    an, space = load(name)
    cams, times = walkthrough_cameras(name, frames, width, height)
    bakes = {p: cached_bake(name, p, an, space, cache)[0] for p in presets}
    lum = np.asarray(REC709_WEIGHTS, np.float64)
    rows = []
    t0 = time.perf_counter()
    for i, (cam, t) in enumerate(zip(cams, times, strict=True)):
        truth, _, mask, _ = converged_frame(ReferenceRenderer(an.scene_at(float(t))), cam, i, TRUTH_SEED, noise,
                                            walkthrough_preset(presets[0]).indirect_bounces)
        y_ref = truth.astype(np.float64) @ lum
        mean = float(y_ref[mask].mean())
        row: dict[str, Any] = {"frame": i, "time": float(t), "settings": {}}
        for preset, bake in bakes.items():
            eye_distance = float(np.min(np.linalg.norm(bake.views - np.asarray(cam.eye, np.float64), axis=1)))
            time_distance = float(np.min(np.abs(bake.indirect_times - t)))
            for fill in FILLS:
                out = WalkthroughRenderer(bake, an if fill == "trace" else None).render(cam, float(t), fill=fill,
                                                                                           strict=False)
                sq = np.square(out.radiance.astype(np.float64) @ lum - y_ref) / mean ** 2
                n = int(mask.sum())
                prov = {PROVENANCE[int(k)]: {"share": float((mask & (out.provenance == k)).sum()) / n,
                                             "sq": float(sq[mask & (out.provenance == k)].sum()) / n}
                        for k in np.unique(out.provenance[mask])}
                row["settings"][f"{preset}/{fill}"] = {"error": float(np.sqrt(sq[mask].mean())), "provenance": prov,
                                                       "eye_distance": eye_distance, "time_distance": time_distance}
        rows.append(row)
        print(f"[{name}] frame {i}: {time.perf_counter() - t0:.0f} s, "
              + ", ".join(f"{k} {v['error']:.3f}" for k, v in row["settings"].items()), flush=True)
    return rows


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else float("nan")


def analyse(name: str, rows: list[dict[str, Any]]) -> None:
    probes = [i for i in range(len(rows)) if i % 3 == 1]
    held = [i for i in range(len(rows)) if i % 3 != 1]
    settings = list(rows[0]["settings"])
    print(f"\n{name}: {len(rows)} frames; models fitted on frames {probes}, judged on the other {len(held)}")
    print("| setting | error min-max | held-out max / probe max | provenance model: correlation, measured / "
          "predicted (sd of log) | constant model: measured / predicted (sd of log) | error ~ eye distance, "
          "~ time distance | error ~ provenance share |")
    print("|---|---|---|---|---|---|---|")
    for s in settings:
        err = np.array([r["settings"][s]["error"] for r in rows])
        names = sorted({k for r in rows for k in r["settings"][s]["provenance"]})
        share = np.array([[r["settings"][s]["provenance"].get(k, {}).get("share", 0.0) for k in names] for r in rows])
        sq = np.array([[r["settings"][s]["provenance"].get(k, {}).get("sq", 0.0) for k in names] for r in rows])
        per_px = sq[probes].sum(0) / np.maximum(share[probes].sum(0), 1e-12)
        predicted = np.sqrt(share @ per_px)
        const = float(err[probes].max())
        lp, lc = np.log(err[held] / predicted[held]), np.log(err[held] / const)
        eye = np.array([r["settings"][s]["eye_distance"] for r in rows])
        dt = np.array([r["settings"][s]["time_distance"] for r in rows])
        print(f"| {s} | {err.min():.3f}-{err.max():.3f} | {err[held].max() / const:.2f} | "
              f"{_corr(err[held], predicted[held]):+.2f}, "
              f"{np.exp(lp.min()):.2f}-{np.exp(lp.max()):.2f} ({lp.std():.2f}) | "
              f"{np.exp(lc.min()):.2f}-{np.exp(lc.max()):.2f} ({lc.std():.2f}) | {_corr(err, eye):+.2f}, "
              f"{_corr(err, dt):+.2f} | "
              + ", ".join(f"{k} {share[:, j].mean():.3f}: {_corr(err, share[:, j]):+.2f}" for j, k in enumerate(names))
              + " |")
    table = np.array([[r["settings"][s]["error"] for s in settings] for r in rows])
    print(f"correlation of a frame's errors across {', '.join(settings)}:")
    print(np.round(np.corrcoef(table.T), 2))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="cornell_animated", choices=("cornell_animated", "static_room"))
    ap.add_argument("--presets", default="low,medium")
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--height", type=int, default=48)
    ap.add_argument("--truth-noise", type=float, default=0.01)
    ap.add_argument("--bake-cache", type=Path, help="the bakes (bench/walkthrough_contracts.py's --bake-cache)")
    ap.add_argument("--json", type=Path, help="keep the rows here")
    a = ap.parse_args(argv)
    rows = measure(a.scene, a.presets.split(","), a.frames, a.width, a.height, a.truth_noise, a.bake_cache)
    if a.json:
        a.json.write_text(json.dumps(rows))
    analyse(a.scene, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
