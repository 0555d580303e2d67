"""Preview interaction latency (issue 7): orbit a sample scene in the browser page, 50 steps.

Starts the real stack on this machine (embedded Redis, one bake and one render worker, the
API via uvicorn) in a temporary data directory, loads the sample scenes, opens the preview
page in Debian's chromium (Playwright, headless) at ``?size=512&scene=<sample>``, then drags
the view N times, one mouse move per step, waiting after each for the new image.

Latency per step = the page's own instrumentation (``window.__preview``): ``performance.now()``
at the pointer event that changed the camera to the ``load`` event of the image showing that
camera. With only the ``reference`` renderer every new camera is a full reference render (the
artifact cache only helps for a view seen before), so this is reference render time plus the
queue, polling and image transfer.

    python -m bench.preview_latency [--scene teapot_glossy] [--size 512] [--steps 50] [--spp 4]

Writes the ``preview_latency`` block of docs/performance.md (``--no-doc`` to only print).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import statistics
import tempfile
import time
from datetime import date
from pathlib import Path
from typing import Any

from playwright.sync_api import sync_playwright

from bench.docs_writer import replace_block
from service.up import load_samples, start_stack

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "performance.md"
CHROMIUM = "/usr/bin/chromium"
LAUNCH_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
               "--disable-sync", "--no-first-run"]


def pct(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(round(q * (len(s) - 1))))]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def measure(scene: str, size: int, steps: int, spp: int, dx: float) -> dict[str, Any]:
    for k in ("IBR_REDIS_URL", "IBR_STORE_URL", "IBR_API_KEYS"):
        os.environ.pop(k, None)
    with tempfile.TemporaryDirectory(prefix="ibr-", dir="/tmp") as tmp:
        stack = start_stack(Path(tmp), port=_free_port(), log=lambda s: None)
        try:
            load_samples(stack.api_url, log=lambda s: None)
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=LAUNCH_ARGS)
                page = browser.new_page(viewport={"width": 1400, "height": 1000})
                page.set_default_timeout(120_000)
                page.goto(f"{stack.api_url}/preview/?size={size}&spp={spp}&scene={scene}")
                page.wait_for_function("window.__preview.loads >= 1")  # the scene's own view (warm-up)
                first = page.evaluate("window.__preview.last")
                box = page.locator("#viewport").bounding_box()
                assert box is not None
                x, y = box["x"] + box["width"] / 2 - steps * dx / 2, box["y"] + box["height"] / 2
                page.mouse.move(x, y)
                page.mouse.down()
                rows: list[dict[str, Any]] = []
                for i in range(steps):
                    loads = page.evaluate("window.__preview.loads")
                    x += dx
                    page.mouse.move(x, y)  # one pointermove -> one request
                    page.wait_for_function(
                        f"window.__preview.loads > {loads} && "
                        "window.__preview.last.seq === window.__preview.requests")
                    last = page.evaluate("window.__preview.last")
                    rows.append({"step": i, "latency_ms": last["latency"], "status": last["status"],
                                 "job_total_ms": 1000 * float(last["timings"].get("job_total", 0.0)),
                                 "render_total_ms": 1000 * float(last["timings"].get("total", 0.0))})
                page.mouse.up()
                browser.close()
        finally:
            stack.stop()
    lat = [r["latency_ms"] for r in rows]
    job = [r["job_total_ms"] for r in rows if r["job_total_ms"] > 0]
    ren = [r["render_total_ms"] for r in rows if r["render_total_ms"] > 0]
    return {
        "scene": scene, "size": size, "steps": steps, "spp": spp, "dx_px": dx,
        "first_view_ms": first["latency"],
        "p50_ms": statistics.median(lat), "p95_ms": pct(lat, 0.95), "min_ms": min(lat), "max_ms": max(lat),
        "job_total_p50_ms": statistics.median(job) if job else None,
        "render_total_p50_ms": statistics.median(ren) if ren else None,
        "cached": sum(r["status"] == "cached" for r in rows),
        "rows": rows,
    }


def report(res: dict[str, Any], argv: str) -> str:
    def ms(v: float | None) -> str:
        return "n/a" if v is None else f"{v:,.0f} ms"

    return "\n".join([
        "## Browser preview: orbit latency",
        "",
        "`python -m bench.preview_latency` (issue 7; loopback only, bounded).",
        "",
        f"Measured with `python -m bench.preview_latency {argv}` ({date.today().isoformat()}, "
        f"{os.cpu_count()} cores, {platform.machine()}; headless chromium, the API, Redis and the workers share "
        "the machine).",
        "",
        f"Orbiting `{res['scene']}` at {res['size']}x{res['size']} (reference renderer, spp {res['spp']}), "
        f"{res['steps']} drag steps of {res['dx_px']:g} px, each waited for: time from the pointer event to the "
        "`load` event of the image showing that camera (the page's own `performance.now()` instrumentation).",
        "",
        "| measurement | value |",
        "|---|---:|",
        f"| mouse move to new image, p50 / p95 | {ms(res['p50_ms'])} / {ms(res['p95_ms'])} |",
        f"| min / max | {ms(res['min_ms'])} / {ms(res['max_ms'])} |",
        f"| of which the render job (`job_total`: load, render, encode, store), p50 | {ms(res['job_total_p50_ms'])} |",
        f"| of which the reference render itself (`total`), p50 | {ms(res['render_total_p50_ms'])} |",
        f"| first view of the scene (cold worker) | {ms(res['first_view_ms'])} |",
        f"| views answered from the artifact cache | {res['cached']} of {res['steps']} |",
        "",
        "Only the `reference` method exists today, so every new camera is a full reference render: there is "
        "no bake to warp and the artifact cache only serves views seen before. The latency is therefore the "
        "reference render time plus queueing, the page's polling (the API waits up to 0.25 s server-side, then "
        "the page polls the job every 50 ms, backing off to 250 ms) and the PNG transfer and decode. This is the "
        "baseline the `ldc` methods must beat once they land.",
    ])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="teapot_glossy")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--dx", type=float, default=6.0, help="pixels per drag step (0.01 rad per pixel)")
    ap.add_argument("--no-doc", action="store_true")
    a = ap.parse_args()
    t0 = time.perf_counter()
    res = measure(a.scene, a.size, a.steps, a.spp, a.dx)
    res["wall_s"] = time.perf_counter() - t0
    print(json.dumps({k: v for k, v in res.items() if k != "rows"}, indent=1))
    if not a.no_doc:
        argv = f"--scene {a.scene} --size {a.size} --steps {a.steps} --spp {a.spp}"
        replace_block(DOC, "preview_latency", report(res, argv))
        print(f"wrote the preview_latency block of {DOC}")


if __name__ == "__main__":
    main()
